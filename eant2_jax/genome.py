"""The EANT2 linear genome: a network as a list of genes in prefix order.

Paper section III.A, figure 2. Each gene carries exactly one weight, so the genome's length is
its number of parameters and its weight vector is in gene order.

Text form (tokens separated by whitespace; ``#`` starts a comment that runs to the end of its
line, which is where genome files keep their header, see `eant2_jax.genomefile`; lines end
with ``\n`` or ``\r\n`` only, see `split_lines`):

* ``N<id>/<k>*<w>`` neuron ``id`` (non-negative, unique) with ``k >= 1`` inputs, weight ``w``
* ``I<j>*<w>``      network input ``j`` (0-based)
* ``B*<w>``         bias (the constant 1.0)
* ``F<id>*<w>``     forward jumper: the current-step output of neuron ``id``
* ``R<id>*<w>``     recurrent jumper: the previous-step output of neuron ``id`` (0.0 at step 0)

Numbers are ASCII digits, at most ``MAX_ID`` = 2**31 - 1; weights are float literals of at
most 64 ASCII characters, finite.

Semantics: walk the genes from last to first with a stack. ``I``, ``B``, ``F`` and ``R`` push
``w * value``. ``N`` pops ``k`` values, sums them to ``a``, computes ``o = act(a)`` (output
activation for roots, hidden activation otherwise), records ``o`` as the neuron's output at
this step and pushes ``w * o``. At the end the stack holds the outputs; output 0 is the
leftmost root.

This module is host-side Python (NumPy); nothing here is traced by JAX.
"""

from __future__ import annotations

import dataclasses
import enum
import math
import numbers
import re
from collections.abc import Iterable, Sequence

import numpy as np

__all__ = ["MAX_ID", "Gene", "GeneKind", "Genome", "GenomeError", "parse_gene", "split_lines"]


class GeneKind(enum.IntEnum):
    """The five gene kinds; the integer codes are used by the compiler's tables."""

    NEURON = 0
    INPUT = 1
    BIAS = 2
    FORWARD = 3
    RECURRENT = 4


_LETTER = {
    GeneKind.NEURON: "N",
    GeneKind.INPUT: "I",
    GeneKind.BIAS: "B",
    GeneKind.FORWARD: "F",
    GeneKind.RECURRENT: "R",
}

# One regex per token; the weight is matched loosely and parsed by float() so that any Python
# float literal (1, -2.5, 1e-3, 1_000.5, .5) is accepted and anything else is reported.
# Numbers are ASCII digits only (\d would take any Unicode digit, int() would convert it).
_TOKEN = re.compile(
    r"""^(?:
        N(?P<nid>[0-9]+)/(?P<k>[0-9]+)
      | I(?P<inp>[0-9]+)
      | (?P<bias>B)
      | F(?P<fid>[0-9]+)
      | R(?P<rid>[0-9]+)
    )\*(?P<w>\S+)$""",
    re.VERBOSE,
)
# Neuron ids, input indices and arities are below 2**31 (they index int32 tables); a
# longer digit string is refused before int() sees it.
MAX_ID = 2**31 - 1

# Characters Python's str.splitlines() takes as line ends, besides "\n" and the "\r" of
# "\r\n". A viewer or terminal shows most of them inside a line (U+2028 as nothing, "\r"
# by overwriting the line's start), so a parser that broke lines there would read genes
# out of what a reader sees as a comment; the text is refused instead (docs/genome.md).
_OTHER_BREAKS = re.compile("[\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")


class GenomeError(ValueError):
    """A malformed genome. ``position`` is the 0-based token index (None if not one token)."""

    def __init__(self, reason: str, position: int | None = None, token: str | None = None):
        self.reason = reason
        self.position = position
        self.token = token
        where = "" if position is None else f"token {position}"
        if token is not None:
            where += f" {token if len(token) <= 40 else token[:37] + '...'!r}"
        super().__init__(
            f"invalid genome: {where}: {reason}" if where else f"invalid genome: {reason}"
        )


@dataclasses.dataclass(frozen=True, slots=True)
class Gene:
    """One gene. ``ref`` is the neuron id (N, F, R), the input index (I) or -1 (B)."""

    kind: GeneKind
    ref: int
    weight: float
    arity: int = 0  # number of inputs, neurons only

    def __str__(self) -> str:
        w = repr(float(self.weight))
        if self.kind == GeneKind.NEURON:
            return f"N{self.ref}/{self.arity}*{w}"
        if self.kind == GeneKind.BIAS:
            return f"B*{w}"
        return f"{_LETTER[self.kind]}{self.ref}*{w}"


