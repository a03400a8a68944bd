"""Run-directory edits the trust tests make as an attacker would (a test helper module)."""

from __future__ import annotations

import hashlib
import json

from eant2_jax.rundir import CHECKPOINT, CONFIG


def retask(out, task, options):
    """Point a complete run directory at another task, its checksum in the checkpoint
    recomputed (checksums detect accidents, they do not authenticate)."""
    meta = json.loads((out / CONFIG).read_text())
    meta.update(task=task, task_options=options)
    data = (json.dumps(meta, indent=2) + "\n").encode()
    (out / CONFIG).write_bytes(data)
    ckpt = json.loads((out / CHECKPOINT).read_text())
    ckpt["sha256"][CONFIG] = hashlib.sha256(data).hexdigest()
    (out / CHECKPOINT).write_text(json.dumps(ckpt) + "\n")
