"""Smoke test of the determinism benchmark (tiny sizes, CPU): both parts run and report."""

import json

import pytest

pytestmark = pytest.mark.slow


def test_determinism_bench_quick(tmp_path):
    from bench import bench_determinism

    out = tmp_path / "det.json"
    bench_determinism.main(["--quick", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    it = [r for r in rows if r["part"] == "iteration"]
    assert [r["deterministic"] for r in it] == [False, True]
    for r in it:  # --quick times the engine without a pruner only (one compile per process)
        assert "covariance" not in r
        assert r["none"]["iteration_ms"] > 0 and r["none"]["genes"] >= 30
    # On a CPU the flag changes nothing: the same chunk gives the same best cost.
    assert it[0]["none"]["best"] == it[1]["none"]["best"]
    rep = [r for r in rows if r["part"] == "repeat"]
    order = [(r["deterministic"], r["run"]) for r in rep]
    assert order == [(True, 1), (True, 2), (False, 1), (False, 2)]
    # CPU programs repeat exactly, whatever the flag.
    assert all(r["same_as_run_1"] for r in rep)
    assert all(len(r["best_costs"]) == 2 for r in rep)  # generations 0 and 1
    # Each row names its last padding bucket (neurons, genes, sweeps), equal across repeats.
    assert all(len(r["bucket"]) == 3 and r["bucket"] == rep[0]["bucket"] for r in rep)
    md = out.with_suffix(".md").read_text()
    assert "| this | deterministic |" in md and "off (EANT2_GPU_DETERMINISTIC=0)" in md


def test_unknown_part_is_one_error(tmp_path):
    from bench import bench_determinism
    from bench.common import BenchInputError

    with pytest.raises(ValueError, match=r"unknown part\(s\) \['fast'\]"):
        bench_determinism.main(["--quick", "--parts", "fast", "--out", str(tmp_path / "d.json")])
    with pytest.raises(BenchInputError, match="--pruners must include none"):
        bench_determinism.main(["--pruners", "covariance", "--out", str(tmp_path / "d.json")])
