"""Smoke test of bench/bench_cmaes.py in --quick mode: it runs and writes sane results."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

# bench/ is a folder of scripts at the repository root, not part of the installed package;
# plain `pytest` puts tests/ (not the root) on sys.path.
_ROOT = Path(__file__).resolve().parents[1]
if str(_ROOT) not in sys.path:
    sys.path.insert(0, str(_ROOT))

pytest.importorskip(
    "cma", reason="the pycma baseline needs the bench extra: pip install -e .[bench]"
)

from bench import bench_cmaes  # noqa: E402


@pytest.mark.slow
def test_quick_run_writes_json_and_markdown(tmp_path, capsys):
    out = tmp_path / "cmaes.json"
    bench_cmaes.main(["--quick", "--out", str(out)])
    payload = json.loads(out.read_text())
    for key in ("device_kind", "platform", "jax_version", "config", "rows"):
        assert key in payload, key
    rows = payload["rows"]
    assert [r["engine"] for r in rows] == ["batched-P8", "evosax-loop", "pycma"]
    for r in rows:
        assert r["S"] == 2 and len(r["dims"]) == 2 and len(r["times_s"]) == 3
        for key in ("median_s", "iters_per_s", "structure_iters_per_s", "speedup_vs_pycma"):
            assert np.isfinite(r[key]) and r[key] > 0, (key, r[key])
        assert r["compile_s"] >= 0
    md = out.with_suffix(".md").read_text()
    assert len([line for line in md.splitlines() if line.startswith("| ")]) == len(rows) + 2
    assert "iterations/s" in capsys.readouterr().out


def test_dimensions_spread_over_the_grid():
    grid = list(range(20, 201, 20))
    assert bench_cmaes.dimensions(1, grid) == [120]
    assert bench_cmaes.dimensions(8, grid) == [20, 40, 80, 100, 120, 140, 180, 200]
    assert sorted(set(bench_cmaes.dimensions(32, grid))) == grid


@pytest.mark.slow
def test_the_lazy_variant_is_the_scan_variant_when_every_iteration_decomposes():
    """An interval under one iteration decomposes every C every iteration: the lazy engine's
    trajectory is then exactly the eager one; with pycma's F = 0.5 it is another (the
    larger structures keep their decomposition for several iterations)."""
    dims, make = [6, 30], bench_cmaes.batched_engine
    eager = make(dims, 32, 9, 1e3, 0, chunk=3)
    every = make(dims, 32, 9, 1e3, 0, chunk=3, lazy=1e-9)
    pycma = make(dims, 32, 9, 1e3, 0, chunk=3, lazy=0.5)
    for _ in range(4):
        a, b, c = eager(), every(), pycma()
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.all(np.isfinite(np.asarray(c))) and not np.array_equal(np.asarray(a), np.asarray(c))
