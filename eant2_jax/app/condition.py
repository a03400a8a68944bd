"""The paper's condition experiment (section V.A, figure 7): prune an evolved network,
re-initialise it and its pruned version with random weights, and record cond(C) of a CMA-ES
run on each (no pruning). `eant2_jax.app.experiments.reproduce` runs it on the best
unpruned network of a reproduction.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..config import ExploitConfig
from ..exploitation import run as run_engine
from ..genome import Genome
from ..pruning import kept_genes, reduce, where_rows
from ..tasks.base import Task
from ..tuning import optimize, prepare, tune

__all__ = ["condition_experiment", "from_evolved", "prune_rounds", "recording_config"]


def condition_experiment(
    genome: Genome,
    task: Task,
    *,
    key: jax.Array,
    prune_iters: int = 2000,
    prune_window: int = 100,
    prune_sigma0: float = 0.1,
    rounds: int = 10,
    prune_candidates: int = 4,
    iters: int = 10_000,
    inits: int = 5,
    sigma0: float = 0.5,
    weight_scale: float = 0.5,
    dtype: str = "float64",
    max_condition: float = 1e17,
    evolved_warmup: int = 0,
) -> dict:
    """Paper V.A: cond(C) of a network against its pruned version.

    First the network is pruned in rounds (each a CMA-ES run from its current weights, until
    a round removes nothing). Then the original and the pruned network each start from
    ``inits`` random weight vectors (the pruned one from the same draws on the genes it
    kept), and all ``2 * inits`` CMA-ES runs go as ONE batch, without pruning or early stop,
    recording cond(C) every iteration. The paper ran one initialisation of each, limited cond
    at about 1e17, and reports 1.8e17 against 9e13; a float32 state cannot resolve such
    condition numbers, hence ``dtype="float64"`` (JAX's x64 mode must be on).

    Args:
      genome: an evolved network (with tuned weights).
      task: its task.
      key: PRNG key.
      prune_iters: CMA-ES budget of each pruning round (from the current weights).
      prune_window: W of the pruning trigger in those rounds.
      prune_sigma0: initial step size of those rounds (small: the weights are tuned).
      rounds: at most this many pruning rounds; they stop when one removes nothing.
      prune_candidates: candidates tested per attempt.
      iters: CMA-ES budget of each run from random weights.
      inits: random initialisations of each network.
      sigma0: initial step size of those runs.
      weight_scale: std of the random initial weights.
      dtype: the CMA-ES state's dtype in those runs.
      max_condition: the bound on cond(C) in those runs.
      evolved_warmup: if > 0, also the variant that continues from an EVOLVED covariance
        instead of restarting at C = I: the original network's CMA-ES runs ``evolved_warmup``
        iterations from its tuned weights (``inits`` runs, step size ``prune_sigma0``); then
        each run goes on ``iters`` iterations twice, as it is and with the pruned genes
        removed (C conditioned on them, the pruned network's weights), from the same state
        and the same random numbers. Results under ``evolved``.

    Returns:
      ``before``/``after``: ``[inits][iters]`` cond(C) per run and iteration;
      ``peak_before``/``peak_after``: the peak of each run; ``cost_before``/``cost_after``:
      each run's best cost; ``size_before``/``size_after``; ``genome_before``/
      ``genome_after``; ``removed``: accepted pruning records.
    """
    k_prune, k_init, k_run = jax.random.split(key, 3)
    current, removed = prune_rounds(
        genome, task, k_prune, rounds=rounds, iters=prune_iters, window=prune_window,
        sigma0=prune_sigma0, candidates=prune_candidates,
    )  # fmt: skip
    starts_a, starts_b = _random_starts(genome, current, k_init, inits, weight_scale)
    config = recording_config(sigma0, iters, max_condition, dtype)
    res = tune(starts_a + starts_b, task, key=k_run, config=config, pad_count=False)
    cond = np.asarray(res.history.cond, np.float64).T  # [runs, iters]
    before, after = cond[:inits], cond[inits:]
    evolved = None
    if evolved_warmup > 0:
        evolved = from_evolved(
            genome, current, task, jax.random.fold_in(k_run, 1), config, inits, evolved_warmup,
            prune_sigma0,
        )  # fmt: skip
    result = _result(genome, current, before, after, res.costs, dtype, max_condition, removed)
    return {**result, "evolved": evolved}


def _random_starts(genome, pruned, key, inits, weight_scale) -> tuple[list, list]:
    """The ``inits`` random starts of the network and of its pruned version: the pruned one
    from the same draw on the genes it kept (NumPy draws seeded by ``key``'s data)."""
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)))
    starts_a, starts_b = [], []
    for _ in range(inits):
        w = rng.normal(0, weight_scale, genome.n_params)
        starts_a.append(genome.with_weights(w))
        starts_b.append(pruned.with_weights(w[_kept_genes(genome, pruned)]))
    return starts_a, starts_b


