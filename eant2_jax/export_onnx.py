"""A network as an ONNX graph: `to_onnx` (needs the ``export`` extra: ``onnx``).

The graph is one time step of the network over a batch, the evaluation rule of
`eant2_jax.kernels.network` written out in ONNX operators (opset 17 or later):

    base = x @ W_in^T + bias + h_prev @ W_rec^T
    h    = settle(base);  repeat `sweeps - 1` times:  h = settle(base + h @ W_ff^T)
    y    = h @ W_out^T

with ``settle(a) = where(is_root, output(a), hidden(a))``, the dense float32 tensors of
`eant2_jax.export.dense` (no padding: neuron slots in evaluation order) and ``sweeps`` the
network's depth. Every product keeps the kernels' rule for non-finite values
(`eant2_jax.kernels.netdot`): a NaN or infinite value reaches only the neurons whose genes
read it. Activations are the registry's built-ins, each written with the same clipping and
constants (`eant2_jax.kernels.activations`); a registered one has no ONNX form and is refused.

Inputs and outputs (``batch`` is a free dimension):

* ``x`` ``[batch, n_in]`` float32 -> ``y`` ``[batch, n_out]``;
* a recurrent network (``R`` genes) also takes ``h_prev`` ``[batch, H]`` (the neurons'
  outputs at the previous step, zeros before the first) and returns ``h`` ``[batch, H]``,
  to be fed back as the next step's ``h_prev``. Slot ``i`` of the state is neuron
  ``neurons[i]`` (the model's ``neurons`` metadata). A feed-forward network has no state.

The model is data: weights as initializers, the canonical genome text and the activation
names as metadata. See docs/export.md for the measured agreement with the library.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .genome import GeneKind
from .genomefile import GenomeFile, GenomeFileError
from .kernels import activations as acts

__all__ = ["MIN_OPSET", "ONNX_ACTIVATIONS", "save", "to_onnx"]

MIN_OPSET = 17

_MISSING = "ONNX export needs the onnx package: pip install 'eant2-jax[export]'"


def _onnx():
    try:
        import onnx
    except ImportError:
        raise ImportError(_MISSING) from None
    return onnx


class _Graph:
    """Nodes and initializers of one graph, with fresh names."""

    def __init__(self, onnx: Any):
        self.onnx = onnx
        self.nodes: list = []
        self.inits: list = []
        self._n = 0
        self._consts: dict = {}

    def name(self, stem: str) -> str:
        self._n += 1
        return f"{stem}_{self._n}"

    def op(self, op: str, *inputs: str, out: str | None = None, **attrs) -> str:
        out = out or self.name(op.lower())
        self.nodes.append(self.onnx.helper.make_node(op, list(inputs), [out], **attrs))
        return out

    def tensor(self, stem: str, a: np.ndarray) -> str:
        name = self.name(stem)
        self.inits.append(self.onnx.numpy_helper.from_array(np.ascontiguousarray(a), name))
        return name

    def const(self, value: float) -> str:
        """A float32 scalar (one initializer per value)."""
        key = np.float32(value).tobytes()
        if key not in self._consts:
            self._consts[key] = self.tensor("c", np.asarray(value, np.float32))
        return self._consts[key]

    def axes(self, *axes: int) -> str:
        key = ("axes", axes)
        if key not in self._consts:
            self._consts[key] = self.tensor("axes", np.asarray(axes, np.int64))
        return self._consts[key]


def _clip(g: _Graph, a: str, lo: float, hi: float) -> str:
    return g.op("Clip", a, g.const(lo), g.const(hi))


def _gauss(g: _Graph, a: str) -> str:
    c = _clip(g, a, -3.4, 3.4)
    return g.op("Exp", g.op("Mul", g.const(-5.0), g.op("Mul", c, c)))


def _softplus(g: _Graph, a: str) -> str:
    s = g.op("Softplus", _clip(g, g.op("Mul", g.const(5.0), a), -60.0, 60.0))
    return g.op("Mul", g.const(0.2), s)


# Each built-in activation as ONNX operators on the pre-activation ``a``, with the clipping
# and constants of its JAX form (kernels/activations.py).
ONNX_ACTIVATIONS = {
    "identity": lambda g, a: a,
    "tanh": lambda g, a: g.op("Tanh", a),
    "sigmoid": lambda g, a: g.op("Sigmoid", a),
    "relu": lambda g, a: g.op("Relu", a),
    "sin": lambda g, a: g.op("Sin", _clip(g, g.op("Mul", g.const(5.0), a), -60.0, 60.0)),
    "gauss": _gauss,
    "abs": lambda g, a: g.op("Abs", a),
    "clamped": lambda g, a: _clip(g, a, -1.0, 1.0),
    "softplus": _softplus,
    "elu": lambda g, a: g.op("Elu", a, alpha=1.0),
    "selu": lambda g, a: g.op(
        "Selu",
        a,
        alpha=float(np.float32(acts._SELU_ALPHA)),
        gamma=float(np.float32(acts._SELU_LAMBDA)),
    ),
    "lelu": lambda g, a: g.op("LeakyRelu", a, alpha=0.005),
    "square": lambda g, a: g.op("Mul", a, a),
    "cube": lambda g, a: g.op("Mul", g.op("Mul", a, a), a),
    "log": lambda g, a: g.op("Log", g.op("Max", a, g.const(1e-7))),
    "exp": lambda g, a: g.op("Exp", _clip(g, a, -60.0, 60.0)),
    "hat": lambda g, a: g.op("Max", g.const(0.0), g.op("Sub", g.const(1.0), g.op("Abs", a))),
}


def _activation(name: str):
    acts.get(name)  # one clear error for an unknown name
    if name not in ONNX_ACTIVATIONS:
        raise GenomeFileError(
            f"activation {name!r} has no ONNX form; ONNX export supports the built-ins "
            f"({', '.join(sorted(ONNX_ACTIVATIONS))})"
        )
    return ONNX_ACTIVATIONS[name]


def _product(
    g: _Graph, v: str, w: np.ndarray, read: np.ndarray, w_nf: np.ndarray, *, always: bool
) -> str | None:
    """``v @ w^T`` for ``v [batch, k]`` and ``w [rows, k]`` as `kernels.netdot.dot` computes
    it: the finite values through the dense weights, each non-finite ``v[:, j]`` only into
    the rows that read it (``read``), with its own weight (``w_nf``). None where no row
    reads anything (the product is 0) unless ``always`` (then a product of zeros, which
    gives the result its batch dimension)."""
    if not read.any() and not always:
        return None
    finite = g.op("Not", g.op("Or", g.op("IsNaN", v), g.op("IsInf", v)))
    v0 = g.op("Where", finite, v, g.const(0.0))
    dense = g.op("MatMul", v0, g.tensor("w", w.T.astype(np.float32)))
    if not read.any():
        return dense
    # [batch, 1, k] against [rows, k]: the terms of the non-finite entries, 0 elsewhere.
    v3 = g.op("Unsqueeze", v, g.axes(1))
    nf3 = g.op("Unsqueeze", g.op("Not", finite), g.axes(1))
    take = g.op("And", nf3, g.tensor("read", read.astype(bool)))
    terms = g.op("Mul", g.tensor("w_nf", w_nf.astype(np.float32)), v3)
    picked = g.op("Where", take, terms, g.const(0.0))
    return g.op("Add", dense, g.op("ReduceSum", picked, g.axes(2), keepdims=0))


def _tensors(spec: GenomeFile) -> dict:
    """The unpadded dense tensors (`export.dense`) with the non-finite reads of each product."""
    import jax

    from .compiler import networks
    from .export import dense

    d = dense(spec)
    g = spec.genome
    n_in = spec.n_inputs if spec.n_inputs is not None else g.n_inputs
    net = jax.tree.map(np.asarray, networks([g], n_in))
    h = len(d["neurons"])
    rows = {"w_in": slice(0, h), "w_rec": slice(0, h), "w_ff": slice(0, h), "w_out": slice(None)}
    cols = {"w_in": slice(None), "w_rec": slice(0, h), "w_ff": slice(0, h), "w_out": slice(0, h)}
    names = ("w_in", "w_rec", "w_ff", "w_out")  # the order of Network.reads
    for key, (read, w_nf) in zip(names, net.reads, strict=True):
        d[key + "_reads"] = tuple(np.asarray(a[0])[rows[key], cols[key]] for a in (read, w_nf))
    return d


def _step(g: _Graph, d: dict, recurrent: bool, hidden: str, output: str) -> tuple[str, str]:
    """The step's nodes; returns the names of ``y`` and ``h``."""
    act_h, act_o = _activation(hidden), _activation(output)

    def product(v: str, key: str, always: bool = False) -> str | None:
        return _product(g, v, d[key], *d[key + "_reads"], always=always)

    base = g.op("Add", product("x", "w_in", True), g.tensor("bias", d["bias"]))
    rec = product("h_prev", "w_rec") if recurrent else None
    if rec is not None:
        base = g.op("Add", base, rec)

    roots: list[str] = []

    def settle(a: str) -> str:
        if hidden == output:
            return act_h(g, a)
        if not roots:  # made once, only where the two activations differ
            roots.append(g.tensor("is_root", d["is_root"].astype(bool)))
        return g.op("Where", roots[0], act_o(g, a), act_h(g, a))

    h = settle(base)  # the first sweep reads h = 0 (kernels/network.py)
    for _ in range(1, d["sweeps"]):
        ff = product(h, "w_ff")
        h = settle(base if ff is None else g.op("Add", base, ff))
    return product(h, "w_out", True), h


