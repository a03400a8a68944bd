"""`optimize` with ANY valid ``sigma0`` never returns worse than its start (issue 40's Done
when; tests/test_optimize.py holds the large step sizes the issue found): step sizes drawn
afresh, log-uniform over the whole range a float32 `ExploitConfig` accepts, and its two ends."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eant2_jax import ExploitConfig, Genome
from eant2_jax.tasks import xor
from eant2_jax.tuning import cost, optimize

START = Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0")
TINY = float(np.finfo(np.float32).tiny)
# The largest sigma0 a float32 config accepts: sigma0 * sigma_up must stay finite.
LARGEST = float(np.finfo(np.float32).max) / ExploitConfig().sigma_up / 2


def _check(sigma0: float) -> None:
    ExploitConfig(sigma0=sigma0)  # a valid setting
    task = xor()
    start_cost = float(cost(START, task, key=jax.random.key(0))[0])
    res = optimize(START, task, key=jax.random.key(1), sigma0=sigma0, max_iters=3, popsize=6)
    assert math.isfinite(res.cost) and res.cost <= start_cost, (sigma0, res.cost, start_cost)
    again = float(cost(res.genome, task, key=jax.random.key(2))[0])
    assert again == pytest.approx(res.cost), sigma0  # the cost it reports is the genome's


@pytest.mark.slow
@pytest.mark.parametrize("sigma0", [TINY, 1e-20, LARGEST])
def test_the_ends_of_the_valid_sigma0_range(sigma0):
    _check(sigma0)


@pytest.mark.slow
@settings(max_examples=8)
@given(st.floats(math.log10(TINY), math.log10(LARGEST)))
def test_any_valid_sigma0_never_returns_worse_than_the_start(exponent):
    # 10**log10(TINY) rounds a few ulps below TINY: keep the draw inside the valid range.
    _check(min(max(10.0**exponent, TINY), LARGEST))