def _result(genome, pruned, before, after, costs, dtype, max_condition, removed) -> dict:
    """`condition_experiment`'s record of the runs from random weights (``before``/``after``
    ``[inits, iters]`` cond(C), ``costs`` the best cost of the ``2 * inits`` runs)."""
    inits = len(before)
    return {
        "before": before.tolist(),
        "after": after.tolist(),
        "peak_before": before.max(axis=1).tolist(),
        "peak_after": after.max(axis=1).tolist(),
        "cost_before": costs[:inits],
        "cost_after": costs[inits:],
        "size_before": genome.n_params,
        "size_after": pruned.n_params,
        "genome_before": str(genome),
        "genome_after": str(pruned),
        "dtype": dtype,
        "max_condition": max_condition,
        "removed": removed,
    }


def prune_rounds(genome, task, key, *, rounds, iters, window, sigma0, candidates):
    """Prune ``genome`` in rounds, each a CMA-ES run from its current weights, until a
    round removes nothing: (the pruned genome, the accepted pruning records)."""
    current, removed = genome, []
    for r in range(rounds):
        res = optimize(
            current,
            task,
            key=jax.random.fold_in(key, r),
            pruner="covariance",
            prune_window=window,
            max_iters=iters,
            patience=iters,
            sigma0=sigma0,
            prune_candidates=candidates,
        )
        accepted = [dict(x.to_json(), round=r) for x in res.pruning if x.accepted]
        removed += accepted
        current = res.genome
        if not accepted:
            break
    return current, removed


def recording_config(sigma0, iters, max_condition, dtype) -> ExploitConfig:
    """CMA-ES runs of ``iters`` iterations with nothing that stops or prunes them, cond(C)
    recorded every iteration."""
    return ExploitConfig(
        pruner="none",
        sigma0=sigma0,
        max_iters=iters,
        chunk=min(iters, 500),
        patience=iters,
        sigma_tol=0.0,
        tolfun=None,
        sigma_up=1e30,
        bound_patience=iters + 1,
        max_condition=max_condition,
        dtype=dtype,
        lazy_eigen=0.0,  # cond(C) is recorded per iteration: decompose every iteration
    )


def from_evolved(genome, pruned, task, key, config, inits, warmup, sigma0) -> dict:
    """The condition experiment continuing from an evolved covariance (see
    `condition_experiment`): rows ``[0, inits)`` the original network, rows
    ``[inits, 2 inits)`` the same states with the pruned genes removed."""
    kept = _kept_genes(genome, pruned)
    w = np.zeros(genome.n_params)
    w[kept] = pruned.weights
    warm = config.replace(sigma0=sigma0, max_iters=warmup, patience=warmup + 1, tolfun=None)
    # Row i and row inits + i share their key: the same evolution up to the branch, the
    # same random numbers after it.
    keys = jax.random.split(key, inits)
    prep = prepare([genome] * (2 * inits), task, key=key, config=warm,
                   keys=jnp.concatenate([keys, keys]), pad_count=False)  # fmt: skip
    st, _ = run_engine(prep.state, prep.batch.layout, task, key=key, config=warm)
    p = prep.batch.bucket.genes
    remove = np.zeros((2 * inits, p), bool)
    remove[inits:, : genome.n_params] = ~np.isin(np.arange(genome.n_params), kept)
    means = np.asarray(st.cma.mean).copy()
    means[inits:, : genome.n_params] = w
    cma, params = jax.jit(reduce)(
        st.cma, st.params, jnp.asarray(remove), jnp.asarray(means, st.cma.mean.dtype),
        jnp.full(2 * inits, jnp.inf),
    )  # fmt: skip
    branch = jnp.arange(2 * inits) >= inits
    st = st.replace(
        cma=where_rows(branch, cma, st.cma),
        params=where_rows(branch, params, st.params),
        stop=jnp.zeros_like(st.stop),
        since_improve=jnp.zeros_like(st.since_improve),
    )
    go_on = config.replace(max_iters=warmup + config.max_iters, patience=warmup + config.max_iters)
    st, hist = run_engine(st, prep.batch.layout, task, key=jax.random.fold_in(key, 1),
                          config=go_on)  # fmt: skip
    cond = np.asarray(hist.cond, np.float64).T
    before, after = cond[:inits], cond[inits:]
    best = np.asarray(st.cma.best_cost, np.float64)
    return {
        "warmup": warmup,
        "before": before.tolist(),
        "after": after.tolist(),
        "peak_before": before.max(axis=1).tolist(),
        "peak_after": after.max(axis=1).tolist(),
        "cost_before": best[:inits].tolist(),
        "cost_after": best[inits:].tolist(),
    }


def _kept_genes(original: Genome, pruned: Genome) -> np.ndarray:
    """`eant2_jax.pruning.kept_genes`, refusing a genome that is not a pruned copy."""
    kept = kept_genes(original, pruned)
    if len(kept) != len(pruned):
        raise ValueError("the pruned genome is not a sub-sequence of the original")
    return np.asarray(kept, np.int64)
