"""A damaged persistent-cache folder cannot break or change a run (issue 40): every XLA
cache entry and every program-store entry flipped in one byte, ``eant2 run`` still exits 0
with the records of a run on a cold cache (JAX checksums its cache entries; the store
checks its manifest and SHA-256, docs/reliability.md)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

RUN_DEPENDENT = ("wall_s", "generation_s", "compiles", "compile_s", "cache_hits", "cache_misses")


def _run(out: Path, cache: Path) -> list[dict]:
    env = {**os.environ, "EANT2_CACHE_DIR": str(cache)}
    # A small run without a pruner: what is cached and damaged is its programs, whatever
    # they compute (a smaller engine program compiles in two thirds of the time).
    cmd = [sys.executable, "-m", "eant2_jax.app.cli", "run", "xor", "--generations", "1",
           "--population", "3", "--max-iters", "30", "--pruner", "none", "--seed", "5",
           "--out", str(out)]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    records = [json.loads(line) for line in (out / "generations.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k not in RUN_DEPENDENT} for r in records]


@pytest.mark.slow
def test_a_damaged_cache_leaves_the_run_as_it_was(tmp_path):
    cache = tmp_path / "cache"
    cold = _run(tmp_path / "cold", cache)
    entries = [p for p in cache.rglob("*") if p.is_file() and p.stat().st_size > 0]
    assert any(p.parent == cache for p in entries), "no XLA cache entry to damage"
    assert any(p.parent.name == "eant2-programs" for p in entries), "no store entry to damage"
    for p in entries:  # one byte of each entry flipped, in the middle
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x40
        p.write_bytes(bytes(data))
    assert _run(tmp_path / "damaged", cache) == cold
