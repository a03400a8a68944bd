"""The report's statistics: per arm, final fitness and size (mean and sd), size reduction,
generations and evaluations to 99% of the final fitness (and of the reference arm's), and
Welch t-test p-values against the reference arm; and the protocol's tests (docs/protocol.md,
"Verdicts"): Welch's interval of a difference of means, TOST equivalence, the percentile
bootstrap, and the held / not held / undecided verdict."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np

from ..loop import GenerationRecord

__all__ = ["condition_peaks", "first_within", "reference_arm", "summarise", "to_target"]
__all__ += ["BOOTSTRAP_RESAMPLES", "HELD", "NOT_HELD", "UNDECIDED", "bootstrap_indices"]
__all__ += ["bootstrap_interval", "median", "tost", "verdict", "welch_interval"]


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
    """Welch's p-value (None where undefined). scipy warns of "precision loss" whenever a
    sample is constant or nearly so, although NumPy's two-pass variance of such a sample is
    exact or within its values' rounding: that warning is silenced, not passed to the user."""
    if np.all(a == a[0]) and np.all(b == b[0]):
        return 1.0 if a[0] == b[0] else 0.0
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Precision loss", RuntimeWarning)
        p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    return None if math.isnan(p) else p


def condition_peaks(condition: dict, which: str) -> list[float]:
    """Peak cond(C) of each run of the condition experiment (``which``: ``"before"`` or
    ``"after"`` pruning; one run in older files)."""
    curves = condition[which]
    if curves and not isinstance(curves[0], list):
        curves = [curves]
    return [float(max(c)) for c in curves]


# ---------------------------------------------------------------------- the protocol's tests
# docs/protocol.md, "Verdicts": every claim is an estimate, an interval and one verdict.
HELD, NOT_HELD, UNDECIDED = "held", "not held", "undecided"
BOOTSTRAP_RESAMPLES = 10_000


def welch_interval(a, b, confidence: float = 0.95) -> tuple[float, float, float]:
    """``(difference, low, high)``: ``mean(a) - mean(b)`` and its two-sided Welch t interval
    (unequal variances, Welch-Satterthwaite degrees of freedom), as
    ``scipy.stats.ttest_ind(a, b, equal_var=False).confidence_interval(confidence)``.

    Two samples without spread give the difference as both ends; ValueError for a sample of
    fewer than two values.
    """
    from scipy import stats

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.size < 2 or b.size < 2:
        raise ValueError("Welch's interval needs at least two values in each sample")
    d = float(a.mean() - b.mean())
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    se2 = va + vb
    if se2 == 0:
        return d, d, d
    df = se2**2 / (va**2 / (a.size - 1) + vb**2 / (b.size - 1))
    half = float(stats.t.ppf(0.5 + confidence / 2, df) * np.sqrt(se2))
    return d, d - half, d + half


def verdict(low: float, high: float, threshold: float = 0.0, *, claim: str = "below") -> str:
    """The verdict on a claim from its interval ``[low, high]``: ``claim="below"`` (the
    quantity is below ``threshold``) is held if the whole interval is below it, not held if
    the whole interval is above it, else undecided; ``"above"`` the mirror image."""
    if claim == "below":
        return HELD if high < threshold else NOT_HELD if low > threshold else UNDECIDED
    if claim == "above":
        return HELD if low > threshold else NOT_HELD if high < threshold else UNDECIDED
    raise ValueError(f"claim must be 'below' or 'above', got {claim!r}")


def tost(a, b, margin: float, confidence: float = 0.90) -> dict:
    """Equivalence of the means of ``a`` and ``b`` within ``±margin`` (two one-sided tests
    at level ``(1 - confidence) / 2`` each, through their ``confidence`` Welch interval of
    ``mean(a) - mean(b)``): held if the interval lies within the margin, not held if it lies
    wholly outside it, else undecided. A non-significant difference is never equivalence.

    Returns:
      ``{"difference", "low", "high", "margin", "verdict"}``.
    """
    if not margin > 0:
        raise ValueError(f"the equivalence margin must be positive, got {margin!r}")
    d, low, high = welch_interval(a, b, confidence)
    if -margin < low and high < margin:
        v = HELD
    elif low > margin or high < -margin:
        v = NOT_HELD
    else:
        v = UNDECIDED
    return {"difference": d, "low": low, "high": high, "margin": float(margin), "verdict": v}


def bootstrap_indices(key, n: int, resamples: int = BOOTSTRAP_RESAMPLES) -> np.ndarray:
    """``int [resamples, n]``: resampling with replacement of ``n`` runs, drawn from ``key``
    (``jax.random.randint``; the same key, the same resamples)."""
    import jax

    return np.asarray(jax.random.randint(key, (resamples, n), 0, n))


def bootstrap_interval(
    samples, statistic, key=None, *, confidence: float = 0.95, resamples: int = BOOTSTRAP_RESAMPLES
) -> tuple[float, float, float]:
    """``(estimate, low, high)``: ``statistic(*samples)`` and its percentile bootstrap
    interval, each sample resampled within itself (runs within their arm), sample ``i``
    from ``fold_in(key, i)`` (default ``key``: ``jax.random.key(0)``, docs/protocol.md).

    Args:
      samples: one or more 1-D samples (an arm's values each).
      statistic: a function of as many 1-D arrays, vectorised over a leading axis
        (``statistic(*[s[idx] for s, idx in ...])`` with ``idx [resamples, n]`` rows), e.g.
        ``lambda x: np.median(x, axis=-1)``; it may return ``inf`` (an arm whose median run
        never reached a target), which the percentiles keep.
    """
    import jax

    key = jax.random.key(0) if key is None else key
    samples = [np.asarray(s, np.float64) for s in samples]
    if any(s.ndim != 1 or s.size == 0 for s in samples):
        raise ValueError("each bootstrap sample must be a non-empty 1-D array")
    estimate = float(statistic(*samples))
    drawn = [
        s[bootstrap_indices(jax.random.fold_in(key, i), s.size, resamples)]
        for i, s in enumerate(samples)
    ]
    values = np.asarray(statistic(*drawn), np.float64)
    alpha = (1 - confidence) / 2
    # Interpolating between inf and a number (or inf) is undefined: with infinite values
    # the ends are order statistics (the empirical distribution's quantiles).
    method = "linear" if np.all(np.isfinite(values)) else "inverted_cdf"
    low, high = np.quantile(values, [alpha, 1 - alpha], method=method)
    return estimate, float(low), float(high)


def median(x: np.ndarray) -> np.ndarray:
    """The median over the last axis (a `bootstrap_interval` statistic)."""
    return np.median(x, axis=-1)
