"""The separable (diagonal) CMA-ES of ONE masked structure: the parts that differ from the
full one (`eant2_jax.kernels.cmaes`, which runs them when ``Params.diagonal`` is set).

sep-CMA-ES (Ros & Hansen, "A Simple Modification in CMA-ES Achieving Linear Time and Space
Complexity", PPSN X, 2008) adapts only the diagonal of C: the rank-one and rank-mu updates,
Eq. (47) of Hansen's tutorial (arXiv:1604.00772), are applied to ``diag(C)`` alone, and the
covariance learning rates ``c_1`` and ``c_mu`` are multiplied by ``(n + 2) / 3`` (the
diagonal has n entries to learn, not n (n + 1) / 2). Then ``B`` is the identity on the
valid axes and ``D = sqrt(diag C)``: sampling and the step-size path cost O(n) per
candidate instead of O(n^2), and no eigendecomposition is ever needed. Everything else
(weights, paths, step size, the condition bound, non-finite costs) is the full kernel's.

The state keeps the full kernel's shapes (``C`` ``[P, P]``, exactly 0 off the diagonal;
``B`` the identity), so the engine and the pruner read it unchanged. docs/algorithm.md,
"Separable CMA-ES", says what pruning does on a diagonal run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["COVARIANCES", "covariance", "rate_scale", "spectrum"]

# ``ExploitConfig.covariance``: the full CMA-ES or the separable one.
COVARIANCES = ("full", "diagonal")


def rate_scale(n: jax.Array) -> jax.Array:
    """Ros & Hansen's factor ``(n + 2) / 3`` on the covariance learning rates (``[]``)."""
    return (n + 2) / 3


def covariance(
    c: jax.Array,
    decay: jax.Array,
    c_1: jax.Array,
    c_mu: jax.Array,
    p_c: jax.Array,
    w_o: jax.Array,
    y_k: jax.Array,
) -> jax.Array:
    """The diagonal of C after Eq. (47) restricted to the diagonal, ``[P]``.

    Args:
      c: ``[P]`` the diagonal of C (0 on padded coordinates).
      decay: ``[]`` ``1 + c_1 delta(h_sigma) - c_1 - c_mu sum(w)``, Eq. (47)'s factor on C.
      c_1: ``[]`` the (separable) rank-one learning rate.
      c_mu: ``[]`` the (separable) rank-mu learning rate.
      p_c: ``[P]`` the rank-one path.
      w_o: ``[popsize]`` the rank-mu weights of Eq. (46).
      y_k: ``[popsize, P]`` the steps ``(x_k - m) / sigma``, 0 on padded coordinates.
    """
    return decay * c + c_1 * p_c**2 + c_mu * (w_o @ y_k**2)


def spectrum(
    C: jax.Array, mask: jax.Array, max_condition: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    """`eant2_jax.kernels.eigen.eigen` of a diagonal covariance, without an eigensolver.

    The eigenvalues of a diagonal C are its diagonal and its eigenvectors the coordinate
    axes, so ``B = I``, ``D = sqrt(diag C)`` and ``valid_axes = mask``; the condition bound
    and the absolute floor are `eigen`'s, applied to the diagonal.

    Args:
      C: ``[P, P]`` covariance; only its diagonal on the valid coordinates is read.
      mask: ``[P]`` bool, valid coordinates.
      max_condition: ``[]`` bound on ``max(diag C) / min(diag C)`` over the valid axes.

    Returns:
      ``(C, B, D, valid_axes, cond, bounded)`` as `eigen` returns them: ``C`` the diagonal
      matrix of the clipped diagonal (0 off it and on padded coordinates), ``B = I``.
    """
    dtype = C.dtype
    lam = jnp.where(mask, jnp.diagonal(C), 0)
    lam_max = jnp.max(jnp.where(mask, lam, -jnp.inf))
    bound = lam_max / max_condition
    # `eigen`'s floor: 1/D stays finite when C has collapsed.
    floor = jnp.sqrt(jnp.asarray(jnp.finfo(dtype).tiny, dtype))
    lower = jnp.maximum(bound, floor)
    bounded = jnp.any(mask & (lam < bound))
    lam = jnp.where(mask, jnp.maximum(lam, lower), 0)
    cond = jnp.max(jnp.where(mask, lam, -jnp.inf)) / jnp.min(jnp.where(mask, lam, jnp.inf))
    cond = jnp.where(jnp.any(mask), cond, 1)  # an empty structure (n = 0) has no spectrum
    P = mask.shape[-1]
    return jnp.diag(lam), jnp.eye(P, dtype=dtype), jnp.sqrt(lam), mask, cond, bounded
