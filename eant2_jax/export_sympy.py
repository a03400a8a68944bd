"""A network as sympy expressions, and LaTeX from them: `to_sympy` (the ``export`` extra).

One equation per neuron, in evaluation order, and one per output:

    h<id> = act(sum_j W_in[i, j] x<j> + bias[i] + sum_k W_ff[i, k] h<k> + sum_k W_rec[i, k] hp<k>)
    y<k>  = sum_i W_out[k, i] h<i>

with the float32 weights of the kernels' dense tensors (`eant2_jax.export.dense`: several
genes between the same two nodes add up), exact as sympy Floats,
``act`` the output activation for root neurons and the hidden one otherwise, ``x<j>`` the
inputs and, for a recurrent network, ``hp<id>`` the previous step's output of neuron ``id``
(0 before the first step). `SympyNetwork.outputs` are the outputs with every neuron
substituted: expressions of the inputs (and the state) alone, for a network of any size.
Evaluated in float64 (``sympy.lambdify``) they equal the library's float32 outputs up to
float32 rounding (docs/export.md states the measured difference). The built-in activations
are written with their clipping and constants (`eant2_jax.kernels.activations`); a
registered one appears as an undefined sympy function of its name (give its definition to
``lambdify`` in ``modules``).

This replaces, for any size and for recurrent networks, the string printer
`eant2_jax.export.formula` (small feed-forward networks only).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np

from .genome import GeneKind
from .genomefile import GenomeFile, GenomeFileError

__all__ = ["SympyNetwork", "to_sympy"]

_MISSING = "sympy export needs the sympy package: pip install 'eant2-jax[export]'"


def _sympy():
    try:
        import sympy
    except ImportError:
        raise ImportError(_MISSING) from None
    return sympy


def _activations(sp) -> dict:
    """The built-in activations as sympy functions of the pre-activation ``a``."""
    from .kernels.activations import _SELU_ALPHA, _SELU_LAMBDA

    def clip(a, lo, hi):
        return sp.Min(sp.Max(a, lo), hi)

    def below(a, neg):  # a if a > 0 else neg
        return sp.Piecewise((a, a > 0), (neg, True))

    return {
        "identity": lambda a: a,
        "tanh": sp.tanh,
        "sigmoid": lambda a: 1 / (1 + sp.exp(-a)),
        "relu": lambda a: sp.Max(a, 0),
        "sin": lambda a: sp.sin(clip(5 * a, -60, 60)),
        "gauss": lambda a: sp.exp(-5 * clip(a, sp.Float(-3.4), sp.Float(3.4)) ** 2),
        "abs": sp.Abs,
        "clamped": lambda a: clip(a, -1, 1),
        "softplus": lambda a: sp.Float(0.2) * sp.log(1 + sp.exp(clip(5 * a, -60, 60))),
        # exp of min(a, 0), as the kernels: a lambdified Piecewise evaluates both branches.
        "elu": lambda a: below(a, sp.exp(sp.Min(a, 0)) - 1),
        "selu": lambda a: (
            sp.Float(_SELU_LAMBDA) * below(a, sp.Float(_SELU_ALPHA) * (sp.exp(sp.Min(a, 0)) - 1))
        ),
        "lelu": lambda a: below(a, sp.Float(0.005) * a),
        "square": lambda a: a**2,
        "cube": lambda a: a**3,
        "log": lambda a: sp.log(sp.Max(a, sp.Float(1e-7))),
        "exp": lambda a: sp.exp(clip(a, -60, 60)),
        "hat": lambda a: sp.Max(0, 1 - sp.Abs(a)),
    }


@functools.cache
def _latex_printer() -> type:
    """sympy's LaTeX printer, without its unbounded question on exponents.

    ``LatexPrinter._print_Mul`` splits a product with ``fraction(expr, exact=True)``, which
    asks ``ex.is_constant()`` of every ``exp(ex)`` or ``b**ex`` factor whose exponent it can
    prove negative: ``simplify`` of the exponent, which for a grown network's nested
    sigmoids (``c * exp(-(w / (1 + exp(...)) + ...))`` with every weight positive) runs for
    hours. ``is_constant`` answers at once for an exponent with no free symbols; every other
    such factor is printed here wrapped (an ``UnevaluatedExpr`` sorted as the factor), which
    ``fraction`` keeps in the numerator without a question: where sympy's answer is "not
    constant", which it always is for a network's exponents, the LaTeX is the same.
    """
    sp = _sympy()
    from sympy.printing.latex import LatexPrinter

    class Factor(sp.UnevaluatedExpr):
        is_commutative = True

        def sort_key(self, order=None):
            return self.args[0].sort_key(order)

    def asks(f) -> bool:  # fraction(exact=True) would ask is_constant() of its exponent
        return bool(
            f.is_commutative
            and (f.is_Pow or isinstance(f, sp.exp))
            and f.as_base_exp()[1].free_symbols
        )

    class Printer(LatexPrinter):
        def _print_Mul(self, expr):
            if expr.is_Mul and any(asks(f) for f in expr.args):  # (_print_Pow passes Pows)
                expr = sp.Mul(*[Factor(f) if asks(f) else f for f in expr.args])
            return super()._print_Mul(expr)

    return Printer


@dataclasses.dataclass(frozen=True)
class SympyNetwork:
    """A network as sympy objects (module docstring).

    Attributes:
      inputs: the input symbols ``x0 .. x<n_in - 1>``.
      state: for a recurrent network, ``hp<id>`` for every neuron a recurrent jumper reads
        (the previous step's outputs); empty for a feed-forward one.
      neurons: the neuron symbols ``h<id>``, in evaluation order.
      equations: ``Eq(h<id>, ...)`` per neuron in evaluation order, then ``Eq(y<k>, ...)``
        per output, in terms of the symbols above.
      outputs: ``y<k>`` as an expression of ``inputs`` (and ``state``) alone.
    """

    inputs: tuple
    state: tuple
    neurons: tuple
    equations: tuple
    outputs: tuple

    def latex(self, *, substitute: bool = False, digits: int | None = 6) -> str:
        """LaTeX (sympy's printer, as ``sympy.latex``): an ``aligned`` block of the
        equations, or with ``substitute`` of the outputs as functions of the inputs; weights
        to ``digits`` significant digits (None: all of them)."""
        sp = _sympy()
        printer = _latex_printer()()
        if substitute:
            rows = [
                (sp.Symbol(f"y{k}"), e) for k, e in enumerate(self.outputs)
            ]  # fmt: skip
        else:
            rows = [(eq.lhs, eq.rhs) for eq in self.equations]

        def short(e):
            if digits is None:
                return e
            return e.xreplace({f: sp.Float(f, digits) for f in e.atoms(sp.Float)})

        lines = [f"{printer.doprint(lhs)} &= {printer.doprint(short(rhs))}" for lhs, rhs in rows]
        return "\\begin{aligned}\n" + " \\\\\n".join(lines) + "\n\\end{aligned}"

    def text(self) -> str:
        """The equations as text, one per line (``h3 = tanh(...)``), weights in full."""
        return "".join(f"{eq.lhs} = {eq.rhs}\n" for eq in self.equations)

    def function(self, modules: Any = "numpy"):
        """``sympy.lambdify`` of the outputs: ``f(*inputs, *state) -> [y0, y1, ...]``."""
        return _sympy().lambdify((*self.inputs, *self.state), list(self.outputs), modules)


def to_sympy(spec: GenomeFile) -> SympyNetwork:
    """The network of ``spec`` as sympy equations and expressions (module docstring).

    Built on the host from the genome's genes (no compilation), with each weight rounded to
    float32 as the kernels hold it.

    Raises:
      ImportError: sympy is not installed (the ``export`` extra).
      GenomeFileError: the file names no activations.
    """
    sp = _sympy()
    from .kernels import activations

    if not spec.has_header:
        raise GenomeFileError(
            "the genome file names no activations; use spec.with_activations(hidden, output)"
        )
    known = _activations(sp)
    act = {}
    for name in (spec.hidden, spec.output):
        activations.get(name)  # one clear error for an unknown name
        act[name] = known.get(name, sp.Function(name))
    g = spec.genome
    n_in = spec.n_inputs if spec.n_inputs is not None else g.n_inputs
    # Evaluation order (the kernels' slot order): descending gene index.
    order = [i for i in reversed(range(len(g))) if g[i].kind == GeneKind.NEURON]
    xs = tuple(sp.Symbol(f"x{j}", real=True) for j in range(n_in))
    hs = {g[i].ref: sp.Symbol(f"h{g[i].ref}", real=True) for i in order}
    read_rec = {gene.ref for gene in g if gene.kind == GeneKind.RECURRENT}
    hp = {g[i].ref: sp.Symbol(f"hp{g[i].ref}", real=True) for i in order if g[i].ref in read_rec}
    roots = set(g.roots)
    eqs, exprs = [], {}
    for i in order:  # every neuron a neuron reads now lies to its right: already done
        sym, sub = [], []
        for c in g.children(i):
            gene = g[c]
            w = sp.Float(float(np.float32(gene.weight)))
            if gene.kind == GeneKind.INPUT:
                sym.append(w * xs[gene.ref])
                sub.append(w * xs[gene.ref])
            elif gene.kind == GeneKind.BIAS:
                sym.append(w)
                sub.append(w)
            elif gene.kind == GeneKind.RECURRENT:
                sym.append(w * hp[gene.ref])
                sub.append(w * hp[gene.ref])
            else:  # a sub-neuron or a forward jumper: that neuron's current output
                sym.append(w * hs[gene.ref])
                sub.append(w * exprs[gene.ref])
        f = act[spec.output if i in roots else spec.hidden]
        ref = g[i].ref
        eqs.append(sp.Eq(hs[ref], f(sp.Add(*sym))))
        exprs[ref] = f(sp.Add(*sub))
    outs = []
    for k, r in enumerate(g.roots):
        w = sp.Float(float(np.float32(g[r].weight)))
        eqs.append(sp.Eq(sp.Symbol(f"y{k}", real=True), w * hs[g[r].ref]))
        outs.append(w * exprs[g[r].ref])
    return SympyNetwork(xs, tuple(hp.values()), tuple(hs.values()), tuple(eqs), tuple(outs))
