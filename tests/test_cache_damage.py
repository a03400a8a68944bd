"""A damaged persistent-cache folder cannot break or change a run (issue 40): every XLA
cache entry and every program-store entry flipped in one byte, ``eant2 run`` still exits 0
with the records of a run on a cold cache (JAX checksums its cache entries; the store
checks its manifest and SHA-256, docs/reliability.md)."""

from __future__ import annotations

import shutil

import pytest
from test_trust_cache_cli import cli_run, cold_run


@pytest.mark.slow
def test_a_damaged_cache_leaves_the_run_as_it_was(tmp_path, tmp_path_factory):
    """Every entry of a cold run's cache (a copy of it: `cold_run`, shared with
    tests/test_trust_cache_cli.py) flipped in one byte: ``eant2 run`` exits 0, without a
    traceback, with the cold run's records."""
    cold, cold_cache = cold_run(tmp_path_factory)
    cache = tmp_path / "cache"
    shutil.copytree(cold_cache, cache)
    entries = [p for p in cache.rglob("*") if p.is_file() and p.stat().st_size > 0]
    assert any(p.parent == cache for p in entries), "no XLA cache entry to damage"
    assert any(p.parent.name == "eant2-programs" for p in entries), "no store entry to damage"
    for p in entries:  # one byte of each entry flipped, in the middle
        data = bytearray(p.read_bytes())
        data[len(data) // 2] ^= 0x40
        p.write_bytes(bytes(data))
    assert cli_run(tmp_path / "damaged", cache) == cold
