"""Pruning (paper section IV, figure 5): one stage, on device and on the host.

* Device: the pruning attempt of a batch of CMA-ES runs, as stages that the engine
  (`eant2_jax.exploitation`) drives with its own iterations: `propose` (the
  candidate of eqs. 5-8 with the sign erratum, or a baseline's, and the shift onto
  ``p_i = 0``), `trial_points` (what the next evaluation is), `judge`
  (acceptance, IV.B.3, and the conditioned covariance of the reduced structure) and, after a
  re-fit, `conclude`. The stages never call the task: the engine evaluates the points
  they ask for with the same cost call as its CMA-ES iterations. The maths lives in
  `eant2_jax.kernels.pruning`.
* Host (`eant2_jax.genomepruning`, its names also here): `tables_for`, the genome
  structure the device pruner reads; a removed
  connection is switched off in the CMA-ES mask, so the gene slots of a structure never move
  during a run. After the run, `prune_genome` drops the removed genes from the genome and
  fixes the neurons' input counts, and `attempt_records` turns the device records into
  one `PruneAttempt` per attempt.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from . import pytree

# The host side (`eant2_jax.genomepruning`), named here too so that the stage is one import.
from .genomepruning import PruneAttempt as PruneAttempt
from .genomepruning import attempt_records as attempt_records
from .genomepruning import kept_genes as kept_genes
from .genomepruning import prune_genome as prune_genome
from .genomepruning import tables_for as tables_for
from .kernels import cmaes
from .kernels import pruning as kp
from .kernels.pruning import PRUNERS, Tables
from .rows import where_rows

__all__ = [
    "NORMAL",
    "PRUNERS",
    "REFERENCES",
    "REFIT",
    "TRIAL",
    "Attempt",
    "AttemptRecord",
    "attempt_key",
    "PruneAttempt",
    "attempt_records",
    "conclude",
    "judge",
    "propose",
    "reduce",
    "refit_progress",
    "trial_count",
    "trial_points",
    "inert_tables",
    "kept_genes",
    "prune_genome",
    "tables_for",
    "where_rows",
]


# What an attempt's cost is compared with: the current mean's cost (the paper) or the best
# cost seen before the attempt.
REFERENCES = ("mean", "best")


# ---------------------------------------------------------------------------------- device
@pytree.dataclass
class AttemptRecord:
    """What a step records of the pruning attempt of each of S structures (``[S]`` leaves).

    Attributes:
      attempted: an attempt was made.
      gene: the candidate gene (-1 without an attempt).
      axis: the covariance pruner's principal axis j* (-1 otherwise).
      factor: its scaling factor s_{i*j*} (eq. 7; NaN otherwise).
      e: the cost of the mean before the shift; e_shifted: the cost after it (NaN without an
        attempt).
      e_refit: the best cost of the re-fit of the reduced structure (NaN without a re-fit).
      e_reference: the cost the acceptance compared with (``e``, or the best cost before
        the attempt).
      accepted: the removal was accepted.
      cond_before, cond_after: cond(C) before and after the attempt (NaN without one).
      iteration: the structure's CMA-ES iteration when the attempt started (-1 without one);
        a re-fit's iterations come after it and are not counted as CMA-ES iterations.
    """

    attempted: jax.Array
    gene: jax.Array
    axis: jax.Array
    factor: jax.Array
    e: jax.Array
    e_shifted: jax.Array
    e_refit: jax.Array
    e_reference: jax.Array
    accepted: jax.Array
    cond_before: jax.Array
    cond_after: jax.Array
    iteration: jax.Array

    @classmethod
    def skipped(cls, s_count: int) -> AttemptRecord:
        """The record of S structures none of which attempted (its dtypes rule)."""
        nan = jnp.full(s_count, jnp.nan, jnp.float32)
        no = jnp.zeros(s_count, bool)
        none = jnp.full(s_count, -1, jnp.int32)
        return cls(no, none, none, nan, nan, nan, nan, nan, no, nan, nan, none)


# An attempt in progress is a small state machine per structure, driven by the engine's
# iterations: the engine evaluates whatever points each structure's phase asks for with ONE
# call of the task's cost, compiled once per program; compiling it once per phase (CMA-ES,
# shifted means, re-fit) made the pruner's compile time 2-3x the engine's without it.
NORMAL, TRIAL, REFIT = 0, 1, 2


@pytree.dataclass
class Attempt:
    """The pruning attempts of S structures in progress (``[S]`` leading dims).

    Attributes:
      phase: ``NORMAL`` (CMA-ES iterations), ``TRIAL`` (the next evaluation is of the mean
        and the k shifted means) or ``REFIT`` (CMA-ES iterations of the reduced structure).
      trial: ``[S, k, P]`` the shifted means, removed coordinates at 0; removed: ``[S, k, P]``
        each candidate's removal set; gene, axis, factor, scored: ``[S, k]`` each candidate's
        gene, principal axis, scaling factor and whether its score was finite.
      record: the attempt's record so far (completed when it is decided).
      picked_scored: the re-fitted candidate's score was finite.
      saved_cma, saved_params: the state before the attempt, restored on rejection.
      refit_left, refit_done: re-fit iterations left (of this stretch), and done.
      refit_mid, refit_mark: the ``refit_left`` at the current stretch's midpoint, and the
        re-fit's best cost there (`refit_progress`).
      deferred_stop: the stop an attempt at a stop postponed (0 = none).
    """

    phase: jax.Array
    trial: jax.Array
    removed: jax.Array
    gene: jax.Array
    axis: jax.Array
    factor: jax.Array
    scored: jax.Array
    record: AttemptRecord
    picked_scored: jax.Array
    saved_cma: cmaes.State
    saved_params: cmaes.Params
    refit_left: jax.Array
    refit_done: jax.Array
    refit_mid: jax.Array
    refit_mark: jax.Array
    deferred_stop: jax.Array

    @classmethod
    def idle(cls, cma: cmaes.State, params: cmaes.Params, k: int) -> Attempt:
        """No attempt in progress, room for ``k`` candidates of ``[S, P]`` weights."""
        s_count, p = cma.mean.shape
        k = trial_count(k, p, params.weights.shape[-1])
        zeros = jnp.zeros(s_count, jnp.int32)
        return cls(
            phase=zeros,
            trial=jnp.zeros((s_count, k, p), cma.mean.dtype),
            removed=jnp.zeros((s_count, k, p), bool),
            gene=jnp.zeros((s_count, k), jnp.int32),
            axis=jnp.zeros((s_count, k), jnp.int32),
            factor=jnp.zeros((s_count, k), jnp.float32),
            scored=jnp.zeros((s_count, k), bool),
            record=AttemptRecord.skipped(s_count),
            picked_scored=jnp.zeros(s_count, bool),
            saved_cma=cma,
            saved_params=params,
            refit_left=zeros,
            refit_done=zeros,
            refit_mid=zeros,
            refit_mark=jnp.full(s_count, jnp.inf, cma.best_cost.dtype),
            deferred_stop=zeros,
        )


def trial_count(k: int, genes: int, popsize: int) -> int:
    """Candidates per attempt: ``k``, at most the genes and ``popsize - 1`` (the mean and the
    shifted means are evaluated as one population of the engine)."""
    return max(1, min(k, genes, popsize - 1))


def propose(
    att: Attempt,
    cma: cmaes.State,
    trigger: jax.Array,
    tables: Tables,
    iteration: jax.Array,
    *,
    pruner: str,
    keys: jax.Array | None = None,
) -> Attempt:
    """Start an attempt for every triggered structure (paper eqs. 5-8, or a baseline's
    scores): its k best-scored parameters, their shifted means with their sub-genomes set to
    0, and the next phase ``TRIAL``. Other structures are unchanged.

    Args:
      att: the attempts in progress (none for the triggered structures).
      cma: the CMA-ES state; trigger: ``[S]`` the structures that attempt.
      tables: the pruner tables ``[S, P]``; iteration: ``[S]`` each one's CMA-ES iteration.
      pruner: ``covariance``, ``magnitude``, ``obd``, ``obs``, ``snr`` or ``random``
        (static).
      keys: ``[S]`` each structure's PRNG key (the engine state's ``key``); read by the
        ``random`` pruner alone, through `attempt_key`.
    """
    s_count, p = cma.mean.shape
    k = att.trial.shape[1]
    removable = jax.vmap(kp.removable)(tables, cma.mask)
    scores = functools.partial(kp.scores, pruner)
    args = (cma.mean, cma.sigma, cma.C, cma.B, cma.D, cma.valid_axes, removable)
    if pruner == "random":
        if keys is None:
            raise ValueError("the random pruner needs the structures' keys")
        draw = jax.vmap(attempt_key)(keys, iteration)
        score, shifted, axis, factor = jax.vmap(scores)(*args, draw)
    else:
        score, shifted, axis, factor = jax.vmap(scores)(*args)
    _, top = jax.lax.top_k(-score, k)  # [S, k] the k smallest scores
    rows = jnp.arange(s_count)[:, None]
    removed = jax.vmap(jax.vmap(kp.removal_set, in_axes=(None, None, 0)))(
        tables, cma.mask, top
    )  # [S, k, P]
    proposed = att.replace(
        phase=jnp.full_like(att.phase, TRIAL),
        trial=jnp.where(removed, 0, shifted[rows, top]).astype(att.trial.dtype),
        removed=removed,
        gene=top.astype(jnp.int32),
        axis=axis[rows, top].astype(jnp.int32),
        factor=factor[rows, top].astype(jnp.float32),
        scored=jnp.isfinite(score[rows, top]),
        record=att.record.replace(iteration=iteration.astype(jnp.int32)),
    )
    return where_rows(trigger, proposed, att)


def attempt_key(key: jax.Array, iteration: jax.Array) -> jax.Array:
    """The key of the random pruner's draw for a structure whose attempt starts at CMA-ES
    ``iteration``: its key folded with the iteration with bit 31 set (as its re-fit keys
    are, `eant2_jax.engine_step`) and then with ``2**32 - 1``, a count no re-fit reaches, so
    the draw is apart from every CMA-ES and re-fit sample; the same key and iteration give
    the same draw."""
    first = jax.random.fold_in(key, iteration.astype(jnp.uint32) | jnp.uint32(1 << 31))
    return jax.random.fold_in(first, jnp.uint32(0xFFFFFFFF))


def trial_points(att: Attempt, mean: jax.Array, popsize: int) -> jax.Array:
    """``[S, popsize, P]``: the mean, the k shifted means, then the mean again as filler."""
    s_count, k, p = att.trial.shape
    mean = mean.astype(att.trial.dtype)
    fill = jnp.broadcast_to(mean[:, None], (s_count, popsize - 1 - k, p))
    return jnp.concatenate([mean[:, None], att.trial, fill], axis=1)


def judge(
    att: Attempt,
    cma: cmaes.State,
    params: cmaes.Params,
    costs: jax.Array,
    active: jax.Array,
    *,
    tolerance: float | jax.Array,
    atol: float | jax.Array = 0.0,
    refit: int,
    refit_scale: float | jax.Array,
    refit_limit: int | jax.Array,
    reference: str,
) -> tuple[Attempt, cmaes.State, cmaes.Params, AttemptRecord, jax.Array]:
    """The ``TRIAL`` phase of the ``active`` structures, given the costs of `trial_points` (IV.B.3).

    Without a re-fit (the paper): accept iff the lowest shifted cost that passes rises by
    less than ``tolerance`` (relative) plus ``atol`` (absolute, `kernels.pruning.accept`)
    over the reference (the mean's cost ``e``, or the best cost
    before the attempt with ``reference="best"``); the attempt is decided here. With one, the
    lowest shifted cost goes on to ``min(refit, refit_limit)`` CMA-ES iterations of the
    reduced structure (phase ``REFIT``; its step size is ``max(sigma, refit_scale *
    |shift| / sqrt(n))``, since the straight-line shift is exact only on a quadratic), and
    `conclude` decides.

    Returns:
      ``(attempt, cma, params, record, decided)``: ``record`` holds the attempts decided now
      (``decided`` ``[S]``); a rejected attempt leaves the CMA-ES state exactly as it was.
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}")
    s_count, k, _ = att.trial.shape
    e, e_trial = costs[:, 0], costs[:, 1 : 1 + k]
    e_ref = cma.best_cost if reference == "best" else e
    ok = kp.accept(e_ref[:, None], e_trial, tolerance, atol) & att.scored
    if refit:
        # The lowest shifted cost goes on to the re-fit (the best-scored if none is finite).
        pick = jnp.argmin(jnp.where(att.scored & jnp.isfinite(e_trial), e_trial, jnp.inf), 1)
    else:
        # The lowest shifted cost that passes; if none passes, report the best-scored one.
        pick = jnp.where(jnp.any(ok, axis=1), jnp.argmin(jnp.where(ok, e_trial, jnp.inf), 1), 0)
    s_idx = jnp.arange(s_count)
    remove = att.removed[s_idx, pick]
    mean = att.trial[s_idx, pick]
    e_new = e_trial[s_idx, pick]
    pruned, new_params = reduce(cma, params, remove, mean, e_new)
    record = _trial_record(att, cma, active, (s_idx, pick), e, e_new, e_ref)
    if refit:
        started, pruned = _start_refit(
            att, cma, params, pruned, record, mean, (s_idx, pick), refit, refit_scale, refit_limit
        )
        return (
            where_rows(active, started, att),
            where_rows(active, pruned, cma),
            where_rows(active, new_params, params),
            AttemptRecord.skipped(s_count),
            jnp.zeros(s_count, bool),
        )
    accepted = active & jnp.any(ok, axis=1)
    cond_after = jnp.where(accepted, pruned.cond, record.cond_after)
    record = _cast_record(record.replace(accepted=accepted, cond_after=cond_after))
    done = att.replace(phase=jnp.where(active, NORMAL, att.phase))
    return (
        done,
        where_rows(accepted, pruned, cma),
        where_rows(accepted, new_params, params),
        record,
        active,
    )


