"""The condition protocol's networks (docs/protocol.md, section 2): the controls that remove
as many connections as the covariance pruner did, at random or by magnitude; the positive
control's exact duplicate; and the directions along which a network's cost is exactly flat
(a neuron's scaling symmetry, genes sharing one weight entry). Host-side NumPy on genomes."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from ..compiler import compile_genomes
from ..genome import GeneKind, Genome
from ..genomepruning import prune_genome

__all__ = [
    "HOMOGENEOUS",
    "flat_directions",
    "leaf_removable",
    "remove_like",
    "shared_entries",
    "with_duplicate",
]

# Activations with f(a x) = a f(x) for every a > 0: a neuron with one of them can scale its
# incoming weights by a and every use of its output by 1 / a with no change anywhere.
HOMOGENEOUS = frozenset({"identity", "relu", "lelu"})


def leaf_removable(genome: Genome) -> np.ndarray:
    """``bool[n]``: genes a control may remove, one weight each: a connection that is not a
    neuron (input, bias, jumper) whose neuron keeps at least one other input."""
    parent = genome.parent
    arity = np.array([g.arity for g in genome.genes])
    leaf = np.array([g.kind != GeneKind.NEURON for g in genome.genes])
    has_sibling = np.array([p >= 0 and arity[p] >= 2 for p in parent])
    return leaf & has_sibling


def remove_like(
    genome: Genome, count: int, *, rule: str, key: jax.Array | None = None
) -> tuple[Genome, np.ndarray]:
    """Remove ``count`` connections one at a time, each among `leaf_removable`'s: drawn
    uniformly (``rule="random"``, step ``t`` from ``fold_in(key, t)``) or the smallest
    ``|w|`` (``rule="magnitude"``, ties to the first gene).

    Returns:
      ``(genome, kept)``: the reduced genome and the original index of each gene it kept.
    """
    if rule not in ("random", "magnitude"):
        raise ValueError(f"rule must be 'random' or 'magnitude', got {rule!r}")
    if rule == "random" and key is None:
        raise ValueError("the random control needs a key")
    kept = np.arange(len(genome))
    for t in range(count):
        candidates = np.flatnonzero(leaf_removable(genome))
        if candidates.size == 0:
            raise ValueError(f"only {t} of {count} connections can be removed from {genome}")
        if rule == "random":
            i = int(jax.random.choice(jax.random.fold_in(key, t), candidates))
        else:
            i = int(candidates[np.argmin(np.abs(genome.weights[candidates]))])
        keep = np.arange(len(genome)) != i
        genome, kept = prune_genome(genome, keep), kept[keep]
    return genome, kept


def with_duplicate(genome: Genome, index: int) -> Genome:
    """``genome`` with an exact copy of connection ``index`` (same source, same neuron,
    same weight) inserted right after it: the two weights act only through their sum."""
    gene = genome[index]
    if gene.kind == GeneKind.NEURON:
        raise ValueError(f"gene {index} is a neuron; duplicate a connection (I, B, F or R)")
    p = int(genome.parent[index])
    genes = list(genome.genes)
    genes[p] = dataclasses.replace(genes[p], arity=genes[p].arity + 1)
    genes.insert(index + 1, gene)
    return Genome(genes)


def shared_entries(genome: Genome, n_inputs: int) -> list[list[int]]:
    """Groups of genes that add their weights into one entry of the network (the same
    source and the same neuron, e.g. a second bias): each group's differences are exactly
    flat directions."""
    layout = compile_genomes([genome], n_inputs, pad_count=False).layout
    slot = np.asarray(layout.slot[0])[: len(genome)]
    groups: dict[int, list[int]] = {}
    for i, s in enumerate(slot):
        groups.setdefault(int(s), []).append(i)
    return [g for g in groups.values() if len(g) > 1]


def flat_directions(
    genome: Genome, weights: np.ndarray, *, hidden: str, output: str, n_inputs: int
) -> np.ndarray:
    """``[k, n]`` directions in weight space along which the cost is exactly flat at
    ``weights``: per neuron with a `HOMOGENEOUS` activation (roots use ``output``, the
    others ``hidden``; docs/genome.md) the tangent of its scaling orbit, ``+w`` on its
    inputs and ``-w`` on every use of its output (its own gene, the jumpers that read it;
    a jumper of its own output into itself is both and stays 0); per pair of genes that
    share an entry (`shared_entries`), their difference."""
    w = np.asarray(weights, np.float64)
    parent, roots = genome.parent, set(genome.roots)
    out = []
    for i, gene in enumerate(genome.genes):
        if gene.kind != GeneKind.NEURON:
            continue
        if (output if i in roots else hidden) not in HOMOGENEOUS:
            continue
        v = np.zeros(len(genome))
        incoming = parent == i
        v[incoming] += w[incoming]
        users = [i] + [
            j
            for j, g in enumerate(genome.genes)
            if g.kind in (GeneKind.FORWARD, GeneKind.RECURRENT) and g.ref == gene.ref
        ]
        v[users] -= w[users]
        out.append(v)
    for group in shared_entries(genome, n_inputs):
        for b in group[1:]:
            v = np.zeros(len(genome))
            v[group[0]], v[b] = 1.0, -1.0
            out.append(v)
    return np.array(out).reshape(len(out), len(genome))
