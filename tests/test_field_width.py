"""The batch-width choice (docs/protocol.md section 6; bench/field_width.py) on synthetic
result files: each seed's value is eant2_jax's test return at TensorNEAT's wall time, the
ranks, the tie-break and the refusals."""

from __future__ import annotations

import json
import math

import pytest

from bench import field_width as fw
from bench.__main__ import main as bench_main
from bench.common import BenchInputError


def _curve(points):
    return [
        {"wall_s": w, "evaluations": 1000 * i, "test_return": r, "champion": "x"}
        for i, (w, r) in enumerate(points)
    ]


def _payload(env, name, eant2, tn_wall=100.0, device="H100", seeds=fw.SEEDS):
    width, iters = fw.CANDIDATES[name]
    args = {
        "envs": [env],
        "first_seed": 100,
        "seeds": 3,
        "width": width,
        "max_iters": iters[env],
        "budget": None,
    }
    recs = [
        {
            "env": env,
            "seed": s,
            "judged": {
                "eant2": {"curve": _curve(eant2[k])},
                "tensorneat": {"curve": _curve([(tn_wall / 2, 5.0), (tn_wall, 9.0)])},
            },
        }
        for k, s in enumerate(seeds)
    ]
    return {
        "protocol": True,
        "trial": True,
        "args": args,
        "seeds": recs,
        "environment": {"device_kind": device},
    }


def _write(folder, env, name, medians, **kw):
    # Per seed: one champion before TensorNEAT's wall time (the value) and a better one
    # after it, which must not count.
    eant2 = [[(10.0, m), (100.0, m), (150.0, m + 1000)] for m in medians]
    (folder / f"{env}-{name}.json").write_text(json.dumps(_payload(env, name, eant2, **kw)))


def test_return_at_takes_the_last_champion_by_that_wall_time():
    curve = _curve([(10.0, 1.0), (20.0, 3.0), (30.0, 2.0)])
    assert fw.return_at(curve, 25.0) == 3.0
    assert fw.return_at(curve, 30.0) == 2.0  # the last one, not the best one
    assert fw.return_at(curve, 5.0) == -math.inf  # no champion yet


def test_ranks_sums_and_the_winner(tmp_path):
    # hopper: w4096 best, w1024 and frozen equal (shared rank 2.5); halfcheetah: w1024 best.
    for name, m in {"frozen": 5, "w1024": 5, "w4096": 9, "w10000": 1}.items():
        _write(tmp_path, "hopper", name, [m, m + 1, m - 1])
    for name, m in {"frozen": 4, "w1024": 8, "w4096": 2, "w10000": 6}.items():
        _write(tmp_path, "halfcheetah", name, [m, m, m])
    c = fw.choose(tmp_path)
    assert c["envs"]["hopper"]["frozen"]["rank"] == c["envs"]["hopper"]["w1024"]["rank"] == 2.5
    assert c["envs"]["hopper"]["w4096"]["values"] == [9.0, 10.0, 8.0]
    assert c["summed_rank"] == {"frozen": 5.5, "w1024": 3.5, "w4096": 5.0, "w10000": 6.0}
    assert (c["winner"], c["width"], c["missing"]) == ("w1024", 1024, [])
    assert "Chosen: **w1024**" in fw.render(c)


def test_equal_sums_go_to_the_smaller_width_frozen_first(tmp_path):
    for env in fw.ENVS:
        for name in fw.CANDIDATES:
            _write(tmp_path, env, name, [7, 7, 7])
    c = fw.choose(tmp_path)
    assert set(c["summed_rank"].values()) == {5.0} and c["winner"] == "frozen"
    (tmp_path / "hopper-frozen.json").unlink()
    _write(tmp_path, "hopper", "frozen", [1, 1, 1])
    assert fw.choose(tmp_path)["winner"] == "w1024"


def test_nothing_is_decided_while_a_run_is_missing_or_going(tmp_path):
    _write(tmp_path, "hopper", "frozen", [1, 2, 3])
    going = _payload("hopper", "w1024", [[(1.0, 2.0)]] * 2, seeds=[100, 101])
    (tmp_path / "hopper-w1024.json").write_text(json.dumps(going))
    c = fw.choose(tmp_path)
    assert c["winner"] is None and c["envs"]["hopper"]["frozen"]["rank"] == 1
    assert "hopper-w1024.json (seeds judged: [100, 101])" in c["missing"]
    assert "halfcheetah-w10000.json" in c["missing"] and len(c["missing"]) == 7
    assert "Not decided: missing hopper-w1024.json" in fw.render(c)


@pytest.mark.parametrize(
    "change,phrase",
    [
        (lambda p: p["args"].update(width=2048), "width is 2048, section 6 says 1024"),
        (lambda p: p["args"].update(max_iters=5), "max_iters is 5, section 6 says 3"),
        (lambda p: p["args"].update(first_seed=0), "first_seed is 0, section 6 says 100"),
        (lambda p: p.update(protocol=False), "not a `--protocol` run"),
        (lambda p: p.pop("args"), "no 'args' object"),
        (lambda p: p["seeds"][0].update(seed=7), "judged seeds [7, 101, 102]"),
    ],
)
def test_a_file_of_other_settings_is_refused_with_the_difference(tmp_path, change, phrase):
    payload = _payload("hopper", "w1024", [[(1.0, 2.0)]] * 3)
    change(payload)
    (tmp_path / "hopper-w1024.json").write_text(json.dumps(payload))
    with pytest.raises(BenchInputError, match="hopper-w1024.json") as e:
        fw.choose(tmp_path)
    assert phrase in str(e.value)


def test_another_device_kind_or_no_folder_is_refused(tmp_path, capsys):
    _write(tmp_path, "hopper", "frozen", [1, 2, 3])
    _write(tmp_path, "hopper", "w1024", [1, 2, 3], device="H200")
    with pytest.raises(BenchInputError, match="more than one device kind"):
        fw.choose(tmp_path)
    assert bench_main(["width", "--dir", str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_the_command_prints_and_writes_json_without_overwriting(tmp_path, capsys):
    _write(tmp_path, "hopper", "frozen", [1, 2, 3])
    going = _payload("hopper", "w1024", [[(500.0, 2.0)]] * 3)  # no champion by TN's time
    (tmp_path / "hopper-w1024.json").write_text(json.dumps(going))
    out = tmp_path / "choice.json"
    assert bench_main(["width", "--dir", str(tmp_path), "--out", str(out)]) == 0
    saved = json.loads(out.read_text())
    assert saved["envs"]["hopper"]["w1024"]["values"] == [None] * 3  # -inf written as null
    assert "| hopper | frozen | 1, 2, 3 | 2 | 1 |" in capsys.readouterr().out
    assert bench_main(["width", "--dir", str(tmp_path), "--out", str(out)]) == 2