def _parse_weight(text: str, position: int, token: str) -> float:
    if not text.isascii() or len(text) > 64:
        raise GenomeError(f"unparsable weight {text[:20]!r}", position, token[:40])
    # float() accepts 'nan', 'inf', 'infinity' and surrounding spaces; the regex already
    # excluded spaces, and non-finite values get their own message.
    try:
        w = float(text)
    except ValueError:
        raise GenomeError(f"unparsable weight {text!r}", position, token) from None
    if not math.isfinite(w):
        raise GenomeError(f"non-finite weight {text!r}", position, token)
    return w


def parse_gene(token: str, position: int = 0) -> Gene:
    """One token of the text form as a `Gene`; ``position`` is the token index errors name.

    Raises:
      GenomeError: the token is not a gene (the message names it and the reason).
    """
    m = _TOKEN.match(token)
    if m is None:
        if "*" not in token or token.endswith("*"):
            raise GenomeError("missing weight (expected '<gene>*<weight>')", position, token)
        raise GenomeError(
            "unknown token (expected N<id>/<k>*w, I<j>*w, B*w, F<id>*w or R<id>*w)",
            position,
            token,
        )
    w = _parse_weight(m["w"], position, token)
    for group in ("nid", "k", "inp", "fid", "rid"):
        digits = m[group]
        if digits is not None and (len(digits) > 10 or int(digits) > MAX_ID):
            raise GenomeError(
                f"number {digits[:12]}{'...' if len(digits) > 12 else ''} is larger than {MAX_ID}",
                position,
                token,
            )
    if m["nid"] is not None:
        k = int(m["k"])
        if k < 1:
            raise GenomeError("a neuron needs k >= 1 inputs", position, token)
        return Gene(GeneKind.NEURON, int(m["nid"]), w, k)
    if m["inp"] is not None:
        return Gene(GeneKind.INPUT, int(m["inp"]), w)
    if m["bias"] is not None:
        return Gene(GeneKind.BIAS, -1, w)
    if m["fid"] is not None:
        return Gene(GeneKind.FORWARD, int(m["fid"]), w)
    return Gene(GeneKind.RECURRENT, int(m["rid"]), w)


def split_lines(text: str) -> list[str]:
    """The lines of a genome text, by the one rule every reader of genome text follows.

    A line ends at ``\n`` or ``\r\n``. Any other character that Python's
    ``str.splitlines`` takes as a line end (a lone ``\r``, ``\x0b``, ``\x0c``,
    ``\x1c``-``\x1e``, ``\x85``, U+2028, U+2029) is refused wherever it stands, comments
    included: viewers show those characters inside a line, so genes after one would load
    as a network other than the file shows.

    Raises:
      GenomeError: such a character, with its line number (1-based) and code point.
    """
    lines = text.split("\n")
    for number, line in enumerate(lines, start=1):
        body = line[:-1] if line.endswith("\r") and number < len(lines) else line
        bad = _OTHER_BREAKS.search(body)
        if bad is not None:
            raise GenomeError(
                f"line {number}: character U+{ord(bad.group()):04X} breaks lines in some "
                "readers and not in others; genome text ends its lines with \\n or \\r\\n"
            )
        lines[number - 1] = body
    return lines


