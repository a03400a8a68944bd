"""Scale-out: 2 virtual CPU devices and 2 local processes (gloo), each in a subprocess.

XLA fixes the number of CPU devices when the backend starts, so the scenarios run in a fresh
interpreter with ``--xla_force_host_platform_device_count=2``: one interpreter for every
scenario (a module fixture; each scenario's error is its own test's failure; scenarios of
the same rows, bucket, chunk and pruner share their compiled programs), and the two
processes of the gloo test, which split the same batch as the two devices do. Eight devices,
each one's rows bit for bit as one device computes them: tests/test_multidevice.py.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from shared import once

pytestmark = pytest.mark.slow

PRELUDE = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
import eant2_jax as E
from eant2_jax import distributed, tuning
rng = np.random.default_rng(0)
x = rng.normal(size=(64, 3))
y = np.tanh(x @ np.array([[0.5], [-1.0], [0.25]])) + 0.1 * rng.normal(size=(64, 1))
task = E.tasks.regression(x, y, hidden="tanh", output="tanh")
genomes = [E.Genome.parse(t) for t in [
    "N0/3*1 I0*0.1 I1*0.1 I2*0.1",
    "N0/4*1 I0*0.1 I1*0.1 I2*0.1 B*0.0",
    "N0/4*1 N1/2*0.0 I0*0.3 I2*-0.2 I0*0.1 I1*0.1 I2*0.1",
]]
# One engine configuration for every scenario (max_iters, patience and prune_window are
# traced, not compiled in), so that its programs of one device and of two compile once.
cfg = E.ExploitConfig(max_iters=200, chunk=4, pruner="covariance", prune_window=40,
                      prune_at_stop=False)
"""


def xla_flags(devices: int) -> str:
    """The suite's XLA_FLAGS (tests/conftest.py: the faster-compiling CPU emitters, which the
    children keep, as every command the suite starts does) with ``devices`` CPU devices."""
    kept = [f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f]
    return " ".join([*kept, f"--xla_force_host_platform_device_count={devices}"])


