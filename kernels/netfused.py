"""The step of a whole batch of small networks as one GPU kernel (Pallas on Triton).

`eant2_jax.kernels.network.step` is written for one network and one example and batched
with ``vmap``. On a GPU, networks of at most 12 neurons run it with the non-finite rule
inline (unrolled element-wise products, `netdot.dot`), which XLA turns into two
fusions per sweep that write every neuron's column, its finiteness and its finite and
non-finite parts to memory between them: for a servo batch (384 networks of 8 neurons times
1023 moves) most of an engine iteration's device time. Here one program computes a block of
examples of one network from its inputs to its outputs with every intermediate in
registers: plain products first, and the rule only where some value of the block was not
finite (see the kernel). The values are the rule's; a product's terms are summed in
Triton's order, so float32 results may differ from XLA's in the last bits.

`step_batch` takes the batch as ``[B]`` networks and ``[B or 1, E]`` examples each (the
caller, `network._fused_batch`, flattens the vmapped levels into these two axes). Only what
Triton lowers runs here (float32, the activations of `ACTIVATIONS`); elsewhere the caller
keeps the plain path. This module imports nothing from the rest of eant2_jax.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pl_triton

from . import activations

__all__ = ["ACTIVATIONS", "step_batch"]

# The built-in activations: each one's JAX function lowers to Triton (checked by the tests
# through a CUDA lowering on any machine). A registered activation is not known to, so a
# network that uses one keeps the plain path.
ACTIVATIONS = activations.BUILTIN

# Examples per program and warps per program (1023 servo moves make 8 programs of a
# network), the fastest of the pairs measured (docs/design.md, "One fused kernel").
_BLOCK = 128
_WARPS = 4


def _pow2(n: int) -> int:
    return 1 << max(0, (n - 1).bit_length())


def step_batch(
    w_in: jax.Array,
    bias: jax.Array,
    w_ff: jax.Array,
    w_rec: jax.Array,
    w_out: jax.Array,
    reads: tuple[tuple[jax.Array, jax.Array], ...],
    is_root: jax.Array,
    neuron_mask: jax.Array,
    x: jax.Array,
    h_prev: jax.Array,
    *,
    sweeps: int,
    hidden: str,
    output: str,
    block: int | None = None,
    warps: int | None = None,
    interpret: bool = False,
) -> tuple[jax.Array, jax.Array]:
    """One step of ``B`` networks on ``E`` examples each, with the non-finite rule.

    Args:
      w_in: ``[B, H, n_in]``, the `network.Network` field of each network; likewise
      bias: ``[B, H]``;
      w_ff: ``[B, H, H]``;
      w_rec: ``[B, H, H]``;
      w_out: ``[B, n_out, H]``;
      reads: ``Network.reads`` (the ``(mask, weights)`` pairs of ``w_in``, ``w_rec``,
        ``w_ff`` and ``w_out``), each with a leading ``[B]``.
      is_root: ``bool[B, H]``;
      neuron_mask: ``bool[B, H]``.
      x: ``[B or 1, E, n_in]`` inputs (1: the same examples for every network).
      h_prev: ``[B or 1, E, H]`` neuron outputs at the previous step.
      sweeps: the networks' sweeps per step, as in `network.Network`.
      hidden: activation name of hidden neurons (one of `ACTIVATIONS`).
      output: activation name of root (output) neurons (one of `ACTIVATIONS`).
      block: examples per program (default `_BLOCK`).
      warps: Triton warps per program (default `_WARPS`).
      interpret: run the kernel in Pallas' interpreter (any backend; for tests).

    Returns:
      ``(y [B, E, n_out], h [B, E, H])``: what `network.step` gives for each network and
      example (to float32 rounding; NaN and inf entries exactly).
    """
    b, h = bias.shape
    n_in, n_out = w_in.shape[-1], w_out.shape[-2]
    e = x.shape[1]
    hp, ip, op = _pow2(h), _pow2(n_in), _pow2(n_out)
    act_h, act_o = activations.get(hidden).jax, activations.get(output).jax
    r_in, r_rec, r_ff, r_out = reads
    m_in = _matrices(w_in, r_in, hp, ip)
    m_rec = _matrices(w_rec, r_rec, hp, hp)
    m_ff = _matrices(w_ff, r_ff, hp, hp)
    m_out = _matrices(w_out, r_out, op, hp)
    per_neuron = jnp.stack([bias, is_root.astype(bias.dtype), neuron_mask.astype(bias.dtype)], 1)
    per_neuron = jnp.pad(per_neuron, ((0, 0), (0, 0), (0, hp - h)))

    blk = min(block or _BLOCK, _pow2(e))
    padded = -(-e // blk) * blk

    def columns(a, rows):
        # [B or 1, E, n] -> [B or 1, rows, E']: a feature is a contiguous row of examples.
        a = jnp.swapaxes(a, 1, 2)
        return jnp.pad(a, ((0, 0), (0, rows - a.shape[1]), (0, padded - e)))

    xt, ht = columns(x, ip), columns(h_prev, hp)

    networks = (m_in, m_rec, m_ff, m_out, per_neuron)
    batched = (x.shape[0] > 1, h_prev.shape[0] > 1)
    kernel = _kernel(sweeps, act_h, act_o)
    call = _call(kernel, networks, batched, (ip, hp, op), blk, padded, warps or _WARPS, interpret)
    yt, h_t = call(*networks, xt, ht)
    return jnp.swapaxes(yt[:, :n_out, :e], 1, 2), jnp.swapaxes(h_t[:, :h, :e], 1, 2)


def _call(
    kernel: Callable, networks, batched, rows, blk: int, padded: int, warps: int, interpret: bool
) -> Callable:
    """The ``pallas_call`` of ``kernel`` over the grid (networks, blocks of ``blk``
    examples): each program gets its network's arrays whole (``networks``, each ``[B,
    ...]``) and its block of the inputs and states (``[B or 1, rows, padded]``, shared by
    every network where ``batched`` says not), and writes its block of the outputs."""
    ip, hp, op = rows
    b = networks[0].shape[0]

    def whole(a):
        return pl.BlockSpec((1, *a.shape[1:]), lambda i, j: (i,) + (0,) * (a.ndim - 1))

    def examples(rows, batched):
        if batched:
            return pl.BlockSpec((1, rows, blk), lambda i, j: (i, 0, j))
        return pl.BlockSpec((1, rows, blk), lambda i, j: (0, 0, j))

    return pl.pallas_call(
        kernel,
        out_shape=(
            jax.ShapeDtypeStruct((b, op, padded), jnp.float32),
            jax.ShapeDtypeStruct((b, hp, padded), jnp.float32),
        ),
        grid=(b, padded // blk),
        in_specs=[
            *(whole(a) for a in networks),
            examples(ip, batched[0]),
            examples(hp, batched[1]),
        ],
        out_specs=(examples(op, True), examples(hp, True)),
        compiler_params=pl_triton.CompilerParams(num_warps=warps, num_stages=1),
        interpret=interpret,
        name="eant2_network_step",
    )


def _matrices(w, reads, rows, cols):
    """``[B, 3, rows, cols]``: the weights, which entries a gene sets, the non-finite
    weights; padded with zeros (entries no gene reads) to Triton's powers of two."""
    read, w_nf = reads
    m = jnp.stack([w, read.astype(w.dtype), w_nf], axis=1)
    return jnp.pad(m, ((0, 0), (0, 0), (0, rows - m.shape[2]), (0, cols - m.shape[3])))


