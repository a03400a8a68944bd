"""`optimize` counts its start point as a candidate (issue 40 item 4): whatever valid
``sigma0`` it is given, it never returns a genome worse than the one it started from, and
never cost inf for a genome whose own cost is finite."""

from __future__ import annotations

import math

import jax
import pytest

from eant2_jax import ExploitConfig, Genome
from eant2_jax.tasks import xor
from eant2_jax.tuning import cost, optimize

# XOR with one hidden neuron, already a fair start (its cost is finite and well below 1).
START = Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0")


@pytest.mark.slow
@pytest.mark.parametrize("sigma0", [1e3, 1e12, 1e30])
def test_a_large_sigma0_never_returns_worse_than_the_start(sigma0):
    """With a step size so large that every sample's network saturates or overflows (cost
    inf, or far worse than the start), the result is the start itself, at its own cost."""
    ExploitConfig(sigma0=sigma0)  # a valid setting
    task = xor()
    start_cost = float(cost(START, task, key=jax.random.key(0))[0])
    assert math.isfinite(start_cost)
    res = optimize(START, task, key=jax.random.key(1), sigma0=sigma0, max_iters=3, popsize=6)
    assert math.isfinite(res.cost) and res.cost <= start_cost
    assert float(cost(res.genome, task, key=jax.random.key(2))[0]) == pytest.approx(res.cost)


@pytest.mark.slow
def test_a_search_that_improves_returns_its_best():
    """The usual case is unchanged: a search that finds better weights returns them."""
    task = xor()
    start_cost = float(cost(START, task, key=jax.random.key(0))[0])
    res = optimize(START, task, key=jax.random.key(1), max_iters=3, popsize=6)
    assert res.cost < start_cost and res.genome != START
