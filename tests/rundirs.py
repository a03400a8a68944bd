"""Test helpers: the command line run in-process, and run-directory edits the trust tests
make as an attacker would."""

from __future__ import annotations

import hashlib
import json
import sys

from eant2_jax.app.cli import main
from eant2_jax.records import RUN_DEPENDENT
from eant2_jax.rundir import CHECKPOINT, CONFIG


def run_records(run_dir) -> list[dict]:
    """A run directory's generation records without the fields that describe the process,
    not the run (wall times, and what it compiled: a second run in one process compiles
    nothing)."""
    lines = (run_dir / "generations.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(x).items() if k not in RUN_DEPENDENT} for x in lines]


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


def run_main(argv, capsys, monkeypatch):
    """``eant2 ARGV`` in this process: ``(exit code, stdout, the non-blank stderr lines)``,
    with the compilation cache off and ``sys.path`` restored after (``--task`` appends the
    working directory)."""
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    monkeypatch.setattr(sys, "path", list(sys.path))
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse's errors
        rc = e.code
    cap = capsys.readouterr()
    return rc, cap.out, [x for x in cap.err.splitlines() if x.strip()]
