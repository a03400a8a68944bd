"""Building one compiled EANT2 network: its layout, its flat parameter buffer, its dense tensors.

A compiled network has ``H`` neuron slots in topological order (every neuron after the
neurons it reads at the current step) and ``P`` gene slots. Its parameters live in one flat
buffer laid out as::

    [ w_in (H * n_in) | bias (H) | w_ff (H * H) | w_rec (H * H) | w_out (n_out * H) | trash (1) ]

and every gene adds its weight into one entry of that buffer (``Layout.slot``); padding genes
point at the trash entry. Several genes may share an entry (a neuron reading the same input
twice): their weights add, exactly as the stack semantics add them. `network` scatters a
parameter vector into the dense tensors (`Network`) that `eant2_jax.kernels.network.step`
runs (docs/genome.md, The compiled layout).

Everything here is written for ONE network; batch with ``jax.vmap``. This module imports
nothing from the rest of eant2_jax.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import pytree

__all__ = ["Layout", "Network", "buffer_size", "network"]


def buffer_size(n_neurons: int, n_inputs: int, n_outputs: int) -> int:
    """Length of the flat parameter buffer, trash entry included."""
    h = n_neurons
    return h * n_inputs + h + 2 * h * h + n_outputs * h + 1


@pytree.dataclass
class Layout:
    """The structure of one compiled network (no weights).

    Attributes:
      slot: ``int32[P]`` entry of the flat buffer each gene adds its weight to.
      gene_mask: ``bool[P]`` true for real genes, false for padding.
      is_root: ``bool[H]`` neuron slots that are network outputs (use the output activation).
      neuron_mask: ``bool[H]`` true for real neurons.
      depth: ``int32[]`` the network's depth (informative; ``sweeps`` is what runs).
      n_inputs, n_outputs, sweeps: static sizes shared by every network of a batch.
    """

    slot: jax.Array
    gene_mask: jax.Array
    is_root: jax.Array
    neuron_mask: jax.Array
    depth: jax.Array
    n_inputs: int = pytree.field(pytree_node=False)
    n_outputs: int = pytree.field(pytree_node=False)
    sweeps: int = pytree.field(pytree_node=False)


@pytree.dataclass
class Network:
    """Dense tensors of one network, ready to run.

    Attributes:
      w_in: ``[H, n_in]`` weights of network inputs into neurons.
      bias: ``[H]`` bias of each neuron (sum of its bias genes).
      w_ff: ``[H, H]`` current-step weights, ``w_ff[i, j]``: neuron j into neuron i (j < i).
      w_rec: ``[H, H]`` previous-step weights (recurrent jumpers).
      w_out: ``[n_out, H]`` output selection: root r's own weight at its neuron's slot.
      is_root, neuron_mask: ``bool[H]`` as in `Layout`.
      reads: for ``w_in``, ``w_rec``, ``w_ff`` and ``w_out``: ``(mask, weights)``, the entries
        some gene sets (a connection; its weight may still be 0) and the weights a
        non-finite source is multiplied by (NaN where the genes' own products give NaN).
        None (a network built by hand): plain dense products, where a non-finite input
        reaches every neuron.
      sweeps: static number of dense sweeps per step (>= depth).
    """

    w_in: jax.Array
    bias: jax.Array
    w_ff: jax.Array
    w_rec: jax.Array
    w_out: jax.Array
    is_root: jax.Array
    neuron_mask: jax.Array
    sweeps: int = pytree.field(pytree_node=False)
    reads: tuple[tuple[jax.Array, jax.Array], ...] | None = None


def network(layout: Layout, params: jax.Array) -> Network:
    """Scatter a parameter vector into the dense tensors of one network.

    Args:
      layout: the network's structure.
      params: ``[P]`` one weight per gene slot, in gene order (padding entries are ignored).

    Returns:
      The `Network`. Differentiable in ``params``; jit/vmap friendly.
    """
    h = layout.is_root.shape[-1]
    n_in, n_out = layout.n_inputs, layout.n_outputs
    # For non-finite sources: the stack semantics add w_i * v gene by gene, so an entry set
    # by a gene of weight 0, or by genes of both signs, gives NaN for v = +-inf where the
    # summed weight would not; NaN marks those entries in the weights used for such values.
    flat, used, poison = _gather_genes(layout, params, buffer_size(h, n_in, n_out))
    sizes = (h * n_in, h, h * h, h * h, n_out * h)
    offsets = [0]
    for s in sizes:
        offsets.append(offsets[-1] + s)
    part = [flat[offsets[i] : offsets[i + 1]] for i in range(len(sizes))]
    w_nf = jnp.where(used, jnp.where(poison, jnp.nan, flat), 0.0).astype(flat.dtype)
    shapes = ((h, n_in), (h,), (h, h), (h, h), (n_out, h))

    def pair(i):
        a, b = offsets[i], offsets[i + 1]
        return used[a:b].reshape(shapes[i]), w_nf[a:b].reshape(shapes[i])

    return Network(
        reads=(pair(0), pair(3), pair(2), pair(4)),
        w_in=part[0].reshape(h, n_in),
        bias=part[1],
        w_ff=part[2].reshape(h, h),
        w_rec=part[3].reshape(h, h),
        w_out=part[4].reshape(n_out, h),
        is_root=layout.is_root,
        neuron_mask=layout.neuron_mask,
        sweeps=layout.sweeps,
    )


def _gather_genes(
    layout: Layout, params: jax.Array, size: int
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The flat buffer and two flags per entry: ``(flat, used, poison)``, each ``[size]``.

    ``flat``: each entry the sum of the weights of the genes that point at it. ``used``:
    some gene points at it. ``poison``: one of those genes has weight 0, or they have both
    signs (`network`'s non-finite rule).

    Not a scatter-add: a float scatter-add with repeated indices is non-deterministic on GPUs
    (atomic adds in any order), and XLA's deterministic mode (``--xla_gpu_deterministic_ops``)
    turns it into a sort. Here the genes that share an entry are summed first, onto the first
    of them (a masked ``[P, P]`` sum over a matrix that depends on the layout only, so vmapped
    over a structure's candidates it is built once), and a scatter with unique indices
    (deterministic by construction, left alone by that mode) writes one value per entry. The
    flags are reduced over the same groups and written by the same scatter, as columns next
    to the sums: one scatter per network instead of four (the flags were scatter-adds of
    their own, each a GPU kernel with its buffer's initialisation and copy on every engine
    iteration). Padding genes (all pointing at the trash entry) write nothing, so the trash
    entry stays 0.
    """
    values = jnp.where(layout.gene_mask, params, jnp.zeros_like(params))
    p = values.shape[-1]
    genes = jnp.arange(p)
    same = (layout.slot[:, None] == layout.slot[None, :]) & layout.gene_mask[None, :]
    first = layout.gene_mask & ~jnp.any(same & (genes[None, :] < genes[:, None]), axis=1)
    summed = jnp.sum(jnp.where(same, values[None, :], jnp.zeros_like(values)[None, :]), axis=1)

    def any_in_group(cond):
        return jnp.any(same & cond[None, :], axis=1)

    poison = any_in_group(params == 0) | (any_in_group(params > 0) & any_in_group(params < 0))
    columns = jnp.stack([summed, first.astype(values.dtype), poison.astype(values.dtype)], -1)
    # Every gene gets its own index: the first of each entry its entry, the others a distinct
    # index past the end, which mode="drop" discards, so the promise of unique indices holds.
    target = jnp.where(first, layout.slot, size + genes)
    out = (
        jnp.zeros((size, 3), values.dtype)
        .at[target]
        .set(columns, mode="drop", unique_indices=True, indices_are_sorted=False)
    )
    return out[:, 0], out[:, 1] > 0, out[:, 2] > 0
