"""The condition protocol's endpoints and verdicts (docs/protocol.md, section 2): log10
cond(C) at fixed iterations, its slope over the last half, the plateau, and the paired
verdict of a claim "version A has lower cond(C) than version B" (same network, same
initialisation), through `eant2_jax.app.report_stats`."""

from __future__ import annotations

import numpy as np

from .report_stats import bootstrap_interval, verdict

__all__ = ["PLATEAU_SLOPE", "endpoints", "half_slope", "paired_claim", "paired_t_interval"]

# A trace has plateaued when its slope over the last half lies within this many decades per
# 1,000 iterations of 0 (docs/protocol.md).
PLATEAU_SLOPE = 0.01


def half_slope(log_cond: np.ndarray) -> np.ndarray:
    """``[runs]`` least-squares slope of ``log_cond`` ``[runs, iters]`` (row ``i``'s entry
    ``t`` is log10 cond(C) after iteration ``t + 1``) over its last half (iterations
    ``iters // 2 + 1`` to ``iters``), in decades per 1,000 iterations."""
    y = np.asarray(log_cond, np.float64)
    iters = y.shape[-1]
    t = np.arange(iters // 2 + 1, iters + 1, dtype=np.float64)
    y = y[..., iters // 2 :]
    tc = t - t.mean()
    return 1000.0 * ((y - y.mean(axis=-1, keepdims=True)) @ tc) / (tc @ tc)


def endpoints(log_cond: np.ndarray, at=(1000, 5000, 10000)) -> dict:
    """Per run: log10 cond(C) after each iteration of ``at`` that the trace reaches (key
    ``"at_<k>"``), ``slope`` over the last half (decades per 1,000 iterations), and
    ``plateau``: the last half's mean where ``|slope| <= PLATEAU_SLOPE``, else None."""
    y = np.asarray(log_cond, np.float64)
    out = {f"at_{k}": y[:, k - 1].tolist() for k in at if k <= y.shape[-1]}
    slope = half_slope(y)
    level = y[:, y.shape[-1] // 2 :].mean(axis=-1)
    out["slope"] = slope.tolist()
    out["plateau"] = [
        float(v) if abs(s) <= PLATEAU_SLOPE else None for s, v in zip(slope, level, strict=True)
    ]
    return out


def paired_t_interval(d, confidence: float = 0.95) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean of paired differences ``d`` and its two-sided t
    interval (``n - 1`` degrees of freedom), as ``scipy.stats.ttest_1samp(d,
    0).confidence_interval(confidence)``; differences without spread give the mean as both
    ends."""
    from scipy import stats

    d = np.asarray(d, np.float64)
    if d.size < 2:
        raise ValueError("a paired interval needs at least two pairs")
    m = float(d.mean())
    se = float(d.std(ddof=1) / np.sqrt(d.size))
    if se == 0:
        return m, m, m
    half = float(stats.t.ppf(0.5 + confidence / 2, d.size - 1) * se)
    return m, m - half, m + half


def paired_claim(a, b, key=None) -> dict:
    """The claim "``a`` is lower than ``b``" on pairs (``a[i]`` and ``b[i]`` the same
    network and initialisation): the mean difference ``a - b`` with its t interval, which
    decides the verdict (`eant2_jax.app.report_stats.verdict`, below 0), and the percentile
    bootstrap interval of the mean (``key``, default ``jax.random.key(0)``, 10,000
    resamples) beside it."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mean, low, high = paired_t_interval(d)
    _, b_low, b_high = bootstrap_interval([d], lambda x: np.mean(x, axis=-1), key)
    return {
        "pairs": int(d.size),
        "difference": mean,
        "low": low,
        "high": high,
        "bootstrap_low": b_low,
        "bootstrap_high": b_high,
        "verdict": verdict(low, high, 0.0, claim="below"),
    }
