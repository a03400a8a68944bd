"""Every registered task builds, compiles under jit, and scores a batch of networks.

The test iterates over the registry at collection time, so a newly registered task is
covered without editing this file; ``SMALL`` only makes known tasks cheap on a CPU.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from compiles import count_compiles

from eant2_jax import tasks
from eant2_jax.compiler import networks
from eant2_jax.exploration import initial_genome

_cost = jax.jit(lambda task, key, nets: task.cost(key, nets))

# Options that keep a task CPU-sized (a task not listed is built with its defaults).
SMALL = {
    "servo": {"n_starts": 8},
    "dpv": {"max_steps": 50},
    "dpnv": {"max_steps": 50},
}
SLOW = {"servo"}  # MJX compiles for tens of seconds on a small CPU


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in tasks.names()],
)
def test_registered_task_scores_a_batch_of_networks(name):
    task = tasks.make(name, **SMALL.get(name, {}))
    assert isinstance(task, tasks.Task)
    assert task.n_inputs >= 1 and task.n_outputs >= 1
    rng = np.random.default_rng(0)
    genomes = [
        initial_genome(rng, task.n_inputs, task.n_outputs, connectivity=1.0, weight_scale=0.1)
        for _ in range(6)
    ]
    nets = jax.tree.map(lambda a: a.reshape(2, 3, *a.shape[1:]), networks(genomes, task.n_inputs))
    cost = _cost(task, jax.random.key(0), nets)
    assert cost.shape == (2, 3)
    assert np.issubdtype(np.asarray(cost).dtype, np.floating)
    assert np.all(np.isfinite(np.asarray(cost)))
    # A second task built alike, other networks: no second program (a task is a pytree
    # argument of the compiled function, not a constant baked into it).
    again = tasks.make(name, **SMALL.get(name, {}))
    others = jax.tree.map(lambda a: a * 0.5 if a.dtype.kind == "f" else a, nets)
    key = jax.random.key(1)
    with count_compiles() as c:
        _cost(again, key, others)
    assert c.count == 0
