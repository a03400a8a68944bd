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

from pathlib import Path
from typing import Any

import numpy as np

from bench.common import BenchInputError, Column, markdown_table
from bench.field_choice import SEEDS, checked_result, choice_main, choice_runs
from bench.field_stats import return_at

__all__ = ["CANDIDATES", "ENVS", "SEEDS", "choose", "render", "return_at"]

ENVS = ("hopper", "halfcheetah")
# name -> (width, max_iters per environment): docs/protocol.md section 6.
CANDIDATES: dict[str, tuple[int | None, dict[str, int | None]]] = {
    "frozen": (None, {"hopper": None, "halfcheetah": None}),
    "w1024": (1024, {"hopper": 3, "halfcheetah": 57}),
    "w4096": (4096, {"hopper": 2, "halfcheetah": 15}),
    "w10000": (10000, {"hopper": 2, "halfcheetah": 6}),
}


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


def main(argv: list[str]) -> None:
    choice_main(argv, prog="python -m bench width", doc=__doc__, folder="bench/results/field-width",
                choose=choose, render=render)  # fmt: skip
