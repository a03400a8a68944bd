"""The field protocol's ``--normalize`` trial (docs/protocol.md section 8): eant2_jax's inputs
normalised by frozen random-policy statistics reach eant2_jax's training task and the judging
task, and nothing of TensorNEAT's. The normalisation itself is tested in test_obs_norm.py, the
conversion of TensorNEAT's networks to a normalised task's inputs in test_field_protocol.py."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from fieldchoice import check_trial_option, protocol_args, write_result

from bench import field_protocol, field_workers
from bench.common import BenchInputError
from bench.field_settings import ENVS, NORM_EPISODES, NORM_SEED


@pytest.fixture
def made(monkeypatch):
    """Each ``tasks.make`` call's ``(name, options)``; the task itself is not built."""
    from eant2_jax import tasks

    calls: list[tuple[str, dict]] = []
    monkeypatch.setattr(tasks, "make", lambda name, **kw: calls.append((name, kw)) or name)
    return calls


def _args(tmp_path, *extra: str):
    return protocol_args(tmp_path, "halfcheetah", *extra)


def test_the_protocol_task_takes_the_frozen_convention_or_the_trials(made):
    """Without the option each family's frozen convention (gymnax's ``normalize``, brax raw,
    the same call as before the option); with ``random`` the section's episodes and seed."""
    hc, cp = ENVS["halfcheetah"], ENVS["cartpole"]
    field_workers.protocol_task(hc, 1)
    field_workers.protocol_task(hc, 1, "random")
    field_workers.protocol_task(cp, 5)
    field_workers.protocol_task(cp, 5, "none")
    base = {"episodes": 1, "max_steps": 1000, "backend": "spring"}
    assert made[0] == ("brax:halfcheetah", base)
    assert made[1] == ("brax:halfcheetah", {**base, "normalize": "random",
                                            "norm_episodes": NORM_EPISODES,
                                            "norm_seed": NORM_SEED})  # fmt: skip
    assert made[2] == ("gymnax:CartPole-v1", {"episodes": 5, "max_steps": 500,
                                              "normalize": "bounds"})  # fmt: skip
    assert made[3][1]["normalize"] == "none" and (NORM_EPISODES, NORM_SEED) == (1000, 0)


def test_normalize_is_a_trial_option_of_eant2_alone(tmp_path):
    check_trial_option(tmp_path, "halfcheetah", "--normalize", "random", "bounds")


def test_the_judge_scores_both_methods_on_the_task_eant2_trained_on(tmp_path, monkeypatch):
    """The judging process gets the trial's convention and builds its one task with it."""
    run = tmp_path / "halfcheetah-s100-eant2.json"
    run.write_text(json.dumps({"method": "eant2", "curve": [], "candidates": {}}))
    out = tmp_path / "judged.json"
    for extra, want in (((), None), (("--normalize", "random"), "random")):
        argv = field_protocol.judge_argv(_args(tmp_path, *extra), "halfcheetah", out, [25000],
                                         [run])  # fmt: skip
        built: list[str | None] = []

        def task(env, episodes, normalize=None, built=built):
            built.append(normalize)

        monkeypatch.setattr(field_workers, "protocol_task", task)
        assert field_workers.main(argv[argv.index("judge") :]) == 0
        assert built == [want] and json.loads(out.read_text()) == {}


def _write_choice(folder, returns: dict[tuple[str, str], list[float]], change=None) -> None:
    """Section 8's result files with eant2_jax's test returns at the last budget per seed
    (an earlier budget's return beside it, which the rule must not read)."""
    from bench import field_normalize as fn

    for (env, name), values in returns.items():
        judged = [{"budgets": [{"budget": 100_000, "test_return": v},
                               {"budget": 25_000, "test_return": -1e9}]}
                  for v in values]  # fmt: skip
        write_result(folder, env, name, {"normalize": fn.CANDIDATES[name]}, judged,
                     (change or {}).get((env, name)))  # fmt: skip


