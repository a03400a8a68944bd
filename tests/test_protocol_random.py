"""The random pruner, the protocol's control (docs/protocol.md, section 1): the default rule
(trigger, re-fit, acceptance) with the connection tried drawn uniformly among the removable
ones, from a key derived from each structure's own key (`pruning.attempt_key`)."""

from __future__ import annotations

import functools
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pruning import attempt_task

import eant2_jax
from eant2_jax import exploitation as ex
from eant2_jax import pruning
from eant2_jax.compiler import compile_genomes
from eant2_jax.genome import Genome
from eant2_jax.kernels import pruning as kp
from eant2_jax.pruning import tables_for

P = 8
# Genes 1..5 are removable (every input of the root but one may go; the root's own weight may
# not): five candidates, and three slots of padding that never are.
GENOME = Genome.parse("N0/5*0.9 I0*1.5 I1*-0.8 B*0.3 I0*0.001 I1*0.002")


@functools.partial(jax.jit, static_argnames="n")
def _random_choices(key, candidates, n):
    """The random pruner's choice (the smallest score) under ``n`` keys split from ``key``."""
    z = jnp.zeros(P)

    def one(k):
        score, *_ = kp.scores(
            "random", z, 1.0, jnp.eye(P), jnp.eye(P), z + 1, z > -1, candidates, k
        )
        return jnp.argmin(score)

    return jax.vmap(one)(jax.random.split(key, n))


@pytest.mark.slow
def test_random_scores_choose_uniformly_among_the_candidates():
    rng = np.random.default_rng(0)
    candidates = rng.random(P) < 0.6
    candidates[rng.integers(P)] = True
    n = 20_000
    picks = np.asarray(
        _random_choices(jax.random.key(int(rng.integers(2**31))), jnp.asarray(candidates), n)
    )
    counts = np.bincount(picks, minlength=P)
    assert np.all(counts[~candidates] == 0)  # never a gene that may not go
    m = candidates.sum()
    expected = n / m
    # Each count is binomial(n, 1/m): within 5 standard deviations, and a chi-square test
    # against the uniform distribution far from rejecting.
    sd = np.sqrt(n * (1 / m) * (1 - 1 / m))
    assert np.all(np.abs(counts[candidates] - expected) < 5 * sd), counts
    from scipy import stats

    assert stats.chisquare(counts[candidates]).pvalue > 1e-4


@pytest.mark.slow
def test_random_scores_need_a_key_and_repeat_for_the_same_key():
    z = jnp.zeros(P)
    args = (z, 1.0, jnp.eye(P), jnp.eye(P), z + 1, z > -1, z > -1)
    with pytest.raises(ValueError, match="needs a PRNG key"):
        kp.scores("random", *args)
    a = kp.scores("random", *args, jax.random.key(3))[0]
    b = kp.scores("random", *args, jax.random.key(3))[0]
    np.testing.assert_array_equal(a, b)
    others = [int(jnp.argmin(kp.scores("random", *args, jax.random.key(s))[0])) for s in range(8)]
    assert len(set(others)) > 1


def _state(genomes, keys, config):
    batch = compile_genomes(genomes, len(genomes), pad_count=False)
    st = ex.init(keys, batch.weights, batch.layout.gene_mask, config, popsize=8)
    return st, batch.layout, tables_for(genomes, P)


