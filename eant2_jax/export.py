"""Exports of a network beyond the text genome: JSON, a standalone JAX function, a formula.

Each takes a `GenomeFile` with its activations (a file with a
header, or one given them with ``with_activations``):

* `to_json` — genes, weights, activations, sizes and the dense float32 tensors;
  `from_json` reads it back.
* `to_jax_source` — a Python module that needs only ``jax``: the dense tensors as
  literals and ``network(xs)`` (``[T, M, n_in] -> [T, M, n_out]``) plus ``step(x, h)``;
  `to_jax` runs that source and returns its ``network``.
* `formula` — for small feed-forward networks, one line of Python per neuron (for any
  size, recurrent networks and LaTeX: `eant2_jax.export_sympy`; ONNX:
  `eant2_jax.export_onnx`; docs/export.md).

The dense tensors are those of `eant2_jax.kernels.network` for this genome alone,
without padding: neuron slots in topological order (descending gene index), so ``w_ff`` is
strictly lower-triangular and ``depth`` sweeps compute a step exactly.

The generated source is built from the validated structure, never from the file's text:
numbers are formatted from the dense float32 tensors and the genome's canonical form, the
activations' code comes from this process's registry (the file only names an entry), and
the only names it carries (task, activations) are those matching ``[A-Za-z0-9_.:-]{1,64}``;
any other is left out. A hostile genome file therefore cannot put code in it
(docs/reliability.md, "Genome files").
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import jax
import numpy as np

from .compiler import networks
from .genome import GeneKind, Genome
from .genomefile import FORMAT, GenomeFile, GenomeFileError
from .kernels import activations

__all__ = ["dense", "formula", "from_json", "to_jax", "to_jax_source", "to_json"]

_KIND_NAMES = {k: k.name.lower() for k in GeneKind}
# The only text from a genome file that generated source may carry (module docstring).
_SAFE_NAME = re.compile(r"[A-Za-z0-9_.:-]{1,64}")


def _need_activations(spec: GenomeFile) -> None:
    if not spec.has_header:
        raise GenomeFileError(
            "the genome file names no activations; use spec.with_activations(hidden, output)"
        )


def dense(spec: GenomeFile) -> dict[str, np.ndarray | int | list[int]]:
    """The unpadded dense tensors of the network (float32 values, as the kernels use).

    Returns:
      ``neurons`` (neuron ids in slot order), ``w_in [H, n_in]``, ``bias [H]``,
      ``w_ff [H, H]``, ``w_rec [H, H]``, ``w_out [n_out, H]``, ``is_root [H]``, ``sweeps``
      (= the depth), with ``H`` the number of neurons.
    """
    g = spec.genome
    n_in = spec.n_inputs if spec.n_inputs is not None else g.n_inputs
    net = jax.tree.map(lambda a: np.asarray(a[0]), networks([g], n_in))
    h = g.n_neurons  # the compiler puts the real neurons in the first slots
    order = sorted((i for i, gene in enumerate(g) if gene.kind == GeneKind.NEURON), reverse=True)
    return {
        "neurons": [g[i].ref for i in order],
        "w_in": net.w_in[:h],
        "bias": net.bias[:h],
        "w_ff": net.w_ff[:h, :h],
        "w_rec": net.w_rec[:h, :h],
        "w_out": net.w_out[:, :h],
        "is_root": net.is_root[:h],
        "sweeps": g.depth(),
    }


def to_json(spec: GenomeFile) -> dict:
    """A JSON-ready description: the header's fields, the genes, weights and dense tensors."""
    _need_activations(spec)
    d = dense(spec)
    return {
        **spec.header(),
        "n_inputs": spec.n_inputs if spec.n_inputs is not None else spec.genome.n_inputs,
        "genome": str(spec.genome),
        "genes": [
            {
                "kind": _KIND_NAMES[gene.kind],
                "ref": gene.ref,
                "arity": gene.arity,
                "weight": gene.weight,
            }
            for gene in spec.genome
        ],  # fmt: skip
        "weights": spec.genome.weights.tolist(),
        "dense": {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in d.items()},
    }


def from_json(d: dict) -> GenomeFile:
    """The `GenomeFile` of a `to_json` document (its ``genome`` text rules)."""
    fmt = d.get("format") if isinstance(d, dict) else None
    if type(fmt) is not int or fmt != FORMAT or not isinstance(d.get("genome"), str):
        raise GenomeFileError(f"not an eant2 network document of format {FORMAT}")
    return GenomeFile(
        Genome.parse(d["genome"]),
        hidden=d.get("hidden"),
        output=d.get("output"),
        n_inputs=d.get("n_inputs"),
        task=d.get("task"),
        task_options=d.get("task_options"),
    )


def _literal(a: np.ndarray) -> str:
    """A nested list literal whose float32 values parse back exactly (weights that add up
    beyond float32 in one entry are infinite, as in the kernels' tensors)."""
    if a.ndim == 0:
        x = float(a)
        return repr(x) if math.isfinite(x) else f"float({str(x)!r})"
    return "[" + ", ".join(_literal(x) for x in a) + "]"


def _name(text: object) -> str | None:
    """``text`` if it may appear in generated source (module docstring), else None."""
    return text if isinstance(text, str) and _SAFE_NAME.fullmatch(text) else None


def _source(name: str) -> str:
    act = activations.get(name)
    if act.source is None:
        raise GenomeFileError(
            f"activation {name!r} has no source; register it with source=... to export it"
        )
    return act.source


