"""The engine over 8 virtual CPU devices: the same results as one device, to the bit; each
device holds only its rows; nothing crosses devices or reaches the host within a chunk.

XLA fixes the number of CPU devices when its backend starts, so the scenario runs in a fresh
interpreter with ``--xla_force_host_platform_device_count=8`` (as tests/test_distributed.py
does). One subprocess runs every check, so the two engine programs compile once.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
from shared import once

pytestmark = pytest.mark.slow

SCENARIO = """
import json, re
import jax, numpy as np
import eant2_jax as E
from eant2_jax import distributed, tuning
from eant2_jax import exploitation as ex

assert len(jax.devices()) == 8
rng = np.random.default_rng(0)
x = rng.normal(size=(32, 3))
y = np.tanh(x @ np.array([[0.5], [-1.0], [0.25]])) + 0.1 * rng.normal(size=(32, 1))
task = E.tasks.regression(x, y, hidden="tanh", output="tanh")
genomes = [E.Genome.parse(t) for t in [
    "N0/3*1 I0*0.1 I1*0.1 I2*0.1",
    "N0/4*1 I0*0.1 I1*0.1 I2*0.1 B*0.0",
    "N0/4*1 N1/2*0.0 I0*0.3 I2*-0.2 I0*0.1 I1*0.1 I2*0.1",
]] * 5
cfg = ex.ExploitConfig(max_iters=24, chunk=8, pruner="covariance", prune_window=6)
prep = tuning.prepare(genomes, task, key=jax.random.key(0), config=cfg, min_rows=16)
rows, genes = prep.batch.layout.slot.shape
per = rows // 8
run_key = jax.random.key(1)

trips = []
gather = distributed.gather
def counted(tree):
    trips.append(1)
    return gather(tree)
distributed.gather = counted

def host(tree):  # every leaf on the host as NumPy, keys as their data
    return gather(jax.tree.map(
        lambda a: jax.random.key_data(a)
        if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key) else a, tree))

def bits(tree):  # every leaf's bytes
    return [np.asarray(a).tobytes() for a in jax.tree.leaves(host(tree))]

def rows_of(tree, lo, hi, axis=0):  # the rows lo:hi of every leaf with a structure axis
    return jax.tree.map(
        lambda a: a[(slice(None),) * axis + (slice(lo, hi),)]
        if np.ndim(a) > axis and np.shape(a)[axis] == rows else a, tree)

mesh = distributed.make_mesh(8)
st8, hist8 = ex.run(prep.state, prep.batch.layout, task, key=run_key, config=cfg,
                    tables=prep.tables, mesh=mesh)
ticks = int(hist8.running.shape[0])
trips8 = len(trips)
# The mesh's results are read on the host: slicing a sharded array on the devices would
# run a program with collectives, and 8 virtual devices on few busy cores can time out
# in XLA:CPU's rendezvous.
st8_host, hist8_host = host((st8, hist8))

# Each device's rows, tuned on one device alone (the same rows, keys and task key).
same_state, same_history, trips1 = [], [], []
for k in range(8):
    lo, hi = k * per, (k + 1) * per
    part = rows_of((prep.state, prep.batch.layout, prep.tables), lo, hi)
    trips.clear()
    st1, hist1 = ex.run(part[0], part[1], task, key=run_key, config=cfg, tables=part[2])
    trips1.append(len(trips) * cfg.chunk == hist1.running.shape[0])
    mine = rows_of(st8_host, lo, hi)
    same_state.append(bits(mine.replace(tick=np.int32(0))) == bits(st1.replace(tick=np.int32(0))))
    t = hist1.running.shape[0]
    mine = rows_of(hist8_host, lo, hi, axis=1)
    same_history.append(bits(jax.tree.map(lambda a: a[:t], mine)) == bits(hist1)
                        and not np.any(mine.running[t:]))

# Each device holds only its rows of every leaf with a structure axis.
split = [a for a in jax.tree.leaves(st8) if a.ndim >= 1 and a.shape[0] == rows]
shards = [[(s.device.id, s.data.shape[0]) for s in a.addressable_shards] for a in split]

# A batch prepared on the mesh is the same batch, made where `run` holds it: `run` moves
# none of its arrays (each is handed on as it is).
born = tuning.prepare(genomes, task, key=jax.random.key(0), config=cfg, min_rows=16,
                      mesh=mesh)
