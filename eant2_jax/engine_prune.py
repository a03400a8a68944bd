"""The pruning phase of an engine iteration (paper IV.B.1): when an attempt fires, and the
engine's bookkeeping of the attempts that the stages of `eant2_jax.pruning` decide."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from . import pruning
from .engine_state import PRUNE_AT, RESUME_AFTER, RUNNING, cond_rare, decomposed, is_lazy
from .kernels import pruning as kp
from .rows import where_rows

__all__ = ["prune_phase", "start_attempt"]


def prune_phase(new, st, normal, in_trial, in_refit, f, tables, config):
    """The pruning stage of one engine iteration: decide the attempts whose shifted means
    (``in_trial``) or re-fit (``in_refit``, last iteration) were just evaluated, then start
    an attempt for every structure whose trigger fired (paper IV.B.1), and the engine's
    bookkeeping of both."""
    att, cma, params = new.attempt, new.cma, new.params
    skipped = pruning.AttemptRecord.skipped(in_trial.shape[0])
    judge = functools.partial(
        pruning.judge,
        tolerance=config.prune_tolerance,
        atol=config.improve_atol,
        refit=config.prune_refit,
        refit_scale=config.prune_refit_scale,
        # The re-fit gets what is left of the budget (at least one iteration: an attempt
        # at the budget stop still has its reduced structure tuned once).
        refit_limit=config.max_iters - new.iteration,
        reference=config.prune_reference,
    )
    # Paper IV.B.1: attempt when sigma_bar has decreased for >= W iterations, then
    # increases; with prune_at_stop also when the structure stops (its CMA-ES converged).
    # Only structures in the NORMAL phase trigger, so deciding the attempts of the others
    # (below) changes nothing this depends on.
    trigger = normal & (new.sigma_bar > st.sigma_bar) & (st.down_run >= config.prune_window)
    if config.prune_at_stop:
        trigger |= normal & jnp.isin(new.stop, jnp.asarray(PRUNE_AT))
    trigger &= jnp.any(jax.vmap(kp.removable)(tables, cma.mask), axis=-1)

    def rare(a, c, p):
        # Shifted means evaluated: decide (no re-fit) or start the re-fit (the conditioned
        # covariance's eigendecomposition); then propose the triggered structures' attempts.
        # The two touch disjoint rows (TRIAL and NORMAL), so one branch, one read of its
        # predicate by the host on a GPU, does both; each leaves the rows of the other
        # unchanged. When only one has rows the other's batched eigh still runs: attempts
        # are rare (about one per structure in a 300-iteration servo run), a read per
        # iteration is not.
        a, c, p, record, decided = judge(a, c, p, f, in_trial)
        a, c = _begin(a, c, p, trigger, tables, new.iteration, config, new.key)
        return a, c, p, record, decided

    def usual(a, c, p):
        return a, c, p, skipped, jnp.zeros_like(in_trial)

    att, cma, params, record, decided = cond_rare(
        jnp.any(in_trial) | jnp.any(trigger), rare, usual, att, cma, params
    )
    if config.prune_refit:
        limits = dict(tolerance=config.prune_tolerance, atol=config.improve_atol)
        att, finishing = pruning.refit_progress(
            att, cma, in_refit, refit=config.prune_refit,
            budget_left=config.max_iters - new.iteration, **limits,
        )  # fmt: skip
        att, cma, params, refit_record = pruning.conclude(att, cma, params, finishing, **limits)
        record = where_rows(finishing, refit_record, record)
        decided |= finishing
    accepted = decided & record.accepted
    # An accepted removal at a stop (other than the budget) lets the structure run on.
    resume = accepted & jnp.isin(att.deferred_stop, jnp.asarray(RESUME_AFTER))
    stop = jnp.where(decided & ~resume, att.deferred_stop, new.stop)
    new = new.replace(
        cma=cma,
        params=params,
        attempt=att,
        stop=stop,
        since_improve=jnp.where(accepted, 0, new.since_improve),
        bound_run=jnp.where(accepted, 0, new.bound_run),
        flat_run=jnp.where(accepted, 0, new.flat_run),
        prune_attempts=new.prune_attempts + decided,
        prune_accepted=new.prune_accepted + accepted,
    )
    return _started(new, trigger, config), record


def _begin(att, cma, params, trigger, tables, iteration, config, keys):
    """``(attempt, cma)`` with a pruning attempt proposed for the ``trigger`` structures
    (the next engine iteration evaluates their shifted means); the other rows unchanged."""
    if is_lazy(config):
        # The candidate comes from the covariance as it is now, not as last decomposed.
        cma = decomposed(cma, params, trigger)
    att = pruning.propose(att, cma, trigger, tables, iteration, pruner=config.pruner, keys=keys)
    return att, cma


def _started(st, trigger, config):
    """The engine's bookkeeping of the attempts `_begin` started: a stop that fired with
    one waits for its decision."""
    if is_lazy(config):
        st = st.replace(eigen_age=jnp.where(trigger, 0, st.eigen_age))
    return st.replace(
        attempt=st.attempt.replace(
            deferred_stop=jnp.where(trigger, st.stop, st.attempt.deferred_stop)
        ),
        stop=jnp.where(trigger, RUNNING, st.stop),
        down_run=jnp.where(trigger, 0, st.down_run),
    )


def start_attempt(st, trigger, tables, config):
    """Start a pruning attempt of the ``trigger`` structures: `_begin` in one branch (one
    predicate read) for the decomposition and the proposal, then `_started`."""

    def begin(att, cma):
        return _begin(att, cma, st.params, trigger, tables, st.iteration, config, st.key)

    att, cma = cond_rare(jnp.any(trigger), begin, lambda a, c: (a, c), st.attempt, st.cma)
    return _started(st.replace(attempt=att, cma=cma), trigger, config)