def to_jax_source(spec: GenomeFile) -> str:
    """A standalone Python module (it imports only jax) computing the network.

    The module defines ``network(xs)``, jitted, ``[T, M, n_in] -> [T, M, n_out]`` with the
    recurrent state zero before the first step (as `eant2_jax.evaluate`), and
    ``step(x, h) -> (y, h)`` for ONE example (``x [n_in]``, ``h [H]``, zeros at first).
    """
    _need_activations(spec)
    d = dense(spec)
    hidden, output = _source(spec.hidden), _source(spec.output)
    n_in = int(d["w_in"].shape[1])
    # The file's strings enter only through _name; the genome through its canonical form
    # (letters from a fixed table, integers, repr of finite floats).
    task = f" on task {_name(spec.task)}" if _name(spec.task) else ""
    acts = [_name(spec.hidden) or "(a registered one)", _name(spec.output) or "(a registered one)"]
    lines = [
        f'"""A network evolved by eant2_jax{task}: {n_in} inputs, {spec.n_outputs:d} outputs, '
        f"{len(d['neurons']):d} neurons,",
        f"hidden activation {acts[0]}, output activation {acts[1]}.",
        "",
        f"Genome: {spec.genome}",
        "",
        "network(xs): [T, M, n_in] -> [T, M, n_out], M streams with their own recurrent state",
        "(zero before the first step). step(x, h) -> (y, h): one step of ONE example.",
        '"""',
        "",
        "import jax",
        "import jax.numpy as jnp",
        "",
        "_HI = jax.lax.Precision.HIGHEST",
        "W_IN = jnp.array(" + _literal(d["w_in"]) + ", jnp.float32)",
        "BIAS = jnp.array(" + _literal(d["bias"]) + ", jnp.float32)",
        "W_FF = jnp.array(" + _literal(d["w_ff"]) + ", jnp.float32)",
        "W_REC = jnp.array(" + _literal(d["w_rec"]) + ", jnp.float32)",
        "W_OUT = jnp.array(" + _literal(d["w_out"]) + ", jnp.float32)",
        "IS_ROOT = jnp.array(" + _literal(d["is_root"].astype(int)) + ", bool)",
        f"SWEEPS = {d['sweeps']:d}",
        "",
        "",
        "def _hidden(a):",
        f"    return {hidden}",
        "",
        "",
        "def _output(a):",
        f"    return {output}",
        "",
        "",
        "def step(x, h):",
        "    base = jnp.dot(W_IN, x, precision=_HI) + BIAS + jnp.dot(W_REC, h, precision=_HI)",
        "    h = jnp.zeros_like(base)",
        "    for _ in range(SWEEPS):  # neurons of depth <= k are exact after k sweeps",
        "        a = base + jnp.dot(W_FF, h, precision=_HI)",
        "        h = jnp.where(IS_ROOT, _output(a), _hidden(a))",
        "    return jnp.dot(W_OUT, h, precision=_HI), h",
        "",
        "",
        "@jax.jit",
        "def network(xs):",
        "    xs = jnp.asarray(xs, jnp.float32)",
        "",
        "    def stream(seq):",
        "        def body(h, x):",
        "            y, h = step(x, h)",
        "            return h, y",
        "",
        "        return jax.lax.scan(body, jnp.zeros_like(BIAS), seq)[1]",
        "",
        "    return jax.vmap(stream, in_axes=1, out_axes=1)(xs)",
        "",
    ]
    return "\n".join(lines)


def to_jax(spec: GenomeFile) -> Callable[[jax.Array], jax.Array]:
    """The ``network`` function of `to_jax_source`: it closes over constant arrays
    and calls nothing of eant2_jax."""
    namespace: dict = {}
    exec(compile(to_jax_source(spec), "<eant2_jax export>", "exec"), namespace)  # noqa: S102
    return namespace["network"]


def formula(spec: GenomeFile, *, max_neurons: int = 12) -> str:
    """The network as Python lines, one per neuron, for small feed-forward networks.

    Neuron ``id``'s output is ``h<id>``, input ``j`` is ``x<j>``, output ``k`` is ``y<k>``;
    each activation is called by its name, and a comment line defines each one used. The
    lines run as Python given those names (NumPy functions of the registry, for instance).

    Raises:
      GenomeFileError: the network is recurrent (it has ``R`` genes), has more than
        ``max_neurons`` neurons, or the file names no activations.
    """
    _need_activations(spec)
    g = spec.genome
    if any(gene.kind == GeneKind.RECURRENT for gene in g):
        raise GenomeFileError("formula: the network is recurrent (R genes); no formula")
    if g.n_neurons > max_neurons:
        raise GenomeFileError(
            f"formula: {g.n_neurons} neurons, more than max_neurons={max_neurons}"
        )
    roots = set(g.roots)
    used = set()
    lines = []
    for i in reversed(range(len(g))):  # every input of a neuron lies to its right
        gene = g[i]
        if gene.kind != GeneKind.NEURON:
            continue
        terms = []
        for c in g.children(i):
            child = g[c]
            w = repr(float(child.weight))
            if child.kind == GeneKind.INPUT:
                terms.append(f"{w} * x{child.ref}")
            elif child.kind == GeneKind.BIAS:
                terms.append(w)
            else:  # a sub-neuron or a forward jumper: that neuron's current output
                terms.append(f"{w} * h{child.ref}")
        total = " + ".join(terms).replace("+ -", "- ")
        act = spec.output if i in roots else spec.hidden
        used.add(act)
        lines.append(
            f"h{gene.ref} = {total}" if act == "identity" else f"h{gene.ref} = {act}({total})"
        )
    for k, r in enumerate(g.roots):
        lines.append(f"y{k} = {float(g[r].weight)!r} * h{g[r].ref}")
    defs = [f"# {n}(a) = {activations.get(n).doc}" for n in sorted(used - {"identity"})]
    return "\n".join(defs + lines) + "\n"
