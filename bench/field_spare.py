"""The spare-rows choice of docs/protocol.md section 9, applied to the choice runs' result
files: ``python -m bench spare [--dir bench/results/field-spare]``.

Per environment (hopper, halfcheetah) the two candidates' files ``ENV-idle.json`` (the
settings in force) and ``ENV-restarts.json`` (``--spare-rows restarts``) each hold eant2_jax's
runs on the choice seeds 100-102 at the frozen budget, run one process at a time on one GPU.
Per seed, two paired differences (``restarts`` minus ``idle``):

* **at the evaluation count**: the test returns of the champions at the last reporting
  budget (100,000 evaluations);
* **at a wall time**: the test returns of each run's last judged champion at or before the
  earlier of the two runs' last judged champions (`bench.field_stats.return_at`), so both
  have one.

``restarts`` is adopted when, on both environments, the median of the wall-time differences
is above 0 and the median of the evaluation-count differences is not below 0; otherwise the
padding rows stay idle.

Nothing is decided while a file is missing or has fewer than the three seeds judged: the
report names what is missing. A file made with other options than section 9 gives, or on
another device kind than the others, is refused with the difference named. Result files are
read as JSON only.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from bench.field_choice import (
    SEEDS,
    checked_result,
    choice_main,
    choice_runs,
    judged_eant2,
    verdict_lines,
)
from bench.field_stats import return_at

__all__ = ["CANDIDATES", "ENVS", "SEEDS", "choose", "main", "render"]

ENVS = ("hopper", "halfcheetah")
CANDIDATES = {"idle": None, "restarts": "restarts"}  # file name -> the call's --spare-rows


def _payload(path: Path, env: str, name: str) -> dict[str, Any]:
    want = {"envs": [env], "methods": ["eant2"], "first_seed": SEEDS[0], "seeds": len(SEEDS),
            "spare_rows": CANDIDATES[name], "normalize": None, "budget": None,
            "population": None, "max_iters": None, "width": None}  # fmt: skip
    return checked_result(path, want, 9, f"{env} {name}")


def _runs(payload: dict[str, Any], path: Path) -> dict[int, dict[str, Any]]:
    """Seed -> eant2_jax's test return at the last reporting budget and its judged curve."""
    out = {}
    for seed, judged in judged_eant2(payload).items():
        last = max(judged["budgets"], key=lambda b: b["budget"])
        out[seed] = {"evals": float(last["test_return"]), "curve": judged.get("curve") or []}
    return out


def _at_common_wall(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, float, float]:
    """``(wall_s, a's return, b's return)`` at the earlier of the two runs' last judged
    champions (-inf where a run has none)."""
    ends = [max((p["wall_s"] for p in r["curve"]), default=-math.inf) for r in (a, b)]
    wall = min(ends)
    return wall, return_at(a["curve"], wall), return_at(b["curve"], wall)


def choose(folder: str | Path) -> dict[str, Any]:
    """The rule applied to ``folder`` (the module docstring): per environment each
    candidate's returns at both points, the paired differences and their medians;
    ``adopted`` is None, with ``missing`` naming what is absent, until every file holds the
    three seeds."""
    found, missing, device = choice_runs(folder, ENVS, CANDIDATES, _payload, _runs)
    envs: dict[str, dict[str, Any]] = {}
    for env, row in found.items():
        if len(row) < len(CANDIDATES):
            envs[env] = {n: [r["evals"] for r in runs] for n, runs in row.items()}
            continue
        walls = [_at_common_wall(a, b) for a, b in zip(row["idle"], row["restarts"], strict=True)]
        evals = [b["evals"] - a["evals"] for a, b in zip(row["idle"], row["restarts"], strict=True)]
        envs[env] = {
            "idle": [r["evals"] for r in row["idle"]],
            "restarts": [r["evals"] for r in row["restarts"]],
            "evals_difference": evals, "evals_median": float(np.median(evals)),
            "wall_s": [w[0] for w in walls], "idle_at_wall": [w[1] for w in walls],
            "restarts_at_wall": [w[2] for w in walls],
            "wall_difference": [w[2] - w[1] for w in walls],
            "wall_median": float(np.median([w[2] - w[1] for w in walls])),
        }  # fmt: skip
    adopted = None
    if not missing:
        adopted = all(envs[e]["wall_median"] > 0 and envs[e]["evals_median"] >= 0 for e in ENVS)
    return {"folder": str(folder), "seeds": SEEDS, "envs": envs, "adopted": adopted,
            "missing": missing, "device_kind": device}  # fmt: skip


def _cells(values: list[float]) -> str:
    return ", ".join(f"{v:.0f}" for v in values) or "—"


def render(choice: dict[str, Any]) -> str:
    head = ", ".join(map(str, SEEDS))
    lines = [f"The spare-rows choice (docs/protocol.md section 9) from `{choice['folder']}` "
             f"({choice['device_kind']}): test returns, seeds {head}.", "",
             "| env | point | idle | restarts | restarts - idle | median |",
             "| --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for env, row in choice["envs"].items():
        if "wall_median" not in row:
            lines.append(f"| {env} | 100,000 evaluations | {_cells(row.get('idle', []))} | "
                         f"{_cells(row.get('restarts', []))} | — | — |")  # fmt: skip
            continue
        lines.append(f"| {env} | 100,000 evaluations | {_cells(row['idle'])} | "
                     f"{_cells(row['restarts'])} | {_cells(row['evals_difference'])} | "
                     f"{row['evals_median']:.0f} |")  # fmt: skip
        lines.append(f"| {env} | wall {_cells(row['wall_s'])} s | {_cells(row['idle_at_wall'])} | "
                     f"{_cells(row['restarts_at_wall'])} | {_cells(row['wall_difference'])} | "
                     f"{row['wall_median']:.0f} |")  # fmt: skip
    lines += verdict_lines(choice, "--spare-rows restarts", "the padding rows stay idle")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    choice_main(argv, prog="python -m bench spare", doc=__doc__,
                folder="bench/results/field-spare", choose=choose, render=render)  # fmt: skip
