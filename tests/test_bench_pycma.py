"""The pycma + NumPy reference benchmark: its NumPy servo cost equals the JAX task's cost."""

import pytest

pytestmark = pytest.mark.slow


def test_pycma_bench_quick_numpy_cost_matches(tmp_path):
    from bench import bench_pycma

    payload = bench_pycma.main(["--quick", "--genes", "20", "--out", str(tmp_path / "p.json")])
    row = payload["rows"][0]
    # float64 NumPy vs float32 JAX on the same candidates: rounding only.
    assert row["max_rel_err"] < 1e-5
    assert row["pycma_numpy_ms"] > 0 and row["engine_ms"] > 0
