"""What the tests of the field's choices (docs/protocol.md sections 8 and 9) share: a
``bench field --protocol`` call's parsed options, and a choice run's result file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench import bench_field, field_protocol, harness
from bench.common import BenchInputError

__all__ = ["check_trial_option", "protocol_args", "write_result"]


def protocol_args(tmp_path: Path, env: str, *extra: str):
    """``bench field --protocol --envs ENV *extra`` parsed, with a stand-in TensorNEAT
    folder (found, never imported)."""
    (tmp_path / "tensorneat").mkdir(exist_ok=True)
    (tmp_path / "tensorneat" / "pipeline.py").write_text("")
    argv = ["--protocol", "--envs", env, "--tensorneat", str(tmp_path),
            "--out", str(tmp_path / "f.json"), *extra]  # fmt: skip
    return harness.parse_args(bench_field.SUITE, argv)


def write_result(folder: Path, env: str, name: str, options: dict[str, Any],
                 judged: list[dict[str, Any]], change: dict[str, Any] | None = None,
                 device: str = "H200") -> None:  # fmt: skip
    """``folder/ENV-NAME.json``: a ``--protocol`` choice run of eant2_jax on ``env`` with the
    choice seeds 100-102 and the trial ``options``; seed ``100 + i`` judged as
    ``judged[i]``; ``change`` replaces top-level fields of the payload."""
    args = {"envs": [env], "methods": ["eant2"], "first_seed": 100, "seeds": 3,
            "budget": None, "population": None, "max_iters": None, "width": None,
            "tensorneat_pop": None, **options}  # fmt: skip
    seeds = [{"seed": 100 + i, "judged": {"eant2": j}} for i, j in enumerate(judged)]
    payload = {"protocol": True, "args": args, "environment": {"device_kind": device},
               "seeds": seeds, **(change or {})}  # fmt: skip
    folder.mkdir(exist_ok=True)
    (folder / f"{env}-{name}.json").write_text(json.dumps(payload))


def check_trial_option(tmp_path: Path, env: str, flag: str, value: str, bad: str) -> None:
    """``flag value`` is a ``--protocol`` trial option that reaches eant2_jax's training
    process and not TensorNEAT's, is recorded in the call's settings only where given (a
    checkpoint written before the option still matches a call without it), belongs to
    ``--protocol`` alone, and refuses ``bad``."""
    args = protocol_args(tmp_path, env, flag, value)
    assert args.trial and flag in field_protocol.trial_overrides(args)
    out, name = tmp_path / "run.json", flag[2:].replace("-", "_")
    eant2 = field_protocol.METHODS["eant2"]("eant2", args, env, 100, out)
    tn = field_protocol.METHODS["tensorneat"]("tensorneat", args, env, 100, out)
    assert eant2[eant2.index(flag) + 1] == value and flag not in tn
    assert field_protocol.call_settings(args)["args"][name] == value
    plain = protocol_args(tmp_path, env)
    assert not plain.trial and name not in field_protocol.call_settings(plain)["args"]
    with pytest.raises(BenchInputError, match=f"{flag} belongs to --protocol"):
        bench_field.main([flag, value, "--quick", "--out", str(tmp_path / "g.json")])
    with pytest.raises(SystemExit):
        protocol_args(tmp_path, env, flag, bad)  # not one of the trial's choices
