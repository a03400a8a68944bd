"""Row selection over batched pytrees: the engine's one way to update some structures of a
batch and leave the others as they are."""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["where_rows"]


def where_rows(pred: jax.Array, new, old):
    """``where(pred, new, old)`` leaf by leaf, ``pred`` ``[S]`` broadcast over trailing dims."""

    def pick(a, b):
        p = pred.reshape(pred.shape + (1,) * (a.ndim - pred.ndim))
        return jnp.where(p, a, b)

    return jax.tree.map(pick, new, old)
