"""Smoke test of bench/bench_forward.py in --quick mode: it runs and writes sane results."""

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

from bench import bench_forward  # noqa: E402
from bench.common import random_population  # noqa: E402
from eant2_jax import evaluate, interpret  # noqa: E402

ROW_FIELDS = {
    "config",
    "T",
    "M",
    "G",
    "genes_mean",
    "neurons_mean",
    "bucket_neurons",
    "bucket_genes",
    "sweeps",
    "pad",
    "network_steps",
    "first_call_s",
    "median_s",
    "steps_per_s",
    "mlp_first_call_s",
    "mlp_median_s",
    "mlp_steps_per_s",
}


@pytest.mark.slow
def test_quick_run_writes_json_and_markdown(tmp_path, capsys):
    out = tmp_path / "forward.json"
    bench_forward.main(["--quick", "--genes", "8", "16", "--out", str(out)])
    payload = json.loads(out.read_text())
    for key in ("device_kind", "platform", "jax_version", "config", "rows"):
        assert key in payload, key
    rows = payload["rows"]
    # 2 shapes x 2 sizes, the larger size also with 2x padding.
    assert len(rows) == 6
    assert {r["pad"] for r in rows} == {"fit", "2x"}
    for r in rows:
        assert ROW_FIELDS <= set(r), ROW_FIELDS - set(r)
        assert r["network_steps"] == r["G"] * r["T"] * r["M"]
        assert len(r["times_s"]) >= 5
        for key in ("first_call_s", "median_s", "steps_per_s", "mlp_median_s", "mlp_steps_per_s"):
            assert np.isfinite(r[key]) and r[key] > 0, (key, r[key])
        assert r["first_call_s"] >= r["min_s"]
    md = out.with_suffix(".md").read_text()
    table = [line for line in md.splitlines() if line.startswith("| ")]
    assert len(table) == len(rows) + 2  # header, separator, one line per row
    assert "M steps/s" in capsys.readouterr().out


@pytest.mark.slow
def test_random_genomes_are_deterministic_and_evaluate_like_the_reference():
    a = random_population(7, 3, 80)
    b = random_population(7, 3, 80)
    assert a == b
    assert all(80 <= g.n_params <= 85 for g in a)
    x = np.random.default_rng(0).normal(size=(4, 3, 10))
    got = np.asarray(evaluate(a, x))
    want = np.stack([interpret(g, x) for g in a])
    # float32 kernel vs float64 reference, depth <= ~10 tanh layers of O(1) values.
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
