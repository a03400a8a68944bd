"""The field benchmark (bench/bench_field.py): its bookkeeping on made-up runs, its input
checks, and a --quick eant2 run on gymnax CartPole in a fresh process (skipped without
gymnax). TensorNEAT itself is not installed here: its worker runs in the GPU bench."""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest

from bench import bench_field, field_runner
from bench.common import BenchInputError


def _run(method, curve, *, env="cartpole", seed=0, done=True, **extra):
    points = [{"evaluations": e, "wall_s": w, "test_return": r, "size": s} for e, w, r, s in curve]
    return {"method": method, "env": env, "seed": seed, "curve": points, "done": done, **extra}


def test_summary_compares_at_tensorneats_final_return_and_budget():
    eant2 = _run("eant2", [(100, 5.0, 50.0, 9), (300, 6.0, 420.0, 9), (900, 9.0, 500.0, 7)])
    tn = _run("tensorneat", [(1000, 20.0, 300.0, 30), (2000, 25.0, 410.0, 31)])
    (row,) = bench_field.summarise([eant2, tn])
    assert row["tensorneat_return"] == 410.0 and row["eant2_return"] == 500.0
    # eant2's first champion at or above 410 is the one at 300 evaluations (420).
    assert (row["eant2_evals_to_tn"], row["eant2_wall_to_tn_s"]) == (300, 6.0)
    # At TensorNEAT's 2000 evaluations eant2's last point within them is the one at 900.
    assert row["eant2_return_at_tn_evals"] == 500.0
    # TensorNEAT reached its own final return at its last point.
    assert (row["tn_wall_to_own_s"], row["tn_evals_to_own"]) == (25.0, 2000)
    assert (row["eant2_size"], row["tensorneat_size"]) == (7, 31)
    assert (row["eant2_status"], row["tensorneat_status"]) == ("ok", "ok")
    assert row["verdict"] == "win"
    # Later than TensorNEAT from process start: a loss on wall time alone.
    slow = _run("eant2", [(100, 5.0, 50.0, 9), (300, 26.0, 420.0, 9), (900, 29.0, 500.0, 7)])
    assert bench_field.summarise([slow, tn])[0]["verdict"] == "loss: wall"


def test_summary_says_never_reached_killed_and_not_run():
    eant2 = _run("eant2", [(100, 5.0, 10.0, 9)], done=False)
    tn = _run("tensorneat", [(1000, 20.0, 300.0, 30)], deadline=True)
    (row,) = bench_field.summarise([eant2, tn])
    assert row["eant2_evals_to_tn"] is None and row["eant2_wall_to_tn_s"] is None
    assert (row["eant2_status"], row["tensorneat_status"]) == ("killed", "deadline")
    assert row["verdict"] == "loss: return, wall"
    (alone,) = bench_field.summarise([_run("eant2", [(100, 5.0, 10.0, 9)], seed=3)])
    assert alone["tensorneat_status"] == "not run" and alone["eant2_evals_to_tn"] is None
    assert alone["verdict"] is None
    assert bench_field.first_reaching(eant2["curve"], -math.inf) == eant2["curve"][0]
    md = bench_field.render({"runs": [eant2, tn], "config": {"test_episodes": 20}})
    assert "| cartpole | 0 | 10 / 300 |" in md and "killed / deadline" in md


def test_tensorneat_size_counts_connections_and_non_input_biases():
    nodes = np.full((8, 5), np.nan)
    nodes[:5, 0] = np.arange(5)  # 3 inputs, 1 output, 1 hidden
    conns = np.full((10, 3), np.nan)
    conns[:4] = 1.0
    assert field_runner.tensorneat_size((nodes, conns), n_inputs=3) == 4 + 2


@pytest.mark.parametrize(
    "argv,phrase",
    [
        (["--methods", "tensorneat"], "--tensorneat"),
        (["--tensorneat", "/nonexistent"], "--tensorneat"),
        (["--methods", "eant2", "--seeds", "0"], "--seeds"),
        (["--methods", "eant2", "--budget", "0"], "--budget"),
    ],
)
def test_bad_arguments_are_one_clear_error(argv, phrase, tmp_path):
    with pytest.raises(BenchInputError, match=phrase):
        bench_field.main([*argv, "--out", str(tmp_path / "f.json")])
    assert not (tmp_path / "f.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("env", ["servo", "cartpole"])
def test_quick_eant2_run_in_a_fresh_process(env, tmp_path, capsys):
    if env == "cartpole" and importlib.util.find_spec("gymnax") is None:
        pytest.skip("gymnax not installed")
    out = tmp_path / "field.json"
    payload = bench_field.main(["--quick", "--envs", env, "--methods", "eant2", "--out", str(out)])
    (run,) = payload["runs"]
    assert run["done"] and not run.get("error") and run["env"] == env
    curve = run["curve"]
    evals = [p["evaluations"] for p in curve]
    assert evals == sorted(evals) and evals[-1] >= bench_field.QUICK["budget"]
    assert all(p["evaluations"] < bench_field.QUICK["budget"] for p in curve[:-1])
    walls = [p["wall_s"] for p in curve]
    assert walls == sorted(walls) and 0 < run["start_s"] < walls[0] <= run["process_s"]
    if env == "cartpole":  # CartPole-v1 returns are episode lengths, --quick's at most
        assert all(1 <= p["test_return"] <= bench_field.QUICK_MAX_STEPS for p in curve)
    else:  # deterministic: the test is the task's cost again
        for p in curve:
            assert p["test_return"] == pytest.approx(p["train_return"], rel=1e-5)
    assert json.loads(out.read_text())["runs"][0]["curve"] == curve
    assert f"| {env} | 0 |" in out.with_suffix(".md").read_text()
    capsys.readouterr()


def test_figure_draws_the_curves_and_never_replaces_a_file(tmp_path):
    """``python -m bench field figure``: one PNG from result files (a row per environment),
    refused over an existing file, and one clear error for a file that is not a result."""
    payload = {
        "environment": {"device_kind": "cpu", "date_utc": "2026-11-24T00:00:00Z"},
        "runs": [
            _run("eant2", [(100, 5.0, 50.0, 9), (900, 9.0, 500.0, 7)]),
            _run("tensorneat", [(1000, 20.0, 300.0, 30)]),
            _run("eant2", [(10, 1.0, -90.0, 20)], env="acrobot", seed=2),
        ],
    }
    results = tmp_path / "field.json"
    results.write_text(json.dumps(payload))
    out = tmp_path / "img" / "curves.png"
    bench_field.main(["figure", str(out), str(results)])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    before = out.read_bytes()
    with pytest.raises(BenchInputError, match="never replaces"):
        bench_field.main(["figure", str(out), str(results)])
    assert out.read_bytes() == before
    (tmp_path / "bad.json").write_text("{}")
    for bad, phrase in ((tmp_path / "bad.json", "with runs"), (tmp_path / "no.json", "readable")):
        with pytest.raises(BenchInputError, match=phrase):
            bench_field.main(["figure", str(tmp_path / "other.png"), str(bad)])
    with pytest.raises(BenchInputError, match="usage"):
        bench_field.main(["figure", str(tmp_path / "x.png")])