class Genome:
    """An immutable, validated EANT2 linear genome.

    Construct with `parse` (text form) or from a sequence of `Gene`. Validation
    runs on construction, so every ``Genome`` in existence is evaluable.

    Derived structure (all in gene order, computed once at construction):

    * ``parent[g]``: index of the neuron gene that consumes gene ``g`` (-1 for roots);
    * ``roots``: gene indices of the root neurons, left to right (output order);
    * ``neuron_position[id]``: gene index of neuron ``id``.
    """

    __slots__ = ("_genes", "_parent", "_roots", "_neuron_position", "_weights", "_hash")

    def __init__(self, genes: Iterable[Gene]):
        genes = tuple(genes)
        self._genes = genes
        self._parent, self._roots, self._neuron_position = _validate(genes)
        self._weights = np.array([g.weight for g in genes], dtype=np.float64)
        self._weights.setflags(write=False)
        self._hash = None

    # ----------------------------------------------------------------------------- text form
    @classmethod
    def parse(cls, text: str) -> Genome:
        """Parse the text form; raises `GenomeError` naming the token and the reason.

        ``#`` starts a comment that runs to the end of its line (a genome file's header).
        """
        if not isinstance(text, str):
            raise TypeError(f"Genome.parse expects a str, got {type(text).__name__}")
        tokens = [t for line in split_lines(text) for t in line.split("#", 1)[0].split()]
        if not tokens:
            raise GenomeError("empty genome")
        return cls(parse_gene(t, i) for i, t in enumerate(tokens))

    def __str__(self) -> str:
        """Canonical text form: one space between tokens, weights as ``repr(float)``."""
        return " ".join(str(g) for g in self._genes)

    def __repr__(self) -> str:
        text = str(self)
        if len(text) > 80:
            text = text[:77] + "..."
        return f"Genome({text!r})"

    # ------------------------------------------------------------------------------ equality
    def __eq__(self, other: object) -> bool:
        return isinstance(other, Genome) and self._genes == other._genes

    def __hash__(self) -> int:
        if self._hash is None:
            self._hash = hash(self._genes)
        return self._hash

    def structure_key(self) -> tuple:
        """The genome with its weights dropped: equal keys mean identical structures."""
        return tuple((g.kind, g.ref, g.arity) for g in self._genes)

    # ----------------------------------------------------------------------------- accessors
    @property
    def genes(self) -> tuple[Gene, ...]:
        return self._genes

    def __len__(self) -> int:
        return len(self._genes)

    def __iter__(self):
        return iter(self._genes)

    def __getitem__(self, index: int) -> Gene:
        return self._genes[index]

    @property
    def n_params(self) -> int:
        """Number of parameters = number of genes (paper: the network's "size")."""
        return len(self._genes)

    @property
    def weights(self) -> np.ndarray:
        """The weight vector in gene order, float64 ``[n_params]`` (read-only)."""
        return self._weights

    @property
    def n_outputs(self) -> int:
        return len(self._roots)

    @property
    def n_inputs(self) -> int:
        """Number of network inputs this genome reads: 1 + the largest input index (0 if none)."""
        return 1 + max((g.ref for g in self._genes if g.kind == GeneKind.INPUT), default=-1)

    @property
    def n_neurons(self) -> int:
        return len(self._neuron_position)

    @property
    def neuron_ids(self) -> tuple[int, ...]:
        """Neuron ids in gene order."""
        return tuple(g.ref for g in self._genes if g.kind == GeneKind.NEURON)

    @property
    def parent(self) -> np.ndarray:
        """``parent[g]``: gene index of the neuron consuming gene ``g``; -1 for roots."""
        return self._parent

    @property
    def roots(self) -> tuple[int, ...]:
        """Gene indices of the root neurons, in output order."""
        return self._roots

    @property
    def neuron_position(self) -> dict[int, int]:
        """Map neuron id -> gene index."""
        return dict(self._neuron_position)

    def with_weights(self, weights: Sequence[float] | np.ndarray) -> Genome:
        """A copy with a new weight vector (length ``n_params``, finite)."""
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (len(self._genes),):
            raise ValueError(
                f"with_weights: expected {len(self._genes)} weights, got shape {w.shape}"
            )
        if not np.all(np.isfinite(w)):
            bad = int(np.flatnonzero(~np.isfinite(w))[0])
            raise GenomeError(f"non-finite weight {w[bad]!r}", bad)
        # The same structure: its derived parts (read-only) are shared, not validated again.
        new = object.__new__(Genome)
        new._genes = tuple(
            Gene(g.kind, g.ref, float(x), g.arity) for g, x in zip(self._genes, w, strict=True)
        )
        new._parent, new._roots = self._parent, self._roots
        new._neuron_position = self._neuron_position
        new._weights = w.copy()
        new._weights.setflags(write=False)
        new._hash = None
        return new

    def subtree_end(self, index: int) -> int:
        """One past the last gene of the sub-genome rooted at gene ``index``."""
        need = 1
        j = index
        while need:
            need += self._genes[j].arity - 1 if self._genes[j].kind == GeneKind.NEURON else -1
            j += 1
        return j

    def depth(self) -> int:
        """Longest chain of neurons along forward edges (sub-neurons and forward jumpers).

        A network of output neurons only has depth 1. One right-to-left pass: every input of
        a gene lies to its right, and a forward jumper's source too.
        """
        level: dict[int, int] = {}  # neuron id -> its depth
        below = np.zeros(len(self._genes), dtype=np.int64)  # per gene: deepest input so far
        for i in reversed(range(len(self._genes))):
            gene = self._genes[i]
            if gene.kind == GeneKind.NEURON:
                level[gene.ref] = 1 + int(below[i])
                lv = level[gene.ref]
            elif gene.kind == GeneKind.FORWARD:
                lv = level[gene.ref]
            else:
                continue
            p = self._parent[i]
            if p >= 0:
                below[p] = max(below[p], lv)
        return max(level.values())

    def children(self, index: int) -> list[int]:
        """Gene indices of the direct inputs of the neuron at gene ``index``, left to right."""
        gene = self._genes[index]
        if gene.kind != GeneKind.NEURON:
            return []
        out = []
        j = index + 1
        for _ in range(gene.arity):
            out.append(j)
            j = self.subtree_end(j)
        return out