def _python(code: str, *, devices: int = 1, env: dict | None = None, timeout: float = 240):
    full = dict(os.environ)
    full["XLA_FLAGS"] = xla_flags(devices)
    full.update(env or {})
    proc = subprocess.run(
        [sys.executable, "-W", "error", "-c", PRELUDE + textwrap.dedent(code)],
        env=full,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


# Runs each scenario (code that sets ``out``) in a copy of the prelude's names, in order;
# one that raises records its traceback and the next still runs.
RUNNER = """
import traceback
results = {}
for name, body in SCENARIOS.items():
    scope = dict(globals())
    try:
        exec(body, scope)
        results[name] = scope["out"]
    except BaseException:
        results[name] = {"error": traceback.format_exc()}
print(json.dumps(results))
"""


def _scenarios(scenarios: dict[str, str], *, devices: int, timeout: float) -> dict:
    """Every scenario in one fresh interpreter of ``devices`` CPU devices: their ``out``s."""
    code = "SCENARIOS = " + repr({k: textwrap.dedent(v) for k, v in scenarios.items()})
    return _python(code + "\n" + RUNNER, devices=devices, timeout=timeout)


def _out(results: dict, name: str):
    out = results[name]
    assert not (isinstance(out, dict) and "error" in out), out["error"][-4000:]
    return out


DEVICES_2 = {
    "no_hang": """
        from eant2_jax.kernels import eigen
        m = np.random.default_rng().normal(size=(5, 7, 7)).astype(np.float32)
        m = jnp.asarray(m @ m.transpose(0, 2, 1))
        got, want = jax.jit(jax.vmap(eigen.eigh))(m), jax.jit(jax.vmap(jnp.linalg.eigh))(m)
        assert all(np.array_equal(np.asarray(g), np.asarray(w)) for g, w in zip(got, want))
        assert "scan" in str(jax.make_jaxpr(jax.vmap(eigen.eigh))(m))  # one at a time
        from eant2_jax.kernels import linalg
        b = jnp.asarray(np.random.default_rng().normal(size=(5, 7, 3)).astype(np.float32))
        got, want = jax.jit(jax.vmap(linalg.solve))(m, b), jax.jit(jax.vmap(jnp.linalg.solve))(m, b)
        assert np.array_equal(np.asarray(got), np.asarray(want))
        shared = (jax.vmap(f, in_axes=(0, None)) for f in (linalg.solve, jnp.linalg.solve))
        one, ref = (np.asarray(jax.jit(f)(m, b[0])) for f in shared)  # b shared by the batch
        assert np.array_equal(one, ref)
        assert "scan" in str(jax.make_jaxpr(jax.vmap(linalg.solve))(m, b))
        # Four structures, two per device, of the bucket, rows, chunk and pruner of the
        # scenarios below (so the engine's two programs, one device and two, compile once);
        # the covariance pruner's programs hold its solves too.
        from eant2_jax import exploitation as ex
        four = [*genomes, E.Genome.parse("N0/3*1 I0*0.2 I1*-0.3 B*0.1")]
        c1 = cfg.replace(max_iters=4)
        prep = tuning.prepare(four, task, key=jax.random.key(0), config=c1, min_rows=2)
        assert prep.batch.layout.slot.shape[0] == 4  # two real structures per device
        def go(mesh):
            st, h = ex.run(prep.state, prep.batch.layout, task, key=jax.random.key(1),
                           config=c1, tables=prep.tables, mesh=mesh)
            return distributed.gather((st.cma.mean, st.cma.C, st.evals))
        a, s = go(None), go(distributed.make_mesh(2))
        err = [float(np.max(np.abs(np.asarray(u, float) - np.asarray(v, float))))
               for u, v in zip(a, s)]
        evals = [np.asarray(a[2]).tolist(), np.asarray(s[2]).tolist()]
        out = {"err": err, "evals": evals}
        """,
    "one_iteration": """
        # The structures of the tune below padded to 4 rows, 2 per device, in no_hang's
        # programs (its rows, bucket, chunk and pruner; max_iters is traced, not compiled in):
        # one chunk of 4 iterations on one device and split over two (no pruning attempt:
        # its window is 40 iterations).
        from eant2_jax import exploitation as ex
        c1 = cfg.replace(max_iters=4)
        prep = tuning.prepare(genomes, task, key=jax.random.key(0), config=c1, min_rows=4)
        assert prep.popsize == 10 and prep.batch.layout.slot.shape[0] == 4
        def go(mesh):
            st, h = ex.run(prep.state, prep.batch.layout, task, key=jax.random.key(1), config=c1,
                           tables=prep.tables, mesh=mesh)
            return distributed.gather((st.cma.mean, st.cma.C, st.cma.sigma, st.evals))
        a, s = go(None), go(distributed.make_mesh(2))
        err = [float(np.linalg.norm(np.asarray(u, float) - np.asarray(v, float))
                     / max(np.linalg.norm(np.asarray(u, float)), 1e-30)) for u, v in zip(a, s)]
        out = {"err": err, "evals": np.asarray(s[3]).tolist()}
        """,
    "sharded_tune": """
        assert len(jax.devices()) == 2
        # One device's 4 rows (a padding row, as on two devices): no_hang's program.
        one = tuning.tune(genomes, task, key=jax.random.key(3), config=cfg, min_rows=4)
        mesh = distributed.make_mesh("all")
        two = tuning.tune(genomes, task, key=jax.random.key(3), config=cfg, mesh=mesh)
        out = {"one": one.costs, "two": two.costs,
               "evals": [sum(one.evaluations), sum(two.evaluations)],
               "attempts": [len(one.pruning), len(two.pruning)],
               "sizes": [[g.n_params for g in r.genomes] for r in (one, two)]}
        """,
    "run_many": """
        cfg2 = E.EANT2Config(population=2, offspring=2,
                             exploit=E.ExploitConfig(max_iters=50, pruner="none"))
        keys = [jax.random.key(i) for i in range(2)]
        many = E.run_many(task, keys, config=cfg2, generations=1, devices=2)
        # Each alone on device 0 (one of them ran on device 1 above), pinned there as
        # run_many pins its runs: run_many's program of device 0, not one more compile.
        with jax.default_device(jax.devices()[0]):
            solo = [E.run(task, key=k, config=cfg2, generations=1) for k in keys]
        out = [[str(m.best), str(s.best)] for m, s in zip(many, solo)]
        """,
    "warm_start": """
        from eant2_jax import exploitation as ex
        c = cfg.replace(max_iters=12)  # too short for a pruning attempt (window 40)
        first = tuning.tune(genomes, task, key=jax.random.key(3), config=c, keep_search=True,
                            min_rows=4)  # no_hang's program of one device
        mesh = distributed.make_mesh(2)
        args = dict(key=jax.random.key(4), config=c, start=first.searches)
        def bits(st):
            st = jax.tree.map(lambda t: jax.random.key_data(t)
                              if jax.dtypes.issubdtype(t.dtype, jax.dtypes.prng_key) else t, st)
            return [np.asarray(a).tobytes() for a in jax.tree.leaves(st)]
        one = tuning.prepare(first.genomes, task, multiple_of=2, **args).state
        two = tuning.prepare(first.genomes, task, mesh=mesh, **args).state
        a = tuning.tune(first.genomes, task, min_rows=4, **args)
        b = tuning.tune(first.genomes, task, mesh=mesh, **args)
        out = {"same": bits(one) == bits(two),
               "devices": sorted({len(x.sharding.device_set) for x in jax.tree.leaves(two)}),
               "costs": [a.costs, b.costs], "evals": [a.evaluations, b.evaluations]}
        """,
    "own_loop": """
        from eant2_jax import exploitation as ex
        # The chunk of the scenarios above (max_iters and patience are traced, not compiled
        # in): rows 0-1 (device 0) tune two structures for many chunks; rows 2-3 (device 1)
        # are padding, which never runs: device 1's loop ends at once in every chunk while
        # device 0's runs on (30 iterations: too few for a pruning attempt, window 40)
        c = cfg.replace(max_iters=30, patience=10)
        two = [genomes[2], genomes[1]]
        prep = tuning.prepare(two, task, key=jax.random.key(0), config=c, min_rows=4)
        def go(mesh):
            st, h = ex.run(prep.state, prep.batch.layout, task, key=jax.random.key(1),
                           config=c, tables=prep.tables, mesh=mesh)
            st = distributed.gather(st)
            return st, h
        (a, ha), (b, hb) = go(None), go(distributed.make_mesh(2))
        stop_at = [int(np.argmin(ha.running[:, r])) for r in range(4)]
        out = {
            "running": [ha.running.tolist(), hb.running.tolist()],
            "evals": [ha.evaluations.tolist(), hb.evaluations.tolist()],
            "sigma": [ha.sigma.tolist(), hb.sigma.tolist()],
            "tick": [int(a.tick), int(b.tick)], "stop_at": stop_at, "chunk": c.chunk,
            "cost": [np.asarray(a.cma.best_cost).tolist(), np.asarray(b.cma.best_cost).tolist()],
        }
        """,
}


@pytest.fixture(scope="module")
def devices_2() -> dict:
    # The hang scenario first, in a fresh process as before; a hang fails at the timeout.
    # Once for the session, whichever worker gets a test of this file first (tests/shared.py).
    return once("distributed-devices-2", lambda: _scenarios(DEVICES_2, devices=2, timeout=600))


def test_sharded_exploitation_matches_single_device(devices_2):
    out = _out(devices_2, "sharded_tune")
    # Same structures, budgets and stop decisions; the costs agree up to float reduction
    # order (batched products of 4 vs 2 structures per device may sum in another order),
    # which CMA-ES amplifies only within the same optimum on this well-posed regression.
    assert out["evals"][0] == out["evals"][1]
    for a, b in zip(out["one"], out["two"], strict=True):
        assert abs(a - b) <= 1e-3 * abs(a), (out["one"], out["two"])


def test_one_sharded_iteration_equals_unsharded(devices_2):
    out = _out(devices_2, "one_iteration")
    # ||a - b|| / ||a||: float32 reduction-order differences only (~1e-7 per operation).
    assert max(out["err"]) < 1e-5, out
    # 4 iterations of popsize 10 for the three structures; the padding row never runs.
    assert out["evals"][:3] == [40, 40, 40] and out["evals"][3:] == [0], out


def test_two_cpu_devices_with_several_structures_each_do_not_hang(devices_2):
    """On two cores, two CPU devices each running a batch of eigendecompositions (or of the
    pruner's solves: an LU) held both threads of XLA's pool while jaxlib's batched LAPACK
    kernel waited on that pool for its batch: this run hung in its first chunk, under some
    timings, not in every attempt (kernels/linalg.py). The subprocess's timeout turns a hang
    into a failure. With several CPU devices `eigh` and `solve` take a batch one matrix at a
    time: the same bits as the batched kernels, checked here on fresh random matrices."""
    out = _out(devices_2, "no_hang")
    assert out["evals"][0] == out["evals"][1]
    assert max(out["err"]) < 1e-5, out  # float32 reduction order only


def test_run_many_equals_solo_runs(devices_2):
    out = _out(devices_2, "run_many")
    for many, solo in out:
        assert many == solo  # each run is exactly the run it would be alone


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_agree(devices_2):
    # jax.distributed must start before anything touches the backend (the prelude does).
    code = "from eant2_jax import distributed\ndistributed.initialize()\n" + PRELUDE
    code += textwrap.dedent(
        """
        assert jax.process_count() == 2
        mesh = distributed.make_mesh("all")
        r = tuning.tune(genomes, task, key=jax.random.key(3), config=cfg, mesh=mesh)
        print(json.dumps({"costs": r.costs, "evals": sum(r.evaluations),
                          "best": [str(g) for g in r.genomes]}))
        """
    )
    port = _free_port()
    procs = []
    for pid in range(2):
        env = dict(os.environ)
        env.update(
            XLA_FLAGS=xla_flags(1),
            EANT2_COORDINATOR=f"127.0.0.1:{port}",
            EANT2_NUM_PROCESSES="2",
            EANT2_PROCESS_ID=str(pid),
        )
        procs.append(
            subprocess.Popen(
                [sys.executable, "-W", "error", "-c", code],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
    outs = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=240)
            assert p.returncode == 0, stderr[-4000:]
            outs.append(json.loads(stdout.strip().splitlines()[-1]))
    finally:  # a failed rank must not leave its peer waiting for it
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate()
    # Both processes run the same host-side loop and see the same gathered results.
    assert outs[0] == outs[1]
    # One process's run of the same tune on one device (the 2-device process's run
    # without a mesh: the one program of one device).
    single = _out(devices_2, "sharded_tune")
    assert single["evals"][0] == outs[0]["evals"]
    for a, b in zip(single["one"], outs[0]["costs"], strict=True):
        assert abs(a - b) <= 1e-3 * abs(a)


def test_a_warm_started_batch_is_made_on_the_mesh_with_the_same_bits(devices_2):
    """`tune(start=...)` on a mesh (inherited searches, as ``inherit_search`` passes them):
    `tuning.prepare` puts the covariances and step sizes straight onto the devices and
    starts the engine there, with the bits one device gives; the tune then agrees."""
    out = _out(devices_2, "warm_start")
    assert out["same"] and out["devices"] == [2]
    assert out["evals"][0] == out["evals"][1]
    for x, y in zip(*out["costs"], strict=True):  # float reduction order only (see above)
        assert abs(x - y) <= 1e-3 * abs(x)


def test_make_mesh_errors():
    from eant2_jax import distributed

    with pytest.raises(ValueError, match="'all'"):
        distributed.make_mesh("some")
    with pytest.raises(ValueError, match="device"):
        distributed.make_mesh(10_000)
    assert distributed.make_mesh(None) is None
    with pytest.raises(ValueError, match="EANT2_COORDINATOR"):
        distributed.initialize(coordinator_address="127.0.0.1:1")


def test_each_device_runs_its_own_loop_and_records_what_one_device_does(devices_2):
    """A chunk split over two devices (`exploitation.split_chunk`): the device whose
    structures stop first ends its loop early; its later records must still be those one
    device writes for stopped structures, and the engine counter must end the same."""
    out = _out(devices_2, "own_loop")
    assert out["running"][0] == out["running"][1]
    assert out["evals"][0] == out["evals"][1]
    assert out["tick"][0] == out["tick"][1]
    # the scenario the test is for: device 1 had nothing to run, device 0 ran on for
    # several chunks
    assert out["stop_at"][2:] == [0, 0], out["stop_at"]
    assert min(out["stop_at"][:2]) > 4 * out["chunk"], out["stop_at"]
    # Device 1's records after its loop ended are the frozen rows one device records. (The
    # tuned rows agree only up to rounding: the per-device program batches 2 rows, not 4;
    # on a GPU CMA-ES amplified that to 18% in sigma late in the run, with the same stops.)
    np.testing.assert_array_equal(*(np.asarray(s)[:, 2:] for s in out["sigma"]))
    assert out["cost"][0][2:] == out["cost"][1][2:] == [float("inf")] * 2
