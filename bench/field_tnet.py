"""A TensorNEAT network as the library's network: the field protocol evaluates both methods'
networks through one task object (docs/protocol.md section 3), so a TensorNEAT genome becomes
an `eant2_jax.kernels.network.Network` that the library's episode code runs.

TensorNEAT's ``DefaultGenome`` with ``BiasNode`` nodes (its examples' genomes) is a
feed-forward graph. Its arrays, padded with NaN rows:

* ``nodes [N, 4]``: ``key, bias, aggregation index, activation index`` (index -1:
  identity); inputs are keys ``0 .. n_in - 1``, outputs ``n_in .. n_in + n_out - 1``;
* ``conns [C, 3]``: ``source key, target key, weight``.

A node's value is ``act(bias + sum of weight * source value)`` over its incoming connections
from sources that have a value; an output node skips ``act`` (the example's output
transform, argmax or tanh, then acts on it); a node none of whose sources has a value has
none itself (NaN in TensorNEAT), and nothing reads it.

The library's network carries the same function, exactly up to float rounding:

* tanh nodes are neurons (hidden activation ``tanh``); a ``scaled_tanh`` node (3 tanh) is a
  tanh neuron whose outgoing weights carry the factor 3;
* identity nodes and output nodes read as sources are linear: they are substituted into
  their readers (each node's value is kept as an affine form of inputs and neurons);
* output nodes are root neurons with the task's output activation (identity for an argmax
  action, tanh for a continuous one, which the task clips and maps onto the bounds, as
  TensorNEAT's ``scale * tanh``); an output without a value is a root of bias NaN (the
  argmax of NaN picks it first, as TensorNEAT's does), kept from other rows by the
  network's ``reads``;
* TensorNEAT's input convention is folded into the first weights: its input is
  ``(u - in_offset) * in_scale`` of the task's network input ``u`` (`input_affine`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["TN_SCALE", "TNNet", "input_affine", "stack", "tensorneat_net"]

TN_SCALE = 3.0  # tensorneat.common.functions.act_jnp.SCALE: scaled_tanh = 3 tanh
_FACTORS = {"tanh": 1.0, "scaled_tanh": TN_SCALE}


class TNNet:
    """One converted network as NumPy arrays (``H`` neurons, ``sweeps`` >= its depth)."""

    def __init__(self, w_in, bias, w_ff, w_out, is_root, sweeps: int):
        self.w_in, self.bias, self.w_ff, self.w_out = w_in, bias, w_ff, w_out
        self.is_root, self.sweeps = is_root, int(sweeps)

    @property
    def neurons(self) -> int:
        return int(self.bias.shape[0])


def input_affine(lib_offset, lib_scale, tn_mean=None, tn_std=None, eps: float = 1e-6):
    """``(in_offset, in_scale)`` with TensorNEAT's input ``= (u - in_offset) * in_scale`` of
    the library task's input ``u = (obs - lib_offset) * lib_scale``, where TensorNEAT reads
    ``(obs - tn_mean) / (tn_std + eps)`` (its observation normalisation) or raw ``obs``."""
    o, s = np.asarray(lib_offset, np.float64), np.asarray(lib_scale, np.float64)
    m = np.zeros_like(o) if tn_mean is None else np.asarray(tn_mean, np.float64)
    d = np.ones_like(o) if tn_std is None else np.asarray(tn_std, np.float64) + eps
    return s * (m - o), 1.0 / (s * d)


def _order(keys: list[int], edges: list[tuple[int, int, float]]) -> list[int]:
    """The node keys in topological order (Kahn's rule; ties by key); ValueError on a cycle."""
    indeg = {k: 0 for k in keys}
    out: dict[int, list[int]] = {k: [] for k in keys}
    for s, t, _ in edges:
        indeg[t] += 1
        out[s].append(t)
    ready = sorted(k for k in keys if indeg[k] == 0)
    order = []
    while ready:
        k = ready.pop(0)
        order.append(k)
        for t in out[k]:
            indeg[t] -= 1
            if indeg[t] == 0:
                ready.append(t)
        ready.sort()
    if len(order) != len(keys):
        raise ValueError("a TensorNEAT genome with a cycle is not a feed-forward network")
    return order


def tensorneat_net(
    nodes, conns, *, n_inputs: int, n_outputs: int, activations, in_offset, in_scale
) -> TNNet:
    """The library network of one TensorNEAT genome (module docstring).

    Args:
      nodes: ``[N, 4]`` node rows (NaN rows unused); conns: ``[C, 3]`` connection rows.
      n_inputs, n_outputs: the genome's inputs and outputs.
      activations: the node gene's ``activation_options`` names (``tanh``/``scaled_tanh``).
      in_offset, in_scale: ``[n_inputs]`` `input_affine` of the task's inputs.

    Raises:
      ValueError: an aggregation other than sum, an unknown activation, or a cycle.
    """
    nodes, conns = np.asarray(nodes, np.float64), np.asarray(conns, np.float64)
    rows = {int(r[0]): r for r in nodes if not np.isnan(r[0])}
    edges = [(int(c[0]), int(c[1]), float(c[2])) for c in conns if not np.isnan(c[0])]
    outputs = list(range(n_inputs, n_inputs + n_outputs))
    # value[k]: (constant, {("u", i) or ("h", j): coefficient}) or None (no value).
    value: dict[int, tuple[float, dict] | None] = {}
    neurons: list[tuple[float, dict]] = []  # (bias, terms) of each neuron, in slot order
    roots: dict[int, int] = {}  # output key -> neuron slot
    for k in _order(sorted(rows), edges):
        if k < n_inputs:
            value[k] = (-in_offset[k] * in_scale[k], {("u", k): float(in_scale[k])})
            continue
        agg, act = int(rows[k][2]), int(rows[k][3])
        if agg != 0:
            raise ValueError(f"node {k}: only the sum aggregation is supported")
        live = [(value[s], w) for s, t, w in edges if t == k and value.get(s) is not None]
        if not live:
            value[k] = None
            if k in roots or k in outputs:
                roots[k] = len(neurons)
                neurons.append((np.nan, {}))
            continue
        const, terms = float(rows[k][1]), {}
        for (c, form), w in live:
            const += w * c
            for var, a in form.items():
                terms[var] = terms.get(var, 0.0) + w * a
        if k in outputs:
            roots[k] = len(neurons)
            neurons.append((const, terms))
            value[k] = (const, terms)  # read before the output transform: linear
        elif act == -1:
            value[k] = (const, terms)
        else:
            name = activations[act]
            if name not in _FACTORS:
                raise ValueError(f"node {k}: activation {name!r} is not supported")
            value[k] = (0.0, {("h", len(neurons)): _FACTORS[name]})
            neurons.append((const, terms))
    for k in outputs:  # an output node missing from the genome has no value
        if k not in roots:
            roots[k] = len(neurons)
            neurons.append((np.nan, {}))
    return _dense(neurons, [roots[k] for k in outputs], n_inputs)


def _dense(neurons, root_slots, n_inputs) -> TNNet:
    h = len(neurons)
    w_in, w_ff = np.zeros((h, n_inputs)), np.zeros((h, h))
    bias, depth = np.zeros(h), np.zeros(h, int)
    for j, (b, terms) in enumerate(neurons):
        bias[j] = b
        for (kind, i), a in terms.items():
            if kind == "u":
                w_in[j, i] += a
            else:
                w_ff[j, i] += a
                depth[j] = max(depth[j], depth[i])
        depth[j] += 1
    w_out = np.zeros((len(root_slots), h))
    w_out[np.arange(len(root_slots)), root_slots] = 1.0
    is_root = np.zeros(h, bool)
    is_root[root_slots] = True
    return TNNet(w_in, bias, w_ff, w_out, is_root, max(1, int(depth.max(initial=1))))


def stack(nets: list[TNNet], neurons: int | None = None):
    """The networks as one batched `Network` ``[len(nets)]``: padded to ``neurons`` (default
    the largest) slots and run for the largest ``sweeps``; ``reads`` mark the set entries
    (a NaN root reaches no other row)."""
    import jax.numpy as jnp

    from eant2_jax.kernels.network import Network

    h = max([n.neurons for n in nets] + [neurons or 0])
    n_in, n_out = nets[0].w_in.shape[1], nets[0].w_out.shape[0]

    def pad(a, shape):
        out = np.zeros(shape)
        out[tuple(slice(0, s) for s in a.shape)] = a
        return out

    def batch(fn, shape):
        return np.stack([pad(fn(n), shape) for n in nets])

    w_in = batch(lambda n: n.w_in, (h, n_in))
    w_ff = batch(lambda n: n.w_ff, (h, h))
    w_out = batch(lambda n: n.w_out, (n_out, h))
    bias = batch(lambda n: n.bias, (h,))
    is_root = batch(lambda n: n.is_root, (h,)).astype(bool)
    mask = batch(lambda n: np.ones(n.neurons), (h,)).astype(bool)
    w_rec = np.zeros((len(nets), h, h))

    def reads(w):
        return jnp.asarray(w != 0), jnp.asarray(w, jnp.float32)

    f32 = [jnp.asarray(a, jnp.float32) for a in (w_in, bias, w_ff, w_rec, w_out)]
    return Network(
        w_in=f32[0], bias=f32[1], w_ff=f32[2], w_rec=f32[3], w_out=f32[4],
        is_root=jnp.asarray(is_root), neuron_mask=jnp.asarray(mask),
        sweeps=max(n.sweeps for n in nets),
        reads=(reads(w_in), reads(w_rec), reads(w_ff), reads(w_out)),
    )  # fmt: skip
