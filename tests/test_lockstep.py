"""Runs in lock-step (`eant2_jax.run_lockstep`): the runs alone, their directories, resume."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from compiles import force_compile_ahead, joined

import eant2_jax as E
from eant2_jax import run_lockstep


def _task():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(32, 2))
    y = np.tanh(x @ np.array([[0.5], [-1.0]])) + 0.3 * np.tanh(x[:, :1] * x[:, 1:])
    return E.tasks.regression(x, y, hidden="tanh", output="tanh")


def _config(**exploit):
    options = {"max_iters": 30, "pruner": "covariance", "prune_window": 5, **exploit}
    return E.EANT2Config(population=3, offspring=3, exploit=E.ExploitConfig(**options))


def _same(a: E.RunResult, b: E.RunResult):
    assert [str(i.genome) for i in a.population] == [str(i.genome) for i in b.population]
    assert [i.cost for i in a.population] == [i.cost for i in b.population]
    assert [r.evaluations for r in a.generations] == [r.evaluations for r in b.generations]
    assert [r.to_json() for r in a.pruning] == [r.to_json() for r in b.pruning]


def _shape(g: E.Genome) -> str:
    return str(g.with_weights(np.zeros(g.n_params)))


def _same_networks(a: E.RunResult, b: E.RunResult):
    """The same structures in the same order, their costs equal up to float rounding."""
    assert [_shape(i.genome) for i in a.population] == [_shape(i.genome) for i in b.population]
    np.testing.assert_allclose(
        [i.cost for i in a.population], [i.cost for i in b.population], rtol=1e-3
    )


# One group, two runs of a fixed popsize, shared by the tests that read it (the same
# programs: a test that runs this group again, resumed or compiled ahead, compiles nothing
# new for the usual path).
SEEDS, GENERATIONS = (3, 4), 2


@pytest.fixture(scope="module")
def group():
    keys = [jax.random.key(s) for s in SEEDS]
    return run_lockstep(_task(), keys, config=_config(popsize=8), generations=GENERATIONS)


@pytest.mark.slow
def test_each_run_is_the_run_alone_at_a_fixed_popsize(group):
    # With the popsize fixed, the group's shared padding changes only float rounding (wider
    # sums and eigendecompositions): each structure starts from its solo key and draws its
    # own numbers, so each run evolves the same networks as alone.
    task, cfg = _task(), _config(popsize=8)
    keys = [jax.random.key(s) for s in SEEDS]
    for k, r in zip(keys, group, strict=True):
        alone = E.run(task, key=k, config=cfg, generations=GENERATIONS)
        _same_networks(r, alone)
        for a, b in zip(r.population, alone.population, strict=True):
            np.testing.assert_allclose(a.genome.weights, b.genome.weights, rtol=1e-3, atol=1e-4)
        assert [x.evaluations for x in r.generations] == [x.evaluations for x in alone.generations]
    assert len({str(r.best) for r in group}) > 1  # independent runs, not copies


@pytest.mark.slow
def test_a_group_of_one_is_the_run_alone():
    task, cfg = _task(), _config()  # default popsize: follows the (same) bucket
    key = jax.random.key(7)
    (r,) = run_lockstep(task, [key], config=cfg, generations=2)
    _same(r, E.run(task, key=key, config=cfg, generations=2))


class _Kill(Exception):
    pass


@pytest.mark.slow
def test_a_killed_group_resumes_exactly(tmp_path, group):
    task, cfg, whole = _task(), _config(popsize=8), group
    keys = [jax.random.key(s) for s in SEEDS]
    outs = [str(tmp_path / f"r{i}") for i in range(2)]

    def kill(event):  # run 0 has committed generation 1, run 1 has not
        if event["event"] == "generation" and event["run"] == 0 and event["generation"] == 1:
            raise _Kill

    with pytest.raises(_Kill):
        run_lockstep(task, keys, config=cfg, generations=GENERATIONS, outs=outs, callback=kill)
    logs = [tmp_path / r / "generations.jsonl" for r in ("r0", "r1")]
    lines = [len(p.read_text().splitlines()) for p in logs]
    assert lines == [2, 1]
    again = run_lockstep(task, keys, config=cfg, generations=GENERATIONS, outs=outs, resume=True)
    for a, b in zip(whole, again, strict=True):
        _same(a, b)
    # Each directory is an ordinary run directory: resume reads a finished one back.
    alone = E.resume(outs[1], task)
    _same(alone, whole[1])
    rec = [json.loads(x) for x in (tmp_path / "r1" / "generations.jsonl").read_text().splitlines()]
    assert [r["generation"] for r in rec] == [0, 1, 2]


def test_bad_input():
    task, cfg = _task(), _config()
    with pytest.raises(ValueError, match="no keys"):
        run_lockstep(task, [], config=cfg, generations=1)
    with pytest.raises(ValueError, match="outs"):
        run_lockstep(task, [jax.random.key(0)], config=cfg, generations=1, outs=["a", "b"])
    with pytest.raises(ValueError, match="config.devices"):
        run_lockstep(task, [jax.random.key(0)], config=E.EANT2Config(devices=1), generations=1)


@pytest.mark.slow
def test_warm_starts_and_reexploited_parents_go_to_their_own_runs():
    # inherit_search + reexploit: each brood's warm starts and kept searches are sliced
    # back to its own run (a slip would hand one run's covariance to another's structure).
    task = _task()
    cfg = E.EANT2Config(
        population=3, offspring=3, inherit_search=True, reexploit=True,
        exploit=E.ExploitConfig(max_iters=30, pruner="covariance", prune_window=5, popsize=8),
    )  # fmt: skip
    keys = [jax.random.key(s) for s in (8, 9)]
    # One generation after the first: its broods are the first with warm starts and kept
    # searches, and the slicing is the same in every later generation.
    group = run_lockstep(task, keys, config=cfg, generations=1)
    for k, r in zip(keys, group, strict=True):
        alone = E.run(task, key=k, config=cfg, generations=1)
        _same_networks(r, alone)
        assert any(a.search is not None for a in r.population)  # searches were kept
        for a, b in zip(r.population, alone.population, strict=True):
            assert (a.search is None) == (b.search is None)
            if a.search is not None:
                np.testing.assert_allclose(a.search.cov, b.search.cov, rtol=1e-2, atol=1e-4)


@pytest.mark.slow
def test_each_run_stops_at_its_own_target():
    task = E.tasks.make("xor")
    cfg = E.EANT2Config(
        population=4, offspring=4, target_cost=0.05, min_bucket=(16, 48, 6),
        exploit=E.ExploitConfig(max_iters=60, pruner="none", popsize=8),
    )  # fmt: skip
    # One padding bucket for the group and for each run alone: a padded structure follows
    # its unpadded path only up to float rounding (kernels/cmaes.py), which can move a stop.
    # Seeds 3 and 0 stop at generations 1 and 2: the group's first run leaves it first, and
    # the second goes on alone in the group's last row. (Seed 2 stops at 3; seed 1 never
    # reached the target: it kept the group going, one run wide, to generation 8.)
    keys = [jax.random.key(s) for s in (3, 0)]
    group = run_lockstep(task, keys, config=cfg, generations=8)
    alone = [E.run(task, key=k, config=cfg, generations=8) for k in keys]
    counts = [len(r.generations) for r in group]
    assert counts == [len(r.generations) for r in alone]
    assert counts[0] < counts[1]  # the runs did stop at different generations, first first


@pytest.mark.slow
def test_programs_compiled_ahead_are_used_and_change_nothing(monkeypatch, group):
    """On an accelerator a group compiles generation 0's program from shapes and, during
    each generation, its guessed next bucket's (`programs.guesses.compile_next_bucket` over every
    run's pool, for the group's rows). Forced on here, each compilation waited for at once
    (two programs at once on a CPU can deadlock XLA's thread pool): the group runs
    programs compiled ahead (generation 0's called without jit's fallback) and gives
    exactly the group of the usual path."""
    from eant2_jax.programs import guesses as g

    task, cfg, plain = _task(), _config(popsize=8), group
    keys = [jax.random.key(s) for s in SEEDS]

    guesses = []
    guess = g.compile_next_bucket

    def spy_guess(pools, *args):
        guesses.append(len(pools))
        return guess(pools, *args)

    used = force_compile_ahead(monkeypatch, fallback=True)
    monkeypatch.setattr(g, "compile_first_ahead", joined(g.compile_first_ahead))
    monkeypatch.setattr(g, "compile_next_bucket", joined(spy_guess))
    ahead = run_lockstep(task, keys, config=cfg, generations=GENERATIONS)
    assert guesses and set(guesses) == {len(SEEDS)}  # every run's pool, once per generation
    assert len(guesses) == GENERATIONS  # not in the last generation
    assert len(used) >= 2, "generation 0 and a guessed bucket ran programs compiled ahead"
    for a, b in zip(ahead, plain, strict=True):
        _same(a, b)
