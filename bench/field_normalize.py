"""The observation-normalisation choice of docs/protocol.md section 8, applied to the choice
runs' result files: ``python -m bench normalize [--dir bench/results/field-normalize]``.

Per environment (hopper, halfcheetah) the two candidates' files ``ENV-raw.json`` (the frozen
raw inputs) and ``ENV-random.json`` (``--normalize random``) each hold eant2_jax's runs on the
choice seeds 100-102 at the frozen budget. A seed's value is eant2_jax's test return at the
last reporting budget (100,000 evaluations); the paired difference is ``random`` minus raw on
the same seed. ``random`` is adopted when the median of the three differences is above 0 on
both environments; otherwise the raw inputs stay.

Nothing is decided while a file is missing or has fewer than the three seeds judged (a run
still going writes each seed as it ends): the report names what is missing. A file made with
other options than section 8 gives, or on another device kind than the others, is refused
with the difference named. Result files are read as JSON only.
"""

from __future__ import annotations

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

__all__ = ["CANDIDATES", "ENVS", "SEEDS", "choose", "main", "render"]

ENVS = ("hopper", "halfcheetah")
CANDIDATES = {"raw": None, "random": "random"}  # file name -> the call's --normalize


def _payload(path: Path, env: str, name: str) -> dict[str, Any]:
    want = {"envs": [env], "methods": ["eant2"], "first_seed": SEEDS[0], "seeds": len(SEEDS),
            "normalize": CANDIDATES[name], "budget": None, "population": None,
            "max_iters": None, "width": None, "spare_rows": None}  # fmt: skip
    return checked_result(path, want, 8, f"{env} {name}")


def _returns(payload: dict[str, Any], path: Path) -> dict[int, float]:
    """Seed -> eant2_jax's test return at the last reporting budget, for the judged seeds."""
    return {
        seed: float(max(judged["budgets"], key=lambda b: b["budget"])["test_return"])
        for seed, judged in judged_eant2(payload).items()
    }


def choose(folder: str | Path) -> dict[str, Any]:
    """The rule applied to ``folder`` (the module docstring): per environment each
    candidate's returns, the paired differences and their median; ``adopted`` is None, with
    ``missing`` naming what is absent, until every file holds the three seeds."""
    found, missing, device = choice_runs(folder, ENVS, CANDIDATES, _payload, _returns)
    envs: dict[str, dict[str, Any]] = {}
    for env, row in found.items():
        envs[env] = dict(row)
        if len(row) == len(CANDIDATES):
            diff = [b - a for a, b in zip(row["raw"], row["random"], strict=True)]
            envs[env].update(difference=diff, median=float(np.median(diff)))
    adopted = None if missing else all(envs[e]["median"] > 0 for e in ENVS)
    return {"folder": str(folder), "seeds": SEEDS, "envs": envs, "adopted": adopted,
            "missing": missing, "device_kind": device}  # fmt: skip


def render(choice: dict[str, Any]) -> str:
    head = ", ".join(map(str, SEEDS))
    lines = [f"The observation-normalisation choice (docs/protocol.md section 8) from "
             f"`{choice['folder']}` ({choice['device_kind']}).", "",
             f"| env | raw, seeds {head} | random, seeds {head} | random - raw | median |",
             "| --- | --- | --- | --- | --- |"]  # fmt: skip
    for env, row in choice["envs"].items():
        cells = [", ".join(f"{v:.0f}" for v in row.get(k, [])) or "—"
                 for k in ("raw", "random", "difference")]  # fmt: skip
        median = f"{row['median']:.0f}" if "median" in row else "—"
        lines.append(f"| {env} | {' | '.join(cells)} | {median} |")
    lines += verdict_lines(choice, "--normalize random", "the raw inputs stay")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    choice_main(argv, prog="python -m bench normalize", doc=__doc__,
                folder="bench/results/field-normalize", choose=choose, render=render)  # fmt: skip
