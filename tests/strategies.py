"""Hypothesis strategies for EANT2 linear genomes.

``genomes()`` builds VALID genomes by construction, so no example is filtered away:

1. pick the number of outputs (roots) and of neurons;
2. give every non-root neuron a parent among the neurons created before it (a random
   recursive forest), so that each non-root neuron appears exactly once, as a subtree;
3. give every neuron some terminal genes (inputs, repeats allowed; biases; forward and
   recurrent jumpers) and interleave them with its sub-neurons;
4. write the forest out in prefix order, then point each forward jumper at a neuron to its
   RIGHT (a current-step edge may only read a neuron that is already evaluated) and each
   recurrent jumper at any neuron.

Every choice is an integer drawn from a range that starts at its simplest value, so examples
shrink towards one output, few neurons, inputs only, jumpers to the nearest neuron.

``invalid_genomes()`` applies one invalidating edit to a valid genome and says which token
the error must name and a phrase its message must contain.

``genome_file_texts()`` writes genome files as an attacker or a damaged disk would: headers
whose fields take values of any JSON type, hostile strings (quotes, backslashes, every line
end Python knows), deep nesting, comment lines and line ends of every kind.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np
from hypothesis import settings
from hypothesis import strategies as st

from eant2_jax.genome import Gene, GeneKind, Genome

__all__ = [
    "INVALID_CASES",
    "LINE_BREAKS",
    "Invalid",
    "fewer_examples",
    "genome_batches",
    "genome_file_texts",
    "genomes",
    "hostile_strings",
    "invalid_genomes",
    "weights",
]


def fewer_examples(fraction: float, least: int = 5) -> settings:
    """The loaded profile with ``fraction`` of its examples, for tests run many times over
    (parameterised) or paying a compilation per example; the profile still sets the rest."""
    return settings(max_examples=max(least, int(settings.default.max_examples * fraction)))


@functools.cache  # strategies are immutable: one per argument set, not one per draw
def weights(bound: float = 2.0, *, subnormal: bool = True) -> st.SearchStrategy[float]:
    """Finite weights in ``[-bound, bound]``; ``subnormal=False`` leaves out the float32
    subnormals (which XLA's CPU arithmetic flushes to zero)."""
    if subnormal:
        return st.floats(-bound, bound, allow_nan=False, allow_infinity=False)
    tiny = float(np.finfo(np.float32).tiny)
    return st.floats(-bound, bound, allow_nan=False, allow_infinity=False).map(
        lambda w: 0.0 if abs(w) < tiny else w
    )


@st.composite
def genomes(
    draw,
    *,
    n_inputs: int = 3,
    max_outputs: int = 3,
    max_neurons: int = 6,
    min_neurons: int = 1,
    max_terminals: int = 3,
    n_outputs: int | None = None,
    forward: bool = True,
    recurrent: bool = True,
    bias: bool = True,
    max_id: int = 20,
    weight: st.SearchStrategy[float] | None = None,
) -> Genome:
    """Random valid genomes.

    Args:
      n_inputs: inputs are drawn from ``I0 .. I<n_inputs - 1>`` (0: no input genes).
      max_outputs: most roots (ignored if ``n_outputs`` is given).
      max_neurons: most neurons; the genome has at most ``max_neurons * (1 + max_terminals)``
        genes and depth at most ``max_neurons``.
      min_neurons: fewest neurons (at least the number of outputs anyway).
      max_terminals: most terminal genes (I, B, F, R) directly under one neuron.
      n_outputs: exact number of roots.
      forward, recurrent, bias: whether those gene kinds may appear.
      max_id: neuron ids are distinct values in ``[0, max_id]``.
      weight: strategy for each gene's weight (default: finite floats in [-2, 2]).
    """
    weight = weights() if weight is None else weight
    n_out = n_outputs if n_outputs is not None else draw(st.integers(1, max_outputs))
    lo = max(n_out, min_neurons)
    n = draw(st.integers(lo, max(lo, max_neurons)))
    assert n <= max_id + 1, "max_id too small for max_neurons"
    kinds = [GeneKind.INPUT] if n_inputs > 0 else []
    kinds += [GeneKind.BIAS] if bias or not kinds else []
    kinds += [GeneKind.RECURRENT] if recurrent else []
    kinds += [GeneKind.FORWARD] if forward else []

    # Nodes 0 .. n_out-1 are the roots; node j >= n_out hangs under an earlier node.
    sub: list[list[int]] = [[] for _ in range(n)]
    for j in range(n_out, n):
        sub[draw(st.integers(0, j - 1))].append(j)
    ids = draw(st.lists(st.integers(0, max_id), min_size=n, max_size=n, unique=True))

    # Children of each node: sub-neurons ("N", node) and terminals ("T", kind), interleaved.
    children: list[list[tuple[str, int]]] = []
    for j in range(n):
        n_term = draw(st.integers(0 if sub[j] else 1, max_terminals))
        terms = [("T", int(draw(st.sampled_from(kinds)))) for _ in range(n_term)]
        items = [("N", c) for c in sub[j]] + terms
        children.append(draw(st.permutations(items)) if len(items) > 1 else items)

    # Prefix order. A gene is (kind, node-or-None); refs are resolved below.
    layout: list[tuple[GeneKind, int | None]] = []

    def emit(j: int) -> None:
        layout.append((GeneKind.NEURON, j))
        for what, x in children[j]:
            if what == "N":
                emit(x)
            else:
                layout.append((GeneKind(x), None))

    for root in range(n_out):
        emit(root)

    position = {j: i for i, (kind, j) in enumerate(layout) if kind == GeneKind.NEURON}
    arity = [len(children[j]) for j in range(n)]
    genes = []
    for i, (kind, j) in enumerate(layout):
        w = draw(weight)
        if kind == GeneKind.NEURON:
            genes.append(Gene(kind, ids[j], w, arity[j]))
        elif kind == GeneKind.INPUT:
            genes.append(Gene(kind, draw(st.integers(0, n_inputs - 1)), w))
        elif kind == GeneKind.BIAS:
            genes.append(Gene(kind, -1, w))
        elif kind == GeneKind.RECURRENT:
            genes.append(Gene(kind, ids[draw(st.integers(0, n - 1))], w))
        else:
            # A forward jumper reads a neuron to its right; nearest first, so it shrinks to
            # the closest one. The last terminals of a genome have none: I0 (or B) instead.
            right = sorted((p, node) for node, p in position.items() if p > i)
            if right:
                node = right[draw(st.integers(0, len(right) - 1))][1]
                genes.append(Gene(kind, ids[node], w))
            elif n_inputs > 0:
                genes.append(Gene(GeneKind.INPUT, 0, w))
            else:
                genes.append(Gene(GeneKind.BIAS, -1, w))
    return Genome(genes)


def genome_batches(
    *,
    min_size: int = 1,
    max_size: int = 4,
    n_outputs: int | None = None,
    max_outputs: int = 3,
    **kw,
) -> st.SearchStrategy[list[Genome]]:
    """Lists of genomes that share one number of outputs (as one compiled batch needs)."""
    if n_outputs is not None:
        return st.lists(genomes(n_outputs=n_outputs, **kw), min_size=min_size, max_size=max_size)
    return st.integers(1, max_outputs).flatmap(
        lambda k: st.lists(genomes(n_outputs=k, **kw), min_size=min_size, max_size=max_size)
    )


@dataclasses.dataclass(frozen=True)
class Invalid:
    """An invalid genome text, the token index its error must name and a phrase of the reason."""

    text: str
    position: int | None
    phrase: str
    case: str


def _tokens(genome: Genome) -> list[str]:
    return [str(g) for g in genome]


INVALID_CASES = (
    "unknown",
    "missing",
    "unparsable",
    "nonfinite",
    "k0",
    "duplicate",
    "underflow",
    "ghost",
    "cycle",
    "root_append",
    "root_prepend",
)


@st.composite
def invalid_genomes(draw, case: str | None = None, base: st.SearchStrategy[Genome] | None = None):
    """One invalidating edit of a valid genome, with the error it must raise.

    Args:
      case: one of :data:`INVALID_CASES` (default: any).
      base: strategy of the valid genome to edit (default :func:`genomes`).
    """
    if case is None:
        case = draw(st.sampled_from(INVALID_CASES))
    elif case not in INVALID_CASES:
        raise ValueError(f"unknown case {case!r}")
    if base is None:
        base = genomes(min_neurons=2 if case == "duplicate" else 1)
    g = draw(base)
    assert case != "duplicate" or g.n_neurons >= 2, "a duplicate id needs two neurons"
    tok = _tokens(g)
    n = len(tok)
    neurons = [i for i, gene in enumerate(g) if gene.kind == GeneKind.NEURON]
    terminals = [i for i, gene in enumerate(g) if gene.kind != GeneKind.NEURON]
    ids = set(g.neuron_ids)
    i = draw(st.integers(0, n - 1))
    if case == "unknown":
        bad = draw(st.sampled_from(["X1*1", "N1*1", "I*1", "n0/1*1", "J0*1", "Nx/1*1", "*1"]))
        tok[i] = bad
        return Invalid(" ".join(tok), i, "unknown token", case)
    if case == "missing":
        tok[i] = tok[i].split("*")[0] + draw(st.sampled_from(["", "*"]))
        return Invalid(" ".join(tok), i, "missing weight", case)
    if case == "unparsable":
        bad = draw(st.sampled_from(["abc", "1.2.3", "0x10", "1e", "--1", "1,5", "**1"]))
        tok[i] = tok[i].split("*")[0] + "*" + bad
        return Invalid(" ".join(tok), i, "unparsable weight", case)
    if case == "nonfinite":
        bad = draw(st.sampled_from(["nan", "inf", "-inf", "Infinity", "NaN", "1e999"]))
        tok[i] = tok[i].split("*")[0] + "*" + bad
        return Invalid(" ".join(tok), i, "non-finite weight", case)
    if case == "k0":
        j = draw(st.sampled_from(neurons))
        tok[j] = f"N{g[j].ref}/0*{g[j].weight!r}"
        return Invalid(" ".join(tok), j, "k >= 1", case)
    if case == "underflow":
        # The rightmost root reads only its own children: one more input cannot be there.
        j = g.roots[-1]
        extra = draw(st.integers(1, 3))
        tok[j] = f"N{g[j].ref}/{g[j].arity + extra}*{g[j].weight!r}"
        return Invalid(" ".join(tok), j, "stack underflow", case)
    if case == "ghost":
        j = draw(st.sampled_from(terminals))
        ghost = max(ids) + 1 + draw(st.integers(0, 5))
        tok[j] = f"{draw(st.sampled_from('FR'))}{ghost}*1.0"
        return Invalid(" ".join(tok), j, "does not exist", case)
    if case == "cycle":
        # A forward jumper to a neuron at or left of it: the neuron is not evaluated yet.
        j = draw(st.sampled_from(terminals))
        left = [p for p in neurons if p <= j]
        tok[j] = f"F{g[draw(st.sampled_from(left))].ref}*1.0"
        return Invalid(" ".join(tok), j, "not to its right", case)
    if case == "root_append":
        # Appended last, it lies at the bottom of the stack: no neuron takes it.
        tok.append(draw(st.sampled_from(["I0*1.0", "B*1.0", f"R{g[0].ref}*1.0"])))
        return Invalid(" ".join(tok), n, "must be a neuron", case)
    if case == "root_prepend":
        tok.insert(0, draw(st.sampled_from(["I0*1.0", "B*1.0", f"R{g[0].ref}*1.0"])))
        return Invalid(" ".join(tok), 0, "must be a neuron", case)
    # duplicate: a later neuron takes the id of an earlier one; the later one is named.
    a, b = sorted(draw(st.lists(st.sampled_from(neurons), min_size=2, max_size=2, unique=True)))
    tok[b] = f"N{g[a].ref}/{g[b].arity}*{g[b].weight!r}"
    return Invalid(" ".join(tok), b, "duplicate neuron id", case)


# Every character str.splitlines() ends a line at.
LINE_BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"
_HOSTILE_PIECES = [
    '"""', "'''", '"', "'", "\\", "\\n", "#", "{", "}", "[", "]", "\x00", "\x1b[2J",
    "__import__('os').system('true')", '__import__("os").system("true")', "+", ";", "\t",
    "N9/1*5", "B*1", " ", "xor", "gymnax:CartPole-v1", "\ufeff", "\u00e9", "\U0001f600",
    *LINE_BREAKS,
]  # fmt: skip


@functools.cache  # strategies are immutable: one per size, not one per draw
def hostile_strings(max_size: int = 12) -> st.SearchStrategy[str]:
    """Strings built of pieces that break out of quotes, lines or comments, and any text."""
    pieces = st.lists(st.sampled_from(_HOSTILE_PIECES) | st.text(max_size=4), max_size=max_size)
    return pieces.map("".join)


_JSON_LEAVES = (
    st.none()
    | st.booleans()
    | st.integers(-(2**40), 2**40)
    | st.floats(allow_nan=False, allow_infinity=False)
    | hostile_strings()
)
_JSON = st.recursive(
    _JSON_LEAVES,
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(hostile_strings(4), inner, max_size=3)
    ),
    max_leaves=8,
)
_FIELDS = ("format", "hidden", "output", "n_inputs", "n_outputs", "task", "task_options")


