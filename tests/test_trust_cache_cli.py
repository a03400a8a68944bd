"""The program store through the command itself (issue 40's Done when): a pickle planted at
every entry (and at the older store's ``.pkl`` names), then every entry replaced by another
program's valid entry, each leave ``eant2 run`` exit 0 with the records of the run on a cold
cache, and the pickle's code never runs. (One flipped byte in every XLA and store entry:
tests/test_cache_damage.py, which starts from the same cold run, `cold_run`; the same cases
in-process: tests/test_programstore.py.)"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from shared import once

from eant2_jax.loop import RUN_DEPENDENT
from eant2_jax.programs import store as programstore


def cli_run(out: Path, cache: Path, *extra: str) -> list[dict]:
    env = {**os.environ, "EANT2_CACHE_DIR": str(cache)}
    # A small run without a pruner: what is planted and replaced is its programs' entries,
    # whatever they compute (a smaller engine program compiles in two thirds of the time).
    cmd = [sys.executable, "-m", "eant2_jax.app.cli", "run", "xor", "--generations", "1",
           "--population", "3", "--max-iters", "30", "--pruner", "none", "--seed", "5",
           "--out", str(out), *extra]  # fmt: skip
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    records = [json.loads(line) for line in (out / "generations.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if k not in RUN_DEPENDENT} for r in records]


def cold_run(tmp_path_factory) -> tuple[list[dict], Path]:
    """The run on an empty cache folder: its records and the cache folder it filled. Made
    once per session, whichever worker asks first (tests/shared.py), and shared with
    tests/test_cache_damage.py (the same command: one process start and compilation fewer);
    each test changes a copy of the folder only."""

    def compute():
        base = tmp_path_factory.mktemp("cold")
        return [cli_run(base / "cold", base / "cache"), str(base / "cache")]

    records, cache = once("trust-cache-cold-run", compute)
    return records, Path(cache)


def _other_programs(folder: Path) -> list[Path]:
    """Valid store entries (manifest, bytes, their hash) of another program than the run's:
    the engine's chunk for one XOR structure at popsize 9, as the store writes it."""
    from test_programstore import chunk_args, fresh_store

    from eant2_jax import ExploitConfig, exploitation

    with pytest.MonkeyPatch.context() as mp:
        fresh_store(mp, folder)
        task, args = chunk_args("xor", ExploitConfig(popsize=9, pruner="none"))
        assert programstore.lookup(exploitation.run_chunk, args, {"length": 5}, task=task)
    return sorted(folder.glob(f"*{programstore.SUFFIX}"))


class _Plant:
    """A pickle that creates a file when it is unpickled."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.slow
def test_planted_pickles_and_foreign_entries_leave_eant2_run_as_it_was(tmp_path, tmp_path_factory):
    """A pickle at every store entry (and at the older store's ``.pkl`` names), then another
    program's valid entry at every one: ``eant2 run`` on each cache gives the cold run's
    records, the pickle never runs, and every entry is replaced by a good one."""
    cold, cold_cache = cold_run(tmp_path_factory)
    cache = tmp_path / "cache"
    shutil.copytree(cold_cache, cache)  # the cold run's cache, as it left it
    store = cache / programstore.DIRNAME
    entries = sorted(store.glob(f"*{programstore.SUFFIX}"))
    assert entries
    # Another program's valid entries (the engine's chunk at another CMA-ES population
    # size), for the foreign case: written by the store in this process, traced and not
    # compiled (a third command would cost a process start and a compilation).
    others = _other_programs(tmp_path / "other" / programstore.DIRNAME)
    assert others and not set(others) & set(entries)
    marker = tmp_path / "the pickle ran"
    planted = pickle.dumps(_Plant(str(marker)))
    for p in entries:
        p.write_bytes(planted)
        p.with_suffix(".pkl").write_bytes(planted)
    assert cli_run(tmp_path / "pickled", cache) == cold
    assert not marker.exists()
    assert all(p.read_bytes() != planted for p in entries)  # each replaced by a good entry
    foreign = {p: others[i % len(others)].read_bytes() for i, p in enumerate(entries)}
    for p, data in foreign.items():  # another program's entry under each of this run's keys
        p.write_bytes(data)
    assert cli_run(tmp_path / "foreign", cache) == cold
    assert all(p.read_bytes() != data for p, data in foreign.items())  # replaced, not used
