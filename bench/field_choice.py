"""What the field's choices (docs/protocol.md sections 6 and 8) share: the choice seeds, a
choice run's result file checked against the section's settings (read as JSON only), the walk
over a choice folder's ``ENV-NAME.json`` files, and the command that prints a choice."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from bench.common import BenchInputError

__all__ = [
    "SEEDS",
    "checked_result",
    "choice_main",
    "choice_runs",
    "judged_eant2",
    "verdict_lines",
]

SEEDS = [100, 101, 102]  # the choice seeds: never reported as the field's result


def checked_result(path: Path, want: dict[str, Any], section: int, what: str) -> dict[str, Any]:
    """A choice run's result file, read as JSON only: refused (one error naming ``path`` and
    each difference) unless it is a ``--protocol`` run whose ``args`` hold ``want``."""
    try:
        payload = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BenchInputError(f"{path}: not a readable JSON result file ({e})") from None
    args = payload.get("args") if isinstance(payload, dict) else None
    if not isinstance(args, dict):
        raise BenchInputError(f"{path}: no 'args' object; not a `bench field` result file")
    wrong = [
        f"{k} is {args.get(k)!r}, section {section} says {v!r}"
        for k, v in want.items()
        if args.get(k) != v
    ]
    if wrong:
        raise BenchInputError(f"{path}: not section {section}'s {what} run: " + "; ".join(wrong))
    if not payload.get("protocol"):
        raise BenchInputError(f"{path}: not a `--protocol` run")
    return payload


def judged_eant2(payload: dict[str, Any]) -> dict[int, dict[str, Any]]:
    """Seed -> eant2_jax's judging (``budgets``, ``curve``) in a result file, for the seeds
    judged at a reporting budget (a run still going has none yet)."""
    out = {}
    for rec in payload.get("seeds", []):
        judged = (rec.get("judged") or {}).get("eant2") or {}
        if judged.get("budgets"):
            out[int(rec["seed"])] = judged
    return out


def choice_runs(
    folder: str | Path, envs, names, read, values, judged: dict | None = None
) -> tuple[dict, list[str], Any]:
    """A choice's result files ``folder/ENV-NAME.json``: ``({env: {name: [value per seed of
    SEEDS]}}, missing, device_kind)``. ``read(path, env, name)`` checks a file's payload,
    ``values(payload, path)`` gives its judged seeds' values; a file absent or with other
    seeds than `SEEDS` judged is listed in ``missing``. ``judged``, where given, receives
    ``{env: {name: {seed: value}}}`` for every file read, the seeds judged so far. Refused:
    no such folder, or files from more than one device kind."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BenchInputError(f"{folder}: no such folder")
    found: dict[str, dict[str, list[float]]] = {}
    missing, devices = [], {}
    for env in envs:
        found[env] = {}
        for name in names:
            path = folder / f"{env}-{name}.json"
            if not path.is_file():
                missing.append(path.name)
                continue
            payload = read(path, env, name)
            devices[path.name] = (payload.get("environment") or {}).get("device_kind")
            got = values(payload, path)
            if judged is not None:
                judged.setdefault(env, {})[name] = got
            if sorted(got) != SEEDS:  # a run still going: judged seeds are written as they end
                missing.append(f"{path.name} (seeds judged: {sorted(got)})")
                continue
            found[env][name] = [got[s] for s in SEEDS]
    if len(set(devices.values())) > 1:
        raise BenchInputError(f"choice runs on more than one device kind: {devices}")
    return found, missing, next(iter(set(devices.values())), None)


def verdict_lines(choice: dict[str, Any], option: str, otherwise: str) -> list[str]:
    """A choice report's last lines: what is missing, or whether ``option`` (as a call names
    it) is adopted, ``otherwise`` saying what stays if not."""
    missing = ", ".join(choice["missing"])
    if choice["adopted"] is None:
        return ["", f"Not decided: missing {missing}."]
    verdict = "adopted" if choice["adopted"] else f"not adopted: {otherwise}"
    early = []  # a rule that can be settled before every seed is judged (section 8's)
    if choice["missing"]:
        early = ["", f"Decided before every seed is judged: the seeds still missing ({missing}) "
                 "cannot change the outcome."]  # fmt: skip
    return [*early, "", f"`{option}`: **{verdict}**."]


def choice_main(argv: list[str], *, prog: str, doc: str, folder: str, choose, render) -> None:
    """A choice's command: ``--dir`` (default ``folder``) through ``choose``, printed by
    ``render``; ``--out FILE`` also writes the choice as JSON (never over a file)."""
    p = argparse.ArgumentParser(prog=prog, description=" ".join(doc.split("\n\n")[0].split()))
    p.add_argument("--dir", default=folder, help="the choice runs' folder (default: %(default)s)")
    p.add_argument("--out", help="also write the choice as JSON here (never over a file)")
    args = p.parse_args(argv)
    choice = choose(args.dir)
    print(render(choice))
    if args.out:
        _write_new_json(args.out, choice)


def _write_new_json(path: str | Path, value: Any) -> None:
    """``value`` as indented JSON at ``path``, never over an existing file (one error naming
    it); non-finite numbers (a choice's ``-inf``) written as null."""
    out = Path(path)
    if out.exists():
        raise BenchInputError(f"{out} exists; not written over")
    finite = json.loads(json.dumps(value), parse_constant=lambda _: None)
    out.write_text(json.dumps(finite, indent=1) + "\n")
