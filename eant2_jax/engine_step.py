"""One engine iteration of every running structure (paper section III.A): a CMA-ES
iteration, or the phase of a pruning attempt it is in, with ONE evaluation of the task's
cost for all of them; and a whole pruning attempt driven by it (`attempt`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from . import pruning
from .config import ExploitConfig
from .engine_prune import prune_phase, start_attempt
from .engine_state import (
    BUDGET,
    COND_BOUND,
    FLAT,
    GROWTH,
    RUNNING,
    SIGMA_COLLAPSE,
    STAGNATION,
    TARGET,
    ExploitState,
    StepRecord,
    is_lazy,
    lazy_decompose,
    record,
)
from .kernels import cmaes, threefry
from .kernels import network as kn
from .kernels import pruning as kp
from .rows import where_rows
from .tasks.base import Task, check_costs

__all__ = ["attempt", "costs", "step"]


def costs(task: Task, key: jax.Array, layout: kn.Layout, x: jax.Array) -> jax.Array:
    """Costs ``[S, K]`` of candidate weight vectors ``x`` ``[S, K, P]`` of S structures.

    Networks are evaluated in float32 whatever the dtype of the CMA-ES state.
    """
    x = x.astype(jnp.float32)
    nets = jax.vmap(jax.vmap(kn.network, in_axes=(None, 0)))(layout, x)
    return check_costs(task, task.cost(key, nets), x.shape[:2])


def _tick_keys(
    st: ExploitState, task_key: jax.Array, in_refit: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """``(keys [S], key)``: each structure's key of this engine iteration and the task's.

    A CMA-ES iteration folds the iteration number (below 2^31) into the structure's key; a
    re-fit iteration folds it with bit 31 set, then the re-fit's own count, so its samples
    are apart from every CMA-ES iteration's; the task's key folds the engine iteration.
    The independent folds run as ONE batched ``fold_in`` (the same numbers as one call
    each), `jax.random.fold_in`'s own bits with the rounds written out on a CPU
    (`kernels.threefry`).
    """
    rows = st.key.shape[0]
    iteration = st.iteration.astype(jnp.uint32)
    sources = [st.key, task_key[None]]
    data = [iteration, st.tick.astype(jnp.uint32)[None]]
    if st.attempt is not None:
        sources.append(st.key)
        data.append(iteration | jnp.uint32(1 << 31))
    folded = jax.vmap(threefry.fold_in)(jnp.concatenate(sources), jnp.concatenate(data))
    keys, key = folded[:rows], folded[rows]
    if st.attempt is not None:
        refit_keys = jax.vmap(threefry.fold_in)(folded[rows + 1 :], st.attempt.refit_done)
        keys = jnp.where(in_refit, refit_keys, keys)
    return keys, key


def step(
    st: ExploitState,
    layout: kn.Layout,
    tables: kp.Tables,
    task: Task,
    task_key: jax.Array,
    config: ExploitConfig,
) -> tuple[ExploitState, StepRecord]:
    """One engine iteration of every running structure: a CMA-ES iteration, or the phase of
    a pruning attempt it is in, with ONE evaluation of the task's cost for all of them."""
    running = st.stop == RUNNING
    att = st.attempt
    phase = jnp.zeros_like(st.stop) if att is None else jnp.where(running, att.phase, 0)
    normal = running & (phase == pruning.NORMAL)
    in_trial = running & (phase == pruning.TRIAL)
    in_refit = running & (phase == pruning.REFIT)
    cma, eigen_age, f, updated = _evaluate_and_tell(
        st, layout, task, task_key, config, normal, in_trial, in_refit
    )
    new, nonfinite = _advance(st, cma, eigen_age, f, normal, updated, in_trial, config)
    prune = None
    if att is not None:
        new, prune = prune_phase(new, st, normal, in_trial, in_refit, f, tables, config)
    return new, record(new, running, phase, nonfinite, prune)


def _evaluate_and_tell(st, layout, task, task_key, config, normal, in_trial, in_refit):
    """Ask every structure for its candidates (a trial's shifted means where it is in one),
    evaluate them all with ONE call of the task's cost, and tell the structures this
    iteration updates: ``(cma, eigen_age, costs [S, lambda], updated [S])``."""
    att = st.attempt
    keys, key = _tick_keys(st, task_key, in_refit)
    x, asked = jax.vmap(cmaes.ask)(keys, st.cma, st.params)  # [S, lambda, P]
    popsize = x.shape[1]
    if att is not None:
        x = jnp.where(in_trial[:, None, None], pruning.trial_points(att, st.cma.mean, popsize), x)
    f = costs(task, key, layout, x)  # the task's one call site in the program
    lazy = is_lazy(config)
    told = jax.vmap(functools.partial(cmaes.tell, decompose=not lazy))(asked, x, f, st.params)
    # The structures whose CMA-ES state this iteration updates (a re-fit iteration is a
    # CMA-ES iteration of the reduced structure).
    updated = normal | in_refit
    cma = where_rows(updated, told, st.cma)
    eigen_age = st.eigen_age
    if lazy:
        cma, eigen_age = lazy_decompose(
            cma, st.params, st.eigen_age, updated, st.tick, config.lazy_eigen
        )
    return cma, eigen_age, f, updated