def test_the_normalisation_rule_adopts_only_a_median_gain_on_both(tmp_path, capsys):
    from bench import field_normalize as fn

    raw = [1000.0, 2000.0, 3000.0]
    gain = {
        ("hopper", "raw"): raw,
        ("hopper", "random"): [1100.0, 1900.0, 3300.0],
        ("halfcheetah", "raw"): raw,
        ("halfcheetah", "random"): [900.0, 2500.0, 3050.0],
    }
    _write_choice(tmp_path / "a", gain)
    choice = fn.choose(tmp_path / "a")
    assert choice["envs"]["hopper"]["difference"] == [100.0, -100.0, 300.0]
    assert (choice["envs"]["hopper"]["median"], choice["envs"]["halfcheetah"]["median"]) == (
        100.0, 50.0)  # fmt: skip
    assert choice["adopted"] is True and "**adopted**" in fn.render(choice)
    # A median of exactly 0 on one environment: not above 0, the raw inputs stay.
    _write_choice(tmp_path / "b", {**gain, ("hopper", "random"): [1100.0, 2000.0, 2900.0]})
    choice = fn.choose(tmp_path / "b")
    assert choice["adopted"] is False and "raw inputs stay" in fn.render(choice)
    # A missing file or seed: nothing decided, what is missing named.
    _write_choice(tmp_path / "c", {k: v for k, v in gain.items() if k != ("hopper", "raw")})
    _write_choice(tmp_path / "c", {("halfcheetah", "random"): [1.0, 2500.0]})
    choice = fn.choose(tmp_path / "c")
    assert choice["adopted"] is None and choice["missing"] == [
        "hopper-raw.json", "halfcheetah-random.json (seeds judged: [100, 101])"]  # fmt: skip
    assert "Not decided: missing hopper-raw.json" in fn.render(choice)
    assert choice["envs"]["halfcheetah"]["known"] == {100: -999.0, 101: 500.0}  # still open
    fn.main(["--dir", str(tmp_path / "a"), "--out", str(tmp_path / "a.json")])
    assert json.loads((tmp_path / "a.json").read_text())["adopted"] is True
    with pytest.raises(BenchInputError, match="exists; not written over"):
        fn.main(["--dir", str(tmp_path / "a"), "--out", str(tmp_path / "a.json")])
    capsys.readouterr()
    # halfcheetah's two judged differences (-999, -1998) already fix its median at or below
    # 0: decided (raw stays) while hopper's file and halfcheetah's third seed are missing.
    _write_choice(tmp_path / "d", {("halfcheetah", "raw"): raw[:2],
                                   ("halfcheetah", "random"): [1.0, 2.0]})  # fmt: skip
    choice = fn.choose(tmp_path / "d")
    assert choice["envs"]["halfcheetah"]["known"] == {100: -999.0, 101: -1998.0}
    assert choice["adopted"] is False and choice["envs"]["halfcheetah"]["settled"] is False
    text = fn.render(choice)
    assert "-999 (seed 100), -1998 (seed 101) | <= 0 whatever the rest |" in text
    assert "cannot change the outcome" in text and "**not adopted" in text
    # One gain and one loss known: open; two gains on both: adopted before the third seeds.
    _write_choice(
        tmp_path / "e",
        {
            ("hopper", "raw"): raw[:2],
            ("hopper", "random"): [1.0, 2500.0],
            ("halfcheetah", "raw"): raw,
            ("halfcheetah", "random"): raw,
        },
    )
    assert fn.choose(tmp_path / "e")["adopted"] is False  # halfcheetah: three ties, at most 0
    _write_choice(tmp_path / "f", {("hopper", "raw"): raw[:2], ("hopper", "random"): [1.0, 2500.0],
                                   ("halfcheetah", "raw"): raw[:2],
                                   ("halfcheetah", "random"): [1100.0, 2100.0]})  # fmt: skip
    choice = fn.choose(tmp_path / "f")
    assert choice["adopted"] is None and choice["envs"]["hopper"]["settled"] is None
    assert choice["envs"]["halfcheetah"]["settled"] is True
    _write_choice(tmp_path / "f", {("hopper", "random"): [1001.0, 2500.0]})
    assert fn.choose(tmp_path / "f")["adopted"] is True


@pytest.mark.parametrize(
    "known, want",
    [
        ([], None),
        ([1.0], None),
        ([1.0, -1.0], None),
        ([1.0, 2.0], True),
        ([0.0, -3.0], False),
        ([1.0, 0.0], None),
        ([1.0, -1.0, 0.5], True),
        ([1.0, -1.0, 0.0], False),
    ],
)
def test_settled_is_the_sign_of_the_median_of_three_whatever_is_missing(known, want):
    from bench import field_normalize as fn

    assert fn.settled(known) is want
    rest = [-1e9, 0.0, 1e9]  # every way the missing seeds could fall gives the same sign
    outcomes = {bool(np.median(known + list(fill)) > 0)
                for fill in itertools.product(rest, repeat=3 - len(known))}  # fmt: skip
    assert (outcomes == {want}) if want is not None else (outcomes == {True, False})


def test_a_file_of_other_options_or_another_device_is_refused(tmp_path):
    from bench import field_normalize as fn

    three = [1.0, 2.0, 3.0]
    files = {(e, n): three for e in fn.ENVS for n in fn.CANDIDATES}
    wrong = {("hopper", "random"): {"args": {"envs": ["hopper"], "methods": ["eant2"],
                                             "first_seed": 100, "seeds": 3}}}  # fmt: skip
    _write_choice(tmp_path / "a", files, wrong)
    with pytest.raises(BenchInputError, match="normalize is None, section 8 says 'random'"):
        fn.choose(tmp_path / "a")
    other = {("halfcheetah", "raw"): {"environment": {"device_kind": "H100"}}}
    _write_choice(tmp_path / "b", files, other)
    with pytest.raises(BenchInputError, match="more than one device kind"):
        fn.choose(tmp_path / "b")
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "hopper-raw.json").write_text("{not json")
    with pytest.raises(BenchInputError, match="not a readable JSON result file"):
        fn.choose(tmp_path / "c")
    with pytest.raises(BenchInputError, match="no such folder"):
        fn.choose(tmp_path / "none")