def _trial_record(att, cma, active, picked, e, e_new, e_ref) -> AttemptRecord:
    """The record of the ``active`` structures' trial of their ``picked`` candidates (the
    rows' and candidates' indices), not accepted yet (`judge`)."""
    nan, s_count = jnp.nan, active.shape[0]
    record = AttemptRecord(
        attempted=active,
        gene=jnp.where(active, att.gene[picked], -1),
        axis=jnp.where(active, att.axis[picked], -1),
        factor=jnp.where(active, att.factor[picked], nan),
        e=jnp.where(active, e, nan),
        e_shifted=jnp.where(active, e_new, nan),
        e_refit=jnp.full(s_count, nan),
        e_reference=jnp.where(active, e_ref, nan),
        accepted=jnp.zeros(s_count, bool),
        cond_before=jnp.where(active, cma.cond, nan),
        cond_after=jnp.where(active, cma.cond, nan),
        iteration=att.record.iteration,
    )
    return _cast_record(record)


def _start_refit(att, cma, params, pruned, record, mean, picked, refit, refit_scale, refit_limit):
    """``(attempt, pruned)`` entering the ``REFIT`` phase with the picked candidate: the
    reduced structure's step size ``max(sigma, refit_scale * |shift| / sqrt(n))`` and the
    state before the attempt saved (`judge`; ``picked``: the rows' and candidates' indices)."""
    n_keep = jnp.maximum(pruned.n, 1).astype(cma.sigma.dtype)
    step = jnp.linalg.norm(jnp.where(pruned.mask, mean - cma.mean, 0), axis=-1)
    sigma = jnp.maximum(cma.sigma, refit_scale * step / jnp.sqrt(n_keep))
    pruned = pruned.replace(sigma=sigma.astype(cma.sigma.dtype))
    left = jnp.broadcast_to(jnp.maximum(jnp.minimum(refit, refit_limit), 1), att.refit_left.shape)
    left = left.astype(jnp.int32)
    started = att.replace(
        phase=jnp.full_like(att.phase, REFIT),
        record=record,
        picked_scored=att.scored[picked],
        saved_cma=cma,
        saved_params=params,
        refit_left=left,
        refit_done=jnp.zeros_like(att.refit_done),
        refit_mid=left // 2,
        refit_mark=jnp.full_like(att.refit_mark, jnp.inf),
    )
    return started, pruned


