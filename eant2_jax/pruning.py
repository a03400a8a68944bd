"""Pruning (paper section IV, figure 5): one stage, on device and on the host.

* Device: :func:`attempt` is the pruning attempt of a batch of CMA-ES runs — candidate
  (eqs. 5-8, with the sign erratum), shift, acceptance (IV.B.3) and the conditioned
  covariance of the reduced structure — for whichever structures the engine triggered. It
  takes the cost function as an argument and imports nothing from the CMA-ES engine
  (:mod:`eant2_jax.exploitation`), which decides when to call it; the maths lives in
  :mod:`eant2_jax.kernels.pruning`.
* Host: :func:`tables_for`, the genome structure the device pruner reads; a removed
  connection is switched off in the CMA-ES mask, so the gene slots of a structure never move
  during a run. After the run, :func:`prune_genome` drops the removed genes from the genome and
  fixes the neurons' input counts, and :func:`attempt_records` turns the device records into
  one :class:`PruneAttempt` per attempt.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from .genome import Gene, GeneKind, Genome
from .kernels import cmaes
from .kernels import pruning as kp
from .kernels.pruning import PRUNERS, Tables
from .rundir import typed_fields

__all__ = [
    "PRUNERS",
    "REFERENCES",
    "AttemptRecord",
    "PruneAttempt",
    "attempt",
    "attempt_records",
    "inert_tables",
    "kept_genes",
    "prune_genome",
    "tables_for",
    "where_rows",
]


# What an attempt's cost is compared with: the current mean's cost (the paper) or the best
# cost seen before the attempt.
REFERENCES = ("mean", "best")


def where_rows(pred: jax.Array, new, old):
    """``where(pred, new, old)`` leaf by leaf, ``pred`` ``[S]`` broadcast over trailing dims."""

    def pick(a, b):
        p = pred.reshape(pred.shape + (1,) * (a.ndim - pred.ndim))
        return jnp.where(p, a, b)

    return jax.tree.map(pick, new, old)


# ---------------------------------------------------------------------------------- device
@struct.dataclass
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

    @classmethod
    def skipped(cls, s_count: int) -> AttemptRecord:
        """The record of S structures none of which attempted (its dtypes rule)."""
        nan = jnp.full(s_count, jnp.nan, jnp.float32)
        no = jnp.zeros(s_count, bool)
        none = jnp.full(s_count, -1, jnp.int32)
        return cls(no, none, none, nan, nan, nan, nan, nan, no, nan, nan)


def attempt(
    cost_fn: Callable[[jax.Array], jax.Array],
    cma: cmaes.State,
    params: cmaes.Params,
    trigger: jax.Array,
    tables: Tables,
    keys: jax.Array,
    *,
    pruner: str,
    candidates: int = 1,
    tolerance: float | jax.Array = 1e-3,
    refit: int = 0,
    refit_scale: float | jax.Array = 0.3,
    refit_limit: int | jax.Array | None = None,
    reference: str = "mean",
) -> tuple[cmaes.State, cmaes.Params, AttemptRecord]:
    """A pruning attempt for every triggered structure of a batch (paper IV.B, fig. 5).

    The paper's attempt (``refit=0, reference="mean"``): the candidate of eqs. 5-8 (or a
    baseline pruner's), the shift onto ``p_i = 0``, and acceptance iff the shifted cost
    rises by less than ``tolerance`` over the cost ``e`` of the current mean. The tentative
    attempt (``refit > 0``) adds a short CMA-ES run of the reduced structure from the
    shifted mean, with the removed weights clamped to 0 (the other weights move back onto
    the cost's valley, which a straight-line shift leaves), before the acceptance test; with
    ``reference="best"`` the test is against the best cost seen before the attempt, never
    the mean that CMA-ES has drifted from it. A rejected attempt leaves the CMA-ES state
    exactly as it was.

    Args:
      cost_fn: costs ``[S, K]`` of weight vectors ``[S, K, P]`` (the task's, on the key of
        the current iteration, so the shifted means are ranked on the same draw as ``e``).
      cma: batched CMA-ES state ``[S]``; params: its hyper-parameters ``[S]``.
      trigger: ``[S]`` bool, the structures that attempt now (the engine's trigger).
      tables: batched pruner tables ``[S, P]`` (:func:`tables_for`).
      keys: ``[S]`` PRNG keys of the re-fit's samples (unused without a re-fit).
      pruner: ``covariance``, ``magnitude``, ``obd``, ``obs`` or ``snr`` (static).
      candidates: k, the k best-scored parameters are shifted and evaluated in one batch
        (static; 1 = the paper). Without a re-fit the lowest shifted cost that passes is
        taken; with one, the lowest shifted cost is re-fitted and tested.
      tolerance: accept iff the cost rises by less than this fraction (0.001: the paper).
      refit: CMA-ES iterations of the re-fit (static; 0 = none, the paper).
      refit_limit: at most this many re-fit iterations (traced; the engine passes the
        structure's own iteration budget, so a short run is not dominated by its re-fits).
      refit_scale: the re-fit starts from step size ``max(sigma, refit_scale * |shift| /
        sqrt(n))``, ``n`` the kept coordinates: the shift's error grows with its length.
      reference: ``"mean"`` (the paper: the cost of the current mean) or ``"best"`` (the
        best cost before the attempt) (static).

    Returns:
      ``(cma, params, record)``: the state and hyper-parameters with accepted removals
      applied (others unchanged), and the :class:`AttemptRecord`. A structure attempts only
      if it has a removable parameter; ``record.attempted`` says which did, and each costs
      ``1 + k + min(refit, refit_limit) * popsize`` evaluations.
    """
    if reference not in REFERENCES:
        raise ValueError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}")
    removable = jax.vmap(kp.removable)(tables, cma.mask)
    trigger = trigger & jnp.any(removable, axis=-1)
    skipped = AttemptRecord.skipped(trigger.shape[0])
    go = functools.partial(
        _attempt,
        cost_fn,
        tables,
        removable,
        keys,
        pruner=pruner,
        k=candidates,
        tolerance=tolerance,
        refit=refit,
        refit_scale=refit_scale,
        refit_limit=refit if refit_limit is None else refit_limit,
        reference=reference,
    )
    return jax.lax.cond(jnp.any(trigger), go, lambda c, p, t: (c, p, skipped), cma, params, trigger)


def _attempt(
    cost_fn, tables, removable, keys, cma, params, trigger, *, pruner, k, tolerance, refit,
    refit_scale, refit_limit, reference,
):  # fmt: skip
    s_count, p = removable.shape
    k = min(k, p)
    score, shifted, axis, factor = jax.vmap(functools.partial(kp.scores, pruner))(
        cma.mean, cma.sigma, cma.C, cma.B, cma.D, cma.valid_axes, removable
    )
    _, top = jax.lax.top_k(-score, k)  # [S, k] the k smallest scores
    rows = jnp.arange(s_count)[:, None]
    removed = jax.vmap(jax.vmap(kp.removal_set, in_axes=(None, None, 0)))(
        tables, cma.mask, top
    )  # [S, k, P]
    trial = jnp.where(removed, 0, shifted[rows, top])  # [S, k, P]
    costs = cost_fn(jnp.concatenate([cma.mean[:, None], trial], axis=1))
    e, e_trial = costs[:, 0], costs[:, 1:]
    e_ref = cma.best_cost if reference == "best" else e
    scored = jnp.isfinite(score[rows, top])
    ok = kp.accept(e_ref[:, None], e_trial, tolerance) & scored
    if refit:
        # The lowest shifted cost goes on to the re-fit (the best-scored if none is finite).
        pick = jnp.argmin(jnp.where(scored & jnp.isfinite(e_trial), e_trial, jnp.inf), 1)
    else:
        # Among the candidates that pass, the lowest shifted cost; if none passes, report
        # the best-scored one.
        pick = jnp.where(jnp.any(ok, axis=1), jnp.argmin(jnp.where(ok, e_trial, jnp.inf), 1), 0)
    s_idx = jnp.arange(s_count)
    gene = top[s_idx, pick]
    remove = removed[s_idx, pick] & trigger[:, None]
    mean = trial[s_idx, pick]
    e_new = e_trial[s_idx, pick]
    keep = cma.mask & ~remove
    conditioned = jax.vmap(kp.condition)(cma.C, keep, remove)
    C, B, D, valid_axes, cond, bounded = jax.vmap(cmaes.eigen)(
        conditioned, keep, params.max_condition
    )
    n = jnp.sum(keep, axis=-1, dtype=jnp.int32)
    popsize = params.weights.shape[-1]
    new_params = jax.vmap(lambda n, bound: cmaes.default_params(n, popsize, max_condition=bound))(
        jnp.maximum(n, 1), params.max_condition
    )
    new_params = jax.tree.map(lambda a, b: a.astype(b.dtype), new_params, params)
    pruned = cma.replace(
        mean=jnp.where(keep, mean, 0),
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
        best_x=jnp.where(keep, mean, 0),
        best_cost=e_new.astype(cma.best_cost.dtype),
    )
    if refit:
        # The straight-line shift is exact only on a quadratic; its error grows with the
        # length of the shift. A converged sigma is far smaller than that, so the re-fit
        # starts from a step size of ``refit_scale`` times the shift's RMS length per kept
        # coordinate (or the current sigma if larger).
        n_keep = jnp.maximum(jnp.sum(keep, axis=-1), 1).astype(cma.sigma.dtype)
        step = jnp.linalg.norm(jnp.where(keep, mean - cma.mean, 0), axis=-1)
        sigma = jnp.maximum(cma.sigma, refit_scale * step / jnp.sqrt(n_keep))
        iterations = jnp.minimum(refit, refit_limit)
        pruned = pruned.replace(sigma=sigma.astype(cma.sigma.dtype))
        pruned = _refit(cost_fn, keys, pruned, new_params, iterations)
        e_after = pruned.best_cost
        passed = kp.accept(e_ref, e_after, tolerance) & scored[s_idx, pick]
    else:
        e_after = e_new
        passed = jnp.any(ok, axis=1)
    accepted = trigger & passed
    nan = jnp.nan
    record = AttemptRecord(
        attempted=trigger,
        gene=jnp.where(trigger, gene, -1).astype(jnp.int32),
        axis=jnp.where(trigger, axis[s_idx, gene], -1),
        factor=jnp.where(trigger, factor[s_idx, gene], nan),
        e=jnp.where(trigger, e, nan),
        e_shifted=jnp.where(trigger, e_new, nan),
        e_refit=jnp.where(trigger & (refit > 0), e_after, nan),
        e_reference=jnp.where(trigger, e_ref, nan),
        accepted=accepted,
        cond_before=jnp.where(trigger, cma.cond, nan),
        cond_after=jnp.where(trigger, jnp.where(accepted, pruned.cond, cma.cond), nan),
    )
    skipped = AttemptRecord.skipped(s_count)
    record = jax.tree.map(lambda a, b: a.astype(b.dtype), record, skipped)
    return (
        where_rows(accepted, pruned, cma),
        where_rows(accepted, new_params, params),
        record,
    )


def _refit(cost_fn, keys, cma, params, iterations: jax.Array):
    """``iterations`` CMA-ES iterations of every structure from its shifted state (the removed
    coordinates are masked out, so they stay exactly 0); the best cost and weights include
    the shifted mean's own."""

    def body(r, state):
        ks = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, r)
        x, state = jax.vmap(cmaes.ask)(ks, state, params)
        return jax.vmap(cmaes.tell)(state, x, cost_fn(x), params)

    return jax.lax.fori_loop(0, iterations, body, cma)


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


def tables_for(genomes: Sequence[Genome], genes: int, rows: int | None = None) -> Tables:
    """Pruner tables for a batch, ``[rows, genes]`` (padding rows and slots are inert).

    Args:
      genomes: the structures.
      genes: padded number of gene slots ``P``.
      rows: padded number of structures (default ``len(genomes)``).
    """
    rows = len(genomes) if rows is None else rows
    idx = np.arange(genes, dtype=np.int32)
    parent = np.full((rows, genes), -1, np.int32)
    subtree_end = np.tile(idx + 1, (rows, 1)).astype(np.int32)
    reads = np.full((rows, genes), -1, np.int32)
    is_neuron = np.zeros((rows, genes), bool)
    for r, g in enumerate(genomes):
        n = len(g)
        parent[r, :n] = g.parent
        pos = g.neuron_position
        for i, gene in enumerate(g.genes):
            if gene.kind == GeneKind.NEURON:
                is_neuron[r, i] = True
                subtree_end[r, i] = g.subtree_end(i)
            elif gene.kind in (GeneKind.FORWARD, GeneKind.RECURRENT):
                reads[r, i] = pos[gene.ref]
    return Tables(
        parent=jnp.asarray(parent),
        subtree_end=jnp.asarray(subtree_end),
        reads=jnp.asarray(reads),
        is_neuron=jnp.asarray(is_neuron),
    )


def kept_genes(original: Genome, pruned: Genome) -> list[int]:
    """Indices of ``original``'s genes that ``pruned`` kept, matched in order (the pruner
    removes whole sub-genomes and keeps the order of the rest). If ``pruned`` is not such a
    sub-sequence, fewer than ``len(pruned)`` indices come back."""
    kept, j = [], 0
    for i, g in enumerate(original.genes):
        if j < len(pruned) and (pruned[j].kind, pruned[j].ref) == (g.kind, g.ref):
            kept.append(i)
            j += 1
    return kept


def prune_genome(genome: Genome, keep: np.ndarray, weights: np.ndarray | None = None) -> Genome:
    """The genome without the genes where ``keep`` is False, with neuron arities fixed.

    Args:
      genome: the original genome.
      keep: ``bool[len(genome)]``; removed genes must form whole sub-genomes (as the pruner
        removes them), and no kept jumper may read a removed neuron.
      weights: optional ``[len(genome)]`` weights for the kept genes (others ignored).

    Returns:
      The pruned, validated genome (evaluating it equals evaluating the original with the
      removed weights set to 0).
    """
    keep = np.asarray(keep, bool)
    if keep.shape != (len(genome),):
        raise ValueError(f"keep must have shape ({len(genome)},), got {keep.shape}")
    w = genome.weights if weights is None else np.asarray(weights, np.float64)
    parent = genome.parent
    kept_inputs = np.zeros(len(genome), np.int64)
    for i in range(len(genome)):
        if keep[i] and parent[i] >= 0:
            kept_inputs[parent[i]] += 1
    genes = []
    for i, gene in enumerate(genome.genes):
        if not keep[i]:
            continue
        if parent[i] >= 0 and not keep[parent[i]]:
            raise ValueError(
                f"gene {i} is kept but the neuron reading it (gene {parent[i]}) is not"
            )
        arity = int(kept_inputs[i]) if gene.kind == GeneKind.NEURON else 0
        genes.append(Gene(gene.kind, gene.ref, float(w[i]), arity))
    return Genome(genes)


_KIND_NAME = {k: k.name.lower() for k in GeneKind}


@dataclasses.dataclass(frozen=True)
class PruneAttempt:
    """One pruning attempt, as the run directory's ``pruning.jsonl`` holds it.

    Attributes:
      structure: the structure's index in its batch (or the label the caller gave it).
      iteration: the CMA-ES iteration of the attempt (1-based).
      pruner: the pruner's name.
      gene: the candidate gene; kind: its kind (``input``, ``bias``, ``neuron``, ...).
      axis: the covariance pruner's principal axis j* (-1 for the other pruners).
      s: its scaling factor s_{i*j*} (eq. 7), None for the other pruners.
      e, e_shifted: the cost of the mean before the shift, and of the shifted mean.
      e_refit: the best cost of the re-fit of the reduced structure (None without one).
      e_reference: the cost the acceptance compared with.
      accepted: the removal was kept.
      cond_before, cond_after: cond(C) before and after.
      generation: the EANT2 generation (None outside the loop).
    """

    structure: int
    iteration: int
    pruner: str
    gene: int
    kind: str
    axis: int
    s: float | None
    e: float
    e_shifted: float
    e_refit: float | None
    e_reference: float
    accepted: bool
    cond_before: float
    cond_after: float
    generation: int | None = None

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        if self.generation is None:
            del d["generation"]
        return d

    @classmethod
    def from_json(cls, d: dict) -> PruneAttempt:
        # Records written before the tentative attempt existed have neither field.
        if isinstance(d, dict):
            d = {"e_refit": None, "e_reference": d.get("e"), **d}
        return cls(**typed_fields(cls, d, "a pruning record"))


def attempt_records(
    history: AttemptRecord | None,
    genomes: Sequence[Genome],
    pruner: str,
    structure_ids: Sequence[int] | None = None,
) -> list[PruneAttempt]:
    """One record per pruning attempt from an exploitation history.

    Args:
      history: the engine history's pruning part, :class:`AttemptRecord` of
        ``[iterations, S]`` arrays (None without a pruner).
      genomes: the structures, in batch order (to name the kind of the gene).
      pruner: the pruner's name.
      structure_ids: label of each structure in the records (default its batch index).

    Returns:
      The attempts, sorted by iteration then structure.
    """
    if history is None:
        return []
    out = []
    for it, s in zip(*np.nonzero(history.attempted), strict=True):
        if s >= len(genomes):
            continue
        gene = int(history.gene[it, s])
        factor = float(history.factor[it, s])
        out.append(
            PruneAttempt(
                structure=int(s if structure_ids is None else structure_ids[s]),
                iteration=int(it) + 1,
                pruner=pruner,
                gene=gene,
                kind=_KIND_NAME[genomes[s][gene].kind],
                axis=int(history.axis[it, s]),
                s=None if np.isnan(factor) else factor,
                e=float(history.e[it, s]),
                e_shifted=float(history.e_shifted[it, s]),
                e_refit=None if np.isnan(history.e_refit[it, s]) else float(history.e_refit[it, s]),
                e_reference=float(history.e_reference[it, s]),
                accepted=bool(history.accepted[it, s]),
                cond_before=float(history.cond_before[it, s]),
                cond_after=float(history.cond_after[it, s]),
            )
        )
    return out