born_same = (bits((born.state, born.batch, born.tables))
             == bits((prep.state, prep.batch, prep.tables)))
ours = (born.state, born.batch.layout, born.tables)
kept = [a is b for a, b in zip(jax.tree.leaves(ex.placed(*ours, task, mesh)[:3]),
                               jax.tree.leaves(ours))
        if not jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key)]

# A chunk call moves nothing: not between host and devices, not between devices.
args = (*ex.placed(prep.state, prep.batch.layout, prep.tables, task, mesh), run_key, cfg)
chunk = ex.split_chunk(mesh, rows, args, cfg.chunk)
jax.block_until_ready(chunk(*args))
with jax.transfer_guard("disallow_explicit"):
    moved = chunk(*args)
    jax.block_until_ready(moved)
text = chunk.lower(*args).compile().as_text()
crossing = sorted(set(re.findall(
    r"\\b(all-reduce|all-gather|all-to-all|collective-permute|reduce-scatter|send|recv|"
    r"outfeed|infeed)(?:-start|-done)?\\(", text)))
print(json.dumps({
    "born_same": born_same, "born_kept": kept,
    "rows": rows, "ticks": ticks, "chunk": cfg.chunk, "trips8": trips8, "trips1": trips1,
    "same_state": same_state, "same_history": same_history,
    "evals": np.asarray(st8_host.evals).tolist(),
    "shards": shards, "crossing": crossing, "callbacks": "callback" in text,
    "full_cov": f"f32[{rows},{genes},{genes}]" in text,
    "own_cov": f"f32[{per},{genes},{genes}]" in text,
}))
"""


def _scenario() -> dict:
    # XLA_FLAGS replaced, not extended: the bit-for-bit claims are made with XLA:CPU's default
    # (fusion) emitters. With the suite's older ones (tests/conftest.py) device 4's sigma at
    # the run's last iteration differed from one device's in the last bit (measured).
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=8")
    proc = subprocess.run(
        [sys.executable, "-W", "error", "-c", textwrap.dedent(SCENARIO)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def scenario() -> dict:
    return once("multidevice-scenario", _scenario)  # once for the session (tests/shared.py)


def test_each_devices_rows_are_one_devices_bits(scenario):
    # Every leaf of the final state and of every engine iteration's record of a device's
    # rows, bit for bit, is what one device computes for those rows alone. (One device
    # holding all 16 rows rounds differently in the last bits: XLA:CPU's rounding depends
    # on the rows of a program, as batching runs in lock-step does; docs/design.md.)
    assert scenario["same_state"] == [True] * 8
    assert scenario["same_history"] == [True] * 8
    assert all(e > 0 for e in scenario["evals"][:15]) and scenario["evals"][15] == 0


def test_each_device_holds_only_its_rows(scenario):
    rows = scenario["rows"]
    assert rows == 16 and scenario["shards"]
    for leaf in scenario["shards"]:
        assert sorted(d for d, _ in leaf) == list(range(8))  # one shard on each device
        assert all(n == rows // 8 for _, n in leaf)
    # The per-device program works on its own rows' covariances, never the whole batch's.
    assert scenario["own_cov"] and not scenario["full_cov"]


def test_a_batch_prepared_on_the_mesh_is_the_same_and_stays_put(scenario):
    # `tuning.prepare(mesh=...)`, as `tune` calls it: the same bits as the batch made on one
    # device, each array made on the devices where `run` holds it, so `run` moves none.
    assert scenario["born_same"]
    assert scenario["born_kept"] and all(scenario["born_kept"])


def test_nothing_crosses_devices_or_reaches_the_host_within_a_chunk(scenario):
    # No collective, host transfer or host callback in the per-device program, and a chunk
    # call moved nothing (it ran under jax.transfer_guard("disallow_explicit")).
    assert scenario["crossing"] == [] and not scenario["callbacks"]
    # The host reads the engine once per chunk, not once per iteration, on eight devices
    # and on one alike.
    assert scenario["ticks"] > scenario["chunk"]
    assert scenario["trips8"] * scenario["chunk"] == scenario["ticks"]
    assert scenario["trips1"] == [True] * 8