def reduce(
    cma: cmaes.State,
    params: cmaes.Params,
    remove: jax.Array,
    mean: jax.Array,
    best_cost: jax.Array,
) -> tuple[cmaes.State, cmaes.Params]:
    """The CMA-ES states ``[S]`` with the coordinates ``remove`` ``[S, P]`` removed (paper
    IV.B.3): masked out, the covariance conditioned on them (Schur complement) and decomposed
    again, the paths cleared on them, the hyper-parameters of the new dimension, and the
    mean and best set to ``mean`` (0 on the removed coordinates) and ``best_cost``."""
    keep = cma.mask & ~remove
    conditioned = jax.vmap(kp.condition)(cma.C, keep, remove)
    C, B, D, valid_axes, cond, bounded = jax.vmap(cmaes.spectrum)(conditioned, keep, params)
    n = jnp.sum(keep, axis=-1, dtype=jnp.int32)
    popsize = params.weights.shape[-1]
    new_params = jax.vmap(
        lambda n, bound: cmaes.default_params(
            n, popsize, max_condition=bound, diagonal=params.diagonal
        )
    )(jnp.maximum(n, 1), params.max_condition)
    new_params = jax.tree.map(lambda a, b: a.astype(b.dtype), new_params, params)
    reduced = cma.replace(
        mean=jnp.where(keep, mean, 0).astype(cma.mean.dtype),
        p_sigma=jnp.where(keep, cma.p_sigma, 0),
        p_c=jnp.where(keep, cma.p_c, 0),
        C=C,
        B=B,
        D=D,
        mask=keep,
        valid_axes=valid_axes,
        n=n,
        cond=cond,
        cond_bounded=bounded,
        best_x=jnp.where(keep, mean, 0).astype(cma.best_x.dtype),
        best_cost=jnp.asarray(best_cost).astype(cma.best_cost.dtype),
    )
    return reduced, new_params