# genome_file_texts' fixed strategies, built once (building them on every draw was most of
# the fuzz's time).
_FILE_GENOMES = genomes(max_neurons=4)
_TASKS = st.none() | hostile_strings()
_TASK_OPTIONS = st.none() | st.dictionaries(hostile_strings(4), _JSON, max_size=3)
_FIELD_EDITS = st.lists(st.sampled_from(_FIELDS), max_size=3, unique=True)
_DEPTHS = st.sampled_from([0, 0, 0, 30, 40, 100_000])
_SEPARATORS = st.sampled_from([" ", "  ", "\t", "\n", "\r\n", "\u00a0", "\u3000", *LINE_BREAKS])
_LINE_ENDS = st.sampled_from(["\n", "\r\n", *LINE_BREAKS])


@st.composite
def genome_file_texts(draw, activations: tuple[str, ...] = ("tanh", "sigmoid", "identity")):
    """The text of a genome file, valid or not (module docstring).

    A valid genome and a header true to it are drawn first; then each header field may be
    replaced by any JSON value or dropped, a key added, raw non-ASCII kept in the JSON
    (``ensure_ascii=False``), the object wrapped in deep brackets, comment lines added, the
    lines ended by any line end, and the genome's tokens separated by any whitespace.
    """
    g = draw(_FILE_GENOMES)
    head = {
        "format": 1,
        "hidden": draw(st.sampled_from(activations)),
        "output": draw(st.sampled_from(activations)),
        "n_inputs": g.n_inputs + draw(st.integers(0, 2)),
        "n_outputs": g.n_outputs,
        "task": draw(_TASKS),
        "task_options": draw(_TASK_OPTIONS),
    }
    for key in draw(_FIELD_EDITS):
        if draw(st.booleans()):
            head[key] = draw(_JSON)
        else:
            del head[key]
    if draw(st.booleans()):
        head[draw(hostile_strings(4))] = draw(_JSON)
    body = json.dumps(head, ensure_ascii=draw(st.booleans()))
    depth = draw(_DEPTHS)
    if depth:
        body = body[:-1] + ', "deep": ' + "[" * depth + "]" * depth * draw(st.booleans()) + "}"
    lines = [] if draw(st.integers(0, 4)) == 0 else ["# eant2-genome " + body]
    lines += ["#" + draw(hostile_strings()) for _ in range(draw(st.integers(0, 2)))]
    tokens = [str(gene) for gene in g]
    genes = tokens[0] + "".join(draw(_SEPARATORS) + t for t in tokens[1:])
    end = draw(_LINE_ENDS)
    return end.join([*lines, genes]) + draw(st.sampled_from(["", "\n", end]))
