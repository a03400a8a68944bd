"""The brax benchmark suite: a --quick run (a tiny run, its resume, new episodes) end to end
(the test extra installs brax)."""

from __future__ import annotations

import json

import jax
import pytest


@pytest.mark.slow
def test_quick_run_resumes_and_plays_new_episodes(tmp_path, capsys):
    from bench import bench_brax

    out = tmp_path / "brax.json"
    payload = bench_brax.main(["--quick", "--out", str(out), "--replay-precision", "default"])
    (row,) = payload["rows"]
    assert (row["run"], row["resume"], row["generation"]) == ("ok", "ok", 0)
    assert row["resume_best_cost"] == row["best_cost"]  # a finished run resumes to itself
    assert row["new_episodes"] == 4 and 0 < row["new_return_min"] <= 20  # max_steps=20
    # The replay plays the same episodes; a CPU computes float32 products alike at any
    # precision setting, so the returns are the same.
    if jax.default_backend() == "cpu":
        assert row["new_return_mean_default"] == row["new_return_mean"]
    assert json.loads(out.read_text())["rows"] == payload["rows"]
    md = out.with_suffix(".md").read_text()
    assert "| inverted_pendulum" in md and "mean return, precision=default" in md
    capsys.readouterr()