def refit_progress(
    att: Attempt,
    cma: cmaes.State,
    in_refit: jax.Array,
    *,
    refit: int,
    budget_left: jax.Array,
    tolerance: float | jax.Array,
    atol: float | jax.Array = 0.0,
) -> tuple[Attempt, jax.Array]:
    """Count one re-fit iteration of the ``in_refit`` structures; returns ``(attempt,
    finishing [S])``, the structures whose re-fit ends now (`conclude` decides them).

    A re-fit runs in stretches of ``refit`` iterations (`judge` starts the first). Its best
    cost is marked at a stretch's midpoint; at the stretch's end the re-fit goes on for
    another stretch (within ``budget_left``, what ``max_iters`` leaves) while it is still
    closing in on the acceptance limit (`kernels.pruning.acceptance_limit`): above it, by at
    most half what it was above it at the midpoint. The acceptance compares the re-fit with
    a converged search's best, fair only once the re-fit has converged too (docs/pruning.md,
    "Plain cases"); a re-fit that levels off above the limit ends with its stretch.
    """
    left = att.refit_left - in_refit
    best = cma.best_cost
    mark = jnp.where(in_refit & (left == att.refit_mid), best, att.refit_mark)
    end = in_refit & (left <= 0)
    limit = kp.acceptance_limit(att.record.e_reference, tolerance, atol)
    gap, gap_mid = best - limit, mark - limit
    closing = jnp.isfinite(gap) & jnp.isfinite(gap_mid) & (gap > 0) & (gap <= 0.5 * gap_mid)
    more = jnp.minimum(refit, budget_left).astype(jnp.int32)
    extend = end & closing & att.picked_scored & (more > 0)
    att = att.replace(
        refit_left=jnp.where(extend, more, left),
        refit_done=att.refit_done + in_refit,
        refit_mid=jnp.where(extend, more // 2, att.refit_mid),
        refit_mark=mark,
    )
    return att, end & ~extend


def conclude(
    att: Attempt,
    cma: cmaes.State,
    params: cmaes.Params,
    finishing: jax.Array,
    *,
    tolerance: float | jax.Array,
    atol: float | jax.Array = 0.0,
) -> tuple[Attempt, cmaes.State, cmaes.Params, AttemptRecord]:
    """The end of the re-fit of the ``finishing`` structures: accept iff the re-fit's best
    cost (the shifted mean's own included) passes against the attempt's reference; on
    rejection restore the state from before the attempt exactly."""
    rec = att.record
    e_after = cma.best_cost
    accepted = finishing & kp.accept(rec.e_reference, e_after, tolerance, atol) & att.picked_scored
    rejected = finishing & ~accepted
    record = rec.replace(
        attempted=finishing,
        e_refit=jnp.where(finishing, e_after, jnp.nan),
        accepted=accepted,
        cond_after=jnp.where(accepted, cma.cond, rec.cond_before),
    )
    record = where_rows(finishing, _cast_record(record), AttemptRecord.skipped(finishing.shape[0]))
    return (
        att.replace(phase=jnp.where(finishing, NORMAL, att.phase)),
        where_rows(rejected, att.saved_cma, cma),
        where_rows(rejected, att.saved_params, params),
        record,
    )


def _cast_record(record: AttemptRecord) -> AttemptRecord:
    """The record in the dtypes of `AttemptRecord.skipped` (one structure per branch)."""
    skipped = AttemptRecord.skipped(record.attempted.shape[0])
    return jax.tree.map(lambda a, b: a.astype(b.dtype), record, skipped)


# ------------------------------------------------------------------------------------ host
def inert_tables(rows: int, genes: int) -> Tables:
    """Tables ``[rows, genes]`` of padding only: nothing is removable."""
    idx = jnp.arange(genes, dtype=jnp.int32)
    return Tables(
        parent=jnp.full((rows, genes), -1, jnp.int32),
        subtree_end=jnp.broadcast_to(idx + 1, (rows, genes)),
        reads=jnp.full((rows, genes), -1, jnp.int32),
        is_neuron=jnp.zeros((rows, genes), bool),
    )