def _advance(st, cma, eigen_age, f, normal, updated, in_trial, config):
    """The engine's bookkeeping after the CMA-ES update: sigma_bar, counters and the stop
    rules: ``(state, nonfinite [S])``."""
    att = st.attempt
    popsize = f.shape[1]
    prev_best = st.cma.best_cost
    margin = config.improve_rtol * jnp.abs(prev_best) + config.improve_atol
    # The first finite cost improves on "none yet": with prev_best = inf the margin is
    # inf * rtol and inf - inf = NaN, which compares False.
    improved = jnp.where(
        jnp.isfinite(prev_best), cma.best_cost < prev_best - margin, cma.best_cost < prev_best
    )
    improved &= normal
    sigma_bar = st.g * cma.sigma + (1 - st.g) * st.sigma_bar  # Paper eq. (5)
    # A re-fit iteration spends the structure's iteration budget like any other, so pruning
    # adds to a structure's evaluations only the one iteration that scores its shifted means.
    iteration = st.iteration + updated
    since_improve = jnp.where(improved, 0, st.since_improve + normal)
    spread = cma.sigma * jnp.max(cma.D, axis=-1)
    bound_run = jnp.where(normal, jnp.where(cma.cond_bounded, st.bound_run + 1, 0), st.bound_run)
    # TolFun (Hansen's tutorial, B.3; pycma's tolfun): every cost of this iteration, and so
    # every iteration's best, within tolfun of the best so far for 10 + ceil(30 n / lambda)
    # iterations in a row. A NaN/inf cost is never flat.
    flat = jnp.max(f, axis=-1) - cma.best_cost <= config.tolfun
    flat_run = jnp.where(normal, jnp.where(flat, st.flat_run + 1, 0), st.flat_run)
    flat_window = 10 + jnp.ceil(30 * st.params.n / popsize)
    stop = jnp.select(
        [
            ~normal,
            cma.best_cost <= config.target_cost,
            spread > config.sigma_up * config.sigma0,
            iteration >= config.max_iters,
            spread < config.sigma_tol,
            since_improve >= config.patience,
            bound_run >= config.bound_patience,
            flat_run >= flat_window,
        ],
        [st.stop, TARGET, GROWTH, BUDGET, SIGMA_COLLAPSE, STAGNATION, COND_BOUND, FLAT],
        RUNNING,
    ).astype(jnp.int32)
    decreased = normal & (sigma_bar < st.sigma_bar)
    evals = updated * popsize
    if att is not None:
        evals += in_trial * (1 + att.trial.shape[1])
    nonfinite = updated * cma.num_nonfinite
    new = ExploitState(
        cma=cma,
        params=st.params,
        key=st.key,
        sigma_bar=jnp.where(normal, sigma_bar, st.sigma_bar),
        g=st.g,
        iteration=iteration,
        evals=st.evals + evals,
        since_improve=since_improve,
        nonfinite=st.nonfinite + nonfinite,
        stop=stop,
        down_run=jnp.where(decreased, st.down_run + 1, jnp.where(normal, 0, st.down_run)),
        bound_run=bound_run,
        flat_run=flat_run,
        prune_attempts=st.prune_attempts,
        prune_accepted=st.prune_accepted,
        tick=st.tick + 1,
        eigen_age=eigen_age,
        attempt=att,
    )
    return new, nonfinite


def attempt(st, trigger, layout, tables, task, key, config):
    """A whole pruning attempt of the ``trigger`` structures, driven by `step` (the
    engine's own path) until every one is decided: ``(state, record)`` with each
    structure's decided attempt. For tests and benchmarks; every triggered structure must
    be running and have a removable parameter."""
    st = start_attempt(st, trigger, tables, config)

    def body(carry):
        s, rec = carry
        s, done = step(s, layout, tables, task, key, config)
        return s, where_rows(done.prune.attempted, done.prune, rec)

    def pending(carry):
        return jnp.any(carry[0].attempt.phase != pruning.NORMAL)

    skipped = pruning.AttemptRecord.skipped(trigger.shape[0])
    return jax.lax.while_loop(pending, body, (st, skipped))
