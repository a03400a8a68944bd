"""The safe eigendecomposition of ONE masked covariance matrix (`eant2_jax.kernels.cmaes`
decomposes its C with it; the pruner reads its B and D)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .linalg import eigh  # safe on several CPU devices (see there)

__all__ = ["eigen", "eigh", "symmetrised"]


def symmetrised(C: jax.Array, mask: jax.Array) -> jax.Array:
    """``C`` made exactly symmetric on its valid block, 0 elsewhere (idempotent)."""
    return jnp.where(mask[:, None] & mask[None, :], 0.5 * (C + C.T), 0)


def eigen(
    C: jax.Array, mask: jax.Array, max_condition: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    """Safe eigendecomposition of a masked covariance matrix.

    Args:
      C: ``[P, P]`` covariance; only the valid block (``mask`` x ``mask``) is read.
      mask: ``[P]`` bool, valid coordinates.
      max_condition: ``[]`` bound on lambda_max / lambda_min over the valid axes.

    Returns:
      ``(C, B, D, valid_axes, cond, bounded)``: the symmetrised (and, if an eigenvalue was
      clipped, rebuilt) ``C`` ``[P, P]`` with padded block 0; eigenvectors ``B`` ``[P, P]``
      (columns); ``D`` ``[P]`` square roots of the clipped eigenvalues, 0 on padded axes;
      ``valid_axes`` ``[P]`` bool; ``cond`` ``[]`` of the returned ``C`` over the valid axes;
      ``bounded`` ``[]`` bool, whether ``max_condition`` clipped an eigenvalue.
    """
    dtype = C.dtype
    C = symmetrised(C, mask)
    # Padded axes would be exact zero eigenvalues, degenerate with any tiny valid eigenvalue,
    # and eigh may then mix valid and padded directions. Shifting the padded diagonal to
    # -max(diag C_valid) separates them by a gap >= lambda_max / n (C_valid is PSD, so
    # lambda_max <= trace <= n * max diag) while keeping the matrix norm of the same order
    # (so the valid eigenvalues lose no accuracy). Only eigh sees the shift.
    diag = jnp.diagonal(C)
    d_max = jnp.max(jnp.where(mask, jnp.abs(diag), 0))
    shift = jnp.where(d_max > 0, d_max, 1)
    lam, B = eigh(C - jnp.diag(jnp.where(mask, 0, shift)))
    # A valid axis has (up to rounding, thanks to the gap) all its mass on valid coordinates.
    mass = jnp.sum(jnp.where(mask[:, None], B**2, 0), axis=0)
    valid_axes = mass > 0.5
    # Zero the leakage so padded coordinates of samples are exactly 0 (and the pruner, which
    # reads b_ij of valid axes, sees 0 on padded coordinates).
    B = jnp.where(mask[:, None] == valid_axes[None, :], B, 0)

    any_valid = jnp.any(valid_axes)
    lam_max = jnp.max(jnp.where(valid_axes, lam, -jnp.inf))
    bound = lam_max / max_condition
    # An absolute floor keeps 1/D finite when C has collapsed (lambda_max <= 0 or tiny):
    # sqrt(tiny) makes 1/D <= 1/tiny**0.25 (about 1e9 in float32), far from overflow.
    floor = jnp.sqrt(jnp.asarray(jnp.finfo(dtype).tiny, dtype))
    lower = jnp.maximum(bound, floor)
    bounded = jnp.any(valid_axes & (lam < bound))
    clipped = jnp.any(valid_axes & (lam < lower))
    lam = jnp.where(valid_axes, jnp.maximum(lam, lower), 0)
    D = jnp.sqrt(lam)
    cond = jnp.max(jnp.where(valid_axes, lam, -jnp.inf)) / jnp.min(
        jnp.where(valid_axes, lam, jnp.inf)
    )
    cond = jnp.where(any_valid, cond, 1)  # an empty structure (n = 0) has no spectrum
    # Rebuild C only when the spectrum was changed, so that C stays B diag(D^2) B^T.
    C = jnp.where(clipped, (B * lam[None, :]) @ B.T, C)
    return C, B, D, valid_axes, cond, bounded
