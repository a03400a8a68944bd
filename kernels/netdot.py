"""The products of a network step, ``w @ v``, as the linear genome's stack semantics compute them.

A dense product would let a non-finite value reach every row through the zeros of the dense
matrix (``0 * nan``); the stack semantics add ``w_i * v`` gene by gene, so a NaN or infinite
``v[j]`` reaches only the rows whose genes read it (even with weight 0), as in
`eant2_jax.reference.interpret`. `dot` computes that: the finite values through the dense
weights, the non-finite ones through the weights `eant2_jax.kernels.netbuild.network` marks
for them (``Network.reads``). Short products are written as unrolled element-wise sums,
which XLA fuses with the activations; long ones are dots (docs/genome.md, The compiled
layout).

Written for ONE example; batch with ``jax.vmap``. This module imports nothing from the rest
of eant2_jax.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

__all__ = ["BRANCH_MIN", "UNROLL_MAX", "dot"]

# Exact float32 products: on GPUs the default precision of a float32 dot may use TF32
# (~1e-3 relative error), which would break equality with the reference interpreter. These
# products are tiny, so the cost is nil.
_PRECISION = jax.lax.Precision.HIGHEST

# Products whose contraction is at most this long (inputs or neurons read) are written as an
# unrolled sum of element-wise products instead of a dot: batched over networks and
# examples, a dot of such tiny matrices is a batched GEMM of its own that XLA does not fuse
# with what follows. The bound is measured (docs/design.md, "Products").
UNROLL_MAX = 12

# A long product's non-finite terms are a pass over [rows, k] per example (the finite part
# is a dot). Values are almost always finite, so over a batch of at least this many terms
# the pass runs only when some value of the whole batch is not: one branch (on a GPU, one
# read of its predicate by the host). Smaller batches, where the read would cost more than
# the pass, always run it (docs/design.md, "The non-finite pass").
BRANCH_MIN = 1 << 24


def dot(
    w: jax.Array,
    reads: tuple[jax.Array, jax.Array] | None,
    v: jax.Array,
    *,
    compact: bool = False,
) -> jax.Array:
    """``w @ v`` as the stack semantics compute it: a non-finite ``v[j]`` reaches exactly the
    rows that read it (a dense product would make ``0 * nan`` of every other row NaN). With
    a finite ``v`` it is the sum of ``w[:, j] * v[j]`` (in the order of ``j`` for short
    contractions, `UNROLL_MAX`; as XLA's dot orders it otherwise). ``compact``: always a
    dot, and the non-finite terms as one pass without a branch of their own."""
    k = v.shape[-1]
    if 0 < k <= UNROLL_MAX and not compact:
        return _dot_unrolled(w, reads, v)
    if reads is None:
        return jnp.dot(w, v, precision=_PRECISION)
    read, w_nf = reads
    finite = jnp.isfinite(v)
    y = jnp.dot(w, jnp.where(finite, v, jnp.zeros_like(v)), precision=_PRECISION)
    terms = _nonfinite_terms_plain if compact else _nonfinite_terms
    return jnp.where(jnp.all(finite), y, y + terms(read, w_nf, v))


def _nonfinite_terms_plain(read: jax.Array, w_nf: jax.Array, v: jax.Array) -> jax.Array:
    """The terms of the non-finite entries of ``v`` (any leading batch dims): ``w_nf[i, j] *
    v[j]`` summed over the non-finite ``v[j]`` that row ``i`` reads; 0 where there is none.

    Both factors are masked, not only the product: a NaN in an unselected branch of a
    where would still make the gradient NaN.
    """
    finite = jnp.isfinite(v)
    take = read & ~finite[..., None, :]
    w_take = jnp.where(take, w_nf, jnp.zeros_like(w_nf))
    v_take = jnp.where(finite, jnp.zeros_like(v), v)
    return jnp.sum(jnp.where(take, w_take * v_take[..., None, :], 0), axis=-1)


@jax.custom_jvp
def _nonfinite_terms(read: jax.Array, w_nf: jax.Array, v: jax.Array) -> jax.Array:
    """`_nonfinite_terms_plain`, skipped over a whole batch of at least `BRANCH_MIN`
    entries when every value is finite. The batch is the vmapped one: `_batch_level`
    carries each vmap's axis out to the call outside all of them, which branches once."""
    return _batch_level(())(read, w_nf, v)


@_nonfinite_terms.defjvp
def _nonfinite_terms_jvp(primals, tangents):
    # Differentiation takes the plain pass (no branch, nothing custom to differentiate).
    return jax.jvp(_nonfinite_terms_plain, primals, tangents)


@functools.cache
def _batch_level(shared: tuple[bool, ...]):
    """The branching pass for arguments whose leading axes are vmapped ones: ``v`` has all
    of them, ``read`` and ``w_nf`` (one network's) only those where ``shared`` is False.
    A network's arrays are not broadcast over the examples: a branch's operands are
    materialised, and broadcast they were 10 GB for 200 servo structures."""

    @jax.custom_batching.custom_vmap
    def level(read, w_nf, v):
        index = tuple(None if s else slice(None) for s in shared)  # size 1 where shared
        read, w_nf = read[index], w_nf[index]
        if v.size * read.shape[-2] < BRANCH_MIN:  # the pass's entries
            return _nonfinite_terms_plain(read, w_nf, v)

        def none(r, w, x):
            return jnp.zeros(jnp.broadcast_shapes(r.shape[:-1], x.shape[:-1] + (1,)), w.dtype)

        def some(r, w, x):
            # The barriers keep XLA from turning this small branch into a select, which
            # would run the pass every time (measured: no gain without them).
            r, w, x = jax.lax.optimization_barrier((r, w, x))
            return jax.lax.optimization_barrier(_nonfinite_terms_plain(r, w, x))

        return jax.lax.cond(jnp.all(jnp.isfinite(v)), none, some, read, w_nf, v)

    @level.def_vmap
    def level_vmap(axis_size, in_batched, read, w_nf, v):
        # An enclosing vmap applies this rule once more with its axis in front, so the call
        # outside all of them sees the whole batch.
        b_read, b_w, b_v = in_batched
        if not b_v:
            v = jnp.broadcast_to(v, (axis_size, *v.shape))
        if b_read != b_w:  # one network's arrays: batched together, or not at all
            read, w_nf = (
                a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
                for a, b in ((read, b_read), (w_nf, b_w))
            )
        return _batch_level((not (b_read or b_w), *shared))(read, w_nf, v), True

    return level


def _dot_unrolled(
    w: jax.Array, reads: tuple[jax.Array, jax.Array] | None, v: jax.Array
) -> jax.Array:
    """`dot` as ``k`` element-wise terms (one fusion with what follows). The term of a
    non-finite ``v[j]`` is ``w_nf[:, j] * v[j]`` on the rows that read it and 0 elsewhere;
    the product and its factors are masked (as in `dot`) so that gradients stay finite."""
    if reads is None:
        y = w[:, 0] * v[0]
        for j in range(1, v.shape[-1]):
            y = y + w[:, j] * v[j]
        return y
    read, w_nf = reads
    finite = jnp.isfinite(v)
    v_fin = jnp.where(finite, v, jnp.zeros_like(v))
    v_nf = jnp.where(finite, jnp.zeros_like(v), v)
    y = None
    for j in range(v.shape[-1]):
        take = read[:, j] & ~finite[j]
        w_take = jnp.where(take, w_nf[:, j], jnp.zeros_like(w_nf[:, j]))
        term = w[:, j] * v_fin[j] + jnp.where(take, w_take * v_nf[j], 0)
        y = term if y is None else y + term
    return y
