"""Structural exploration and selection (paper section III.A, figure 3). Host-side Python.

Mutation operators make new structures from a parent genome:

* ``add_subnetwork``: a new hidden neuron connected to about half of the network inputs
  (each input independently with probability ``input_fraction``, at least one), feeding an
  existing neuron;
* ``remove_subnetwork``: a random hidden neuron leaves with its whole sub-genome;
* ``add_connection``: an input, bias, forward jumper or recurrent jumper into a random neuron;
* ``remove_connection``: a random input, bias or jumper gene leaves;
* ``add_bias``: a bias into a random neuron that has none (None when every neuron has one).

The gene that joins new material to the network starts at weight 0 (the new neuron's own
gene, or the new connection gene), while the new neuron's inner weights are random: a new
structure first computes exactly what its parent did. Every offspring is a valid
`Genome` by construction (it is validated on creation anyway); an operator that has
nothing to act on (e.g. no hidden neuron to remove) reports ``None``.

Neuron ids are unique across a whole run (a run-level counter numbers new neurons), so two
genomes have "the same set of neurons" exactly when one was derived from the other — or both
from a common ancestor — by changing connections only. Selection uses that:

* **identical**: equal structure (`Genome.structure_key`: the genes without weights);
* **similar**: the same set of neuron ids.

Selection (rank-based and greedy on cost) keeps at most one copy of an identical structure
and at most ``similar_limit`` (2) similar ones; with ``prefer_smaller`` a network whose cost
is within ``size_tolerance * max(|c1|, |c2|) + size_atol`` of a larger one's ranks before it
(the absolute part makes costs near an exact 0, e.g. 1e-14 and 1e-20, count as equal).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .genome import MAX_ID, Gene, GeneKind, Genome

if TYPE_CHECKING:  # config.py imports this module (OPERATORS)
    from .config import EANT2Config

__all__ = [
    "OPERATORS",
    "initial_genome",
    "mutate",
    "mutate_once",
    "offspring",
    "rank",
    "select",
    "similarity_key",
]

OPERATORS = (
    "add_subnetwork",
    "remove_subnetwork",
    "add_connection",
    "remove_connection",
    "add_bias",
)


def initial_genome(
    rng: np.random.Generator,
    n_inputs: int,
    n_outputs: int,
    *,
    connectivity: float = 1.0,
    weight_scale: float = 0.1,
    recurrent: bool = False,
) -> Genome:
    """A minimal network: one neuron per output (ids 0..n_out-1), no hidden neurons.

    Each output neuron reads each input with probability ``connectivity`` (at least one);
    weights are drawn from N(0, weight_scale^2), the output neurons' own weights are 1.

    With ``recurrent`` the start is *recurrent-ready*: each output neuron ``o`` also reads
    its own previous output through a recurrent jumper ``R<o>`` of weight 0 (its last
    input). The network computes exactly the function of the plain minimal start, but the
    jumper's weight is a parameter like any other, so CMA-ES can give the output a memory
    from generation 0 on (a task without velocity inputs needs one: docs/pole.md). The
    paper's minimal networks have no recurrent connections (section III); this option is
    off by default. The random draws are those of the plain start: with the same ``rng``
    both starts have the same weights.
    """
    genes = []
    for o in range(n_outputs):
        chosen = [j for j in range(n_inputs) if rng.random() < connectivity]
        if not chosen:
            chosen = [int(rng.integers(n_inputs))]
        genes.append(Gene(GeneKind.NEURON, o, 1.0, len(chosen) + recurrent))
        genes += [Gene(GeneKind.INPUT, j, float(rng.normal(0, weight_scale))) for j in chosen]
        if recurrent:
            genes.append(Gene(GeneKind.RECURRENT, o, 0.0))
    return Genome(genes)


def similarity_key(genome: Genome) -> frozenset[int]:
    """The set of neuron ids: equal keys mean "similar" (derived by connection changes)."""
    return frozenset(genome.neuron_ids)


def _insert_child(genome: Genome, neuron_index: int, new: list[Gene]) -> Genome:
    """Insert a sub-genome as the first input of the neuron at ``neuron_index``."""
    genes = list(genome.genes)
    target = genes[neuron_index]
    genes[neuron_index] = dataclasses.replace(target, arity=target.arity + 1)
    genes[neuron_index + 1 : neuron_index + 1] = new
    return Genome(genes)


def _remove_range(genome: Genome, start: int, stop: int) -> Genome:
    """Remove the sub-genome ``genes[start:stop]`` (one input of its parent)."""
    genes = list(genome.genes)
    p = int(genome.parent[start])
    genes[p] = dataclasses.replace(genes[p], arity=genes[p].arity - 1)
    del genes[start:stop]
    return Genome(genes)


def _neuron_indices(genome: Genome) -> list[int]:
    return [i for i, g in enumerate(genome.genes) if g.kind == GeneKind.NEURON]


def _removable_input(genome: Genome, i: int) -> bool:
    """Gene i may leave (with its sub-genome) without breaking the genome."""
    p = int(genome.parent[i])
    if p < 0 or genome[p].arity < 2:
        return False
    if genome[i].kind != GeneKind.NEURON:
        return True
    stop = genome.subtree_end(i)
    inside = {g.ref for g in genome.genes[i:stop] if g.kind == GeneKind.NEURON}
    outside = genome.genes[:i] + genome.genes[stop:]
    return not any(
        g.kind in (GeneKind.FORWARD, GeneKind.RECURRENT) and g.ref in inside for g in outside
    )


def _children(genome: Genome, neuron: int) -> list[Gene]:
    """The genes that neuron gene ``neuron`` reads directly (its inputs)."""
    return [g for i, g in enumerate(genome.genes) if genome.parent[i] == neuron]


def mutate(
    rng: np.random.Generator,
    genome: Genome,
    operator: str,
    *,
    n_inputs: int,
    next_id: int,
    input_fraction: float = 0.5,
    weight_scale: float = 0.5,
) -> Genome | None:
    """Apply one structural mutation.

    Args:
      rng: the random source (derived from the run's key).
      genome: the parent.
      operator: one of ``OPERATORS``.
      n_inputs: number of network inputs of the task.
      next_id: id for a new neuron (unique in the run).
      input_fraction: probability that a new hidden neuron reads each input.
      weight_scale: std of the new neuron's inner weights.

    Returns:
      The offspring, or None when the operator has nothing to act on.
    """
    neurons = _neuron_indices(genome)
    if operator == "add_subnetwork":
        target = neurons[int(rng.integers(len(neurons)))]
        chosen = [j for j in range(n_inputs) if rng.random() < input_fraction]
        if not chosen:
            chosen = [int(rng.integers(n_inputs))]
        inner = [Gene(GeneKind.INPUT, j, float(rng.normal(0, weight_scale))) for j in chosen]
        return _insert_child(
            genome, target, [Gene(GeneKind.NEURON, next_id, 0.0, len(chosen)), *inner]
        )
    if operator == "remove_subnetwork":
        hidden = [i for i in neurons if genome.parent[i] >= 0 and _removable_input(genome, i)]
        if not hidden:
            return None
        i = hidden[int(rng.integers(len(hidden)))]
        return _remove_range(genome, i, genome.subtree_end(i))
    if operator == "remove_connection":
        leaves = [
            i
            for i, g in enumerate(genome.genes)
            if g.kind != GeneKind.NEURON and _removable_input(genome, i)
        ]
        if not leaves:
            return None
        i = leaves[int(rng.integers(len(leaves)))]
        return _remove_range(genome, i, i + 1)
    if operator == "add_bias":
        # A second bias on one neuron is an exact duplicate (two weights on one constant
        # input: a flat direction of the cost that adds nothing), as `add_connection` rules
        # out; only neurons without a bias are targets.
        free = [i for i in neurons if all(g.kind != GeneKind.BIAS for g in _children(genome, i))]
        if not free:
            return None
        target = free[int(rng.integers(len(free)))]
        return _insert_child(genome, target, [Gene(GeneKind.BIAS, -1, 0.0)])
    if operator == "add_connection":
        return _add_connection(rng, genome, neurons, n_inputs)
    raise ValueError(f"unknown operator {operator!r}; known: {', '.join(OPERATORS)}")


def _add_connection(
    rng: np.random.Generator, genome: Genome, neurons: list[int], n_inputs: int
) -> Genome | None:
    """`mutate`'s ``add_connection``: a new input, bias or jumper on a random neuron (None if
    that neuron already has every connection it could get)."""
    target = neurons[int(rng.integers(len(neurons)))]
    # A connection the target already has would be an exact duplicate: two weights on one
    # edge, a flat direction of the cost that adds nothing. Each kind offers only new
    # sources; a forward jumper may read any neuron to the right of the target (already
    # evaluated at this step, so no cycle), a recurrent jumper any neuron.
    have = {(g.kind, g.ref) for g in _children(genome, target)}
    ids = [genome[i].ref for i in neurons]
    sources = {
        GeneKind.INPUT: [j for j in range(n_inputs) if (GeneKind.INPUT, j) not in have],
        GeneKind.BIAS: [-1] if (GeneKind.BIAS, -1) not in have else [],
        GeneKind.RECURRENT: [r for r in ids if (GeneKind.RECURRENT, r) not in have],
        GeneKind.FORWARD: [
            genome[i].ref
            for i in neurons
            if i > target
            and (GeneKind.FORWARD, genome[i].ref) not in have
            and (GeneKind.NEURON, genome[i].ref) not in have
        ],
    }
    kinds = [
        k
        for k in (GeneKind.INPUT, GeneKind.BIAS, GeneKind.RECURRENT, GeneKind.FORWARD)
        if sources[k]
    ]
    if not kinds:
        return None
    kind = kinds[int(rng.integers(len(kinds)))]
    options = sources[kind]
    gene = Gene(kind, options[int(rng.integers(len(options)))], 0.0)
    return _insert_child(genome, target, [gene])


def mutate_once(
    rng: np.random.Generator, genome: Genome, n_inputs: int, next_id: int, config: EANT2Config
) -> tuple[Genome | None, str]:
    """One structural mutation with an operator drawn by ``config.operator_weights``;
    returns the child (None if the operator had nothing to act on) and the operator."""
    p = np.asarray(config.operator_weights) / sum(config.operator_weights)
    op = OPERATORS[int(rng.choice(len(OPERATORS), p=p))]
    child = mutate(
        rng,
        genome,
        op,
        n_inputs=n_inputs,
        next_id=next_id,
        input_fraction=config.input_fraction,
        weight_scale=config.new_weight_scale,
    )
    return child, op


def offspring(
    rng: np.random.Generator,
    parents: Sequence[Genome],
    n_inputs: int,
    next_id: int,
    config: EANT2Config,
) -> tuple[list[Genome], list[str], list[int], int]:
    """The explore box (paper figure 3): ``config.offspring`` (default ``population``)
    children, each of a parent drawn uniformly, by one `mutate_once`; a child whose
    structure exists among the parents or the children already made is dropped (after
    ``20 * wanted`` draws the generation makes do with fewer).

    Returns:
      The children, the operator that made each, each one's parent (an index into
      ``parents``) and the next free neuron id.
    """
    want = config.offspring or config.population
    seen = {g.structure_key() for g in parents}
    children: list[Genome] = []
    ops: list[str] = []
    made_from: list[int] = []
    for _ in range(20 * want):  # give up on duplicates after a while
        if len(children) == want:
            break
        parent = int(rng.integers(len(parents)))
        child, op = mutate_once(rng, parents[parent], n_inputs, next_id, config)
        if child is None or child.structure_key() in seen:
            continue
        if op == "add_subnetwork":
            if next_id >= MAX_ID:  # ids index int32 tables: a later resume would refuse it
                raise ValueError(
                    f"neuron ids are exhausted: no id is left below {MAX_ID} for a new neuron"
                )
            next_id += 1
        seen.add(child.structure_key())
        children.append(child)
        ops.append(op)
        made_from.append(parent)
    return children, ops, made_from, next_id


def rank(
    genomes: Sequence[Genome],
    costs: Sequence[float],
    *,
    prefer_smaller: bool = True,
    size_tolerance: float = 1e-3,
    size_atol: float = 1e-9,
) -> list[int]:
    """Indices from best to worst: by cost; non-finite costs last.

    With ``prefer_smaller``, of two networks whose costs are within
    ``size_tolerance * max(|c1|, |c2|) + size_atol`` the one with fewer parameters ranks
    first. Remaining ties keep the input order (stable), so the ranking is deterministic.
    """
    cost = [float(c) if np.isfinite(c) else np.inf for c in costs]

    def compare(a: int, b: int) -> int:
        ca, cb = cost[a], cost[b]
        if prefer_smaller and np.isfinite(ca) and np.isfinite(cb):
            scale = max(abs(ca), abs(cb))
            if abs(ca - cb) <= size_tolerance * scale + size_atol:
                sa, sb = genomes[a].n_params, genomes[b].n_params
                if sa != sb:
                    return -1 if sa < sb else 1
        if ca != cb:
            return -1 if ca < cb else 1
        return 0

    # Sort by cost first so that the tolerance comparison only reorders near neighbours.
    order = sorted(range(len(cost)), key=lambda i: cost[i])
    return sorted(order, key=functools.cmp_to_key(compare))


def select(
    genomes: Sequence[Genome],
    costs: Sequence[float],
    size: int,
    *,
    similar_limit: int = 2,
    prefer_smaller: bool = True,
    size_tolerance: float = 1e-3,
    size_atol: float = 1e-9,
) -> list[int]:
    """Rank-based greedy selection with the paper's diversity rules.

    Walks the ranking and keeps an individual unless an identical structure is already kept
    or ``similar_limit`` similar ones are; stops at ``size``.

    Returns:
      Indices of the survivors, best first.
    """
    kept: list[int] = []
    seen: set[tuple] = set()
    similar: dict[frozenset[int], int] = {}
    ranking = rank(
        genomes,
        costs,
        prefer_smaller=prefer_smaller,
        size_tolerance=size_tolerance,
        size_atol=size_atol,
    )
    for i in ranking:
        if len(kept) == size:
            break
        key = genomes[i].structure_key()
        group = similarity_key(genomes[i])
        if key in seen or similar.get(group, 0) >= similar_limit:
            continue
        kept.append(i)
        seen.add(key)
        similar[group] = similar.get(group, 0) + 1
    return kept
