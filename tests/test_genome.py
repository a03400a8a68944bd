"""Tests of eant2_jax.genome: text form, derived structure, validation."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import INVALID_CASES, fewer_examples, genomes, invalid_genomes

from eant2_jax.genome import MAX_ID, Gene, GeneKind, Genome, GenomeError, parse_gene, split_lines

# README's worked example: two outputs, a forward jumper to the second root, a recurrent one.
EXAMPLE = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"


# --------------------------------------------------------------------------------- text form
@given(genomes())
def test_str_parse_round_trip(g):
    text = str(g)
    back = Genome.parse(text)
    assert back == g
    assert hash(back) == hash(g)
    assert str(back) == text
    assert back.structure_key() == g.structure_key()


@given(genomes(weight=st.floats(allow_nan=False, allow_infinity=False)))
def test_round_trip_keeps_every_float_bit(g):
    # repr(float) is the shortest text that reads back to the same double: -0.0, subnormals
    # and 1e308 included.
    back = Genome.parse(str(g)).weights
    np.testing.assert_array_equal(back.view(np.int64), g.weights.view(np.int64))


def test_canonical_form():
    text = "  N00/3*1  I0*.5\n\tB*-1e0   R0*1_000 "
    g = Genome.parse(text)
    assert str(g) == "N0/3*1.0 I0*0.5 B*-1.0 R0*1000.0"
    assert Genome.parse(str(g)) == g
    assert repr(Genome.parse("N0/1*1 B*1")) == "Genome('N0/1*1.0 B*1.0')"
    long = Genome.parse("N0/30*1 " + " ".join(["I0*0.25"] * 30))
    assert repr(long).endswith("...')") and len(repr(long)) == len("Genome('')") + 80


def _same_gene_part(reported: str, written: str) -> bool:
    """Errors found while parsing a token quote it as written; errors found by validating the
    whole genome quote the gene in canonical form (``N0/1*1.0`` for ``N00/1*1``)."""
    return reported == written or reported == str(parse_gene(written, 0))


_TOKEN_PIECES = st.sampled_from(
    ["N", "I", "B", "F", "R", "/", "*", "0", "1", "2", "-", ".", "e", "5", "nan", "inf", "x"]
)
_FUZZ_TOKENS = st.lists(_TOKEN_PIECES, min_size=1, max_size=8).map("".join)


@given(st.lists(_FUZZ_TOKENS, max_size=8).map(" ".join))
def test_parse_raises_only_genome_errors(text):
    """Any text either parses (and round-trips) or raises GenomeError naming a real token."""
    try:
        g = Genome.parse(text)
    except GenomeError as err:
        assert isinstance(err, ValueError)
        n = len(text.split())
        assert err.position is None or 0 <= err.position < n
        if err.position is not None:
            assert _same_gene_part(err.token, text.split()[err.position])
            assert f"token {err.position} {err.token!r}: " in str(err)
        assert err.reason in str(err)
    else:
        assert Genome.parse(str(g)) == g


def test_parse_rejects_non_text():
    with pytest.raises(TypeError, match="expects a str"):
        Genome.parse(b"N0/1*1 B*1")  # type: ignore[arg-type]


# -------------------------------------------------------------------------------- accessors
def test_accessors_on_worked_example():
    g = Genome.parse(EXAMPLE)
    assert (g.n_inputs, g.n_outputs, g.n_params, g.n_neurons, len(g)) == (3, 2, 9, 3, 9)
    np.testing.assert_array_equal(g.weights, [1.0, 0.3, 0.5, 1, -2, 0.7, -1.2, 0.1, 0.4])
    assert g.weights.dtype == np.float64
    assert g.roots == (0, 6)
    np.testing.assert_array_equal(g.parent, [-1, 0, 0, 2, 2, 0, -1, 6, 6])
    assert g.neuron_ids == (0, 1, 2)
    assert g.neuron_position == {0: 0, 1: 2, 2: 6}
    assert g.depth() == 2  # N0 reads N1 and (through F2) N2, both of depth 1
    assert g.children(0) == [1, 2, 5]
    assert g.children(2) == [3, 4]
    assert g.children(6) == [7, 8]
    assert g.children(3) == []
    assert [g.subtree_end(i) for i in (0, 2, 6, 8)] == [6, 5, 9, 9]
    assert g[1] == Gene(GeneKind.FORWARD, 2, 0.3)
    assert list(g) == list(g.genes)
    assert g.structure_key()[0] == (GeneKind.NEURON, 0, 3)


def test_no_inputs_and_deep_chain():
    g = Genome.parse("N3/1*1 N2/1*1 N1/1*1 N0/1*1 B*1")
    assert g.n_inputs == 0
    assert g.depth() == 4
    assert g.roots == (0,)
    # A forward jumper lengthens the chain: N5 reads N4 (depth 2) through F4.
    assert Genome.parse("N5/2*1 B*1 F4*1 N4/1*1 N9/1*1 I0*1").depth() == 3


def _independent_depth(g: Genome) -> int:
    """Longest chain of neurons along sub-neuron and forward-jumper edges, by recursion."""
    memo: dict[int, int] = {}

    def level(index: int) -> int:
        if index not in memo:
            below = [0]
            for c in g.children(index):
                gene = g[c]
                if gene.kind == GeneKind.NEURON:
                    below.append(level(c))
                elif gene.kind == GeneKind.FORWARD:
                    below.append(level(g.neuron_position[gene.ref]))
            memo[index] = 1 + max(below)
        return memo[index]

    return max(level(i) for i, gene in enumerate(g) if gene.kind == GeneKind.NEURON)


@given(genomes())
def test_derived_structure_is_consistent(g):
    genes = g.genes
    n = len(genes)
    assert g.n_params == n == len(g.weights)
    np.testing.assert_array_equal(g.weights, [x.weight for x in genes])
    assert g.n_neurons == sum(x.kind == GeneKind.NEURON for x in genes) == len(g.neuron_ids)
    assert g.n_inputs == 1 + max((x.ref for x in genes if x.kind == GeneKind.INPUT), default=-1)
    assert g.neuron_position == {x.ref: i for i, x in enumerate(genes) if x.kind == 0}
    # Roots: neurons, left to right, without parent; their subtrees tile the genome.
    assert g.n_outputs == len(g.roots) >= 1
    assert list(g.roots) == sorted(g.roots)
    ends = [g.subtree_end(r) for r in g.roots]
    assert list(g.roots[1:]) + [n] == ends
    for i, x in enumerate(genes):
        p = int(g.parent[i])
        if i in g.roots:
            assert p == -1 and x.kind == GeneKind.NEURON
            continue
        # Every gene is read by a neuron to its left, inside that neuron's subtree.
        assert 0 <= p < i < g.subtree_end(p)
        assert genes[p].kind == GeneKind.NEURON
        if x.kind == GeneKind.FORWARD:
            assert g.neuron_position[x.ref] > i
    for i, x in enumerate(genes):
        kids = [j for j in range(n) if g.parent[j] == i]
        assert g.children(i) == kids
        assert len(kids) == (x.arity if x.kind == GeneKind.NEURON else 0)
    assert g.depth() == _independent_depth(g)
    assert 1 <= g.depth() <= g.n_neurons


def test_derived_arrays_are_read_only():
    g = Genome.parse(EXAMPLE)
    with pytest.raises(ValueError, match="read-only"):
        g.weights[0] = 5.0
    with pytest.raises(ValueError, match="read-only"):
        g.parent[0] = 5
    g.neuron_position[0] = 99  # a copy
    assert g.neuron_position[0] == 0


# ------------------------------------------------------------------------ equality and copies
def test_equality_and_hash():
    a, b = Genome.parse(EXAMPLE), Genome.parse(EXAMPLE + " ")
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    other_weight = Genome.parse(EXAMPLE.replace("I2*0.4", "I2*0.5"))
    assert other_weight != a
    assert other_weight.structure_key() == a.structure_key()
    other_input = Genome.parse(EXAMPLE.replace("I2*0.4", "I1*0.4"))
    assert other_input != a and other_input.structure_key() != a.structure_key()
    assert a != str(a) and a != a.genes
    assert {a: 1}[b] == 1


@given(genomes(), st.data())
def test_with_weights(g, data):
    w = np.array(data.draw(st.lists(st.floats(-5, 5), min_size=len(g), max_size=len(g))))
    h = g.with_weights(w)
    np.testing.assert_array_equal(h.weights, w)
    assert h.structure_key() == g.structure_key()
    assert g.with_weights(g.weights) == g
    assert (h == g) == bool(np.all(w == g.weights))
    assert Genome.parse(str(h)) == h
    np.testing.assert_array_equal(g.weights, [x.weight for x in g])  # g unchanged
    # Built without validating again: every derived part is what validation derives.
    ref = Genome(dataclasses.replace(x, weight=float(v)) for x, v in zip(g, w, strict=True))
    assert h.genes == ref.genes and h.roots == ref.roots and h.depth() == ref.depth()
    np.testing.assert_array_equal(h.parent, ref.parent)
    assert h.neuron_position == ref.neuron_position and hash(h) == hash(ref)
    assert not h.weights.flags.writeable and not h.parent.flags.writeable


def test_with_weights_errors():
    g = Genome.parse(EXAMPLE)
    with pytest.raises(ValueError, match="expected 9 weights") as err:
        g.with_weights(np.zeros(8))
    assert not isinstance(err.value, GenomeError)
    with pytest.raises(ValueError, match="expected 9 weights"):
        g.with_weights(np.zeros((1, 9)))
    for bad in (math.nan, math.inf, -math.inf):
        w = np.zeros(9)
        w[4] = bad
        with pytest.raises(GenomeError, match="non-finite weight") as err:
            g.with_weights(w)
        assert err.value.position == 4


# -------------------------------------------------------------------------------- validation
INVALID = [
    # (text, position, phrase)
    ("", None, "empty genome"),
    (" \n\t ", None, "empty genome"),
    ("N0/1*1 X0*1", 1, "unknown token"),
    ("N0/1*1 N1*1", 1, "unknown token"),
    ("N0/1*1 i0*1", 1, "unknown token"),
    ("N0/1*1 I-1*1", 1, "unknown token"),
    ("N0/1*1 I0", 1, "missing weight"),
    ("N0/1*1 I0*", 1, "missing weight"),
    ("N0/1*1 B", 1, "missing weight"),
    ("N0/1*1 I0*abc", 1, "unparsable weight 'abc'"),
    ("N0/1*1 I0*1.5.2", 1, "unparsable weight"),
    ("N0/1*1 I0*nan", 1, "non-finite weight 'nan'"),
    ("N0/1*1 I0*inf", 1, "non-finite weight 'inf'"),
    ("N0/1*1 I0*-inf", 1, "non-finite weight '-inf'"),
    ("N0/1*1 I0*-Infinity", 1, "non-finite weight"),
    ("N0/1*1e999 I0*1", 0, "non-finite weight"),
    ("N0/0*1", 0, "k >= 1"),
    ("N0/1*1 N1/0*1", 1, "k >= 1"),
    ("N0/2*1 I0*1 N0/1*1 I0*1", 2, "duplicate neuron id 0 (first at token 0)"),
    ("N0/3*1 I0*1", 0, "stack underflow: neuron 0 takes 3 inputs but only 1 are available"),
    ("N0/1*1 N1/2*1 I0*1", 1, "stack underflow"),
    ("N0/1*1 F7*1", 1, "jumper to neuron 7, which does not exist"),
    ("N0/1*1 R7*1", 1, "jumper to neuron 7, which does not exist"),
    ("N0/1*1 F0*1", 1, "not to its right"),  # a neuron reading itself now
    ("N0/2*1 N1/1*1 F0*1 I0*1", 2, "not to its right"),  # reading its ancestor
    ("N0/2*1 N1/1*1 I0*1 F1*1", 3, "not to its right"),  # a sibling on its left
    ("N0/1*1 N1/1*1 I0*1 N2/1*1 F1*1", 4, "not to its right"),  # a root on its left
    ("I0*1", 0, "must be a neuron"),
    ("N0/1*1 I0*1 B*1", 2, "must be a neuron"),
    ("R0*1 N0/1*1 I0*1", 0, "must be a neuron"),
]


@pytest.mark.parametrize(("text", "position", "phrase"), INVALID)
def test_invalid_text(text, position, phrase):
    with pytest.raises(GenomeError) as info:
        Genome.parse(text)
    err = info.value
    assert isinstance(err, ValueError)
    assert err.position == position
    assert phrase in str(err)
    assert str(err).startswith("invalid genome: ")
    if position is not None:
        assert _same_gene_part(err.token, text.split()[position])
        assert f"token {position} {err.token!r}: " in str(err)


@pytest.mark.parametrize("case", INVALID_CASES)
@fewer_examples(0.25)  # run once per case
@given(data=st.data())
def test_invalid_edits_are_rejected(case, data):
    inv = data.draw(invalid_genomes(case), label="invalid")
    with pytest.raises(GenomeError) as info:
        Genome.parse(inv.text)
    assert info.value.position == inv.position
    assert inv.phrase in str(info.value)


def test_forward_jumper_to_a_root_on_its_right_is_valid():
    g = Genome.parse("N0/1*1 F1*1 N1/1*1 I0*1")
    assert g.n_outputs == 2 and g.depth() == 2


@pytest.mark.parametrize(
    ("genes", "position", "phrase"),
    [
        ([], None, "empty genome"),
        (["N0/1*1 B*1"], 0, "expected a Gene, got str"),
        ([Gene(GeneKind.NEURON, -1, 1.0, 1), Gene(GeneKind.BIAS, -1, 1.0)], 0, "non-negative"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.INPUT, -2, 1.0)], 1, "non-negative"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 0)], 0, "k >= 1"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.BIAS, -1, math.nan)], 1, "non-finite"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.RECURRENT, -3, 1.0)], 1, "not exist"),
        # Fields of the wrong type or range: one error naming the gene, before str(gene)
        # (KeyError: 9) or n_inputs (2.0) could see them.
        ([Gene(9, 0, 1.0)], 0, "unknown gene kind 9"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(-1, 0, 1.0)], 1, "unknown gene kind -1"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene("I", 0, 1.0)], 1, "unknown gene kind 'I'"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(True, 0, 1.0)], 1, "unknown gene kind True"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.INPUT, 1.0, 1.0)], 1, "ref must be"),
        ([Gene(GeneKind.NEURON, 0.0, 1.0, 1), Gene(GeneKind.BIAS, -1, 1.0)], 0, "ref must be"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1.0), Gene(GeneKind.BIAS, -1, 1.0)], 0, "arity must"),
        ([Gene(GeneKind.NEURON, 0, 1.0, True), Gene(GeneKind.BIAS, -1, 1.0)], 0, "arity must"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.INPUT, 2**31, 1.0)], 1, "beyond"),
        ([Gene(GeneKind.NEURON, 0, "1", 1), Gene(GeneKind.BIAS, -1, 1.0)], 0, "weight must be"),
        ([Gene(GeneKind.NEURON, 0, 1.0, 1), Gene(GeneKind.BIAS, -1, 1j)], 1, "weight must be"),
    ],
)
def test_invalid_genes(genes, position, phrase):
    with pytest.raises(GenomeError, match=phrase) as info:
        Genome(genes)
    assert info.value.position == position


def test_gene_fields_of_other_integer_types():
    """Integer codes and NumPy integers are integers (an IntEnum equals its code); the
    genome is the one written with GeneKind members and Python ints."""
    plain = Genome.parse("N3/1*1.5 I2*1.0")
    other = Genome([Gene(0, np.int64(3), np.float32(1.5), np.int32(1)), Gene(1, 2, 1.0)])
    assert other == plain and str(other) == str(plain) and other.n_inputs == 3
    assert type(other.n_inputs) is int
    assert Genome.parse(f"N{MAX_ID}/1*1 I{MAX_ID}*1").n_inputs == MAX_ID + 1


def test_parse_gene():
    assert parse_gene("N4/2*-0.5") == Gene(GeneKind.NEURON, 4, -0.5, 2)
    assert parse_gene("B*1e-3") == Gene(GeneKind.BIAS, -1, 1e-3)
    with pytest.raises(GenomeError, match="token 7 'X1\\*1': unknown token") as e:
        parse_gene("X1*1", 7)
    assert e.value.position == 7


def test_one_line_rule():
    """Lines end at \n or \r\n; any other character str.splitlines() breaks at is refused,
    comments included (a viewer shows it inside the line: genes after it would be read out
    of what the reader sees as a comment)."""
    assert split_lines("a\r\nb\nc\r\n") == ["a", "b", "c", ""]
    assert Genome.parse("N0/2*1 # two\r\n I0*1\r\n\tB*1\r\n") == Genome.parse("N0/2*1 I0*1 B*1")
    breaks = [c for c in map(chr, range(0x110000)) if len(f"a{c}b".splitlines()) == 2]
    assert len(breaks) == 10  # \n and the nine below
    for c in breaks:
        if c == "\n":
            continue
        for text in (f"N0/1*1 # x{c}N1/1*1 B*1\nB*1", f"N0/1*1{c}B*1", f"N0/1*1 B*1\n#{c}"):
            with pytest.raises(GenomeError, match=f"U\\+{ord(c):04X}") as e:
                Genome.parse(text)
            assert e.value.position is None and len(str(e.value).splitlines()) == 1


_ANY_FIELD = (
    st.integers(-3, 8)
    | st.sampled_from(list(GeneKind))
    | st.floats()
    | st.booleans()
    | st.none()
    | st.text(max_size=2)
    | st.integers(MAX_ID - 1, MAX_ID + 2)
)


@pytest.mark.slow
@given(genomes(), st.data())
def test_genes_of_any_field_values(g, data):
    """One field of one gene of a valid genome set to any value: a GenomeError naming a
    gene, or a genome whose text form parses back to it (so str() and n_inputs work on every
    Genome)."""
    genes = list(g)
    i = data.draw(st.integers(0, len(genes) - 1))
    field = data.draw(st.sampled_from(["kind", "ref", "weight", "arity"]))
    genes[i] = dataclasses.replace(genes[i], **{field: data.draw(_ANY_FIELD)})
    try:
        h = Genome(genes)
    except GenomeError as err:
        assert err.position is None or 0 <= err.position < len(genes)
        assert len(str(err).splitlines()) == 1
    else:
        assert Genome.parse(str(h)) == h and type(h.n_inputs) is int
