"""A checkpoint edited past the configs' limits ends in one line before anything runs
(issue 40; docs/reliability.md): a bucket no config accepts would build a program until
killed, a ``next_id`` at the int32 limit would write ids no later resume accepts. The
edits recompute the checksums (they detect accidents, they do not authenticate)."""

from __future__ import annotations

import hashlib
import json

import jax
import numpy as np
import pytest

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, Genome, tasks
from eant2_jax.checkpoint import validate
from eant2_jax.config import MAX_BUCKET
from eant2_jax.exploration import offspring
from eant2_jax.genome import MAX_ID
from eant2_jax.jsonio import dumps
from eant2_jax.rundir import CHECKPOINT, RunDirError

TINY = EANT2Config(population=3, exploit=ExploitConfig(max_iters=20, pruner="none"))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("limits") / "run"
    eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(0), config=TINY, generations=0, out=str(out)
    )
    return out


def _edited(run_dir, tmp_path, **state):
    """A copy of the run whose checkpoint state has ``state``'s fields, checksum recomputed."""
    out = tmp_path / "edited"
    out.mkdir()
    for f in run_dir.iterdir():
        (out / f.name).write_bytes(f.read_bytes())
    ckpt = json.loads((out / CHECKPOINT).read_text())
    ckpt["state"].update(state)
    ckpt["sha256"]["state"] = hashlib.sha256(
        dumps(ckpt["state"], sort_keys=True).encode()
    ).hexdigest()
    (out / CHECKPOINT).write_text(json.dumps(ckpt) + "\n")
    return out


@pytest.mark.parametrize(
    ("field", "value", "phrase"),
    [
        ("bucket", [4, 8, 10**30], f"integers in \\[1, {MAX_BUCKET}\\]"),
        ("bucket", [4, MAX_BUCKET + 1, 4], "bucket"),
        ("next_id", 2**31, "next_id must be an integer in"),
        ("generation", 2**40, "generation"),
    ],
)
def test_a_checkpoint_past_the_limits_is_one_line(run_dir, tmp_path, field, value, phrase):
    out = _edited(run_dir, tmp_path, **{field: value})
    with pytest.raises(RunDirError, match=phrase) as e:
        validate(str(out))
    assert "\n" not in str(e.value)
    with pytest.raises(RunDirError, match=phrase):
        eant2_jax.resume(str(out), generations=1)


def test_a_checkpoint_within_the_limits_still_resumes(run_dir, tmp_path):
    out = _edited(run_dir, tmp_path, bucket=[MAX_BUCKET, 8, 4])
    assert validate(str(out)).state.bucket == (MAX_BUCKET, 8, 4)


def test_no_neuron_id_past_the_int32_limit_is_made():
    """``next_id`` at the limit: a mutation that needs a new neuron ends in one line instead
    of writing an id no resume accepts; below it, ids are handed out as before."""
    parent = Genome.parse("N0/2*1 I0*0.5 I1*-0.5")
    config = EANT2Config(population=1, offspring=20)
    with pytest.raises(ValueError, match="neuron ids are exhausted"):
        for seed in range(50):  # until a draw adds a subnetwork
            offspring(np.random.default_rng(seed), [parent], 2, MAX_ID, config)
    children, ops, _, next_id = offspring(np.random.default_rng(0), [parent], 2, 7, config)
    assert next_id == 7 + ops.count("add_subnetwork")
    assert all(max(c.neuron_ids) < next_id for c in children)
