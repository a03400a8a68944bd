"""The batch-width choice of docs/protocol.md section 6, applied to the choice runs' result
files: ``python -m bench width [--dir bench/results/field-width] [--out FILE.json]``.

Per environment (hopper, halfcheetah) and candidate (the frozen settings, widths 1,024,
4,096 and 10,000), each choice seed's value is eant2_jax's test return at TensorNEAT's wall
time: the test return of eant2_jax's last judged champion whose wall time (from process
start) is at most the wall time of TensorNEAT's last judged champion on the same seed (both
from the same result file; a seed where eant2_jax had no champion by then counts as -inf).
The candidates are ranked per environment by the median of these values over the three seeds
(1 = best; equal medians share their mean rank); the candidate with the smallest summed rank
over the two environments wins; on equal sums the smaller width, the frozen settings (no
width: each structure keeps the frozen popsize) counting as the smallest.

Nothing is decided while a candidate's result file is missing or has fewer than the three
seeds judged (a run still going writes each seed as it ends): the report names what is
missing. A result file made with other settings than section 6 gives (seeds, width,
max_iters, environment) or on another device kind than the others is refused with the
difference named. Result files are read as JSON only.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import BenchInputError, Column, markdown_table, write_new_json
from bench.field_stats import return_at

__all__ = [
    "CANDIDATES",
    "ENVS",
    "SEEDS",
    "checked_result",
    "choice_main",
    "choice_runs",
    "choose",
    "render",
    "return_at",
]

ENVS = ("hopper", "halfcheetah")
SEEDS = [100, 101, 102]
# name -> (width, max_iters per environment): docs/protocol.md section 6.
CANDIDATES: dict[str, tuple[int | None, dict[str, int | None]]] = {
    "frozen": (None, {"hopper": None, "halfcheetah": None}),
    "w1024": (1024, {"hopper": 3, "halfcheetah": 57}),
    "w4096": (4096, {"hopper": 2, "halfcheetah": 15}),
    "w10000": (10000, {"hopper": 2, "halfcheetah": 6}),
}


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


def _checked(path: Path, env: str, name: str) -> dict[str, Any]:
    width, iters = CANDIDATES[name]
    want = {
        "envs": [env],
        "first_seed": SEEDS[0],
        "seeds": len(SEEDS),
        "width": width,
        "max_iters": iters[env],
    }
    return checked_result(path, want, 6, f"{env} {name}")


def _seed_values(payload: dict, path: Path) -> dict[int, float]:
    values = {}
    for rec in payload.get("seeds", []):
        judged = rec.get("judged") or {}
        if "eant2" not in judged or "tensorneat" not in judged:
            continue
        wall = max(p["wall_s"] for p in judged["tensorneat"]["curve"])
        values[int(rec["seed"])] = return_at(judged["eant2"]["curve"], wall)
    if not set(values) <= set(SEEDS):
        raise BenchInputError(f"{path}: judged seeds {sorted(values)}, section 6 has {SEEDS}")
    return values


def _ranks(medians: dict[str, float]) -> dict[str, float]:
    """1 for the highest median; equal medians share their mean rank."""
    ranks = {}
    for name, m in medians.items():
        above = sum(v > m for v in medians.values())
        equal = sum(v == m for v in medians.values())
        ranks[name] = above + (equal + 1) / 2
    return ranks


def _order(name: str) -> float:
    width = CANDIDATES[name][0]
    return -1.0 if width is None else float(width)


def choice_runs(folder: str | Path, envs, names, read, values) -> tuple[dict, list[str], Any]:
    """A choice's result files ``folder/ENV-NAME.json``: ``({env: {name: [value per seed of
    SEEDS]}}, missing, device_kind)``. ``read(path, env, name)`` checks a file's payload,
    ``values(payload, path)`` gives its judged seeds' values; a file absent or with other
    seeds than `SEEDS` judged is listed in ``missing``. Refused: no such folder, or files
    from more than one device kind."""
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
            if sorted(got) != SEEDS:  # a run still going: judged seeds are written as they end
                missing.append(f"{path.name} (seeds judged: {sorted(got)})")
                continue
            found[env][name] = [got[s] for s in SEEDS]
    if len(set(devices.values())) > 1:
        raise BenchInputError(f"choice runs on more than one device kind: {devices}")
    return found, missing, next(iter(set(devices.values())), None)


def choose(folder: str | Path) -> dict[str, Any]:
    """The rule applied to ``folder``'s ``ENV-NAME.json`` files (see the module docstring):
    per environment each candidate's seed values, median and rank; the summed ranks; the
    winner (None, with ``missing`` listing the absent files, until all eight exist)."""
    found, missing, device = choice_runs(folder, ENVS, CANDIDATES, _checked, _seed_values)
    envs: dict[str, dict[str, Any]] = {}
    for env, by in found.items():
        rows = {n: {"values": v, "median": float(np.median(v))} for n, v in by.items()}
        if rows:
            for name, rank in _ranks({n: r["median"] for n, r in rows.items()}).items():
                rows[name]["rank"] = rank
        envs[env] = rows
    winner, summed = None, {}
    if not missing:
        summed = {n: sum(envs[e][n]["rank"] for e in ENVS) for n in CANDIDATES}
        winner = min(CANDIDATES, key=lambda n: (summed[n], _order(n)))
    return {
        "folder": str(folder),
        "seeds": SEEDS,
        "envs": envs,
        "summed_rank": summed,
        "winner": winner,
        "width": CANDIDATES[winner][0] if winner else None,
        "missing": missing,
        "device_kind": device,
    }


def render(choice: dict[str, Any]) -> str:
    rows = [
        {"env": env, "name": name, **row}
        for env, by in choice["envs"].items()
        for name, row in by.items()
    ]
    table = markdown_table(
        rows,
        [
            Column(lambda r: r["env"], "env"),
            Column(lambda r: r["name"], "candidate"),
            Column(
                lambda r: ", ".join(f"{v:.0f}" for v in r["values"]),
                "test return at TensorNEAT's wall time, seeds " + ", ".join(map(str, SEEDS)),
            ),
            Column(lambda r: f"{r['median']:.0f}", "median"),
            Column(lambda r: f"{r['rank']:g}", "rank"),
        ],
    )
    md = (
        f"The batch-width choice (docs/protocol.md section 6) from `{choice['folder']}`"
        f" ({choice['device_kind']}).\n\n{table}\n"
    )
    if choice["winner"] is None:
        md += "\nNot decided: missing " + ", ".join(choice["missing"]) + ".\n"
    else:
        sums = ", ".join(f"{n} {s:g}" for n, s in choice["summed_rank"].items())
        md += f"\nSummed ranks: {sums}. Chosen: **{choice['winner']}**.\n"
    return md


def choice_main(argv: list[str], *, prog: str, doc: str, folder: str, choose, render) -> None:
    """A choice's command: ``--dir`` (default ``folder``) through ``choose``, printed by
    ``render``; ``--out FILE`` also writes the choice as JSON (never over a file)."""
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n")[0])
    p.add_argument("--dir", default=folder, help="the choice runs' folder (default: %(default)s)")
    p.add_argument("--out", help="also write the choice as JSON here (never over a file)")
    args = p.parse_args(argv)
    choice = choose(args.dir)
    print(render(choice))
    if args.out:
        write_new_json(args.out, choice)


def main(argv: list[str]) -> None:
    choice_main(argv, prog="python -m bench width", doc=__doc__, folder="bench/results/field-width",
                choose=choose, render=render)  # fmt: skip
