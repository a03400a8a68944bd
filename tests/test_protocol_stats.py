"""The protocol's statistics (docs/protocol.md, "Verdicts"), each against a plain reference:
Welch's interval against scipy, the bootstrap against a NumPy loop over the same resamples
and against scipy.stats.bootstrap on a large sample, TOST and the verdicts on cases whose
answer is known."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import stats

from eant2_jax.app import report_stats as rs


@pytest.mark.parametrize("seed", range(6))
def test_welch_interval_is_scipys(seed):
    rng = np.random.default_rng(seed + 100)
    a = rng.normal(rng.normal(), rng.uniform(0.1, 3), size=rng.integers(2, 30))
    b = rng.normal(rng.normal(), rng.uniform(0.1, 3), size=rng.integers(2, 30))
    for confidence in (0.95, 0.90):
        d, low, high = rs.welch_interval(a, b, confidence)
        ci = stats.ttest_ind(a, b, equal_var=False).confidence_interval(confidence)
        np.testing.assert_allclose([low, high], [ci.low, ci.high], rtol=1e-10)
        assert d == pytest.approx(a.mean() - b.mean(), rel=1e-12)


def test_welch_interval_edges():
    assert rs.welch_interval([2.0, 2.0], [1.0, 1.0]) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="at least two"):
        rs.welch_interval([1.0], [1.0, 2.0])


@pytest.mark.parametrize(
    ("low", "high", "claim", "want"),
    [
        (-3, -1, "below", "held"),
        (1, 3, "below", "not held"),
        (-1, 1, "below", "undecided"),
        (-1, 0, "below", "undecided"),  # touching the threshold is not wholly below it
        (1, 3, "above", "held"),
        (-3, -1, "above", "not held"),
        (-1, 1, "above", "undecided"),
    ],
)
def test_verdict(low, high, claim, want):
    assert rs.verdict(low, high, claim=claim) == want


def test_tost_reads_the_90_percent_interval_against_the_margin():
    rng = np.random.default_rng(7)
    a = 10 + 0.01 * rng.normal(size=20)
    held = rs.tost(a, a + 0.001 * rng.normal(size=20), margin=0.3)
    assert held["verdict"] == "held" and -0.3 < held["low"] <= held["high"] < 0.3
    d, low, high = rs.welch_interval(a, a + 0.001 * rng.normal(size=20), 0.90)
    assert held["low"] < held["difference"] < held["high"]
    far = rs.tost(a + 5, a, margin=0.3)
    assert far["verdict"] == "not held" and far["low"] > 0.3
    # Noisy samples with the same mean: the difference is not significant (p > 0.05), and
    # still the test cannot say they are equivalent within a small margin.
    x, y = rng.normal(size=8), rng.normal(size=8)
    assert stats.ttest_ind(x, y, equal_var=False).pvalue > 0.05
    assert rs.tost(x, y, margin=0.03)["verdict"] == "undecided"
    with pytest.raises(ValueError, match="margin must be positive"):
        rs.tost(x, y, margin=0)


def _numpy_bootstrap(samples, statistic, key, resamples, confidence):
    """The same resampling written as a plain loop: sample i's indices from fold_in(key, i),
    the statistic of each resample, numpy's percentiles."""
    idx = [
        np.asarray(jax.random.randint(jax.random.fold_in(key, i), (resamples, s.size), 0, s.size))
        for i, s in enumerate(samples)
    ]
    values = []
    for r in range(resamples):
        values.append(float(statistic(*[s[ix[r]] for s, ix in zip(samples, idx, strict=True)])))
    alpha = 100 * (1 - confidence) / 2
    return np.percentile(values, [alpha, 100 - alpha])


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(2))
def test_bootstrap_is_the_plain_loop_over_the_same_resamples(seed):
    rng = np.random.default_rng(seed + 200)
    a = rng.lognormal(size=rng.integers(5, 25))
    b = rng.lognormal(size=rng.integers(5, 25))
    key = jax.random.key(0)
    est, low, high = rs.bootstrap_interval([a], rs.median, resamples=1000)
    want = _numpy_bootstrap([a], np.median, key, 1000, 0.95)
    np.testing.assert_allclose([low, high], want, rtol=1e-12)
    assert est == np.median(a)

    def ratio(x, y):
        return np.median(x, axis=-1) / np.median(y, axis=-1)

    est, low, high = rs.bootstrap_interval([a, b], ratio, resamples=1000)
    want = _numpy_bootstrap([a, b], lambda x, y: np.median(x) / np.median(y), key, 1000, 0.95)
    np.testing.assert_allclose([low, high], want, rtol=1e-12)
    assert low <= high
    # The default is 10,000 resamples from key 0: the same numbers on every call.
    assert rs.bootstrap_interval([a], rs.median) == rs.bootstrap_interval([a], rs.median)
    assert rs.BOOTSTRAP_RESAMPLES == 10_000


@pytest.mark.slow
def test_bootstrap_agrees_with_scipy_on_a_large_sample():
    rng = np.random.default_rng(300)
    x = rng.exponential(size=1500)
    _, low, high = rs.bootstrap_interval([x], rs.median)
    ci = stats.bootstrap(
        (x,), np.median, method="percentile", n_resamples=10_000, random_state=1
    ).confidence_interval
    width = ci.high - ci.low
    assert abs(low - ci.low) < 0.1 * width and abs(high - ci.high) < 0.1 * width


@pytest.mark.slow
def test_bootstrap_keeps_runs_that_never_reached():
    """Evaluations to a target: a run that never reached it is infinite; a median that
    may be infinite gives an infinite upper end, never NaN."""
    x = np.array([100.0, 200.0, 300.0, np.inf, np.inf])
    est, low, high = rs.bootstrap_interval([x], rs.median)
    assert est == 300.0 and low in (100.0, 200.0)
    assert high == np.inf and not np.isnan([est, low, high]).any()