def _is_int(x: object) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _check_fields(g: object, i: int) -> None:
    """The types and ranges of one gene's fields, before anything reads them (``str`` of a
    gene of an unknown kind would fail; a float index would make ``n_inputs`` a float)."""
    if not isinstance(g, Gene):
        raise GenomeError(f"expected a Gene, got {type(g).__name__}", i)
    # The usual gene (as parsing and the library build them) passes every check below.
    if (
        type(g.kind) is GeneKind
        and type(g.ref) is int
        and type(g.arity) is int
        and type(g.weight) is float
        and abs(g.ref) <= MAX_ID
        and abs(g.arity) <= MAX_ID
    ):
        return
    # A GeneKind, or its integer code (an IntEnum equals its code, so both work alike).
    if not (isinstance(g.kind, GeneKind) or (_is_int(g.kind) and 0 <= g.kind < len(GeneKind))):
        raise GenomeError(
            f"unknown gene kind {g.kind!r:.40} (expected a GeneKind: "
            f"{', '.join(k.name for k in GeneKind)})",
            i,
        )
    name = GeneKind(g.kind).name
    for field, value in (("ref", g.ref), ("arity", g.arity)):
        if not _is_int(value):
            raise GenomeError(f"{name} gene: {field} must be an integer, got {value!r:.40}", i)
        if abs(value) > MAX_ID:
            raise GenomeError(f"{name} gene: {field} {value} is beyond +-{MAX_ID}", i)
    if not isinstance(g.weight, numbers.Real) or isinstance(g.weight, bool):
        raise GenomeError(f"{name} gene: weight must be a real number, got {g.weight!r:.40}", i)


def _validate(genes: tuple[Gene, ...]) -> tuple[np.ndarray, tuple[int, ...], dict[int, int]]:
    """Check the genome and derive (parent, roots, neuron_position). Raises GenomeError."""
    if not genes:
        raise GenomeError("empty genome")
    neuron_position: dict[int, int] = {}
    for i, g in enumerate(genes):
        _check_fields(g, i)
        if not math.isfinite(g.weight):
            raise GenomeError(f"non-finite weight {g.weight!r}", i, str(g))
        if g.kind == GeneKind.NEURON:
            if g.arity < 1:
                raise GenomeError("a neuron needs k >= 1 inputs", i, str(g))
            if g.ref < 0:
                raise GenomeError("neuron id must be non-negative", i, str(g))
            if g.ref in neuron_position:
                raise GenomeError(
                    f"duplicate neuron id {g.ref} (first at token {neuron_position[g.ref]})",
                    i,
                    str(g),
                )
            neuron_position[g.ref] = i
        else:
            if g.arity != 0:
                raise GenomeError("only neurons have inputs (arity must be 0)", i, str(g))
            if g.kind == GeneKind.INPUT and g.ref < 0:
                raise GenomeError("input index must be non-negative", i, str(g))
            if g.kind == GeneKind.BIAS and g.ref != -1:
                raise GenomeError("a bias gene has ref -1", i, str(g))
    for i, g in enumerate(genes):
        if g.kind in (GeneKind.FORWARD, GeneKind.RECURRENT):
            if g.ref not in neuron_position:
                raise GenomeError(f"jumper to neuron {g.ref}, which does not exist", i, str(g))
            if g.kind == GeneKind.FORWARD and neuron_position[g.ref] <= i:
                raise GenomeError(
                    f"forward jumper to neuron {g.ref}, which is not to its right "
                    "(it would not be evaluated yet: a cycle); use a recurrent jumper",
                    i,
                    str(g),
                )
    # The stack walk, last gene to first; the stack holds gene indices.
    parent = np.full(len(genes), -1, dtype=np.int64)
    stack: list[int] = []
    for i in reversed(range(len(genes))):
        g = genes[i]
        if g.kind == GeneKind.NEURON:
            if len(stack) < g.arity:
                raise GenomeError(
                    f"stack underflow: neuron {g.ref} takes {g.arity} inputs "
                    f"but only {len(stack)} are available",
                    i,
                    str(g),
                )
            for _ in range(g.arity):
                parent[stack.pop()] = i
        stack.append(i)
    roots = tuple(reversed(stack))  # the stack top is the leftmost root
    for r in roots:
        if genes[r].kind != GeneKind.NEURON:
            raise GenomeError("a root (network output) must be a neuron", r, str(genes[r]))
    parent.setflags(write=False)
    return parent, roots, neuron_position
