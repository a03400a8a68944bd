"""The field protocol's ``--spare-rows`` trial and its choice (docs/protocol.md section 9):
the option reaches eant2_jax's run configuration and nothing of TensorNEAT's, and ``python
-m bench spare`` applies the section's rule, checked against the rule written out here. The
restarts themselves are tested in test_spare_rows.py."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from fieldchoice import check_trial_option, protocol_args, write_result

from bench import field_protocol, field_settings, field_workers
from bench import field_spare as fs
from bench.common import BenchInputError
from eant2_jax import configvalues


def test_spare_rows_is_a_trial_option_of_eant2_alone(tmp_path):
    assert field_settings.SPARE_ROWS == configvalues.SPARE_ROWS
    check_trial_option(tmp_path, "hopper", "--spare-rows", "restarts", "copies")


def test_the_run_configuration_takes_the_trial_s_spare_rows():
    env = field_settings.ENVS["halfcheetah"]
    assert field_workers.eant2_config(env, budget=1000).exploit.spare_rows == "idle"
    config = field_workers.eant2_config(env, budget=1000, spare_rows="restarts")
    assert config.exploit.spare_rows == "restarts"
    # Everything else is the frozen settings.
    frozen = field_workers.eant2_config(env, budget=1000)
    assert dataclasses.replace(config, exploit=frozen.exploit) == frozen
    assert frozen.exploit.replace(spare_rows="restarts") == config.exploit


def test_the_training_process_passes_the_option_to_the_run(tmp_path, monkeypatch):
    """The worker's command line (`field_protocol`'s argv) reaches `train_eant2` intact."""
    got = {}
    monkeypatch.setattr(field_workers, "train_eant2", lambda env, **kw: got.update(kw))
    args = protocol_args(tmp_path, "hopper", "--spare-rows", "restarts")
    argv = field_protocol.METHODS["eant2"]("eant2", args, "hopper", 100, tmp_path / "r.json")
    argv = argv[argv.index("train") :] + ["--t0", "0"]
    assert field_workers.main(argv) == 0
    assert got["spare_rows"] == "restarts" and got["seed"] == 100


def _curve(points):
    return [{"evaluations": 1000 * (i + 1), "wall_s": w, "test_return": r}
            for i, (w, r) in enumerate(points)]  # fmt: skip


def _write_choice(folder, runs: dict, change=None) -> None:
    """Section 9's result files: per (env, name) one ``(return at 100,000, curve)`` per seed
    (an earlier budget's return beside it, which the rule must not read)."""
    for (env, name), values in runs.items():
        judged = [{"curve": _curve(curve), "budgets": [
            {"budget": 100_000, "test_return": v}, {"budget": 25_000, "test_return": -1e9}]}
            for v, curve in values]  # fmt: skip
        # A call without the option does not record it.
        options = {"spare_rows": fs.CANDIDATES[name]} if fs.CANDIDATES[name] else {}
        write_result(folder, env, name, options, judged, (change or {}).get((env, name)),
                     device="H100")  # fmt: skip


def _plain_rule(runs) -> dict:
    """Section 9's rule written out: per env the median paired differences at 100,000
    evaluations and at the earlier of each seed's two last judged wall times."""
    out = {}
    for env in fs.ENVS:
        evals, wall = [], []
        for (va, ca), (vb, cb) in zip(runs[env, "idle"], runs[env, "restarts"], strict=True):
            evals.append(vb - va)
            t = min(max(w for w, _ in ca), max(w for w, _ in cb))
            at = [max(((w, r) for w, r in c if w <= t), default=(0, -math.inf))[1]
                  for c in (ca, cb)]  # fmt: skip
            wall.append(at[1] - at[0])
        out[env] = (float(np.median(evals)), float(np.median(wall)))
    return out


def _random_runs(rng):
    runs = {}
    for env in fs.ENVS:
        for name in fs.CANDIDATES:
            runs[env, name] = [
                (float(rng.integers(0, 5000)),
                 sorted((float(rng.uniform(10, 500)), float(rng.integers(0, 5000)))
                        for _ in range(int(rng.integers(1, 6)))))
                for _ in fs.SEEDS
            ]  # fmt: skip
    return runs


def test_the_spare_rows_rule_matches_the_rule_written_out(tmp_path):
    rng = np.random.default_rng(9)
    seen = set()
    for k in range(30):
        runs = _random_runs(rng)
        _write_choice(tmp_path / str(k), runs)
        choice = fs.choose(tmp_path / str(k))
        want = _plain_rule(runs)
        for env, (evals, wall) in want.items():
            row = choice["envs"][env]
            assert (row["evals_median"], row["wall_median"]) == (evals, wall)
        adopt = all(wall > 0 and evals >= 0 for evals, wall in want.values())
        assert choice["adopted"] is adopt
        seen.add(adopt)
    assert seen == {True, False}


def test_the_rule_needs_both_points_on_both_environments(tmp_path, capsys):
    fast = [(1000.0, [(100.0, 900.0), (200.0, 1500.0)])] * 3  # 1,500 by 200 s
    slow = [(1000.0, [(150.0, 800.0), (300.0, 1000.0)])] * 3  # 800 by 200 s
    both = {(e, n): (fast if n == "restarts" else slow) for e in fs.ENVS for n in fs.CANDIDATES}
    _write_choice(tmp_path / "a", both)
    choice = fs.choose(tmp_path / "a")
    assert choice["envs"]["hopper"]["wall_s"] == [200.0] * 3
    assert choice["envs"]["hopper"]["wall_difference"] == [700.0] * 3
    assert choice["adopted"] is True and "**adopted**" in fs.render(choice)
    # Faster in wall time but worse at the evaluation count on one environment: not adopted.
    worse = [(900.0, c) for _, c in fast]
    _write_choice(tmp_path / "b", {**both, ("halfcheetah", "restarts"): worse})
    choice = fs.choose(tmp_path / "b")
    assert choice["adopted"] is False and "stay idle" in fs.render(choice)
    # A missing file or seed: nothing decided, what is missing named.
    _write_choice(tmp_path / "c", {("hopper", "idle"): slow, ("halfcheetah", "idle"): slow[:2]})
    choice = fs.choose(tmp_path / "c")
    assert choice["adopted"] is None and choice["missing"] == [
        "hopper-restarts.json", "halfcheetah-idle.json (seeds judged: [100, 101])",
        "halfcheetah-restarts.json"]  # fmt: skip
    assert "Not decided: missing hopper-restarts.json" in fs.render(choice)
    fs.main(["--dir", str(tmp_path / "a"), "--out", str(tmp_path / "a.json")])
    assert json.loads((tmp_path / "a.json").read_text())["adopted"] is True
    capsys.readouterr()


def test_a_file_of_other_options_is_refused(tmp_path):
    three = [(1.0, [(1.0, 1.0)])] * 3
    files = {(e, n): three for e in fs.ENVS for n in fs.CANDIDATES}
    normalized = {("hopper", "idle"): {"args": {"envs": ["hopper"], "methods": ["eant2"],
                                                "first_seed": 100, "seeds": 3,
                                                "normalize": "random"}}}  # fmt: skip
    _write_choice(tmp_path / "a", files, normalized)
    with pytest.raises(BenchInputError, match="normalize is 'random', section 9 says None"):
        fs.choose(tmp_path / "a")
    # Section 8's choice refuses a run with restarts as one of its candidates.
    from bench import field_normalize as fn

    folder = tmp_path / "b"
    folder.mkdir()
    args = {"envs": ["hopper"], "methods": ["eant2"], "first_seed": 100, "seeds": 3,
            "spare_rows": "restarts"}  # fmt: skip
    (folder / "hopper-raw.json").write_text(json.dumps({"protocol": True, "args": args}))
    with pytest.raises(BenchInputError, match="spare_rows is 'restarts', section 8 says None"):
        fn.choose(folder)
