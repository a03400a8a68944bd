"""Inherited searches (EANT2Config.inherit_search, issue 14): children start CMA-ES from
their parent's covariance, re-exploited parents continue their own search.

Checked here: the gene alignment against what each mutation operator really kept; the
child's start (parent's block scaled, identity on new genes); the engine's warm start
(``C``, ``B``, ``D``, ``sigma`` as given); the searches ``tune`` hands back (on the genes of
the tuned genome, pruned genes gone); and a run with the option: searches in the checkpoint,
a resume exactly equal to an uninterrupted run, bad searches refused with one error."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest

import eant2_jax
from bench.common import random_genome
from eant2_jax import EANT2Config, ExploitConfig, tasks
from eant2_jax import exploitation as ex
from eant2_jax.exploration import OPERATORS, mutate
from eant2_jax.records import Individual
from eant2_jax.rundir import CHECKPOINT
from eant2_jax.tuning import Search, align, inherited, prepare, tune

N_INPUTS = 4


def _parent(seed: int):
    rng = np.random.default_rng(seed)
    return random_genome(rng, 12 + seed % 7, n_inputs=N_INPUTS, n_outputs=2)


@pytest.mark.parametrize("operator", OPERATORS)
def test_align_finds_exactly_the_genes_each_operator_kept(operator):
    """Adding operators keep every parent gene (in order); removing ones keep only parent
    genes. Weights are random, so a wrong match would show as a changed weight."""
    tried = 0
    for seed in range(40):
        parent = _parent(seed)
        rng = np.random.default_rng(1000 + seed)
        child = mutate(rng, parent, operator, n_inputs=N_INPUTS, next_id=99)
        if child is None:
            continue
        tried += 1
        match = align(parent, child)
        found = [i for i in match if i is not None]
        assert found == sorted(set(found)), "matches keep the order of the parent"
        for j, i in enumerate(match):
            if i is not None:
                a, b = parent.genes[i], child.genes[j]
                assert (a.kind, a.ref, a.weight) == (b.kind, b.ref, b.weight)
        if operator.startswith("add"):
            assert len(found) == len(parent.genes)
            assert len(child.genes) > len(parent.genes)
            assert all(child.genes[j].weight == 0 or operator == "add_subnetwork"
                       for j, i in enumerate(match) if i is None)  # fmt: skip
        else:
            assert len(found) == len(child.genes) < len(parent.genes)
    assert tried >= 10


def test_a_child_inherits_the_scaled_parent_block_and_identity_for_new_genes():
    parent = _parent(3)
    n = parent.n_params
    rng = np.random.default_rng(0)
    a = rng.normal(size=(n, n))
    cov = a @ a.T + 0.1 * np.eye(n)
    child = mutate(np.random.default_rng(5), parent, "add_connection", n_inputs=N_INPUTS,
                   next_id=99)  # fmt: skip
    assert child is not None
    start = inherited(parent, Search(1e-4, cov), child, sigma0=0.5)
    match = align(parent, child)
    new = [j for j, i in enumerate(match) if i is None]
    kept = [j for j, i in enumerate(match) if i is not None]
    scale = n / np.trace(cov)
    assert start.sigma == 0.5 and start.cov.shape == (child.n_params,) * 2
    src = [match[j] for j in kept]
    np.testing.assert_allclose(start.cov[np.ix_(kept, kept)], cov[np.ix_(src, src)] * scale)
    for j in new:
        expect = np.zeros(child.n_params)
        expect[j] = 1.0
        np.testing.assert_array_equal(start.cov[j], expect)
    start.check(child.n_params, "start")  # symmetric, finite


@pytest.mark.slow
def test_the_engine_starts_from_the_given_search():
    genomes = [_parent(1), _parent(2)]
    genomes = [eant2_jax.Genome.parse(str(g)) for g in genomes]
    task = tasks.regression(np.zeros((4, N_INPUTS)), np.zeros((4, 2)))
    n = genomes[1].n_params
    rng = np.random.default_rng(1)
    a = rng.normal(size=(n, n))
    cov = a @ a.T / n + 0.5 * np.eye(n)
    config = ExploitConfig(max_iters=5)
    prep = prepare(genomes, task, key=jax.random.key(0), config=config,
                   start=[None, Search(0.03, cov)])  # fmt: skip
    cma = prep.state.cma
    C, B, D = (np.asarray(x, np.float64) for x in (cma.C, cma.B, cma.D))
    np.testing.assert_allclose(C[1, :n, :n], cov, rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose((B[1] * D[1] ** 2) @ B[1].T, C[1], rtol=1e-3, atol=1e-5)
    assert np.all(C[1, n:] == 0) and np.all(C[1, :, n:] == 0)
    n0 = genomes[0].n_params
    np.testing.assert_array_equal(C[0, :n0, :n0], np.eye(n0))  # no start: C = I
    np.testing.assert_allclose(np.asarray(cma.sigma), [0.5, 0.03], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(prep.state.sigma_bar), [0.5, 0.03], rtol=1e-6)
    with pytest.raises(ValueError, match=r"start\[1\].*cov"):
        prepare(genomes, task, key=jax.random.key(0), config=config,
                start=[None, Search(0.03, cov[:-1, :-1])])  # fmt: skip
    with pytest.raises(ValueError, match=r"start\[0\].*sigma"):
        prepare(genomes, task, key=jax.random.key(0), config=config,
                start=[Search(-1.0, np.eye(genomes[0].n_params)), None])  # fmt: skip
    with pytest.raises(ValueError, match="2 genomes"):
        prepare(genomes, task, key=jax.random.key(0), config=config, start=[None])
    with pytest.raises(ValueError, match="both"):
        ex.init(jax.random.split(jax.random.key(0), 1), np.zeros((1, 4)), np.ones((1, 4), bool),
                config, popsize=4, cov=np.eye(4)[None])  # fmt: skip


@pytest.mark.slow
def test_tune_returns_the_final_searches_on_the_tuned_genes():
    """XOR with pruning: each returned search covers exactly the genes of the returned
    (possibly pruned) genome, matches the engine's final C on those genes, and starts the
    next tuning from there."""
    task = tasks.make("xor")
    genome = eant2_jax.Genome.parse(
        "N0/4*1.0 N2/2*1.0 I0*1.0 I1*1.0 I0*0.5 I0*0.5 B*0.1"
    )  # I0 twice on the root: an exactly redundant pair
    config = ExploitConfig(max_iters=300, pruner="covariance")
    res = tune([genome], task, key=jax.random.key(3), config=config, keep_search=True)
    (search,) = res.searches
    n = res.genomes[0].n_params
    assert search is not None and search.cov.shape == (n, n) and search.sigma > 0
    mask = np.asarray(res.state.cma.mask[0, : genome.n_params])
    keep = np.flatnonzero(mask)
    np.testing.assert_allclose(
        search.cov, np.asarray(res.state.cma.C[0], np.float64)[np.ix_(keep, keep)], rtol=1e-6
    )
    again = tune(res.genomes, task, key=jax.random.key(4), config=config, start=res.searches)
    assert again.costs[0] <= res.costs[0] * 1.01 + 1e-6  # continuing does not lose the fit
    assert tune([genome], task, key=jax.random.key(3), config=config).searches is None


CONFIG = EANT2Config(
    population=4,
    inherit_search=True,
    reexploit=True,
    exploit=ExploitConfig(max_iters=120, pruner="covariance"),
)


@pytest.mark.slow
def test_a_run_with_inherited_searches_resumes_exactly(tmp_path):
    task = tasks.make("xor")
    key = jax.random.key(11)
    whole = eant2_jax.run(task, key=key, config=CONFIG, generations=2, out=str(tmp_path / "a"))
    assert all(ind.search is not None for ind in whole.population)
    state = json.loads((tmp_path / "a" / CHECKPOINT).read_text())["state"]
    for d in state["population"]:
        n = eant2_jax.Genome.parse(d["genome"]).n_params
        assert np.asarray(d["search"]["cov"]).shape == (n, n)
    eant2_jax.run(task, key=key, config=CONFIG, generations=0, out=str(tmp_path / "b"))
    resumed = eant2_jax.resume(str(tmp_path / "b"), task, generations=2)
    assert [str(i.genome) for i in resumed.population] == [str(i.genome) for i in whole.population]
    assert [i.cost for i in resumed.population] == [i.cost for i in whole.population]
    for a, b in zip(resumed.population, whole.population, strict=True):
        np.testing.assert_array_equal(a.search.cov, b.search.cov)
        assert a.search.sigma == b.search.sigma
    # The option changes the run: without it the same key tunes from C = I.
    plain = eant2_jax.run(task, key=key, config=dataclasses.replace(CONFIG, inherit_search=False),
                          generations=2)  # fmt: skip
    assert all(ind.search is None for ind in plain.population)
    assert [r.evaluations for r in plain.generations][1:] != [
        r.evaluations for r in whole.generations
    ][1:]


def test_an_individual_with_a_bad_search_is_refused():
    g = eant2_jax.Genome.parse("N0/2*1.0 I0*0.5 I1*0.25")
    good = Individual(g, 0.5, "init", Search(0.1, np.eye(3))).to_json()
    back = Individual.from_json(json.loads(json.dumps(good)))
    np.testing.assert_array_equal(back.search.cov, np.eye(3))
    for bad, phrase in [
        ({**good, "search": {"sigma": 0.1, "cov": [[1.0]]}}, "3 x 3"),
        ({**good, "search": {"sigma": 0.0, "cov": np.eye(3).tolist()}}, "sigma"),
        ({**good, "search": {"sigma": 0.1, "cov": "x"}}, "cov"),
        ({**good, "search": {"sigma": 0.1}}, "sigma and cov"),
        ({**good, "search": {"sigma": 0.1, "cov": [[1, 2, 0], [0, 1, 0], [0, 0, 1]]}}, "symmetric"),
    ]:
        with pytest.raises(ValueError, match=phrase):
            Individual.from_json(bad)
    assert (
        EANT2Config.from_dict(
            {k: v for k, v in CONFIG.to_dict().items() if k != "inherit_search"}, complete=True
        ).inherit_search
        is False
    )  # a run written before the option ran without it
