"""The condition experiment's variant that continues from an evolved covariance (paper V.A,
issue: "continuing from the evolved C rather than restarting at C = I")."""

import jax
import numpy as np
import pytest

from eant2_jax import ExploitConfig
from eant2_jax.app.condition import from_evolved
from eant2_jax.exploitation import run as run_engine
from eant2_jax.genome import Genome
from eant2_jax.tasks import regression
from eant2_jax.tuning import prepare


@pytest.mark.slow
def test_evolved_branch_continues_the_original_run_exactly():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(256, 2))
    task = regression(x, np.tanh(1.5 * x[:, :1]) + 0.05 * rng.normal(size=(256, 1)))
    genome = Genome.parse("N0/3*1 I0*0.7 I0*0.8 I1*0.5")
    pruned = Genome.parse("N0/2*1 I0*1.5 I1*0.01")  # genes 0, 1 and 3 kept
    config = ExploitConfig(sigma0=0.5, max_iters=40, chunk=20, patience=40, sigma_tol=0.0,
                           sigma_up=1e30, bound_patience=41, pruner="none")  # fmt: skip
    key = jax.random.key(3)
    ev = from_evolved(genome, pruned, task, key, config, inits=2, warmup=30, sigma0=0.1)
    assert np.shape(ev["before"]) == np.shape(ev["after"]) == (2, 40)
    # The original rows go on exactly as one uninterrupted run of warmup + iters iterations
    # (the same batch shape, so the same program).
    whole = config.replace(sigma0=0.1, max_iters=70, patience=71)
    keys = jax.random.split(key, 2)
    keys = jax.numpy.concatenate([keys, keys])
    prep = prepare([genome] * 4, task, key=key, config=whole, keys=keys, pad_count=False)
    _, hist = run_engine(prep.state, prep.batch.layout, task, key=key, config=whole)
    np.testing.assert_array_equal(np.asarray(hist.cond)[30:70, 0], ev["before"][0])
    # The pruned rows start from the same state with gene 2 removed: another conditioning,
    # a finite cost of their own.
    assert ev["after"][0][0] != ev["before"][0][0]
    assert all(np.isfinite(ev["cost_after"])) and all(np.isfinite(ev["peak_after"]))
