"""Tests of eant2_jax.exploration: initial genomes, the mutation operators, rank and select.

The operators are swept over random parent genomes (hypothesis, :mod:`strategies`): every
operator, several draws per parent, about 2,500 mutations per run of the default profile.
"Exactly equal" outputs are compared with ``assert_array_equal`` on the float64 NumPy
reference: a join at weight 0 adds an exact ``+-0.0`` to a sum, which changes no bit of a
finite value other than the sign of a zero (and ``-0.0 == 0.0``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import genomes

import eant2_jax
from eant2_jax import interpret
from eant2_jax.exploration import (
    OPERATORS,
    initial_genome,
    mutate,
    offspring,
    rank,
    select,
    similarity_key,
)
from eant2_jax.genome import Gene, GeneKind, Genome

N_INPUTS = 3
ADD = ("add_subnetwork", "add_connection", "add_bias")
REMOVE = ("remove_subnetwork", "remove_connection")
DRAWS = 5  # mutations per operator and parent genome


def _inputs(seed: int, t: int = 4, m: int = 6) -> np.ndarray:
    """``[T, M, n_in]`` random input streams (T > 1 so that recurrent jumpers matter)."""
    return np.random.default_rng(seed).normal(size=(t, m, N_INPUTS))


def _forward_acyclic(g: Genome) -> bool:
    """The current-step dependency graph (sub-neurons and forward jumpers) has no cycle."""
    reads: dict[int, set[int]] = {nid: set() for nid in g.neuron_ids}
    for i, gene in enumerate(g):
        p = int(g.parent[i])
        if p < 0:
            continue
        if gene.kind in (GeneKind.NEURON, GeneKind.FORWARD):
            reads[g[p].ref].add(gene.ref)
    state: dict[int, int] = {}  # 1 on the DFS stack, 2 done

    def visit(n: int) -> bool:
        state[n] = 1
        for m in reads[n]:
            if state.get(m) == 1 or (m not in state and not visit(m)):
                return False
        state[n] = 2
        return True

    return all(state.get(n) == 2 or visit(n) for n in reads)


def _inserted(parent: Genome, child: Genome) -> tuple[int, tuple[Gene, ...]] | None:
    """If ``child`` is ``parent`` with one block of genes inserted as the FIRST input of one
    neuron (whose arity grew by one), every other gene and weight unchanged: the neuron's
    index and the block; else None."""
    extra = len(child) - len(parent)
    if extra < 1:
        return None
    t = next((i for i, (a, b) in enumerate(zip(parent, child, strict=False)) if a != b), None)
    if t is None or parent[t].kind != GeneKind.NEURON:
        return None
    if child[t] != dataclasses.replace(parent[t], arity=parent[t].arity + 1):
        return None
    if child.genes[:t] != parent.genes[:t] or child.genes[t + 1 + extra :] != parent.genes[t + 1 :]:
        return None
    return t, child.genes[t + 1 : t + 1 + extra]


# ---------------------------------------------------------------------------- initial_genome
@pytest.mark.parametrize("n_in,n_out", [(1, 1), (2, 1), (5, 3), (10, 4)])
def test_initial_genome_full_connectivity(n_in, n_out):
    rng = np.random.default_rng(0)
    g = initial_genome(rng, n_in, n_out, weight_scale=0.1)
    assert g.n_outputs == n_out and g.n_neurons == n_out
    assert g.neuron_ids == tuple(range(n_out))
    assert g.depth() == 1
    assert g.n_params == n_out * (1 + n_in)
    for r, root in enumerate(g.roots):
        assert g[root].weight == 1.0 and g[root].ref == r
        kids = g.children(root)
        assert [g[k].kind for k in kids] == [GeneKind.INPUT] * n_in
        assert [g[k].ref for k in kids] == list(range(n_in))


def test_initial_genome_partial_connectivity():
    rng = np.random.default_rng(1)
    counts = []
    for _ in range(300):
        g = initial_genome(rng, 8, 2, connectivity=0.25)
        for root in g.roots:
            kids = g.children(root)
            assert len(kids) >= 1  # at least one input, even when none was drawn
            assert all(g[k].kind == GeneKind.INPUT for k in kids)
            refs = [g[k].ref for k in kids]
            assert refs == sorted(set(refs))  # distinct, in input order
            counts.append(len(kids))
    # Binomial(8, 0.25) has mean 2 (slightly more: empty draws become one input).
    assert 1.7 < np.mean(counts) < 2.5
    tiny = initial_genome(np.random.default_rng(2), 5, 3, connectivity=1e-9)
    assert all(len(tiny.children(r)) == 1 for r in tiny.roots)


def test_initial_genome_weights_and_determinism():
    a = initial_genome(np.random.default_rng(7), 4, 2, weight_scale=0.0)
    assert all(g.weight == (1.0 if g.kind == GeneKind.NEURON else 0.0) for g in a)
    b = initial_genome(np.random.default_rng(7), 4, 2, weight_scale=0.3)
    c = initial_genome(np.random.default_rng(7), 4, 2, weight_scale=0.3)
    assert b == c and str(b) == str(c)


@pytest.mark.slow
@pytest.mark.parametrize("n_in,n_out,connectivity", [(1, 1, 1.0), (3, 1, 1.0), (6, 3, 0.5)])
def test_recurrent_start_computes_the_plain_start(n_in, n_out, connectivity):
    """The recurrent-ready start is the plain start plus one weight-0 self-jumper per
    output neuron (its last input), with the same weights from the same draws: the same
    outputs at every step, through the reference interpreter (exactly) and the compiled
    network (float32, ~1e-6)."""
    for seed in range(3):
        kw = {"connectivity": connectivity, "weight_scale": 0.7}
        plain = initial_genome(np.random.default_rng(seed), n_in, n_out, **kw)
        ready = initial_genome(np.random.default_rng(seed), n_in, n_out, recurrent=True, **kw)
        assert ready.n_params == plain.n_params + n_out
        assert ready.neuron_ids == plain.neuron_ids and ready.depth() == plain.depth()
        for root, o in zip(ready.roots, range(n_out), strict=True):
            last = ready[ready.children(root)[-1]]
            assert (last.kind, last.ref, last.weight) == (GeneKind.RECURRENT, o, 0.0)
        stripped = [g for g in ready if g.kind != GeneKind.RECURRENT]
        assert [(g.kind, g.ref, g.weight) for g in stripped] == [
            (g.kind, g.ref, g.weight) for g in plain
        ]
        x = np.random.default_rng(seed + 100).normal(0, 2, (6, 4, n_in))  # [T, M, n_in]
        np.testing.assert_array_equal(interpret(ready, x), interpret(plain, x))
        fast = [np.asarray(eant2_jax.evaluate(g, x)) for g in (ready, plain)]
        np.testing.assert_allclose(fast[0], fast[1], rtol=1e-6, atol=1e-6)
        # A non-zero self-weight changes the outputs from the second step on.
        w = ready.weights.copy()
        w[[i for i, g in enumerate(ready) if g.kind == GeneKind.RECURRENT]] = 0.5
        moved = interpret(ready.with_weights(w), x)
        np.testing.assert_array_equal(moved[0], interpret(plain, x)[0])
        assert not np.allclose(moved[1:], interpret(plain, x)[1:])


# -------------------------------------------------------------------------------- mutation
@pytest.mark.slow
@given(genomes(n_inputs=N_INPUTS, max_neurons=5, max_id=20), st.integers(0, 2**32 - 1))
def test_every_operator_on_random_parents(parent, seed):
    """Validity, weight-0 joins, fewer genes on removal, next_id, no cycles (5 x DRAWS)."""
    rng = np.random.default_rng(seed)
    x = _inputs(seed)
    y_parent = interpret(parent, x)
    next_id = max(parent.neuron_ids) + 1 + int(rng.integers(5))
    for op in OPERATORS:
        for _ in range(DRAWS):
            child = mutate(rng, parent, op, n_inputs=N_INPUTS, next_id=next_id)
            if child is None:
                every_bias = all(
                    any(parent[k].kind == GeneKind.BIAS for k in parent.children(i))
                    for i, g in enumerate(parent)
                    if g.kind == GeneKind.NEURON
                )  # add_bias gives no neuron a second bias
                assert op in REMOVE or (op == "add_bias" and every_bias), f"{op}: {parent}"
                continue
            assert isinstance(child, Genome)
            Genome.parse(str(child))  # a valid genome, and its text form round-trips
            assert child.n_outputs == parent.n_outputs
            assert child.n_inputs <= N_INPUTS
            assert _forward_acyclic(child)
            child.depth()  # raises on a forward jumper to an unevaluated neuron
            if op in ADD:
                found = _inserted(parent, child)
                assert found is not None, f"{op}: {parent} -> {child}"
                block = found[1]
                assert block[0].weight == 0.0  # the joining gene starts at weight 0
                np.testing.assert_array_equal(interpret(child, x), y_parent)
                ids = set(child.neuron_ids) - set(parent.neuron_ids)
                if op == "add_subnetwork":
                    assert ids == {next_id}
                    i = child.neuron_position[next_id]
                    assert child[i].weight == 0.0 and child.parent[i] >= 0
                    kids = child.children(i)
                    assert len(kids) >= 1
                    assert all(child[k].kind == GeneKind.INPUT for k in kids)
                    assert child.n_params == parent.n_params + 1 + len(kids)
                else:
                    assert ids == set()
                    assert similarity_key(child) == similarity_key(parent)
                    assert child.n_params == parent.n_params + 1
            else:
                assert child.n_params < parent.n_params
                assert set(child.neuron_ids) <= set(parent.neuron_ids)
                if op == "remove_connection":
                    assert child.n_params == parent.n_params - 1
                    assert similarity_key(child) == similarity_key(parent)
                else:
                    assert child.n_neurons < parent.n_neurons
                    assert child.roots and all(
                        child[r].ref in parent.neuron_ids for r in child.roots
                    )
                    # The output neurons survive (only hidden neurons are removed).
                    assert [child[r].ref for r in child.roots] == [
                        parent[r].ref for r in parent.roots
                    ]


@given(genomes(n_inputs=N_INPUTS, max_neurons=5), st.integers(0, 2**32 - 1))
def test_add_connection_inserts_one_zero_weight_terminal(parent, seed):
    rng = np.random.default_rng(seed)
    for _ in range(DRAWS * 2):
        child = mutate(rng, parent, "add_connection", n_inputs=N_INPUTS, next_id=99)
        t, (gene,) = _inserted(parent, child)
        assert gene.weight == 0.0 and gene.kind != GeneKind.NEURON
        if gene.kind == GeneKind.FORWARD:
            # Its source lies to the right of the target neuron: evaluated earlier in the
            # same step, so no cycle.
            assert child.neuron_position[gene.ref] > t + 1
        if gene.kind == GeneKind.INPUT:
            assert 0 <= gene.ref < N_INPUTS


def test_add_connection_draws_every_kind():
    # Two roots: the left one has a neuron to its right, so all four kinds can be drawn.
    parent = Genome.parse("N0/1*1 I0*1 N1/2*1 I1*1 B*1")
    rng = np.random.default_rng(0)
    kinds = set()
    for _ in range(400):
        child = mutate(rng, parent, "add_connection", n_inputs=2, next_id=2)
        (new,) = [g for g in child if g.weight == 0.0]
        kinds.add(new.kind)
    assert kinds == {GeneKind.INPUT, GeneKind.BIAS, GeneKind.FORWARD, GeneKind.RECURRENT}


def test_add_connection_never_jumps_forward_from_the_rightmost_neuron():
    # One neuron: nothing lies to its right, so no forward jumper may be drawn.
    parent = Genome.parse("N0/1*1 I0*1")
    rng = np.random.default_rng(0)
    for _ in range(300):
        child = mutate(rng, parent, "add_connection", n_inputs=1, next_id=1)
        assert all(g.kind != GeneKind.FORWARD for g in child)


@pytest.mark.parametrize("fraction", [1e-9, 0.5, 1.0])
def test_add_subnetwork_reads_inputs(fraction):
    parent = Genome.parse("N0/2*1 I0*0.5 I1*-0.5")
    rng = np.random.default_rng(3)
    sizes = []
    for _ in range(200):
        child = mutate(
            rng, parent, "add_subnetwork", n_inputs=6, next_id=7, input_fraction=fraction
        )
        i = child.neuron_position[7]
        kids = child.children(i)
        refs = [child[k].ref for k in kids]
        assert all(child[k].kind == GeneKind.INPUT for k in kids)
        assert len(refs) >= 1 and refs == sorted(set(refs))
        sizes.append(len(refs))
    if fraction == 1.0:
        assert set(sizes) == {6}
    elif fraction == 1e-9:
        assert set(sizes) == {1}
    else:
        assert 2.5 < np.mean(sizes) < 3.5


@pytest.mark.parametrize(
    "text,op",
    [
        ("N0/1*1 I0*1", "remove_connection"),  # the only input of a neuron cannot leave
        ("N0/1*1 I0*1", "remove_subnetwork"),  # no hidden neuron
        ("N0/1*1 I0*1 N1/1*1 B*1", "remove_subnetwork"),  # roots only
        ("N0/1*1 N1/1*1 I0*1", "remove_subnetwork"),  # the hidden neuron is an only input
        ("N0/1*1 N1/1*1 I0*1", "remove_connection"),  # every neuron has arity 1
        # The hidden neuron is read by a jumper outside its sub-genome.
        ("N0/2*1 F1*1 N1/1*1 I0*1", "remove_subnetwork"),
    ],
)
def test_remove_operators_report_none(text, op):
    g = Genome.parse(text)
    rng = np.random.default_rng(0)
    for _ in range(20):
        assert mutate(rng, g, op, n_inputs=1, next_id=10) is None


def test_remove_subnetwork_keeps_jumper_sources():
    # Neuron 1 is read by R1 in the other root: removing it would leave a dangling jumper.
    g = Genome.parse("N0/2*1 N1/1*1 I0*1 N3/1*1 I0*1 N2/1*1 R1*1")
    rng = np.random.default_rng(0)
    for _ in range(50):
        child = mutate(rng, g, "remove_subnetwork", n_inputs=1, next_id=10)
        assert 1 in child.neuron_ids and 3 not in child.neuron_ids


def test_remove_subnetwork_takes_the_whole_subgenome():
    g = Genome.parse("N0/2*1 N1/2*1 N2/1*1 I0*1 I1*1 B*1")
    child = mutate(np.random.default_rng(0), g, "remove_subnetwork", n_inputs=2, next_id=10)
    # N1 (with N2 inside) may leave N0, or N2 may leave N1; either takes its whole sub-genome.
    assert str(child) in {"N0/1*1.0 B*1.0", "N0/2*1.0 N1/1*1.0 I1*1.0 B*1.0"}


def test_unknown_operator():
    with pytest.raises(ValueError, match="unknown operator"):
        mutate(np.random.default_rng(0), Genome.parse("N0/1*1 I0*1"), "grow", n_inputs=1, next_id=1)


def test_mutate_is_deterministic():
    g = Genome.parse("N0/3*1 N1/2*0.3 I0*1 I1*1 I1*-1 B*0.2")
    for op in OPERATORS:
        a = mutate(np.random.default_rng(5), g, op, n_inputs=2, next_id=4)
        b = mutate(np.random.default_rng(5), g, op, n_inputs=2, next_id=4)
        assert a == b and str(a) == str(b)


# ---------------------------------------------------------------------------------- ranking
def _net(n_inputs: int, nid: int = 0, extra: tuple[int, ...] = ()) -> Genome:
    """A one-neuron net reading inputs 0..n_inputs-1, plus hidden neurons with ids ``extra``."""
    genes = [Gene(GeneKind.NEURON, nid, 1.0, n_inputs + len(extra))]
    genes += [Gene(GeneKind.INPUT, j, 0.1) for j in range(n_inputs)]
    for h in extra:
        genes += [Gene(GeneKind.NEURON, h, 0.0, 1), Gene(GeneKind.INPUT, 0, 0.2)]
    return Genome(genes)


def test_rank_by_cost():
    gs = [_net(1), _net(2), _net(3), _net(4)]
    assert rank(gs, [3.0, 1.0, 2.0, 0.5], prefer_smaller=False) == [3, 1, 2, 0]
    assert rank(gs, [3.0, 1.0, 2.0, 0.5]) == [3, 1, 2, 0]


def test_rank_prefers_smaller_within_tolerance():
    small, big = _net(1), _net(3)  # 2 and 4 parameters
    # Within 1e-3 relative: the smaller net ranks first even at a slightly higher cost.
    assert rank([big, small], [1.0, 1.0005]) == [1, 0]
    assert rank([big, small], [1.0, 1.0005], prefer_smaller=False) == [0, 1]
    # Outside the tolerance: cost decides.
    assert rank([big, small], [1.0, 1.01]) == [0, 1]
    assert rank([big, small], [1.0, 1.01], size_tolerance=0.05) == [1, 0]
    # Equal size within tolerance: the lower cost still wins.
    assert rank([_net(2), _net(2, nid=1)], [1.0005, 1.0]) == [1, 0]


@pytest.mark.parametrize(
    "c_small,c_big",
    [(1e-14, 1e-20), (1e-12, 0.0), (3.553e-15, 0.0), (0.0, 0.0), (1e-10, -1e-10)],
)
def test_rank_costs_near_zero_count_as_equal(c_small, c_big):
    # Relative tolerance alone would call 1e-14 and 1e-20 different by a factor 1e6; the
    # absolute part (size_atol = 1e-9) makes them equal, so the smaller net wins.
    small, big = _net(1), _net(3)
    assert rank([big, small], [c_big, c_small]) == [1, 0]
    assert rank([big, small], [c_big, c_small], size_atol=0.0) == (
        [1, 0] if c_small == c_big else [0, 1]
    )


def test_rank_non_finite_last_in_input_order():
    gs = [_net(k) for k in range(1, 7)]
    costs = [np.nan, 2.0, np.inf, -np.inf, 1.0, np.nan]
    order = rank(gs, costs)
    assert order[:2] == [4, 1]
    assert order[2:] == [0, 2, 3, 5]  # every non-finite cost (even -inf) last, stable
    # The size preference never lifts a non-finite cost: the smallest net has NaN.
    assert rank([_net(1), _net(5)], [np.nan, 1e6]) == [1, 0]


def test_rank_is_stable_and_deterministic():
    gs = [_net(2, nid=i) for i in range(6)]  # same size
    assert rank(gs, [1.0] * 6) == list(range(6))
    costs = [0.3, 0.1, 0.3, 0.1, 0.2, 0.1]
    first = rank(gs, costs)
    assert first == [1, 3, 5, 4, 0, 2]
    assert all(rank(gs, costs) == first for _ in range(5))


@given(
    st.lists(
        st.tuples(
            st.integers(1, 4),
            st.one_of(
                st.floats(0, 1, allow_nan=False),
                st.sampled_from([0.0, 1e-20, 1e-14, np.nan, np.inf]),
            ),
        ),
        min_size=1,
        max_size=12,
    )
)
def test_rank_properties(items):
    gs = [_net(n, nid=i) for i, (n, _) in enumerate(items)]
    costs = [c for _, c in items]
    order = rank(gs, costs)
    assert sorted(order) == list(range(len(items)))
    finite = [i for i in order if np.isfinite(costs[i])]
    assert order[: len(finite)] == finite  # finite costs first
    plain = rank(gs, costs, prefer_smaller=False)
    key = [c if np.isfinite(c) else np.inf for c in costs]
    assert plain == sorted(range(len(items)), key=lambda i: key[i])  # stable sort by cost
    assert rank(gs, costs) == order  # deterministic


# -------------------------------------------------------------------------------- selection
def test_select_keeps_one_copy_of_identical_structures():
    a = Genome.parse("N0/2*1 I0*0.5 I1*0.5")
    a2 = Genome.parse("N0/2*-3 I0*2 I1*7")  # same structure, other weights
    b = Genome.parse("N5/2*1 I0*0.5 I1*0.5")  # other neuron id: another structure
    assert a.structure_key() == a2.structure_key() != b.structure_key()
    assert select([a, a2, b], [2.0, 1.0, 3.0], 3) == [1, 2]
    assert select([a, a2, a, a2], [1.0, 1.0, 1.0, 1.0], 4) == [0]


@pytest.mark.parametrize("limit", [1, 2, 3])
def test_select_similar_limit(limit):
    # Four structures over the same neuron set {0, 1} (connection changes only), one other.
    similar = [
        Genome.parse("N0/2*1 N1/1*1 I0*1 I1*1"),
        Genome.parse("N0/3*1 N1/1*1 I0*1 I1*1 B*1"),
        Genome.parse("N0/2*1 N1/2*1 I0*1 I1*1 I0*1"),
        Genome.parse("N0/2*1 N1/1*1 I1*1 I0*1"),
    ]
    other = Genome.parse("N0/2*1 N2/1*1 I0*1 I1*1")
    assert len({similarity_key(g) for g in similar}) == 1
    assert similarity_key(other) != similarity_key(similar[0])
    costs = [0.4, 0.1, 0.3, 0.2, 0.9]
    kept = select([*similar, other], costs, 10, similar_limit=limit, prefer_smaller=False)
    assert kept == [1, 3, 2, 0][:limit] + [4]


def test_select_default_limit_is_two_and_similar_means_same_neuron_ids():
    g = [
        Genome.parse("N0/1*1 I0*1"),
        Genome.parse("N0/2*1 I0*1 I1*1"),
        Genome.parse("N0/3*1 I0*1 I1*1 B*1"),
        # A new neuron makes another group, although derived from the ones above.
        Genome.parse("N0/2*1 N7/1*0 I0*1 I1*1"),
        # Same structure shape, another neuron id: another group too.
        Genome.parse("N3/1*1 I0*1"),
    ]
    assert select(g, [0.1, 0.2, 0.3, 0.4, 0.5], 5, prefer_smaller=False) == [0, 1, 3, 4]


def test_select_size_limit_and_greedy_order():
    gs = [_net(2, nid=i) for i in range(8)]  # all distinct, dissimilar
    costs = [0.8, 0.1, 0.5, 0.3, 0.7, 0.2, 0.6, 0.4]
    assert select(gs, costs, 3) == [1, 5, 3]
    assert select(gs, costs, 8) == [1, 5, 3, 7, 2, 6, 4, 0]
    assert select(gs, costs, 20) == select(gs, costs, 8)
    assert select(gs, costs, 0) == []
    # Skipped individuals do not count towards the size.
    dup = [gs[1]] * 4 + gs
    assert select(dup, [0.0] * 4 + costs, 3) == [0, 9, 7]


def test_select_size_preference_near_zero():
    # Both solve the task (cost ~ 0): the smaller one is kept first.
    small = Genome.parse("N0/2*1 N1/2*1 I0*1 I1*1 I0*1")
    big = Genome.parse("N0/3*1 N2/2*1 I0*1 I1*1 I0*1 B*1")
    assert select([big, small], [1e-20, 1e-14], 1) == [1]
    assert select([big, small], [1e-20, 1e-14], 1, prefer_smaller=False) == [0]


def test_select_non_finite_last():
    gs = [_net(2, nid=i) for i in range(4)]
    assert select(gs, [np.nan, np.inf, 5.0, 1.0], 4) == [3, 2, 0, 1]
    assert select(gs, [np.nan, np.inf, 5.0, 1.0], 2) == [3, 2]


_POOL = [
    "N0/1*1 I0*1",
    "N0/2*1 I0*1 I1*1",
    "N0/2*1 I0*1 B*1",
    "N0/3*1 I0*1 I1*1 B*1",
    "N0/2*1 N1/1*1 I0*1 I1*1",
    "N0/3*1 N1/1*1 I0*1 I1*1 B*1",
    "N0/2*1 N2/1*1 I0*1 I1*1",
    "N0/3*1 N1/1*1 I0*1 N2/1*1 I1*1 B*1",
]


@given(
    st.lists(
        st.tuples(st.integers(0, len(_POOL) - 1), st.floats(-2, 2), st.floats(0, 1)),
        min_size=1,
        max_size=16,
    ),
    st.integers(1, 10),
    st.integers(1, 3),
)
def test_select_rules_hold(items, size, limit):
    """Survivors: no identical pair, <= limit per neuron set, a prefix of the ranking minus
    the blocked ones (greedy), at most ``size``."""
    gs = [
        Genome.parse(_POOL[k]).with_weights(np.full(len(Genome.parse(_POOL[k])), w))
        for k, w, _ in items
    ]
    costs = [c for _, _, c in items]
    kept = select(gs, costs, size, similar_limit=limit)
    assert len(kept) <= size
    keys = [gs[i].structure_key() for i in kept]
    assert len(set(keys)) == len(keys)
    groups = [similarity_key(gs[i]) for i in kept]
    assert all(groups.count(k) <= limit for k in groups)
    order = rank(gs, costs)
    assert kept == [i for i in order if i in kept]  # best first, in ranking order
    # Greedy: everything ranked before the last survivor and not kept was blocked.
    last = order.index(kept[-1])
    for i in order[:last]:
        if i not in kept:
            blocked_identical = gs[i].structure_key() in keys
            blocked_similar = groups.count(similarity_key(gs[i])) >= limit
            assert blocked_identical or blocked_similar
    # If fewer than size survive, every individual was considered.
    if len(kept) < size:
        for i in order:
            if i not in kept:
                assert gs[i].structure_key() in keys or groups.count(similarity_key(gs[i])) >= limit
    assert select(gs, costs, size, similar_limit=limit) == kept  # deterministic


def test_offspring_are_new_distinct_structures_with_fresh_ids():
    """The explore box: ``offspring`` children, none a parent's or another child's
    structure, each made by the operator it names from the parent it names (the same draws
    again give it back), new neuron ids counted from ``next_id``; the same seed gives the
    same children."""
    config = eant2_jax.EANT2Config(population=3, offspring=12)
    rng = np.random.default_rng(0)
    parents = [initial_genome(rng, N_INPUTS, 2, weight_scale=1.0) for _ in range(3)]
    made = offspring(np.random.default_rng(5), parents, N_INPUTS, 2, config)
    children, ops, made_from, next_id = made
    assert len(children) == len(ops) == len(made_from) == 12
    keys = [g.structure_key() for g in children]
    assert len(set(keys)) == 12 and not set(keys) & {p.structure_key() for p in parents}
    assert set(ops) <= set(OPERATORS) and all(0 <= i < 3 for i in made_from)
    assert next_id == 2 + ops.count("add_subnetwork")
    hidden = [i for g in children for i in g.neuron_ids if i >= 2]
    assert sorted(hidden) == list(range(2, next_id))
    again = offspring(np.random.default_rng(5), parents, N_INPUTS, 2, config)
    assert [str(g) for g in again[0]] == [str(g) for g in children] and again[1:] == made[1:]
