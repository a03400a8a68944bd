"""The report's statistics: per arm, final fitness and size (mean and sd), size reduction,
generations and evaluations to 99% of the final fitness (and of the reference arm's), and
Welch t-test p-values against the reference arm."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..loop import GenerationRecord

__all__ = ["condition_peaks", "first_within", "reference_arm", "summarise", "to_target"]


def first_within(gens: list[GenerationRecord], cost: float) -> GenerationRecord | None:
    """The first generation whose best cost came within 1% of ``cost`` (None: none did)."""
    return next((g for g in gens if g.best_cost <= cost + 0.01 * abs(cost)), None)


def to_target(gens: list[GenerationRecord]) -> tuple[int, int]:
    """Generation and evaluations at which the best cost first came within 1% of its final
    value (i.e. the fitness reached 99% of its final value)."""
    g = first_within(gens, gens[-1].best_cost) or gens[-1]
    return g.generation, g.evaluations


def reference_arm(arms: Sequence[str], reference: str | None = None) -> str | None:
    """The arm p-values and size reductions are computed against: ``reference`` if given
    (ValueError if no arm has that name), else ``none`` (no pruning) if there is one."""
    if reference is not None:
        if reference not in arms:
            raise ValueError(f"no arm {reference!r} to compare against; arms: {', '.join(arms)}")
        return reference
    return "none" if "none" in arms else None


def _arm_summary(rs: Sequence) -> dict:
    fit = np.array([-r.generations[-1].best_cost for r in rs])
    size = np.array([r.generations[-1].best_size for r in rs], float)
    reach = np.array([to_target(r.generations) for r in rs], float)
    return {
        "runs": len(rs),
        "fitness": fit,
        "size": size,
        "fitness_mean": float(fit.mean()),
        "fitness_sd": float(fit.std(ddof=1)) if len(rs) > 1 else 0.0,
        "size_mean": float(size.mean()),
        "size_sd": float(size.std(ddof=1)) if len(rs) > 1 else 0.0,
        "generations_to_99": float(reach[:, 0].mean()),
        "evaluations_to_99": float(reach[:, 1].mean()),
        "prune_accepted": int(sum(sum(x.accepted for x in r.pruning) for r in rs)),
        "prune_attempts": int(sum(len(r.pruning) for r in rs)),
    }


def summarise(runs: list, *, reference: str | None = None) -> dict[str, dict]:
    """Per arm: final fitness/size mean and sd, size reduction, time to 99%, p-values
    against the `reference_arm`.

    Args:
      runs: `eant2_jax.app.report_runs.LoadedRun`s.
      reference: the reference arm's name (default: ``none`` if there is one).
    """
    from scipy import stats

    arms: dict[str, list] = {}
    for r in runs:
        arms.setdefault(r.arm, []).append(r)
    out = {arm: _arm_summary(rs) for arm, rs in arms.items()}
    reference = reference_arm(list(out), reference)
    for arm, s in out.items():
        # Time to the reference arm's quality: each arm's "to 99%" is to its own final
        # fitness, so an arm that ends better is charged for its later gains; this is the
        # same target for every arm (99% of the reference's mean final fitness).
        s["evaluations_to_reference"] = s["reached_reference"] = None
        if reference is not None:
            target = -out[reference]["fitness_mean"]
            hits = [first_within(r.generations, target) for r in arms[arm]]
            reached = [h.evaluations for h in hits if h is not None]
            s["reached_reference"] = len(reached)
            s["evaluations_to_reference"] = float(np.mean(reached)) if reached else None
        if reference is None or arm == reference:
            s["size_reduction_pct"] = None
            s["p_fitness"] = s["p_size"] = None
            continue
        ref = out[reference]
        s["size_reduction_pct"] = 100.0 * (1 - s["size_mean"] / ref["size_mean"])
        if s["runs"] > 1 and ref["runs"] > 1:
            s["p_fitness"] = _welch(s["fitness"], ref["fitness"], stats)
            s["p_size"] = _welch(s["size"], ref["size"], stats)
        else:
            s["p_fitness"] = s["p_size"] = None
    return out


def _welch(a, b, stats) -> float | None:
    if np.all(a == a[0]) and np.all(b == b[0]):
        return 1.0 if a[0] == b[0] else 0.0
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    return None if math.isnan(p) else p


def condition_peaks(condition: dict, which: str) -> list[float]:
    """Peak cond(C) of each run of the condition experiment (``which``: ``"before"`` or
    ``"after"`` pruning; one run in older files)."""
    curves = condition[which]
    if curves and not isinstance(curves[0], list):
        curves = [curves]
    return [float(max(c)) for c in curves]
