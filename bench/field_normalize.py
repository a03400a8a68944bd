"""The observation-normalisation choice of docs/protocol.md section 8, applied to the choice
runs' result files: ``python -m bench normalize [--dir bench/results/field-normalize]``.

Per environment (hopper, halfcheetah) the two candidates' files ``ENV-raw.json`` (the frozen
raw inputs) and ``ENV-random.json`` (``--normalize random``) each hold eant2_jax's runs on the
choice seeds 100-102 at the frozen budget. A seed's value is eant2_jax's test return at the
last reporting budget (100,000 evaluations); the paired difference is ``random`` minus raw on
the same seed. ``random`` is adopted when the median of the three differences is above 0 on
both environments; otherwise the raw inputs stay.

Nothing is decided while a file is missing or has fewer than the three seeds judged (a run
still going writes each seed as it ends), unless the seeds still missing cannot change the
outcome: an environment with two of its three differences already above 0 (or two at or
below 0) has the sign of its median fixed, and one environment fixed at or below 0 keeps
the raw inputs whatever the rest gives (added to the protocol on 2026-12-05). The report
names what is missing and the differences known so far. A file made with
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

__all__ = ["CANDIDATES", "ENVS", "SEEDS", "choose", "main", "render", "settled"]

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
    candidate's returns, the paired differences and their median, the differences known so
    far (``known``) and whether they fix the median's sign (``settled``); ``adopted`` is None,
    with ``missing`` naming what is absent, until the seeds judged fix the outcome."""
    judged: dict[str, dict[str, dict[int, float]]] = {}
    found, missing, device = choice_runs(folder, ENVS, CANDIDATES, _payload, _returns, judged)
    envs: dict[str, dict[str, Any]] = {}
    for env, row in found.items():
        envs[env] = dict(row)
        if len(row) == len(CANDIDATES):
            diff = [b - a for a, b in zip(row["raw"], row["random"], strict=True)]
            envs[env].update(difference=diff, median=float(np.median(diff)))
    for env in ENVS:  # the seeds judged on both candidates so far
        raw, random = (judged.get(env, {}).get(name, {}) for name in CANDIDATES)
        known = {s: random[s] - raw[s] for s in SEEDS if s in raw and s in random}
        envs.setdefault(env, {}).update(known=known, settled=settled(list(known.values())))
    signs = [envs[e]["settled"] for e in ENVS]
    adopted = False if False in signs else (True if all(signs) else None)
    return {"folder": str(folder), "seeds": SEEDS, "envs": envs, "adopted": adopted,
            "missing": missing, "device_kind": device}  # fmt: skip


def settled(known: list[float]) -> bool | None:
    """Whether the median of the differences of all `SEEDS` is above 0 (True) or not
    (False) whatever the seeds not yet judged give, from the ``known`` ones; None while it
    could still go either way. With every seed known, that is ``median > 0``."""
    need = len(SEEDS) // 2 + 1  # an odd count: the median is the need-th value in order
    if sum(d > 0 for d in known) >= need:
        return True
    if sum(d <= 0 for d in known) >= need:
        return False
    return None


def render(choice: dict[str, Any]) -> str:
    head = ", ".join(map(str, SEEDS))
    lines = [f"The observation-normalisation choice (docs/protocol.md section 8) from "
             f"`{choice['folder']}` ({choice['device_kind']}).", "",
             f"| env | raw, seeds {head} | random, seeds {head} | random - raw | median |",
             "| --- | --- | --- | --- | --- |"]  # fmt: skip
    for env, row in choice["envs"].items():
        cells = [", ".join(f"{v:.0f}" for v in row.get(k, [])) or "—" for k in ("raw", "random")]
        if "difference" in row:
            diff, median = ", ".join(f"{v:.0f}" for v in row["difference"]), f"{row['median']:.0f}"
        else:  # the seeds judged on both so far
            known = row.get("known", {})
            diff = ", ".join(f"{v:.0f} (seed {s})" for s, v in known.items()) or "—"
            median = {True: "> 0 whatever the rest", False: "<= 0 whatever the rest"}.get(
                row.get("settled"), "—"
            )
        lines.append(f"| {env} | {' | '.join(cells)} | {diff} | {median} |")
    lines += verdict_lines(choice, "--normalize random", "the raw inputs stay")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> None:
    choice_main(argv, prog="python -m bench normalize", doc=__doc__,
                folder="bench/results/field-normalize", choose=choose, render=render)  # fmt: skip