def _kernel(sweeps: int, act_h: Callable, act_o: Callable) -> Callable:
    """The program of one block of examples of one network (`step_batch`'s grid cell)."""

    def kernel(in_ref, rec_ref, ff_ref, out_ref, neuron_ref, x_ref, h_ref, y_ref, h_out_ref):
        def is_finite(v):
            return jnp.abs(v) < jnp.inf  # false for NaN and +-inf

        def plain(ref, v):
            return jnp.sum(ref[0, 0][:, :, None] * v[None, :, :], axis=1)

        def ruled(ref, v):
            # `netdot.dot` of a [rows, cols] matrix and v [cols, blk]: the term of a
            # non-finite v[j] is w_nf[i, j] * v[j] where row i reads j, 0 elsewhere.
            w, read, w_nf = ref[0, 0], ref[0, 1] > 0, ref[0, 2]
            finite = is_finite(v)
            zero = jnp.zeros_like(v)
            v_fin, v_nf = jnp.where(finite, v, zero), jnp.where(finite, zero, v)
            take = read[:, :, None] & ~finite[None, :, :]
            nonfinite = jnp.where(take, w_nf[:, :, None] * v_nf[None, :, :], 0.0)
            return jnp.sum(w[:, :, None] * v_fin[None, :, :] + nonfinite, axis=1)

        bias_, root, mask = neuron_ref[0, 0], neuron_ref[0, 1] > 0, neuron_ref[0, 2] > 0
        x_, h_prev_ = x_ref[0], h_ref[0]

        def settle(a):
            o = jnp.where(root[:, None], act_o(a), act_h(a))
            return jnp.where(mask[:, None], o, 0.0)

        def run(dot):
            base = dot(in_ref, x_) + bias_[:, None] + dot(rec_ref, h_prev_)
            if sweeps == 0:
                hs = jnp.zeros_like(base)
            else:
                # The first sweep reads h = 0 (`network.step_inline`).
                hs = jax.lax.fori_loop(
                    1, sweeps, lambda _, v: settle(base + dot(ff_ref, v)), settle(base)
                )
            return dot(out_ref, hs), hs

        def nonfinite(v):
            return jnp.sum(jnp.where(is_finite(v), 0.0, 1.0))

        # Plain products first, the rule only where a value was not finite. With finite
        # inputs and states, a non-finite value inside the network reaches the final states:
        # the next sweep's plain product multiplies it by the zeros of its own row (a neuron
        # does not read itself), so that neuron is NaN from then on, whatever its
        # activation (every one of `ACTIVATIONS` keeps NaN). Without one, every product
        # read finite values only, where the rule's sums are the plain ones.
        y, hs = run(plain)
        bad = nonfinite(x_) + nonfinite(h_prev_) + nonfinite(hs)
        y, hs = jax.lax.cond(bad > 0, lambda: run(ruled), lambda: (y, hs))
        y_ref[0] = y
        h_out_ref[0] = hs

    return kernel
