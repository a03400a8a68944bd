"""Connection pruning from the CMA-ES state alone (Siebel, Botel & Sommer 2009, section IV).

Everything here is for ONE structure of ``P`` padded parameters; batch with ``jax.vmap``.
It imports nothing from the rest of eant2_jax.

* `removable`: which parameters may go alone (structural rules, below).
* `scores`: each pruner's score for every parameter (smaller = prune first) and the
  shifted mean that would put that parameter at 0.
* `accept`: the acceptance rule, eq. ``e~ < 1.001 e`` (plus an absolute resolution,
  `acceptance_limit`).
* `condition`: the covariance after a removal, conditioned on the removed
  coordinates (Schur complement).

The covariance pruner (IV.B.2): with ``C = B D^2 B^T`` and principal axes
``v_j = b_j d_jj``, the factor that takes the mean ``m`` along ``v_j`` onto the hyperplane
``p_i = 0`` is ``s_ij = -m_i / (b_ij d_jj)`` (eq. 7); the candidate is
``(i*, j*) = argmin |s_ij|`` (eq. 8) and the shifted mean ``m~ = m + s_{i*j*} v_{j*}``. (The
paper's line under eq. 7 writes ``m_i - s_ij b_ij d_jj = 0``; with its own definition of
``s_ij`` the right sign is ``m_i + s_ij b_ij d_jj = 0``, i.e. ``m~ = m + s v``.)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import linalg, pytree

__all__ = [
    "PRUNERS",
    "Tables",
    "accept",
    "acceptance_limit",
    "condition",
    "removable",
    "removal_set",
    "scores",
]

PRUNERS = ("covariance", "magnitude", "obd", "obs", "snr", "random", "none")


@pytree.dataclass
class Tables:
    """The genome structure the pruner needs, per gene slot (padding: parent -1, leaf).

    Attributes:
      parent: ``int32[P]`` gene index of the neuron that reads gene i; -1 for roots/padding.
      subtree_end: ``int32[P]`` one past the last gene of gene i's sub-genome (i+1 for leaves).
      reads: ``int32[P]`` for a jumper, the gene index of the neuron it reads; else -1.
      is_neuron: ``bool[P]``.
    """

    parent: jax.Array
    subtree_end: jax.Array
    reads: jax.Array
    is_neuron: jax.Array


def _in_subtree(tables: Tables) -> jax.Array:
    """``[P, P]`` bool: gene j lies in the sub-genome of gene i (i itself included)."""
    idx = jnp.arange(tables.parent.shape[-1])
    return (idx[None, :] >= idx[:, None]) & (idx[None, :] < tables.subtree_end[:, None])


def removable(tables: Tables, active: jax.Array) -> jax.Array:
    """Parameters that can be removed alone, ``bool[P]``.

    Not removable: padding and already-removed genes; a root neuron's own weight (it would
    remove an output); the last remaining input of a neuron (a neuron needs k >= 1); a
    neuron gene's weight while a jumper outside its sub-genome still reads that neuron or
    any neuron inside it (removing the gene removes its whole sub-genome).
    """
    idx = jnp.arange(active.shape[-1])
    parent = tables.parent
    is_root = parent < 0
    # Active inputs of each neuron (indexed by the neuron's gene index).
    n_inputs = jnp.sum(active[None, :] & (parent[None, :] == idx[:, None]), axis=1)
    has_sibling = n_inputs[jnp.maximum(parent, 0)] >= 2
    inside = _in_subtree(tables)
    jumper = active & (tables.reads >= 0)
    # reads_inside[i, j]: jumper j reads a neuron inside the sub-genome of gene i.
    reads_inside = inside[:, jnp.maximum(tables.reads, 0)]
    read_from_outside = jnp.any(jumper[None, :] & reads_inside & ~inside, axis=1)
    return active & ~is_root & has_sibling & ~(tables.is_neuron & read_from_outside)


def removal_set(tables: Tables, active: jax.Array, i: jax.Array) -> jax.Array:
    """``bool[P]``: the genes that leave with gene ``i`` (its active sub-genome)."""
    idx = jnp.arange(active.shape[-1])
    return active & (idx >= i) & (idx < tables.subtree_end[i])


def scores(
    pruner: str,
    mean: jax.Array,
    sigma: jax.Array,
    C: jax.Array,
    B: jax.Array,
    D: jax.Array,
    valid_axes: jax.Array,
    candidates: jax.Array,
    key: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Every parameter's pruning score and shifted mean, for one pruner.

    Args:
      pruner: ``covariance``, ``magnitude``, ``obd``, ``obs``, ``snr`` or ``random``
        (static).
      mean: ``[P]`` CMA-ES mean m.
      sigma: ``[]`` step size.
      C: ``[P, P]`` covariance; B ``[P, P]`` its eigenvectors (columns), D ``[P]`` the square
        roots of its eigenvalues (0 on padded axes), valid_axes ``[P]`` bool.
      candidates: ``[P]`` bool, parameters that may be removed.
      key: the ``random`` pruner's PRNG key (the other pruners read none): its scores are
        i.i.d. uniform draws, so the smallest among the candidates is a uniform choice of
        one of them (a control: the rule's acceptance without any criterion's choice).

    Returns:
      ``(score [P], shifted [P, P], axis [P], factor [P])``: ``score[i]`` (+inf where not a
      candidate; smaller prunes first); ``shifted[i]`` the mean moved so that parameter i
      is exactly 0; for the covariance pruner ``axis[i]`` = j* and ``factor[i]`` = s_{ij*}
      (else -1 and NaN).
    """
    p = mean.shape[-1]
    inf = jnp.asarray(jnp.inf, mean.dtype)
    eye = jnp.eye(p, dtype=mean.dtype)
    axis = jnp.full(p, -1, jnp.int32)
    factor = jnp.full(p, jnp.nan, mean.dtype)
    if pruner == "covariance":
        v = B * D[None, :]  # v[:, j] = b_j d_jj, the principal axes; v[i, j] = b_ij d_jj
        tiny = jnp.finfo(mean.dtype).tiny
        ok = candidates[:, None] & valid_axes[None, :] & (jnp.abs(v) > tiny)
        s = -mean[:, None] / jnp.where(ok, v, 1)  # Eq. (7)
        abs_s = jnp.where(ok, jnp.abs(s), inf)
        axis = jnp.argmin(abs_s, axis=1).astype(jnp.int32)  # Eq. (8), per parameter i
        score = jnp.take_along_axis(abs_s, axis[:, None], axis=1)[:, 0]
        factor = jnp.take_along_axis(s, axis[:, None], axis=1)[:, 0]
        factor = jnp.where(jnp.isfinite(score), factor, 0)
        shifted = mean[None, :] + factor[:, None] * v[:, axis].T  # m~ = m + s v_j (erratum)
    elif pruner == "magnitude":
        score = jnp.abs(mean)
        shifted = jnp.broadcast_to(mean, (p, p))
    elif pruner == "obd":
        # OBD with H ~ (sigma^2 C)^-1: saliency h_ii m_i^2 / 2, no shift.
        inv_d2 = jnp.where(valid_axes, 1 / jnp.where(valid_axes, D, 1) ** 2, 0)
        h_diag = jnp.sum(B**2 * inv_d2[None, :], axis=1) / sigma**2
        score = 0.5 * mean**2 * h_diag
        shifted = jnp.broadcast_to(mean, (p, p))
    elif pruner == "snr":
        # Signal-to-noise (Lange & Sprekeler's ES-lottery rule): |m_i| / (sigma sqrt(C_ii)),
        # the mean in units of the search distribution's own spread along i; no shift.
        spread = sigma * jnp.sqrt(jnp.maximum(jnp.diagonal(C), 0))
        score = jnp.where(spread > 0, jnp.abs(mean) / jnp.where(spread > 0, spread, 1), inf)
        shifted = jnp.broadcast_to(mean, (p, p))
    elif pruner == "random":
        if key is None:
            raise ValueError("the random pruner needs a PRNG key")
        score = jax.random.uniform(key, (p,), mean.dtype)
        shifted = jnp.broadcast_to(mean, (p, p))
    elif pruner == "obs":
        # OBS with H^-1 ~ sigma^2 C: saliency m_i^2 / (2 sigma^2 C_ii), eq. (2);
        # shift m' = m - (m_i / C_ii) C e_i, eq. (3) (sigma^2 cancels).
        c_diag = jnp.diagonal(C)
        safe = jnp.where(c_diag > 0, c_diag, 1)
        score = jnp.where(c_diag > 0, mean**2 / (2 * sigma**2 * safe), inf)
        shifted = mean[None, :] - (mean / safe)[:, None] * C.T
    else:
        raise ValueError(f"unknown pruner {pruner!r}; known: {', '.join(PRUNERS)}")
    score = jnp.where(candidates & jnp.isfinite(score), score, inf)
    # Parameter i is exactly 0 in its own shifted mean (rounding would leave ~1e-8).
    shifted = jnp.where(eye > 0, 0, shifted)
    return score, shifted, axis, factor


