"""run_many on the CPU: one run at a time, whatever the workers asked for."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import eant2_jax as E


def _task():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(32, 2))
    y = np.tanh(x @ np.array([[0.5], [-1.0]]))
    return E.tasks.regression(x, y, hidden="tanh", output="tanh")


@pytest.mark.slow
def test_cpu_workers_warn_and_run_one_at_a_time():
    task = _task()
    cfg = E.EANT2Config(
        population=2, offspring=2, exploit=E.ExploitConfig(max_iters=20, pruner="none")
    )
    keys = [jax.random.key(i) for i in range(2)]
    # Two runs in flight on XLA's CPU pool can deadlock it (multirun's docstring); the
    # request is kept to one worker, with a warning that says so.
    with pytest.warns(UserWarning, match="one run at a time"):
        many = E.run_many(task, keys, config=cfg, generations=1, workers_per_device=2)
    solo = [E.run(task, key=k, config=cfg, generations=1) for k in keys]
    assert [str(r.best) for r in many] == [str(r.best) for r in solo]


def test_workers_must_be_positive():
    with pytest.raises(ValueError, match="workers_per_device"):
        E.run_many(_task(), [jax.random.key(0)], generations=0, workers_per_device=0)
