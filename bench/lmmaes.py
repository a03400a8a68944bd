"""LM-MA-ES in NumPy, written from its paper: the reference `python -m bench variants` runs.

Loshchilov, Glasmachers & Beyer, "Large Scale Black-box Optimization by Limited-Memory
Matrix Adaptation", IEEE TEC 23(2), 2019 (arXiv:1705.06693), Algorithm 1 (LM-MA-ES), with
the paper's default hyper-parameters. Minimisation. It keeps ``m`` direction vectors in
place of CMA-ES's ``n x n`` covariance: sampling costs ``O(m n)`` per candidate and no
eigendecomposition runs. Every random draw comes from the ``numpy`` generator passed in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np


class LMMAParams(NamedTuple):
    """Algorithm 1's constants for dimension ``n``."""

    popsize: int  # lambda = 4 + floor(3 ln n)
    mu: int  # floor(lambda / 2)
    weights: np.ndarray  # [mu], ln(mu + 1/2) - ln i, normalised to sum 1
    mu_w: float  # 1 / sum(w_i^2)
    c_sigma: float  # 2 lambda / n
    c_d: np.ndarray  # [m], 1 / (1.5^(j-1) n)
    c_c: np.ndarray  # [m], lambda / (4^(j-1) n)


def lmmaes_params(n: int, popsize: int | None = None) -> LMMAParams:
    """The paper's defaults: ``lambda = 4 + floor(3 ln n)`` and ``m = lambda`` direction
    vectors. Needs ``c_sigma = 2 lambda / n <= 1`` and ``c_c`` of the first vector at most 1,
    that is ``n >= 2 lambda``: the method is for large ``n``."""
    lam = popsize if popsize is not None else 4 + int(np.floor(3 * np.log(n)))
    if n < 2 * lam:
        raise ValueError(f"LM-MA-ES needs n >= 2 * popsize (c_sigma <= 1); got n={n}, {lam}")
    mu = lam // 2
    w = np.log(mu + 0.5) - np.log(np.arange(1, mu + 1))
    w = w / w.sum()
    m = 4 + int(np.floor(3 * np.log(n)))
    j = np.arange(m)
    return LMMAParams(
        popsize=lam,
        mu=mu,
        weights=w,
        mu_w=float(1 / np.sum(w**2)),
        c_sigma=2 * lam / n,
        c_d=1 / (1.5**j * n),
        c_c=lam / (4.0**j * n),
    )


class LMMAState(NamedTuple):
    mean: np.ndarray  # y
    sigma: float
    p_sigma: np.ndarray
    M: np.ndarray  # [m, n], the direction vectors m_j
    t: int  # iterations done


def lmmaes_init(mean: np.ndarray, sigma: float, params: LMMAParams) -> LMMAState:
    n = mean.shape[0]
    return LMMAState(np.array(mean, np.float64), float(sigma), np.zeros(n),
                     np.zeros((len(params.c_d), n)), 0)  # fmt: skip


def lmmaes_ask(
    rng: np.random.Generator, state: LMMAState, params: LMMAParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lines 6-10: the normals ``z`` ``[lambda, n]``, the directions ``d`` (``z`` passed
    through the first ``min(t, m)`` vectors, in order) and the candidates ``y + sigma d``."""
    z = rng.standard_normal((params.popsize, state.mean.shape[0]))
    d = z.copy()
    for j in range(min(state.t, len(params.c_d))):
        mj = state.M[j]
        d = (1 - params.c_d[j]) * d + params.c_d[j] * (d @ mj)[:, None] * mj[None, :]
    return z, d, state.mean + state.sigma * d


def lmmaes_tell(
    state: LMMAState, z: np.ndarray, d: np.ndarray, cost: np.ndarray, params: LMMAParams
) -> LMMAState:
    """Lines 11-16 from the candidates' costs: the ``mu`` best by cost (ties by index)."""
    best = np.argsort(cost, kind="stable")[: params.mu]
    w = params.weights
    zw, dw = w @ z[best], w @ d[best]
    cs = params.c_sigma
    p_sigma = (1 - cs) * state.p_sigma + np.sqrt(params.mu_w * cs * (2 - cs)) * zw
    cc = params.c_c[:, None]
    M = (1 - cc) * state.M + np.sqrt(params.mu_w * cc * (2 - cc)) * zw[None, :]
    mean = state.mean + state.sigma * dw  # c_m = 1
    n = state.mean.shape[0]
    sigma = state.sigma * np.exp(cs / 2 * (p_sigma @ p_sigma / n - 1))
    return LMMAState(mean, float(sigma), p_sigma, M, state.t + 1)


def lmmaes_evals_to_target(
    f: Callable[[np.ndarray], np.ndarray],
    n: int,
    sigma0: float,
    target: float,
    max_evals: int,
    seed: int,
) -> int:
    """Evaluations until the best cost so far is below ``target`` (``-1`` if not within
    ``max_evals``), starting from the origin; ``f`` maps ``[lambda, n]`` to ``[lambda]``."""
    params = lmmaes_params(n)
    rng = np.random.default_rng(seed)
    state = lmmaes_init(np.zeros(n), sigma0, params)
    evals = 0
    while evals + params.popsize <= max_evals:
        z, d, x = lmmaes_ask(rng, state, params)
        cost = f(x)
        evals += params.popsize
        if np.min(cost) < target:
            return evals
        state = lmmaes_tell(state, z, d, cost, params)
    return -1
