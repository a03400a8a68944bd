"""Pruning, host side: the tables the device pruner reads, pruned genomes, attempt records.

The pruning maths runs on device inside the exploitation step (see
:mod:`eant2_jax.kernels.pruning` and :mod:`eant2_jax.exploitation`): a removed connection is
switched off in the CMA-ES mask, so the gene slots of a structure never move during a run.
After the run, :func:`prune_genome` drops the removed genes from the genome and fixes the
neurons' input counts.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .genome import Gene, GeneKind, Genome
from .kernels.pruning import PRUNERS, Tables

__all__ = ["PRUNERS", "attempt_records", "prune_genome", "tables_for"]


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


def attempt_records(
    history: dict[str, np.ndarray],
    genomes: Sequence[Genome],
    pruner: str,
    structure_ids: Sequence[int] | None = None,
) -> list[dict]:
    """One record per pruning attempt from an exploitation history.

    Args:
      history: the ``prune_*`` arrays ``[iterations, S]`` of :func:`eant2_jax.exploitation.run`.
      genomes: the structures, in batch order (to name the kind of the gene).
      pruner: the pruner's name.
      structure_ids: label of each structure in the records (default its batch index).

    Returns:
      Dicts with ``structure``, ``iteration``, ``pruner``, ``gene``, ``kind``, ``axis``, ``s``,
      ``e``, ``e_shifted``, ``accepted``, ``cond_before``, ``cond_after``, sorted by
      iteration then structure.
    """
    if "prune_attempted" not in history:
        return []
    attempted = history["prune_attempted"]
    out = []
    for it, s in zip(*np.nonzero(attempted), strict=True):
        if s >= len(genomes):
            continue
        gene = int(history["prune_gene"][it, s])
        factor = float(history["prune_factor"][it, s])
        out.append(
            {
                "structure": int(s if structure_ids is None else structure_ids[s]),
                "iteration": int(it) + 1,
                "pruner": pruner,
                "gene": gene,
                "kind": _KIND_NAME[genomes[s][gene].kind],
                "axis": int(history["prune_axis"][it, s]),
                "s": None if np.isnan(factor) else factor,
                "e": float(history["prune_e"][it, s]),
                "e_shifted": float(history["prune_e_shifted"][it, s]),
                "accepted": bool(history["prune_accepted"][it, s]),
                "cond_before": float(history["prune_cond_before"][it, s]),
                "cond_after": float(history["prune_cond_after"][it, s]),
            }
        )
    return out
