"""Smoke test of the generation benchmark (tiny sizes): it runs and reports sane numbers."""

import json

import pytest

pytestmark = pytest.mark.slow


def test_generation_bench_quick(tmp_path):
    from bench import bench_generation

    out = tmp_path / "gen.json"
    # The generations without a pruner: the pruning part times the pruner's attempt itself,
    # and the generations' engine compiles sooner without one.
    payload = bench_generation.main(
        ["--quick", "--parts", "generation,pruning", "--pruner", "none", "--out", str(out)]
    )
    saved = json.loads(out.read_text())
    assert saved["environment"]["platform"] == payload["environment"]["platform"]
    gens = payload["generation"]
    assert [r["generation"] for r in gens] == [0, 1]
    assert all(r["seconds"] > 0 and r["new_evaluations"] > 0 for r in gens)
    assert all(r["attempt_ms"] > 0 and r["iteration_ms"] > 0 for r in payload["pruning"])
    md = out.with_suffix(".md").read_text()
    assert md.startswith("EANT2 generations, pruning and scaling on **")
    assert "### Pruning attempt vs one CMA-ES iteration" in md


def test_generation_bench_eigh_part(tmp_path):
    """The ``eigh`` part times the engine's batched decomposition for every (S, P) asked."""
    from bench import bench_generation

    out = tmp_path / "eigh.json"
    payload = bench_generation.main(
        ["--parts", "eigh", "--eigh-structures", "1", "3", "--eigh-genes", "8", "20",
         "--repeats", "2", "--out", str(out)]
    )  # fmt: skip
    rows = payload["eigh"]
    assert [(r["structures"], r["P"], r["valid"]) for r in rows] == [
        (1, 8, 6), (3, 8, 6), (1, 20, 15), (3, 20, 15)
    ]  # fmt: skip
    for r in rows:
        assert 0 < r["call_ms"] and r["per_matrix_us"] == pytest.approx(
            1e3 * r["call_ms"] / r["structures"]
        )
    assert "### One batched decomposition of S covariances" in out.with_suffix(".md").read_text()
