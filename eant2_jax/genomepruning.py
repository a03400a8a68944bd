"""Pruning on the host (paper section IV): the genome structure the device pruner reads
(`tables_for`), the genome after a run's removals (`prune_genome`, `kept_genes`) and one
`PruneAttempt` record per attempt (`attempt_records`). The device stages are
`eant2_jax.pruning`."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING

import jax
import numpy as np

from . import distributed
from .genome import Gene, GeneKind, Genome
from .jsonio import typed_fields
from .kernels.pruning import Tables

if TYPE_CHECKING:
    from .pruning import AttemptRecord

__all__ = ["PruneAttempt", "attempt_records", "kept_genes", "prune_genome", "tables_for"]


def tables_for(
    genomes: Sequence[Genome],
    genes: int,
    rows: int | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> Tables:
    """Pruner tables for a batch, ``[rows, genes]`` (padding rows and slots are inert).

    Args:
      genomes: the structures.
      genes: padded number of gene slots ``P``.
      rows: padded number of structures (default ``len(genomes)``).
      mesh: put the tables straight from the host onto this device mesh, split along the
        rows (`eant2_jax.distributed.shard`); default JAX's default device.
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
    # device_put: no per-shape program to compile (see compile_genomes); one call for all.
    host = Tables(parent=parent, subtree_end=subtree_end, reads=reads, is_neuron=is_neuron)
    return jax.device_put(host) if mesh is None else distributed.shard(host, mesh)


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
    if keep.all():  # nothing removed (most structures): the same structure, new weights
        return genome.with_weights(w)
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
      history: the engine history's pruning part, `AttemptRecord` of
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
                iteration=int(history.iteration[it, s]),
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
