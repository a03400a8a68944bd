"""Masked CMA-ES for ONE parameter structure, batched over structures by the caller.

EANT2 tunes the weights of many network structures at once (Siebel, Botel & Sommer 2009,
sec. III "Structural Exploitation"). Each structure has its own dimension ``n``; all are
padded to one static size ``P`` with a boolean coordinate mask, so ``jax.vmap(tell)`` over the
structures is one batched program. A padded structure follows the trajectory it would follow
unpadded (same key, equal up to float rounding) because

* the hyper-parameters come from the structure's own ``n`` (``default_params``, traceable),
* coordinate ``i`` draws its normals from ``jax.random.fold_in(key, i)``, whatever ``P`` is,
* sampling uses the symmetric square root ``C^{1/2} = B diag(D) B^T``, which does not depend
  on the order or sign of the eigenvectors, and
* the padded block of ``C`` (and of the mean and the paths) stays exactly 0.

The update is evosax's ``CMA_ES`` (v0.3.2) with active (negative) weights, equation for
equation; equation numbers refer to Hansen, "The CMA Evolution Strategy: A Tutorial",
arXiv:1604.00772. Deviations from evosax, all deliberate:

* the eigendecomposition runs at the end of ``tell`` (and exactly at ``init``), so ``B`` and
  ``D`` in the state always belong to the ``C`` next to them: the pruner (paper sec. IV-B)
  reads them. evosax runs it in ``ask`` and adds ``1e-8 I`` to ``C`` every generation; here
  eigenvalues are instead clipped at ``lambda_max / max_condition`` (the paper, sec. V, limits
  the condition the same way) and ``C`` is rebuilt from the clipped spectrum only when a clip
  bit.
* costs that are NaN or +-inf rank after all finite ones (evosax ranks ``-inf`` first) and
  never receive a positive weight, so a diverging network cannot pull the mean; a generation
  with no finite cost leaves the distribution unchanged. Ties rank by index (evosax averages
  tied ranks and truncates).

``Params.diagonal`` (static) selects the separable variant instead, sep-CMA-ES
(`eant2_jax.kernels.sepcmaes`): only the diagonal of ``C`` is adapted, ``B`` stays the
identity and no eigendecomposition runs.

Minimisation throughout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike

from . import pytree, sepcmaes, threefry
from .eigen import eigen as eigen
from .eigen import symmetrised as _symmetrised

__all__ = [
    "Params",
    "State",
    "ask",
    "decompose",
    "default_params",
    "eigen",
    "eigen_interval",
    "init",
    "spectrum",
    "sqrt_cov",
    "tell",
]

# evosax caps the dimension in c_1, c_mu and chi_n at floor(sqrt(int32 max)) so that
# n**2 cannot overflow int32 (evosax/algorithms/base.py, ``max_num_dims_sq``).
_MAX_NUM_DIMS_SQ = float(np.floor(np.sqrt(np.iinfo(np.int32).max)))


@pytree.dataclass
class Params:
    """Hyper-parameters of one structure; a pytree, so it can be vmapped with the state.

    All leaves are 0-d except ``weights`` ``[popsize]``. They depend on the structure's own
    dimension ``n`` (not on the padded size), so removing a coordinate means recomputing them
    with ``default_params(n - 1, popsize, diagonal=params.diagonal)``. ``diagonal`` is a
    static field (part of the tree's structure): True runs sep-CMA-ES.
    """

    n: jax.Array  # [] the structure's dimension, as a float
    weights: jax.Array  # [popsize] rank weights, positive then negative, Eq. (53)
    mu_eff: jax.Array  # [] variance-effective selection mass, Eq. (8)
    c_mean: jax.Array  # [] learning rate of the mean, Eq. (54)
    c_sigma: jax.Array  # [] cumulation of the step-size path, Eq. (55)
    d_sigma: jax.Array  # [] step-size damping, Eq. (55)
    c_c: jax.Array  # [] cumulation of the rank-one path, Eq. (56)
    c_1: jax.Array  # [] rank-one learning rate, Eq. (57)
    c_mu: jax.Array  # [] rank-mu learning rate, Eq. (58)
    chi_n: jax.Array  # [] E||N(0, I_n)||, page 28
    sigma_min: jax.Array  # [] step-size clip (evosax std_min)
    sigma_max: jax.Array  # [] step-size clip (evosax std_max)
    max_condition: jax.Array  # [] bound on cond(C) over the valid axes
    diagonal: bool = pytree.field(pytree_node=False, default=False)  # sep-CMA-ES (static)


@pytree.dataclass
class State:
    """State of one masked CMA-ES over ``P`` padded coordinates.

    Padded coordinates (``mask`` False) hold exactly 0 in ``mean``, the paths, ``C``,
    ``best_x`` and in the rows of ``B``; padded eigen-axes (``valid_axes`` False) hold ``D = 0``.
    """

    mean: jax.Array  # [P] distribution mean m
    sigma: jax.Array  # [] step size
    p_sigma: jax.Array  # [P] step-size (conjugate) evolution path
    p_c: jax.Array  # [P] rank-one evolution path
    C: jax.Array  # [P, P] covariance matrix, symmetric, padded block 0
    B: jax.Array  # [P, P] eigenvectors of C as columns, C = B diag(D**2) B^T
    D: jax.Array  # [P] square roots of the eigenvalues of C, 0 on padded axes
    mask: jax.Array  # [P] bool, valid coordinates
    valid_axes: jax.Array  # [P] bool, columns of B that span the valid coordinates
    n: jax.Array  # [] int32, number of valid coordinates
    generation: jax.Array  # [] int32, number of ``tell`` calls
    cond: jax.Array  # [] cond(C) over the valid axes, after the bound
    cond_bounded: jax.Array  # [] bool, the condition bound clipped eigenvalues in the last tell
    num_nonfinite: jax.Array  # [] int32, NaN/inf costs in the last tell
    best_x: jax.Array  # [P] best finite-cost candidate seen so far
    best_cost: jax.Array  # [] its cost (+inf before any finite cost)


def _float_dtype(dtype: DTypeLike | None) -> np.dtype:
    if dtype is None:
        return jnp.result_type(float)  # float32, or float64 under jax_enable_x64
    return jnp.dtype(dtype)


def default_params(
    n: jax.Array | int,
    popsize: int,
    *,
    max_condition: float = 1e14,
    dtype: DTypeLike | None = None,
    diagonal: bool = False,
) -> Params:
    """Hyper-parameters of evosax ``CMA_ES._default_params`` for dimension ``n``.

    Args:
      n: the structure's dimension; may be a traced scalar (e.g. under vmap over structures).
      popsize: lambda, the number of candidates per generation (static, >= 2).
      max_condition: bound on cond(C) over the valid axes; eigenvalues below
        ``lambda_max / max_condition`` are clipped up (the paper, sec. V, limits it too).
      dtype: float dtype of the leaves; default float32, or float64 under jax_enable_x64.
      diagonal: sep-CMA-ES (static): ``c_1`` and ``c_mu`` times ``(n + 2) / 3`` (Ros &
        Hansen 2008; `kernels.sepcmaes.rate_scale`), ``c_mu`` capped at ``1 - c_1``, and the
        negative weights' bounds, Eq. (50)-(52), taken with those rates.

    Returns:
      ``Params`` with ``weights`` of shape ``[popsize]`` and 0-d leaves otherwise.
    """
    if popsize < 2:
        raise ValueError(f"popsize must be >= 2, got {popsize}")
    dtype = _float_dtype(dtype)
    n = jnp.asarray(n).astype(dtype)
    # evosax: elite_ratio 0.5, num_elites = max(1, int(0.5 * popsize)).
    num_elites = max(1, int(0.5 * popsize))

    weights_prime = jnp.log(jnp.asarray((popsize + 1) / 2, dtype)) - jnp.log(
        jnp.arange(1, popsize + 1, dtype=dtype)
    )  # Eq. (48)
    w_pos, w_neg = weights_prime[:num_elites], weights_prime[num_elites:]
    mu_eff = jnp.sum(w_pos) ** 2 / jnp.sum(w_pos**2)  # Eq. (8)
    mu_eff_minus = jnp.sum(w_neg) ** 2 / jnp.sum(w_neg**2)  # Table 1

    n_sq = jnp.minimum(n, _MAX_NUM_DIMS_SQ)
    alpha_cov = 2.0
    c_c = (4 + mu_eff / n) / (n + 4 + 2 * mu_eff / n)  # Eq. (56)
    c_1 = alpha_cov / ((n_sq + 1.3) ** 2 + mu_eff)  # Eq. (57)
    c_mu = jnp.minimum(
        1 - c_1 - 1e-8,  # 1e-8 is for large population size (as evosax)
        alpha_cov * (mu_eff + 1 / mu_eff - 2) / ((n_sq + 2) ** 2 + alpha_cov * mu_eff / 2),
    )  # Eq. (58)
    if diagonal:
        scale = sepcmaes.rate_scale(n)
        c_1 = scale * c_1
        mu_rate = (mu_eff + 1 / mu_eff - 2) / ((n_sq + 2) ** 2 + alpha_cov * mu_eff / 2)
        c_mu = jnp.minimum(1 - c_1 - 1e-8, scale * alpha_cov * mu_rate)

    weights = _active_weights(weights_prime, n, mu_eff, mu_eff_minus, c_1, c_mu)

    c_sigma = (mu_eff + 2) / (n + mu_eff + 5)  # Eq. (55)
    d_sigma = 1 + 2 * jnp.maximum(0, jnp.sqrt((mu_eff - 1) / (n + 1)) - 1) + c_sigma  # Eq. (55)
    chi_n = jnp.sqrt(n) * (1.0 - 1.0 / (4.0 * n) + 1.0 / (21.0 * n_sq**2))  # page 28

    def scalar(v):
        return jnp.asarray(v, dtype)

    return Params(
        n=n,
        weights=weights.astype(dtype),
        mu_eff=scalar(mu_eff),
        c_mean=scalar(1.0),  # Eq. (54)
        c_sigma=scalar(c_sigma),
        d_sigma=scalar(d_sigma),
        c_c=scalar(c_c),
        c_1=scalar(c_1),
        c_mu=scalar(c_mu),
        chi_n=scalar(chi_n),
        sigma_min=scalar(0.0),
        sigma_max=scalar(1e8),
        max_condition=scalar(max_condition),
        diagonal=bool(diagonal),
    )


def _active_weights(weights_prime, n, mu_eff, mu_eff_minus, c_1, c_mu) -> jax.Array:
    """Rank weights, Eq. (53): the positive ones sum to 1, the negative ones to minus the
    bound of Eq. (50)-(52)."""
    min_alpha = jnp.minimum(
        1 + c_1 / c_mu,  # Eq. (50)
        1 + (2 * mu_eff_minus) / (mu_eff + 2),  # Eq. (51)
    )
    min_alpha = jnp.minimum(min_alpha, (1 - c_1 - c_mu) / (n * c_mu))  # Eq. (52)
    positive_sum = jnp.sum(weights_prime * (weights_prime > 0))
    negative_sum = jnp.sum(jnp.abs(weights_prime * (weights_prime < 0)))
    return jnp.where(
        weights_prime >= 0,
        weights_prime / positive_sum,
        min_alpha * weights_prime / negative_sum,
    )  # Eq. (53)


def _cast_params(params: Params, dtype: DTypeLike) -> Params:
    # Params built under x64 may meet a float32 state; keep the state's dtype stable (scan carry).
    return jax.tree.map(lambda a: jnp.asarray(a).astype(dtype), params)


def decompose(state: State, params: Params) -> State:
    """``state`` with ``B``, ``D``, ``valid_axes``, ``cond`` and ``cond_bounded`` of its
    ``C`` (clipped to ``params.max_condition``, as in `tell`)."""
    p = _cast_params(params, state.C.dtype)
    C, B, D, valid_axes, cond, bounded = spectrum(state.C, state.mask, p)
    return state.replace(C=C, B=B, D=D, valid_axes=valid_axes, cond=cond, cond_bounded=bounded)


def spectrum(
    C: jax.Array, mask: jax.Array, params: Params
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array, jax.Array, jax.Array]:
    """`eigen` of ``C`` under ``params.max_condition``; for a diagonal ``params`` the
    spectrum of ``diag(C)`` without an eigensolver (`kernels.sepcmaes.spectrum`: its
    off-diagonal entries are dropped, ``B = I``)."""
    if params.diagonal:
        return sepcmaes.spectrum(C, mask, params.max_condition)
    return eigen(C, mask, params.max_condition)


def eigen_interval(params: Params, factor: float | jax.Array) -> jax.Array:
    """Iterations between eigendecompositions under the lazy rule: ``factor / (n (c_1 +
    c_mu))``, at least 1 (``[]`` float).

    Hansen's tutorial (B.2) updates B and D every ``max(1, floor(1 / (10 n (c_1 + c_mu))))``
    iterations (``factor`` 0.1, rounded down: at EANT2's sizes, n up to a few hundred, that is
    every iteration); pycma's ``lazy_gap_evals`` uses 0.5 and decomposes once more than that
    many iterations have passed, as here (a structure decomposes when the iterations since its
    last decomposition reach the interval). The covariance learns at the rate ``c_1 + c_mu``
    per iteration, so it moves by about ``factor / n`` of itself between two decompositions.
    """
    return jnp.maximum(factor / (params.n * (params.c_1 + params.c_mu)), 1.0)


def eigen_period(params: Params, factor: float | jax.Array) -> jax.Array:
    """The lazy rule's period as a power of two: the largest ``2^k <= ceil(eigen_interval)``
    (``[]`` int32, at most 2^30).

    A structure whose C is decomposed on the iterations that are multiples of its period
    is never staler than `eigen_interval` allows (a decomposition once the iterations since
    the last one reach the interval is one every ``ceil(interval)`` iterations). Powers of
    two nest: structures of periods 2^j <= 2^k are all due on every multiple of 2^k, so a
    batch of structures needs its batched ``eigh`` only on the multiples of its smallest
    period, where the per-structure phases of `eigen_interval` make some structure due
    nearly every iteration (`eant2_jax.exploitation._lazy_decompose`).
    """
    k = jnp.minimum(jnp.ceil(eigen_interval(params, factor)), 2.0**30).astype(jnp.int32)
    return jnp.left_shift(jnp.int32(1), 31 - jax.lax.clz(k))


def sqrt_cov(state: State, inverse: bool = False) -> jax.Array:
    """Symmetric square root ``C^{1/2} = B diag(D) B^T`` (or ``C^{-1/2}``), ``[P, P]``.

    Padded rows and columns are exactly 0 in both.
    """
    d = state.D
    if inverse:
        d = jnp.where(state.valid_axes, 1 / jnp.where(state.valid_axes, d, 1), 0)
    return (state.B * d[None, :]) @ state.B.T


def init(mean: jax.Array, sigma: jax.Array | float, mask: jax.Array, params: Params) -> State:
    """Initial state ``N(mean, sigma^2 I)`` on the valid coordinates.

    Args:
      mean: ``[P]`` initial mean; its float dtype (float32 by default) is the state's dtype.
        Padded entries are ignored (set to 0).
      sigma: ``[]`` initial step size.
      mask: ``[P]`` bool, valid coordinates; ``params`` must come from ``n = mask.sum()``.
      params: hyper-parameters (only their dtype-independent meaning is used here).

    Returns:
      ``State`` with ``C = B = I`` on the valid block and ``D = mask``.
    """
    del params  # The initial state does not depend on them; kept for an evosax-like call.
    mean = jnp.asarray(mean)
    if not jnp.issubdtype(mean.dtype, jnp.floating):
        mean = mean.astype(_float_dtype(None))
    dtype = mean.dtype
    mask = jnp.asarray(mask, bool)
    P = mean.shape[-1]
    valid = mask.astype(dtype)
    zeros = jnp.zeros((P,), dtype)
    # C = I is diagonal: its eigendecomposition is exact, so eigh is not needed here.
    return State(
        mean=jnp.where(mask, mean, 0),
        sigma=jnp.asarray(sigma, dtype),
        p_sigma=zeros,
        p_c=zeros,
        C=jnp.diag(valid),
        B=jnp.eye(P, dtype=dtype),
        D=valid,
        mask=mask,
        valid_axes=mask,
        n=jnp.sum(mask, dtype=jnp.int32),
        generation=jnp.asarray(0, jnp.int32),
        cond=jnp.asarray(1, dtype),
        cond_bounded=jnp.asarray(False),
        num_nonfinite=jnp.asarray(0, jnp.int32),
        best_x=zeros,
        best_cost=jnp.asarray(jnp.inf, dtype),
    )


def _normals(key: jax.Array, P: int, popsize: int, dtype: DTypeLike) -> jax.Array:
    """``[popsize, P]`` standard normals; column ``i`` from ``fold_in(key, i)`` only.

    Drawn as ONE flat vector of ``P * popsize`` scalar draws: with vmap over structures (and
    seeds), per-coordinate ``normal(k_i, (popsize,))`` becomes a rank-3 threefry that XLA:CPU
    compiles more slowly (docs/design.md); the flat form stays rank 2 and draws the same
    numbers whatever the batching. The draws are `jax.random`'s, written out on a CPU
    (`kernels.threefry`).
    """
    coord_keys = jax.vmap(lambda i: threefry.fold_in(key, i))(jnp.arange(P))
    c = jnp.arange(P * popsize)
    keys = jax.vmap(lambda c: threefry.fold_in(coord_keys[c // popsize], c % popsize))(c)
    z = jax.vmap(lambda k: threefry.normal(k, dtype))(keys)
    return z.reshape(P, popsize).T


def ask(key: jax.Array, state: State, params: Params) -> tuple[jax.Array, State]:
    """Sample ``popsize`` candidates ``x = m + sigma C^{1/2} z``, Eq. (38)-(40).

    ``popsize`` is ``params.weights.shape[0]`` (static). ``z[j, i]`` (candidate ``j``,
    coordinate ``i``) is ``jax.random.normal(fold_in(fold_in(key, i), j), ())``, so the first
    ``n`` coordinates of ``z`` do not depend on the padded size ``P``; ``C^{1/2} =
    B diag(D) B^T`` is the symmetric square root.

    Args:
      key: PRNG key.
      state: current state.
      params: hyper-parameters (for ``popsize``).

    Returns:
      ``(x, state)``: candidates ``[popsize, P]`` with padded coordinates exactly 0, and the
      state unchanged (returned for evosax-shaped call sites).
    """
    popsize = params.weights.shape[0]
    dtype = state.mean.dtype
    P = state.mean.shape[-1]
    z = _normals(key, P, popsize, dtype)  # Eq. (38)
    z = jnp.where(state.mask[None, :], z, 0)
    if params.diagonal:  # B = I: C^{1/2} z = D z, O(P) per candidate
        y = z * state.D[None, :]
    else:
        # Eq. (39) with C^{1/2} = B diag(D) B^T (symmetric), applied as two [popsize, P] x
        # [P, P] products rather than forming C^{1/2}.
        y = ((z @ state.B) * state.D[None, :]) @ state.B.T
    x = state.mean[None, :] + state.sigma * y  # Eq. (40)
    return jnp.where(state.mask[None, :], x, 0), state


def rank_weights(cost: jax.Array, weights: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Weight of each candidate by its rank; non-finite costs rank last, never positive."""
    popsize = cost.shape[0]
    finite = jnp.isfinite(cost)
    order = jnp.argsort(jnp.where(finite, cost, jnp.inf), stable=True)
    ranks = jnp.zeros((popsize,), jnp.int32).at[order].set(jnp.arange(popsize, dtype=jnp.int32))
    w = weights[ranks]
    # A diverging candidate may still teach C where not to sample (negative weight), but it
    # must not attract the mean (this only bites when fewer than mu costs are finite).
    w = jnp.where(finite | (w < 0), w, 0)
    return w, finite


def tell(
    state: State, x: jax.Array, cost: jax.Array, params: Params, *, decompose: bool = True
) -> State:
    """One CMA-ES update from candidates and their costs (minimisation), Eq. (41)-(47).

    Args:
      state: the state ``x`` was sampled from.
      x: ``[popsize, P]`` candidates (padded coordinates are ignored).
      cost: ``[popsize]`` costs; NaN and +-inf rank after all finite costs.
      params: hyper-parameters from ``default_params(state.n, popsize)``.
      decompose: *static*. Decompose the new ``C`` (default). False keeps ``B``, ``D``,
        ``cond`` and ``cond_bounded`` of ``state`` (the lazy update of Hansen's tutorial,
        B.2, and pycma): sampling and the paths go on with the last decomposition until
        `decompose` is called.

    Returns:
      The new state, with ``B``, ``D``, ``cond`` and ``cond_bounded`` of the new ``C`` (with
      ``decompose``). If no cost is finite, only ``generation`` and ``num_nonfinite`` change.
    """
    dtype = state.mean.dtype
    p = _cast_params(params, dtype)
    mask = state.mask
    x = x.astype(dtype)
    cost = cost.astype(dtype)
    w, finite = rank_weights(cost, p.weights)

    # Mean, Eq. (41)-(42); y_k ~ N(0, C).
    y_k = jnp.where(mask[None, :], (x - state.mean[None, :]) / state.sigma, 0)
    y_w = jnp.where(w > 0, w, 0) @ y_k
    mean = state.mean + p.c_mean * state.sigma * y_w

    # Step-size path and CSA, Eq. (43)-(44); C^{-1/2} = B diag(1/D) B^T, 1/D = 0 off valid axes.
    inv_d = jnp.where(state.valid_axes, 1 / jnp.where(state.valid_axes, state.D, 1), 0)
    p_sigma = (1 - p.c_sigma) * state.p_sigma + jnp.sqrt(p.c_sigma * (2 - p.c_sigma) * p.mu_eff) * (
        y_w * inv_d if p.diagonal else state.B @ ((y_w @ state.B) * inv_d)  # diagonal: B = I
    )  # Eq. (43)
    norm_p_sigma = jnp.linalg.norm(p_sigma)
    sigma = state.sigma * jnp.exp((p.c_sigma / p.d_sigma) * (norm_p_sigma / p.chi_n - 1))
    sigma = jnp.clip(sigma, p.sigma_min, p.sigma_max)  # Eq. (44)

    # Stall of the rank-one path, page 28. evosax passes generation_counter + 1 and adds 1
    # again, i.e. exponent 2 (g + 2) for the (g + 1)-th update; matched so that trajectories
    # agree (the difference fades after a few generations).
    g = state.generation.astype(dtype) + 1
    h_sigma = (
        norm_p_sigma / jnp.sqrt(1 - (1 - p.c_sigma) ** (2 * (g + 1)))
        < (1.4 + 2 / (p.n + 1)) * p.chi_n
    ).astype(dtype)
    p_c = (1 - p.c_c) * state.p_c + h_sigma * jnp.sqrt(
        p.c_c * (2 - p.c_c) * p.mu_eff
    ) * y_w  # Eq. (45)
    delta_h_sigma = (1 - h_sigma) * p.c_c * (2 - p.c_c)

    C = _covariance(state, p, w, y_k, inv_d, p_c, delta_h_sigma)
    if decompose:
        decomposed = spectrum(C, mask, p)
    else:
        # What `eigen` does to C before decomposing it, so that `decompose` later gives
        # exactly what decompose=True would have given now (a diagonal C is already).
        C = C if p.diagonal else _symmetrised(C, mask)
        decomposed = (C, state.B, state.D, state.valid_axes, state.cond, state.cond_bounded)
    return _told(state, x, cost, finite, mean, sigma, p_sigma, p_c, decomposed)


def _covariance(state, p, w, y_k, inv_d, p_c, delta_h_sigma) -> jax.Array:
    """`tell`'s new ``C``: the rank-one and the active rank-mu update, Eq. (46)-(47)."""
    # Active rank-mu: negative weights rescaled by n / ||C^{-1/2} y_k||^2, Eq. (46).
    # ||C^{-1/2} y||^2 = ||diag(1/D) B^T y||^2 as B is orthonormal on the valid axes.
    y_axes = y_k if p.diagonal else y_k @ state.B
    norm2 = jnp.sum((y_axes * inv_d[None, :]) ** 2, axis=-1)
    w_o = w * jnp.where(w >= 0, 1, p.n / jnp.maximum(norm2, 1e-8))
    if p.diagonal:  # Eq. (47) on the diagonal alone
        decay = 1 + p.c_1 * delta_h_sigma - p.c_1 - p.c_mu * jnp.sum(p.weights)
        c = sepcmaes.covariance(jnp.diagonal(state.C), decay, p.c_1, p.c_mu, p_c, w_o, y_k)
        return jnp.diag(jnp.where(state.mask, c, 0))
    rank_mu = (w_o[:, None] * y_k).T @ y_k
    return (
        (1 + p.c_1 * delta_h_sigma - p.c_1 - p.c_mu * jnp.sum(p.weights)) * state.C
        + p.c_1 * jnp.outer(p_c, p_c)
        + p.c_mu * rank_mu
    )  # Eq. (47)


def _told(state, x, cost, finite, mean, sigma, p_sigma, p_c, decomposed) -> State:
    """`tell`'s new state: the updated distribution, the best so far over finite costs; the
    distribution unchanged if no cost is finite."""
    C, B, D, valid_axes, cond, bounded = decomposed
    masked_cost = jnp.where(finite, cost, jnp.inf)
    i_best = jnp.argmin(masked_cost)
    improved = masked_cost[i_best] < state.best_cost

    updated = state.replace(
        mean=mean,
        sigma=sigma,
        p_sigma=p_sigma,
        p_c=p_c,
        C=C,
        B=B,
        D=D,
        valid_axes=valid_axes,
        cond=cond,
        cond_bounded=bounded,
        best_x=jnp.where(improved, jnp.where(state.mask, x[i_best], 0), state.best_x),
        best_cost=jnp.where(improved, masked_cost[i_best], state.best_cost),
    )
    new = jax.tree.map(lambda a, b: jnp.where(jnp.any(finite), a, b), updated, state)
    return new.replace(
        generation=state.generation + 1,
        num_nonfinite=jnp.sum(~finite, dtype=jnp.int32),
    )
