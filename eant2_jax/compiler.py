"""Compile linear genomes into padded dense layouts that one jit-compiled program evaluates.

Host side (NumPy). For each genome:

* neuron slots: neurons sorted by DESCENDING gene index. Every input of a neuron, and the
  source of every forward jumper, lies to its right in the genome, so this order is
  topological: ``w_ff`` is strictly lower-triangular.
* gene slots: gene ``g`` adds its weight into one entry of the flat parameter buffer of
  `eant2_jax.kernels.network`, according to its kind and the neuron that reads it
  (its parent):

  ===================  =====================================================
  gene                 entry
  ===================  =====================================================
  ``I<j>``             ``w_in[slot(parent), j]``
  ``B``                ``bias[slot(parent)]``
  ``F<id>``            ``w_ff[slot(parent), slot(id)]``
  ``R<id>``            ``w_rec[slot(parent), slot(id)]``
  ``N<id>`` (inner)    ``w_ff[slot(parent), slot(id)]``
  ``N<id>`` (root r)   ``w_out[r, slot(id)]``
  padding              the trash entry
  ===================  =====================================================

Padded sizes come from buckets so that networks of different sizes share one compiled
program. Every size is rounded up to the next value of the series
``{2^k, 3 * 2^(k-1)}`` above a floor: 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, ...

* neurons ``H``: floor 4 (4, 6, 8, 12, 16, 24, 32, ...)
* genes ``P`` (= CMA-ES dimension): floor 8 (8, 12, 16, 24, 32, 48, 64, 96, 128, ...)
* sweeps (>= depth): floor 1 (1, 2, 3, 4, 6, 8, ...)
* number of genomes in one call: floor 1, same series.

The series wastes at most a third of a dimension (half, for powers of two only) and keeps the
number of distinct programs logarithmic in the largest size.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import distributed, pytree
from .genome import GeneKind, Genome
from .kernels.network import Layout, Network, buffer_size, network

__all__ = [
    "Bucket",
    "CompiledBatch",
    "batch_rows",
    "bucket_for",
    "bucket_size",
    "compile_genomes",
    "network_batch",
    "networks",
]

NEURON_FLOOR = 4
# Layout.slot is int32: the flat parameter buffer (kernels.network.buffer_size) must index
# within it. 24,576 neuron slots fit (with few inputs); the next bucket, 32,768, does not.
MAX_BUFFER = 2**31 - 1
GENE_FLOOR = 8
SWEEP_FLOOR = 1
BATCH_FLOOR = 1


def bucket_size(n: int, floor: int = 1) -> int:
    """Smallest value of the series 1, 2, 3, 4, 6, 8, 12, 16, 24, ... that is >= max(n, floor)."""
    n = max(int(n), int(floor), 1)
    p = 1
    while p < n:
        if p >= 2 and p + p // 2 >= n:
            return p + p // 2
        p *= 2
    return p


def batch_rows(
    count: int, *, min_rows: int = 1, pad_count: bool = True, multiple_of: int = 1
) -> int:
    """Rows of the batch `compile_genomes` makes of ``count`` genomes (same options)."""
    rows = max(count, min_rows)
    rows = bucket_size(rows, BATCH_FLOOR) if pad_count else rows
    return -(-rows // multiple_of) * multiple_of


@pytree.dataclass
class Bucket:
    """Padded sizes shared by every network of one compiled batch."""

    neurons: int = pytree.field(pytree_node=False)
    genes: int = pytree.field(pytree_node=False)
    sweeps: int = pytree.field(pytree_node=False)


def bucket_for(genomes: Sequence[Genome]) -> Bucket:
    """The smallest bucket that holds every genome given."""
    if not genomes:
        raise ValueError("bucket_for: no genomes")
    return Bucket(
        neurons=bucket_size(max(g.n_neurons for g in genomes), NEURON_FLOOR),
        genes=bucket_size(max(g.n_params for g in genomes), GENE_FLOOR),
        sweeps=bucket_size(max(g.depth() for g in genomes), SWEEP_FLOOR),
    )


@pytree.dataclass
class CompiledBatch:
    """A batch of genomes compiled into one bucket.

    Attributes:
      layout: batched `Layout`, leading dim ``G`` (padded).
      weights: ``float32[G, P]`` each genome's own weights in gene order, 0 on padding.
      count: number of real genomes (the first ``count`` rows); static.
      bucket: the padded sizes; static.
    """

    layout: Layout
    weights: jnp.ndarray
    count: int = pytree.field(pytree_node=False)
    bucket: Bucket = pytree.field(pytree_node=False)


def _slots(genome: Genome, n_neurons: int, n_inputs: int, n_outputs: int) -> tuple:
    """Buffer entry of each gene, and the root / real-neuron masks over neuron slots."""
    genes = genome.genes
    h = n_neurons
    off_bias = h * n_inputs
    off_ff = off_bias + h
    off_rec = off_ff + h * h
    off_out = off_rec + h * h
    positions = sorted((i for i, g in enumerate(genes) if g.kind == GeneKind.NEURON), reverse=True)
    slot_of = {genes[i].ref: s for s, i in enumerate(positions)}
    root_rank = {gene_index: r for r, gene_index in enumerate(genome.roots)}
    parent = genome.parent
    slot = np.empty(len(genes), dtype=np.int32)
    for i, g in enumerate(genes):
        if g.kind == GeneKind.NEURON and i in root_rank:
            slot[i] = off_out + root_rank[i] * h + slot_of[g.ref]
            continue
        ps = slot_of[genes[parent[i]].ref]
        if g.kind == GeneKind.INPUT:
            slot[i] = ps * n_inputs + g.ref
        elif g.kind == GeneKind.BIAS:
            slot[i] = off_bias + ps
        elif g.kind == GeneKind.RECURRENT:
            slot[i] = off_rec + ps * h + slot_of[g.ref]
        else:  # inner neuron or forward jumper: a current-step edge
            slot[i] = off_ff + ps * h + slot_of[g.ref]
    is_root = np.zeros(h, dtype=bool)
    for gene_index in genome.roots:
        is_root[slot_of[genes[gene_index].ref]] = True
    neuron_mask = np.zeros(h, dtype=bool)
    neuron_mask[: len(positions)] = True
    return slot, is_root, neuron_mask


def compile_genomes(
    genomes: Sequence[Genome],
    n_inputs: int,
    *,
    bucket: Bucket | None = None,
    pad_count: bool = True,
    min_rows: int = 1,
    multiple_of: int = 1,
    mesh: jax.sharding.Mesh | None = None,
) -> CompiledBatch:
    """Compile genomes into one padded batch.

    Args:
      genomes: networks with the same number of outputs.
      n_inputs: width of the input vector the networks will read (>= each genome's inputs).
      bucket: padded sizes to use; default the smallest that fits (`bucket_for`).
      pad_count: pad the number of genomes up its bucket series too, so that batches of
        similar counts share a program (padding rows are empty networks).
      min_rows: pad to at least this many rows (a caller that knows its usual batch size
        keeps one program for all of them).
      multiple_of: round the rows up to a multiple of this (the devices they split over).
      mesh: put the arrays straight from the host onto this device mesh, split along the
        structure axis (`eant2_jax.distributed.shard`; the rows are then rounded up to a
        multiple of its size); default JAX's default device.

    Returns:
      The `CompiledBatch`.
    """
    genomes = list(genomes)
    n_out = _check_genomes(genomes, n_inputs)
    bucket = _check_bucket(genomes, bucket, n_inputs, n_out)
    count = len(genomes)
    if mesh is not None:
        multiple_of = distributed.size(mesh)
    rows = batch_rows(count, min_rows=min_rows, pad_count=pad_count, multiple_of=multiple_of)
    tables = _tables(genomes, rows, bucket, n_inputs, n_out)
    slot, gene_mask, is_root, neuron_mask, depth, weights = tables
    # device_put, not jnp.asarray: the latter compiles a small program per new shape (a
    # cold-start cost on a GPU); the arrays already have their final dtypes. One call for all.
    host = {"slot": slot, "gene_mask": gene_mask, "is_root": is_root,
            "neuron_mask": neuron_mask, "depth": depth, "weights": weights}  # fmt: skip
    put = jax.device_put(host) if mesh is None else distributed.shard(host, mesh)
    weights = put.pop("weights")
    layout = Layout(**put, n_inputs=int(n_inputs), n_outputs=int(n_out), sweeps=bucket.sweeps)
    return CompiledBatch(layout=layout, weights=weights, count=count, bucket=bucket)


def _check_genomes(genomes: list[Genome], n_inputs: int) -> int:
    """The genomes' common number of outputs, after checking that they can share a batch
    (same outputs, inputs within ``n_inputs``, weights that fit in float32)."""
    if not genomes:
        raise ValueError("compile_genomes: no genomes")
    n_out = genomes[0].n_outputs
    for i, g in enumerate(genomes):
        if g.n_outputs != n_out:
            raise ValueError(
                f"genomes have different numbers of outputs: genome 0 has {n_out}, "
                f"genome {i} has {g.n_outputs}"
            )
        if g.n_inputs > n_inputs:
            raise ValueError(
                f"genome {i} reads input {g.n_inputs - 1} but the data has {n_inputs} inputs"
            )
        big = np.abs(g.weights) > np.finfo(np.float32).max
        if np.any(big):
            j = int(np.flatnonzero(big)[0])
            raise ValueError(
                f"genome {i}: weight {g.weights[j]!r} of gene {j} does not fit in float32"
            )
    return n_out


def _check_bucket(
    genomes: list[Genome], bucket: Bucket | None, n_inputs: int, n_out: int
) -> Bucket:
    """The bucket to compile into: ``bucket`` if it holds the genomes (default the smallest
    that does), and within the int32 slot table."""
    need = bucket_for(genomes)
    if bucket is None:
        bucket = need
    elif bucket.neurons < need.neurons or bucket.genes < need.genes or bucket.sweeps < need.sweeps:
        raise ValueError(f"bucket {bucket} is too small for these genomes (need {need})")
    h = bucket.neurons
    if buffer_size(h, n_inputs, n_out) > MAX_BUFFER:
        raise ValueError(
            f"network too large to compile: {h} neuron slots (padded) and {n_inputs} inputs "
            f"need {buffer_size(h, n_inputs, n_out):,} parameter entries, more than the "
            f"int32 slot table holds ({MAX_BUFFER:,}; about 24,576 neurons with few inputs)"
        )
    return bucket


def _tables(genomes: list[Genome], rows: int, bucket: Bucket, n_inputs: int, n_out: int) -> tuple:
    """The host arrays of a batch of ``rows`` (`Layout`'s and the weights), padding rows
    empty: ``(slot, gene_mask, is_root, neuron_mask, depth, weights)``."""
    h, p = bucket.neurons, bucket.genes
    trash = buffer_size(h, n_inputs, n_out) - 1
    slot = np.full((rows, p), trash, dtype=np.int32)
    gene_mask = np.zeros((rows, p), dtype=bool)
    is_root = np.zeros((rows, h), dtype=bool)
    neuron_mask = np.zeros((rows, h), dtype=bool)
    depth = np.zeros(rows, dtype=np.int32)
    weights = np.zeros((rows, p), dtype=np.float32)
    for r, g in enumerate(genomes):
        s, root, real = _slots(g, h, n_inputs, n_out)
        n = g.n_params
        slot[r, :n] = s
        gene_mask[r, :n] = True
        is_root[r], neuron_mask[r] = root, real
        depth[r] = g.depth()
        weights[r, :n] = g.weights
    return slot, gene_mask, is_root, neuron_mask, depth, weights


def network_batch(layout: Layout, weights: jax.Array) -> Network:
    """The networks ``[G]`` of a compiled batch: ``network`` of each row (traceable).

    Args:
      layout: batched layout ``[G]`` (`CompiledBatch.layout`).
      weights: ``[G, P]`` weights in gene order (`CompiledBatch.weights`, or tuned ones).
    """
    return jax.vmap(network)(layout, weights)


_network_batch = jax.jit(network_batch)


def networks(genomes: Sequence[Genome], n_inputs: int) -> Network:
    """The one route from genomes to networks: compile, then build each genome's network.

    Args:
      genomes: networks with the same number of outputs.
      n_inputs: width of the input vector they will read.

    Returns:
      A `Network` with leading dimension ``len(genomes)``
      (no padding rows), ready for a task's ``cost`` or the kernels' ``rollout``.
    """
    batch = compile_genomes(genomes, n_inputs, pad_count=False)
    return _network_batch(batch.layout, batch.weights)