def _safe(text: object) -> str:
    """A name from the file, only if it is a plain name (as `export.to_jax_source`)."""
    ok = isinstance(text, str) and 0 < len(text) <= 64
    return text if ok and all(c.isalnum() or c in "_.:-" for c in text) else ""


def to_onnx(spec: GenomeFile, *, opset: int = MIN_OPSET) -> Any:
    """The network of ``spec`` as an ONNX model (module docstring for the graph).

    Args:
      spec: the genome file (it must name its activations: a file with a header, or one
        given them with ``with_activations``).
      opset: the ONNX opset of the default domain (17 or later).

    Returns:
      An ``onnx.ModelProto``, checked with ``onnx.checker``; ``model.SerializeToString()``
      is the file's bytes.

    Raises:
      ImportError: onnx is not installed (the ``export`` extra).
      GenomeFileError: no activations named, or an activation with no ONNX form.
    """
    onnx = _onnx()
    if not isinstance(opset, int) or opset < MIN_OPSET:
        raise ValueError(f"opset must be an integer >= {MIN_OPSET}, got {opset!r}")
    if not spec.has_header:
        raise GenomeFileError(
            "the genome file names no activations; use spec.with_activations(hidden, output)"
        )
    genome = spec.genome
    recurrent = any(gene.kind == GeneKind.RECURRENT for gene in genome)
    d = _tensors(spec)
    n_in, n_h = d["w_in"].shape[1], len(d["neurons"])
    g = _Graph(onnx)
    y, h = _step(g, d, recurrent, spec.hidden, spec.output)
    g.op("Identity", y, out="y")
    f32 = onnx.TensorProto.FLOAT
    inputs = [onnx.helper.make_tensor_value_info("x", f32, ["batch", n_in])]
    outputs = [onnx.helper.make_tensor_value_info("y", f32, ["batch", spec.n_outputs])]
    if recurrent:
        g.op("Identity", h, out="h")
        inputs.append(onnx.helper.make_tensor_value_info("h_prev", f32, ["batch", n_h]))
        outputs.append(onnx.helper.make_tensor_value_info("h", f32, ["batch", n_h]))
    graph = onnx.helper.make_graph(g.nodes, "eant2_network", inputs, outputs, g.inits)
    opsets = [onnx.helper.make_opsetid("", opset)]
    model = onnx.helper.make_model(graph, opset_imports=opsets, producer_name="eant2_jax")
    model.ir_version = onnx.helper.find_min_ir_version_for(opsets)
    task = f" on task {_safe(spec.task)}" if _safe(spec.task) else ""
    model.doc_string = (
        f"A network evolved by eant2_jax{task}: {n_in} inputs, {spec.n_outputs} outputs, "
        f"{n_h} neurons, {d['sweeps']} sweeps; "
        + ("recurrent (state h_prev -> h)." if recurrent else "feed-forward.")
    )
    meta = {
        "genome": str(genome),
        "hidden": spec.hidden,
        "output": spec.output,
        "neurons": json.dumps(d["neurons"]),
        "sweeps": str(d["sweeps"]),
        "task": _safe(spec.task),
    }
    onnx.helper.set_model_props(model, meta)
    onnx.checker.check_model(model)
    return model


def save(model: Any, path: str | os.PathLike) -> Path:
    """Write ``model`` to ``path`` as a new file: whole (a temporary file in the same folder,
    then linked to its name) and never over an existing name, a link included (the link
    step fails on any). The ``eant2 export`` command replaces files with ``--force``."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(model.SerializeToString())
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        try:
            os.link(tmp, path, follow_symlinks=False)
        except FileExistsError:
            raise FileExistsError(f"{path}: already exists; refusing to overwrite it") from None
    finally:
        Path(tmp).unlink(missing_ok=True)
    return path
