"""A TensorNEAT training run goes on from its kept state (bench/field_tnstate.py): the same run
as never stopped; a state of another run or shape is refused; the file runs no code.

TensorNEAT is fetched, not installed, so its ``Pipeline.step`` is stood in for by a jitted
step of the same shape: a state pytree (a raw key, as TensorNEAT's, a typed key, arrays with
NaN) to ``(state, (nodes, conns), fitness)``. The real one was checked the same way on a CPU
(cartpole and halfcheetah, whole against cut and resumed: equal logs and states).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench import field_tnstate
from bench.common import BenchInputError
from bench.field_tensorneat import run_generations
from bench.field_workers import Log, resume_log

POP, GENERATIONS = 6, 5


def _setup(seed: int) -> dict:
    return {
        "randkey": jax.random.PRNGKey(seed),  # TensorNEAT's kind of key: raw uint32
        "typed": jax.random.key(seed + 1),
        "nodes": jnp.full((POP, 4, 4), jnp.nan).at[:, :3].set(0.0),
        "conns": jnp.full((POP, 5, 3), jnp.nan),
        "generation": jnp.int32(0),
    }


@jax.jit
def _step(state):
    k1, k2, k3, k4 = jax.random.split(state["randkey"], 4)
    nodes = state["nodes"].at[:, :3, 1].add(jax.random.normal(k1, (POP, 3)))
    conns = state["conns"].at[:, :2].set(jax.random.normal(k2, (POP, 2, 3)))
    typed, k5 = jax.random.split(state["typed"])
    fitness = jax.random.normal(k3, (POP,)) + jax.random.uniform(k5)
    fitness = jnp.where(jax.random.bernoulli(k4, 0.2, (POP,)), jnp.nan, fitness)
    new = dict(state, randkey=jax.random.split(k4)[0], typed=typed, nodes=nodes, conns=conns,
               generation=state["generation"] + 1)  # fmt: skip
    return new, (nodes, conns), fitness


class _Killed(Exception):
    pass


def _train(log, rundir, digest="run-a", generations=GENERATIONS):
    run_generations(_step, _setup(7), log=log, top=3, pop=POP, generations=generations,
                    rundir=rundir, digest=digest)  # fmt: skip


def _strip(curve):  # as the files hold them, wall times aside
    return [{k: v for k, v in p.items() if k != "wall_s"} for p in json.loads(json.dumps(curve))]


@pytest.mark.parametrize("kill_before_state", [False, True])
def test_a_killed_run_goes_on_from_its_state_to_the_same_run(tmp_path, kill_before_state):
    """Cut after its second generation (after that generation's state was kept, or between
    its logged point and its state: the generation runs again), then resumed as the
    protocol's child does: the same points, candidates and final state as never stopped."""
    whole = Log(tmp_path / "whole.json", 0.0, {})
    _train(whole, tmp_path / "whole.rundir")
    assert len(whole.data["curve"]) == GENERATIONS

    class Dies(Log):
        def point(self, **point):
            super().point(**point)
            if len(self.data["curve"]) == 2:
                if not kill_before_state:
                    field_tnstate.save(rundir, held[0], 2, "run-a")  # as the loop does next
                raise _Killed

    rundir, held = tmp_path / "cut.rundir", []

    def keep(state):  # the state after each step, for the kill after its save
        out = _step(state)
        held[:] = [out[0]]
        return out

    cut = Dies(tmp_path / "cut.json", 0.0, {})
    with pytest.raises(_Killed):
        run_generations(keep, _setup(7), log=cut, top=3, pop=POP, generations=GENERATIONS,
                        rundir=rundir, digest="run-a")  # fmt: skip
    with np.load(rundir / field_tnstate.FILE, allow_pickle=False) as kept:
        assert int(kept["generation"]) == (1 if kill_before_state else 2)
    log = resume_log(tmp_path / "cut.json", 0.0, {})
    _train(log, rundir)
    assert _strip(log.data["curve"]) == _strip(whole.data["curve"])
    assert log.data["candidates"] == whole.data["candidates"]
    for name in ("whole.rundir", "cut.rundir"):
        with np.load(tmp_path / name / field_tnstate.FILE, allow_pickle=False) as f:
            assert int(f["generation"]) == GENERATIONS
    a, _ = field_tnstate.load(tmp_path / "whole.rundir", _setup(0), "run-a")
    b, _ = field_tnstate.load(rundir, _setup(0), "run-a")
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_state_round_trips_to_the_bit(tmp_path):
    state, _, _ = _step(_setup(3))
    field_tnstate.save(tmp_path, state, 4, "d")
    back, generation = field_tnstate.load(tmp_path, _setup(0), "d")
    assert generation == 4 and jax.tree.structure(back) == jax.tree.structure(state)
    assert jax.random.key_impl(back["typed"]) == jax.random.key_impl(state["typed"])
    for x, y in zip(jax.tree.leaves(state), jax.tree.leaves(back), strict=True):
        if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert field_tnstate.load(tmp_path / "none", _setup(0), "d") is None


def test_another_runs_or_a_damaged_state_is_refused(tmp_path):
    field_tnstate.save(tmp_path, _setup(1), 2, "d")
    with pytest.raises(BenchInputError, match="other settings"):
        field_tnstate.load(tmp_path, _setup(0), "another")
    wider = dict(_setup(0), nodes=jnp.zeros((POP + 1, 4, 4)))
    with pytest.raises(BenchInputError, match=r"array \d+ is float32\[6, 4, 4\], the run's is "
                                              r"float32\[7, 4, 4\]"):  # fmt: skip
        field_tnstate.load(tmp_path, wider, "d")
    with pytest.raises(BenchInputError, match="5 arrays, the run has 6"):
        field_tnstate.load(tmp_path, dict(_setup(0), extra=jnp.zeros(1)), "d")
    # A log that holds fewer generations than the state (or none beside a state) is refused.
    log = Log(tmp_path / "log.json", 0.0, {})
    with pytest.raises(BenchInputError, match="2 generations kept, its log holds 0"):
        _train(log, tmp_path, digest="d")
    (tmp_path / field_tnstate.FILE).write_bytes(b"not a zip file")
    with pytest.raises(BenchInputError, match="cannot read it"):
        field_tnstate.load(tmp_path, _setup(0), "d")


class _Planted:
    def __reduce__(self):
        return (exec, ("raise SystemExit('the state file ran code')",))


def test_a_state_file_runs_no_code(tmp_path):
    """An object array (pickled) in place of an array is refused, never unpickled."""
    arrays = {f"leaf{i}": np.asarray(x) for i, x in enumerate(jax.tree.leaves(_setup(0)))
              if not jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)}  # fmt: skip
    arrays["leaf4"] = np.array([_Planted()], dtype=object)
    np.savez(tmp_path / field_tnstate.FILE, generation=np.int64(1), digest=np.array("d"),
             keys=np.array(json.dumps([""] * 5)), **arrays)  # fmt: skip
    with pytest.raises(BenchInputError, match="cannot read it"):
        field_tnstate.load(tmp_path, _setup(0), "d")
