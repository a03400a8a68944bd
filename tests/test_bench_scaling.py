"""`python -m bench scaling`: weak and strong rows on two (virtual CPU) devices, with the
engine split into the placement of the batch and the devices' loops, over interleaved
rounds, each case's loops traced once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_quick_rows_split_the_engine_into_placement_and_loops(tmp_path):
    out = tmp_path / "scaling.json"
    # Two virtual devices, added to the suite's own XLA flags (its faster CPU emitters).
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip())
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "scaling", "--quick", "--devices", "1", "2",
         "--genes", "20", "--out", str(out), "--trace-dir", str(tmp_path / "traces")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    # --quick: one structure per device, a strong batch of one (two programs compiled: the
    # one-device cases share one, the two-device ones another).
    assert [(r["scaling"], r["devices"], r["structures"]) for r in rows] == [
        ("weak", 1, 1), ("weak", 2, 2), ("strong", 1, 1), ("strong", 2, 1)
    ]  # fmt: skip
    for r in rows:
        assert 0 < r["loops_s"] and 0 < r["engine_s"] and 0 < r["seconds"]
        assert r["placement_s"] == pytest.approx(r["engine_s"] - r["loops_s"])
        assert r["host_s"] == pytest.approx(r["seconds"] - r["engine_s"])
        # The handover's start (`tuning.prepare`) and its hand-back (the rest); the median of
        # two rounds is their mean, so the row's parts add up as each round's do.
        assert 0 < r["start_s"] and r["back_s"] == pytest.approx(r["host_s"] - r["start_s"])
    for first in (rows[0], rows[2]):  # one device is the base of both speed-ups
        assert first["speedup"] == pytest.approx(1) and first["loops_speedup"] == pytest.approx(1)
    for r in rows:  # two rounds (--quick): the row is their median, with their range
        for k in ("speedup", "loops_speedup"):
            assert len(r[f"{k}_rounds"]) == 2
            assert r[k] == pytest.approx(sum(r[f"{k}_rounds"]) / 2)
            lo, hi = min(r[f"{k}_rounds"]), max(r[f"{k}_rounds"])
            assert r[f"{k}_range"] == f"{lo:.2f}-{hi:.2f}x"
    for r in rows:  # --trace-dir: each case's loops traced once (the per-device analysis of
        # a trace is tests/test_bench_profile.py's; a CPU trace has no device tracks)
        assert r["trace_wall_s"] > 0 and isinstance(r["per_device"], list)
        assert Path(r["trace_file"]).is_file()
        assert Path(r["trace_file"]).is_relative_to(tmp_path / "traces")
    assert len({r["trace_file"] for r in rows}) == len(rows)
    md = out.with_suffix(".md").read_text()
    assert "| traced loops s | busy s per device | span s per device |" in md
    assert "| loops s | placement s |" in md and "| loops speed-up | range |" in md
    assert "| handover s | start s | hand-back s |" in md
