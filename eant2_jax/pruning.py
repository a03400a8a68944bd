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

__all__ = [
    "PRUNERS",
    "AttemptRecord",
    "PruneAttempt",
    "attempt",
    "attempt_records",
    "inert_tables",
    "prune_genome",
    "tables_for",
    "where_rows",
]


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
      e: the cost before the shift; e_shifted: the cost after it (NaN without an attempt).
      accepted: the removal was accepted.
      cond_before, cond_after: cond(C) before and after the attempt (NaN without one).
    """

    attempted: jax.Array
    gene: jax.Array
    axis: jax.Array
    factor: jax.Array
    e: jax.Array
    e_shifted: jax.Array
    accepted: jax.Array
    cond_before: jax.Array
    cond_after: jax.Array

    @classmethod
    def skipped(cls, s_count: int) -> AttemptRecord:
        """The record of S structures none of which attempted (its dtypes rule)."""
        nan = jnp.full(s_count, jnp.nan, jnp.float32)
        no = jnp.zeros(s_count, bool)
        none = jnp.full(s_count, -1, jnp.int32)
        return cls(no, none, none, nan, nan, nan, no, nan, nan)


def attempt(
    cost_fn: Callable[[jax.Array], jax.Array],
    cma: cmaes.State,
    params: cmaes.Params,
    trigger: jax.Array,
    tables: Tables,
    *,
    pruner: str,
    candidates: int = 1,
    tolerance: float | jax.Array = 1e-3,
) -> tuple[cmaes.State, cmaes.Params, AttemptRecord]:
    """A pruning attempt for every triggered structure of a batch (paper IV.B, fig. 5).

    Args:
      cost_fn: costs ``[S, K]`` of weight vectors ``[S, K, P]`` (the task's, on the key of
        the current iteration, so the shifted means are ranked on the same draw as ``e``).
      cma: batched CMA-ES state ``[S]``; params: its hyper-parameters ``[S]``.
      trigger: ``[S]`` bool, the structures that attempt now (the engine's trigger).
      tables: batched pruner tables ``[S, P]`` (:func:`tables_for`).
      pruner: ``covariance``, ``magnitude``, ``obd`` or ``obs`` (static).
      candidates: k, the k best-scored parameters are tried in one batch; the lowest
        shifted cost that passes is taken (static; 1 = the paper).
      tolerance: accept iff the cost rises by less than this fraction (0.001: the paper).

    Returns:
      ``(cma, params, record)``: the state and hyper-parameters with accepted removals
      applied (others unchanged), and the :class:`AttemptRecord`. A structure attempts only
      if it has a removable parameter; ``record.attempted`` says which did, and each costs
      ``1 + k`` evaluations.
    """
    removable = jax.vmap(kp.removable)(tables, cma.mask)
    trigger = trigger & jnp.any(removable, axis=-1)
    skipped = AttemptRecord.skipped(trigger.shape[0])
    go = functools.partial(
        _attempt, cost_fn, tables, removable, pruner=pruner, k=candidates, tolerance=tolerance
    )
    return jax.lax.cond(jnp.any(trigger), go, lambda c, p, t: (c, p, skipped), cma, params, trigger)


def _attempt(cost_fn, tables, removable, cma, params, trigger, *, pruner, k, tolerance):
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
    ok = kp.accept(e[:, None], e_trial, tolerance)
    ok &= jnp.isfinite(score[rows, top])
    # Among the candidates that pass, the lowest shifted cost; if none passes, report the
    # best-scored one.
    pick = jnp.where(jnp.any(ok, axis=1), jnp.argmin(jnp.where(ok, e_trial, jnp.inf), 1), 0)
    accepted = trigger & jnp.any(ok, axis=1)
    s_idx = jnp.arange(s_count)
    gene = top[s_idx, pick]
    remove = removed[s_idx, pick] & accepted[:, None]
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
    record = AttemptRecord(
        attempted=trigger,
        gene=jnp.where(trigger, gene, -1).astype(jnp.int32),
        axis=jnp.where(trigger, axis[s_idx, gene], -1),
        factor=jnp.where(trigger, factor[s_idx, gene], jnp.nan),
        e=jnp.where(trigger, e, jnp.nan),
        e_shifted=jnp.where(trigger, e_new, jnp.nan),
        accepted=accepted,
        cond_before=jnp.where(trigger, cma.cond, jnp.nan),
        cond_after=jnp.where(trigger, jnp.where(accepted, cond, cma.cond), jnp.nan),
    )
    skipped = AttemptRecord.skipped(s_count)
    record = jax.tree.map(lambda a, b: a.astype(b.dtype), record, skipped)
    return (
        where_rows(accepted, pruned, cma),
        where_rows(accepted, new_params, params),
        record,
    )


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
      e, e_shifted: the cost before and after the shift.
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
        return cls(**d)


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
                accepted=bool(history.accepted[it, s]),
                cond_before=float(history.cond_before[it, s]),
                cond_after=float(history.cond_after[it, s]),
            )
        )
    return out