@pytest.mark.slow
def test_propose_draws_from_each_structures_key():
    """Many structures of one genome, each its own key: the genes tried are the removable
    ones, about equally often; the same keys give the same genes; and the draw does not
    depend on anything but the key and the iteration (the scores of other pruners play no
    part)."""
    n = 1000
    config = ex.ExploitConfig(popsize=8, pruner="random")
    keys = jax.random.split(jax.random.key(11), n)
    st, _, tables = _state([GENOME] * n, keys, config)
    trigger = jnp.ones(n, bool)
    propose = jax.jit(functools.partial(pruning.propose, pruner="random"))
    att = propose(st.attempt, st.cma, trigger, tables, st.iteration, keys=st.key)
    genes = np.asarray(att.gene[:, 0])
    removable = np.asarray(jax.vmap(kp.removable)(tables, st.cma.mask))[0]
    assert set(np.flatnonzero(removable)) == {1, 2, 3, 4, 5}
    counts = np.bincount(genes, minlength=P)
    assert counts[~removable].sum() == 0 and counts[removable].min() > n / 5 - 5 * 13
    again = propose(st.attempt, st.cma, trigger, tables, st.iteration, keys=st.key)
    np.testing.assert_array_equal(again.gene, att.gene)
    later = propose(st.attempt, st.cma, trigger, tables, st.iteration + 1, keys=st.key)
    assert np.any(np.asarray(later.gene) != genes[:, None])  # another iteration, another draw
    with pytest.raises(ValueError, match="needs the structures' keys"):
        pruning.propose(st.attempt, st.cma, trigger, tables, st.iteration, pruner="random")


def test_acceptance_is_the_pruner_independent_code_path():
    """The pruner's name reaches the proposal alone: judging and concluding an attempt take
    no pruner, so a random candidate is accepted or rejected by the very code that decides a
    covariance candidate."""
    for stage in (pruning.judge, pruning.conclude, pruning.reduce):
        assert "pruner" not in inspect.signature(stage).parameters


_task = attempt_task  # the pruning tests' problem for one attempt


@pytest.mark.slow
def test_a_random_attempt_follows_the_default_rule():
    """One attempt of every structure through the engine's iterations, under the default
    rule: the re-fitted cost is compared with the best cost before the attempt by
    `kernels.pruning.accept`, for the random pruner as for the covariance one (whose
    attempt, through the same `exploitation.attempt`, test_pruning's
    test_tentative_attempt_refits_and_restores_on_rejection checks against the same rule);
    a rejection restores the state."""
    config = ex.ExploitConfig(popsize=8, pruner="random", prune_refit=4)
    genomes = [GENOME, Genome.parse("N0/3*0.9 I0*1.5 I1*-0.8 B*0.3")]
    st, layout, tables = _state(genomes, jax.random.split(jax.random.key(5), 2), config)
    # The best cost before the attempt: the mean's own (a fresh state has none).
    best = eant2_jax.cost(genomes, _task(), key=jax.random.key(0))
    st = st.replace(cma=st.cma.replace(best_cost=jnp.asarray(best, jnp.float32)))
    trigger = jnp.ones(2, bool)
    run = jax.jit(ex.attempt)
    new, rec = jax.device_get(run(st, trigger, layout, tables, _task(), jax.random.key(0), config))
    again = jax.device_get(run(st, trigger, layout, tables, _task(), jax.random.key(0), config)[1])
    for a, b in zip(jax.tree.leaves(rec), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)  # the same keys, the same attempt
    st = jax.device_get(st)
    for r in range(2):
        assert rec.attempted[r] and np.isfinite(rec.e_refit[r])
        assert rec.e_reference[r] == st.cma.best_cost[r]
        want = bool(kp.accept(rec.e_reference[r], rec.e_refit[r], config.prune_tolerance))
        assert bool(rec.accepted[r]) == want
        if not rec.accepted[r]:
            np.testing.assert_array_equal(new.cma.mask[r], st.cma.mask[r])
    # The tiny copy (gene 4) goes whichever pruner chose it; the genome that needs every
    # connection keeps them all.
    assert not rec.accepted[1]


@pytest.mark.slow
def test_optimize_with_the_random_pruner_is_deterministic():
    task = _task()
    opts = dict(popsize=8, max_iters=300, pruner="random", prune_window=20, patience=100)
    a = eant2_jax.optimize(GENOME, task, key=jax.random.key(4), **opts)
    b = eant2_jax.optimize(GENOME, task, key=jax.random.key(4), **opts)
    assert str(a.genome) == str(b.genome) and a.cost == b.cost
    assert [r.gene for r in a.pruning] == [r.gene for r in b.pruning] and a.pruning
    assert all(r.gene in (1, 2, 3, 4, 5) for r in a.pruning)
