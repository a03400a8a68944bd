"""The reproduction's arms (docs/protocol.md, section 1): named overrides from a fixed
registry, per-arm run counts, recorded in reproduce.json (checked against the registry on
resume) and in each run directory's config.json."""

from __future__ import annotations

import json

import pytest
from test_manifest import good

from eant2_jax.app import manifest as mf
from eant2_jax.app.arms import PROTOCOL_ARMS, RULE, arm_config, arm_overrides, parse_arms
from eant2_jax.config import EANT2Config, ExploitConfig

DEFAULT = ExploitConfig()


def _rule(config: EANT2Config) -> dict:
    return {f: getattr(config.exploit, f) for f in RULE}


def test_each_protocol_arm_differs_from_default_in_its_one_field():
    # A base that sets the rule otherwise: the protocol's arms fix it whatever the base says.
    base = EANT2Config(exploit=ExploitConfig(prune_window=7, prune_refit=3))
    default = _rule(arm_config(base, "default"))
    assert default == {f: getattr(DEFAULT, f) for f in RULE} | {"pruner": "covariance"}
    changed = {
        "no-refit": {"prune_refit": 0},
        "mean-reference": {"prune_reference": "mean"},
        "trigger-only": {"prune_at_stop": False},
        "window-250": {"prune_window": 250},
        "random": {"pruner": "random"},
        "magnitude": {"pruner": "magnitude"},
        "obs": {"pruner": "obs"},
        "obd": {"pruner": "obd"},
        "snr": {"pruner": "snr"},
        "literal": {"prune_refit": 0, "prune_reference": "mean", "prune_at_stop": False},
    }
    for arm, change in changed.items():
        assert _rule(arm_config(base, arm)) == default | change, arm
    assert arm_config(base, "none").exploit.pruner == "none"
    assert set(changed) | {"none", "default"} == set(PROTOCOL_ARMS)
    # Everything but the pruning fields is the base's.
    other = arm_config(base, "window-250").exploit
    assert other.popsize == base.exploit.popsize and other.max_iters == base.exploit.max_iters
    # The older names keep their meaning: the pruner (and the literal rule) on the base.
    assert arm_overrides("covariance") == {"pruner": "covariance"}
    assert arm_config(base, "covariance").exploit.prune_window == 7


@pytest.mark.parametrize("bad", ["lottery", "default-literal", "none-literal", "", "x" * 100])
def test_unknown_arms_are_one_line(bad):
    with pytest.raises(ValueError, match="unknown arm") as e:
        arm_overrides(bad)
    assert "\n" not in str(e.value)


def test_parse_arms():
    text = "none:20,literal:20,default:20,no-refit:10, random ,snr:3"
    assert parse_arms(text, 10) == [
        ("none", 20), ("literal", 20), ("default", 20), ("no-refit", 10), ("random", 10),
        ("snr", 3),
    ]  # fmt: skip
    assert parse_arms("default", 5) == [("default", 5), ("none", 5)]
    for bad, message in [
        ("default:0", "positive integer"),
        ("default:x", "positive integer"),
        ("default:-2", "positive integer"),
        ("default,default:3", "given twice"),
        ("lottery:3", "unknown arm"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_arms(bad, 10)


def _protocol_manifest() -> dict:
    arms = ["literal", "default", "no-refit", "none"]
    return {
        **good(),
        "pruners": arms[:-1],
        "arm_runs": {"literal": 3, "default": 3, "no-refit": 2, "none": 3},
        "arm_overrides": {a: arm_overrides(a) for a in arms},
    }


def test_a_manifest_with_arm_runs_and_overrides_is_read_back():
    s = mf.check_manifest(_protocol_manifest(), "m")
    assert s["arm_runs"] == {"literal": 3, "default": 3, "no-refit": 2, "none": 3}
    assert mf.check_manifest(good(), "m")["arm_runs"] == {"covariance": 2, "none": 2}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"arm_runs": []}, "arm_runs must be an object"),
        ({"arm_runs": {"obs": 2}}, "arm_runs names 'obs', not an arm"),
        ({"arm_runs": {"default": 0}}, r"arm_runs.default: runs must be in \[1, 10000\]"),
        ({"arm_runs": {"default": "2"}}, "arm_runs.default: runs must be an integer"),
        ({"seed": 2**32 - 2}, r"seed \+ runs must be at most 2\*\*32"),
        ({"arm_overrides": {"default": {}}}, "arm_overrides must be an object with one entry"),
        (
            {
                "arm_overrides": {
                    **_protocol_manifest()["arm_overrides"],
                    "default": {"pruner": "x"},
                }
            },
            "arm_overrides.default is .* but this version's arm default sets",
        ),
    ],
)
def test_arm_fields_are_checked(change, message):
    with pytest.raises(mf.ManifestError, match=f"^m: .*{message}") as e:
        mf.check_manifest({**_protocol_manifest(), **change}, "m")
    assert "\n" not in str(e.value)


@pytest.mark.slow
def test_reproduce_runs_each_arm_its_count_and_records_its_config(tmp_path):
    """Arms of different run counts on XOR (one generation, tiny budgets): the seeds each
    arm takes, its exact configuration in reproduce.json and in every run directory, and
    the report's verdicts."""
    from eant2_jax import tasks
    from eant2_jax.app.experiments import reproduce

    base = EANT2Config(population=3, exploit=ExploitConfig(max_iters=20, prune_window=5))
    out = tmp_path / "rep"
    path = reproduce(
        tasks.make("xor"), out, task_meta={"task": "xor", "task_options": {}}, runs=2,
        generations=1, pruners=("default", "no-refit"), arm_runs={"no-refit": 1}, config=base,
        seed=2000, devices=1, condition=False,
    )  # fmt: skip
    names = sorted(p.name for p in out.iterdir() if p.is_dir() and p.name != "report")
    assert names == ["default-s2000", "default-s2001", "no-refit-s2000", "none-s2000",
                     "none-s2001"]  # fmt: skip
    m = json.loads((out / mf.MANIFEST).read_text())
    assert m["arm_runs"] == {"default": 2, "no-refit": 1, "none": 2}
    assert m["arm_overrides"]["no-refit"] == arm_overrides("no-refit")
    for name in names:
        arm = name.rsplit("-s", 1)[0]
        config = json.loads((out / name / "config.json").read_text())
        assert config["arm"] == arm and config["key"] == [0, int(name.rsplit("-s", 1)[1])]
        want = arm_config(base, arm).exploit
        for field, value in arm_overrides(arm).items():
            assert config["config"]["exploit"][field] == value == getattr(want, field)
    text = path.read_text()
    assert "## Verdicts (docs/protocol.md)" in text
    assert "| default | none |" in text
    verdicts = json.loads((out / "report" / "verdicts.json").read_text())
    assert {c["arm"] for c in verdicts["comparisons"]} == {"default"}  # no-refit: 1 run
    assert set(verdicts["to_target"]) == {"default", "no-refit", "none"}
    assert "no significant fitness difference" not in text
