"""Smoke test of the many-runs benchmark (tiny sizes): every mode runs the same seeds."""

import json

import pytest

pytestmark = pytest.mark.slow


def test_runs_bench_quick(tmp_path):
    from bench import bench_runs

    out = tmp_path / "runs.json"
    payload = bench_runs.main(["--quick", "--out", str(out)])
    rows = {r["mode"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"lockstep", "threads", "sequential"}
    for r in rows.values():
        assert len(r["best"]) == 2 and r["total_s"] > r["runs_s"] > 0 and r["compiles"] > 0
    # On a CPU threads are one at a time: the same runs as sequential, to the bit.
    assert rows["threads"]["best"] == rows["sequential"]["best"]
    assert rows["threads"]["evaluations"] == rows["sequential"]["evaluations"]
    assert payload["rows"][0]["mode"] == "lockstep"
    assert "| lockstep |" in out.with_suffix(".md").read_text()


def test_unknown_mode_is_one_error(tmp_path):
    from bench import bench_runs

    with pytest.raises(ValueError, match="unknown mode 'fast'"):
        bench_runs.main(["--quick", "--modes", "fast", "--out", str(tmp_path / "r.json")])