def acceptance_limit(
    cost: jax.Array, tolerance: float | jax.Array = 1e-3, atol: float | jax.Array = 0.0
) -> jax.Array:
    """The cost a removal must stay under (IV.B.3): ``cost + tolerance |cost| + atol``.

    ``atol`` is the absolute resolution of costs (the engine passes ``improve_atol``, the
    margin under which it counts no improvement either): near a perfect fit, a cost at the
    float resolution (about 1e-15 for a mean squared error of targets of order 1 in
    float32) makes any relative band empty. For a float32 cost above about 3e-5 adding
    1e-12 rounds away: the limit is the paper's to the bit.
    """
    return cost + tolerance * jnp.abs(cost) + atol


def accept(
    cost: jax.Array,
    cost_shifted: jax.Array,
    tolerance: float | jax.Array = 1e-3,
    atol: float | jax.Array = 0.0,
) -> jax.Array:
    """The acceptance rule (IV.B.3): accept iff the cost rises by less than ``tolerance``
    (relative) plus ``atol`` (absolute, see `acceptance_limit`).

    For a positive cost ``e`` and ``atol = 0`` this is the paper's ``e~ < (1 + tolerance) e``.
    Costs that can be zero or negative use ``e~ <= limit`` (so a perfect ``e = 0`` accepts a
    removal that keeps it at 0). A non-finite ``e~`` is always rejected.
    """
    limit = acceptance_limit(cost, tolerance, atol)
    ok = jnp.where(cost > 0, cost_shifted < limit, cost_shifted <= limit)
    return ok & jnp.isfinite(cost_shifted) & jnp.isfinite(cost)


def condition(C: jax.Array, keep: jax.Array, remove: jax.Array) -> jax.Array:
    """The covariance of the kept coordinates given the removed ones (Schur complement).

    ``C' = C_KK - C_KR C_RR^-1 C_RK`` on the kept block, 0 elsewhere.

    Args:
      C: ``[P, P]`` covariance.
      keep: ``[P]`` bool, coordinates that stay.
      remove: ``[P]`` bool, coordinates removed now (disjoint from ``keep``).

    Returns:
      ``[P, P]`` conditioned covariance, symmetric, zero outside ``keep x keep``.
    """
    rr = remove[:, None] & remove[None, :]
    # C_RR padded with the identity outside R, so the solve is well-posed at fixed shape.
    c_rr = jnp.where(rr, C, 0) + jnp.diag(jnp.where(remove, 0, 1).astype(C.dtype))
    c_rk = jnp.where(remove[:, None] & keep[None, :], C, 0)
    x = linalg.solve(c_rr, c_rk)  # C_RR^-1 C_RK, zero rows outside R
    out = C - c_rk.T @ x
    out = 0.5 * (out + out.T)
    return jnp.where(keep[:, None] & keep[None, :], out, 0)
