"""The throughput benchmark suite (issue 41): a --quick run of the eant2_jax side on brax
hopper (spring backend; the test extra installs brax) and its one-line input errors."""

from __future__ import annotations

import json
import math

import pytest

from bench import __main__ as bench_main
from bench import bench_throughput
from bench.common import BenchInputError

# Compiling a brax episode three times (the widest batch's lengths, then each width's
# cost) takes over a minute on a 2-core CPU.


@pytest.mark.slow
def test_quick_run_reports_consistent_rates(tmp_path, capsys):
    out = tmp_path / "throughput.json"
    payload = bench_throughput.main(["--quick", "--envs", "hopper", "--out", str(out)])
    assert json.loads(out.read_text()) == payload
    cfg = payload["config"]
    assert (cfg["widths"], cfg["max_steps"], cfg["repeats"]) == ([4, 8], 20, 1)
    assert payload["commit"] and payload["environment"]["date_utc"]
    rows = payload["rows"]
    assert [(r["env"], r["method"], r["width"]) for r in rows] == [
        ("hopper", "eant2_jax", 4),
        ("hopper", "eant2_jax", 8),
    ]
    for r in rows:
        w = r["width"]
        assert r["episodes"] == w  # the field's brax evaluation: one episode per network
        for key in ("compile_s", "batch_s", "episodes_per_s", "steps_per_s",
                    "computed_steps_per_s"):  # fmt: skip
            assert math.isfinite(r[key]) and r[key] > 0, key
        assert r["episodes_per_s"] == pytest.approx(w / r["batch_s"], rel=1e-12)
        assert r["steps_per_s"] == pytest.approx(r["steps_lived"] / r["batch_s"], rel=1e-12)
        # Lived steps are at most what the device stepped, which is at most a whole block
        # (min(chunk, max_steps) = 20 steps) per episode here.
        assert w <= r["steps_lived"] <= r["steps_computed"] <= w * 20
        assert 1 <= r["mean_length"] <= r["max_length"] <= 20
        assert r["mean_length"] == pytest.approx(r["steps_lived"] / w)
        assert r["hidden_mean"] > 0 and r["genes_mean"] >= 36  # hopper: 3 x (11 + 1) minimal
        assert r["batch_s"] == min(r["times_s"]) == r["batch_min_s"]  # one repeat
    # The first 4 networks of the width-8 batch are the width-4 batch: its lived steps
    # are a part of the wider batch's.
    assert rows[0]["steps_lived"] <= rows[1]["steps_lived"]
    md = out.with_suffix(".md").read_text()
    assert "| hopper | eant2_jax | 4 |" in md and "network-episodes/s" in md
    assert payload["commit"] in md and "Early termination: Neither evaluator" in md
    capsys.readouterr()


@pytest.mark.parametrize("option", ["--widths", "--tn-pops"])
@pytest.mark.parametrize("value", ["0", "-3"])
def test_bad_width_is_one_clear_error(tmp_path, capsys, option, value):
    out = tmp_path / "t.json"
    with pytest.raises(BenchInputError, match=f"^{option} must be positive integers, got "):
        bench_throughput.main(["--quick", option, "4", value, "--out", str(out)])
    assert bench_main.main(["throughput", option, value, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"python -m bench throughput: error: {option} must be positive integers, "
                   f"got {value}"]  # fmt: skip
    assert not out.exists()
