"""The engine's state: S CMA-ES runs side by side, their records, and the updates of their
decompositions (`eant2_jax.exploitation` is the engine's overview).

Per-structure bookkeeping on device, every iteration: step size sigma, its running mean
sigma_bar (paper eq. 5), cond(C), best cost and weights so far, function evaluations, and the
number of non-finite costs. A structure's stop reason is one of ``STOP_REASONS``.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from . import distributed, pruning, pytree
from .config import ExploitConfig
from .kernels import cmaes
from .rows import where_rows

__all__ = [
    "PRUNE_AT",
    "RESUME_AFTER",
    "STOP_REASONS",
    "ExploitState",
    "StepRecord",
    "cond_rare",
    "decomposed",
    "default_popsize",
    "halted",
    "init",
    "is_lazy",
    "lazy_decompose",
    "record",
    "smoothing_for",
]

(RUNNING, BUDGET, SIGMA_COLLAPSE, STAGNATION, PADDING, TARGET, GROWTH, COND_BOUND, HALTED,
 FLAT) = range(10)  # fmt: skip
STOP_REASONS = {
    RUNNING: "running",
    BUDGET: "iteration budget",
    SIGMA_COLLAPSE: "sigma collapse",
    STAGNATION: "no improvement",
    PADDING: "padding",
    TARGET: "target reached",
    GROWTH: "sigma growth",
    COND_BOUND: "condition bound",
    HALTED: "halted",
    FLAT: "flat cost",
}
# Stops after which a converged CMA-ES may still prune (prune_at_stop), and those of them
# after which an accepted removal lets the structure run on.
PRUNE_AT = (BUDGET, SIGMA_COLLAPSE, STAGNATION, COND_BOUND, FLAT)
RESUME_AFTER = (SIGMA_COLLAPSE, STAGNATION, COND_BOUND, FLAT)


def default_popsize(n: int) -> int:
    """CMA-ES default population size ``4 + floor(3 ln n)`` (Hansen's tutorial, Table 1)."""
    return 4 + int(math.floor(3 * math.log(max(int(n), 1))))


def smoothing_for(n):
    """The smoothing constant g of sigma_bar (paper eq. 5; the text calls it gamma).

    The paper asks for g in [0.01, 0.025], smoothing more strongly (smaller g) when the
    dimension is large. Rule: ``g(n) = 0.01 + 0.015 * min(1, 10 / n)`` — 0.025 up to 10
    parameters, 0.0175 at 20, 0.0115 at 100, tending to 0.01. Works on traced ``n``.
    """
    n = jnp.maximum(jnp.asarray(n, jnp.float32), 1.0)
    return 0.01 + 0.015 * jnp.minimum(1.0, 10.0 / n)


@pytree.dataclass
class ExploitState:
    """Batched state of S structures (every leaf has leading dim S, except ``tick``).

    Attributes:
      cma: per-structure CMA-ES state (`eant2_jax.kernels.cmaes.State`).
      params: per-structure CMA-ES hyper-parameters (from each structure's own dimension).
      key: ``[S]`` each structure's PRNG key.
      sigma_bar: ``[S]`` running mean of sigma, paper eq. (5).
      g: ``[S]`` smoothing constant of sigma_bar.
      iteration: ``[S]`` CMA-ES iterations done, a pruning attempt's re-fit included (they
        count against ``max_iters``).
      evals: ``[S]`` cost evaluations spent.
      since_improve: ``[S]`` iterations since the best cost last improved.
      nonfinite: ``[S]`` NaN/inf costs seen in total.
      stop: ``[S]`` 0 while running, else the reason (see ``STOP_REASONS``).
      down_run: ``[S]`` consecutive iterations in which sigma_bar decreased.
      bound_run: ``[S]`` consecutive iterations in which cond(C) sat at its bound.
      flat_run: ``[S]`` consecutive iterations in which every candidate's cost lay within
        ``tolfun`` of the best cost so far.
      prune_attempts, prune_accepted: ``[S]`` pruning attempts made and accepted.
      tick: ``[]`` engine iterations (the task's key is folded with it).
      attempt: the pruning attempts in progress (`eant2_jax.pruning.Attempt`); None
        without a pruner.
    """

    cma: cmaes.State
    params: cmaes.Params
    key: jax.Array
    sigma_bar: jax.Array
    g: jax.Array
    iteration: jax.Array
    evals: jax.Array
    since_improve: jax.Array
    nonfinite: jax.Array
    stop: jax.Array
    down_run: jax.Array
    bound_run: jax.Array
    flat_run: jax.Array
    prune_attempts: jax.Array
    prune_accepted: jax.Array
    tick: jax.Array
    eigen_age: jax.Array
    attempt: pruning.Attempt | None = None


@pytree.dataclass
class StepRecord:
    """What one engine iteration records of every structure (``[S]`` leaves; after
    `run`, ``[iterations, S]`` NumPy arrays).

    Attributes:
      sigma, sigma_bar, cond: step size, its running mean (eq. 5) and cond(C).
      cond_bounded: the ``max_condition`` bound clipped an eigenvalue this iteration.
      best_cost: best cost so far.
      evaluations: cost evaluations spent so far.
      nonfinite: NaN/inf costs seen in this iteration.
      running: the structure ran this iteration (rows after a stop repeat its final values).
      phase: what it ran: a CMA-ES iteration (``pruning.NORMAL``), the evaluation of a
        pruning attempt's shifted means (``TRIAL``) or an iteration of its re-fit (``REFIT``).
      prune: the pruning attempt decided in this iteration
        (`eant2_jax.pruning.AttemptRecord`); None without a pruner.
    """

    sigma: jax.Array
    sigma_bar: jax.Array
    cond: jax.Array
    cond_bounded: jax.Array
    best_cost: jax.Array
    evaluations: jax.Array
    nonfinite: jax.Array
    running: jax.Array
    phase: jax.Array
    prune: pruning.AttemptRecord | None = None

    def structure(self, s: int, iterations: int | None = None) -> StepRecord:
        """The history of structure ``s`` (host side, after `run`): its first
        ``iterations`` engine iterations, by default up to its last running one."""
        if iterations is None:
            ran = np.flatnonzero(np.asarray(self.running)[:, s])
            iterations = int(ran[-1]) + 1 if ran.size else 0
        return jax.tree.map(lambda a: a[:iterations, s], self)


def init(
    keys: jax.Array,
    mean: jax.Array,
    mask: jax.Array,
    config: ExploitConfig,
    *,
    popsize: int,
    active: jax.Array | None = None,
    cov: jax.Array | None = None,
    sigma: jax.Array | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> ExploitState:
    """Start S CMA-ES runs.

    Args:
      keys: ``[S]`` one PRNG key per structure (a structure's trajectory depends only on it).
      mean: ``[S, P]`` initial weights (padded entries ignored).
      mask: ``[S, P]`` bool, valid coordinates of each structure.
      config: the engine's configuration.
      popsize: candidates per iteration (static; the same for all structures).
      active: ``[S]`` bool, False for padding rows that must never run.
      cov: optional ``[S, P, P]`` initial covariance matrices (a warm start: only the valid
        block is read; it is symmetrised and decomposed, its condition bounded as in every
        iteration). Default: ``C = I``.
      sigma: optional ``[S]`` initial step sizes (default: ``config.sigma0``); given with
        ``cov``.
      mesh: make the state on this device mesh, each device its own structures (split as
        `eant2_jax.distributed.place` splits); ``mean`` and ``mask`` placed so beforehand
        (`eant2_jax.compiler.compile_genomes`' mesh), the other arguments placed here.

    Returns:
      The `ExploitState`.
    """
    if config.dtype == "float64" and not jax.config.jax_enable_x64:
        raise ValueError(
            "ExploitConfig.dtype is 'float64' but JAX's x64 mode is off: call "
            "eant2_jax.enable_x64() first (or set JAX_ENABLE_X64=1)"
        )
    mean = jnp.asarray(mean, config.dtype)
    if active is None:
        active = jnp.ones(mean.shape[0], bool)
    if (cov is None) != (sigma is None):
        raise ValueError("a warm start needs both cov and sigma")
    if cov is not None:  # device_put: jnp.asarray would compile a program per new shape
        dtype = np.dtype(config.dtype)
        put = jax.device_put if mesh is None else functools.partial(distributed.shard, mesh=mesh)
        cov, sigma = put((np.asarray(cov, dtype), np.asarray(sigma, dtype)))
    if mesh is not None:  # each device starts its own rows
        keys, active = distributed.shard((keys, active), mesh)
    return _init(
        keys, mean, jnp.asarray(mask, bool), jnp.asarray(active, bool), config, popsize,
        cov, sigma, mesh,
    )  # fmt: skip


# One program per batch shape: run op by op, the ~40 small operations of ``init`` would each
# compile a program of their own for every new bucket and dispatch one by one in every
# generation (docs/design.md, "CMA-ES initialisation is one program").
@functools.partial(jax.jit, static_argnames=("popsize", "mesh"))
def _init(
    keys,
    mean,
    mask,
    active,
    config: ExploitConfig,
    popsize: int,
    cov=None,
    sigma=None,
    mesh=None,
) -> ExploitState:
    n = jnp.sum(mask, axis=-1)
    make_params = functools.partial(
        cmaes.default_params,
        popsize=popsize,
        max_condition=config.max_condition,
        dtype=mean.dtype,
        diagonal=config.covariance == "diagonal",
    )
    # Padding rows have n = 0; give them n = 1 so their (unused) constants stay finite.
    params = jax.vmap(make_params)(jnp.maximum(n, 1))
    cma = jax.vmap(cmaes.init, in_axes=(0, None, 0, 0))(mean, config.sigma0, mask, params)
    s = mean.shape[0]
    if cov is None:
        sigma = jnp.full(s, config.sigma0, mean.dtype)
    else:  # a warm start: the given C and sigma, decomposed as tell would
        cma = jax.vmap(cmaes.decompose)(cma.replace(C=cov, sigma=sigma), params)
    smoothing = config.smoothing
    g = smoothing_for(n) if smoothing is None else jnp.full(s, smoothing)
    zeros = jnp.zeros(s, jnp.int32)
    st = ExploitState(
        cma=cma,
        params=params,
        key=keys,
        sigma_bar=sigma,
        g=g.astype(mean.dtype),
        iteration=zeros,
        evals=zeros,
        since_improve=zeros,
        nonfinite=zeros,
        stop=jnp.where(active, RUNNING, PADDING).astype(jnp.int32),
        down_run=zeros,
        bound_run=zeros,
        flat_run=zeros,
        prune_attempts=zeros,
        prune_accepted=zeros,
        tick=jnp.asarray(0, jnp.int32),
        eigen_age=zeros,
        attempt=None
        if config.pruner == "none"
        else pruning.Attempt.idle(cma, params, config.prune_candidates),
    )
    return distributed.constrain(st, mesh, s)


def record(st: ExploitState, running, phase, nonfinite, prune) -> StepRecord:
    """The per-iteration record of a state."""
    return StepRecord(
        sigma=st.cma.sigma,
        sigma_bar=st.sigma_bar,
        cond=st.cma.cond,
        cond_bounded=st.cma.cond_bounded & running,
        best_cost=st.cma.best_cost,
        evaluations=st.evals,
        nonfinite=nonfinite,
        running=running,
        phase=phase,
        prune=prune,
    )


@jax.jit
def halted(st: ExploitState) -> ExploitState:
    """The state with every running structure stopped (reason ``HALTED``).

    A structure in the middle of a pruning attempt ends as if the attempt had been
    rejected: during a re-fit the state from before the attempt is restored (during the
    trial evaluation the CMA-ES state has not changed yet). Its evaluations stay counted.
    """
    running = st.stop == RUNNING
    att = st.attempt
    if att is not None:
        refit = running & (att.phase == pruning.REFIT)
        st = st.replace(
            cma=where_rows(refit, att.saved_cma, st.cma),
            params=where_rows(refit, att.saved_params, st.params),
            attempt=att.replace(phase=jnp.where(running, pruning.NORMAL, att.phase)),
        )
    return st.replace(stop=jnp.where(running, HALTED, st.stop).astype(st.stop.dtype))


def cond_rare(pred, rare: Callable, usual: Callable, *operands):
    """``jax.lax.cond(pred, rare, usual, *operands)`` for a ``usual`` branch that passes
    (most of) its operands through unchanged.

    XLA elided the copies of a passthrough branch only where it is a conditional's first
    branch; in the second place every operand it passed through was copied (one GPU kernel
    each, about 50 per engine iteration of the servo program) on every call, whichever
    branch ran (openxla/xla#46314, fixed in later XLA; the order here costs nothing
    there). Which branch is first depends on the backend: XLA:GPU makes a two-branch
    conditional its predicated form, the true branch first, so there the predicate is
    negated; XLA:CPU keeps the indexed form, ``lax.cond``'s false branch first. Only the
    branch of the platform the program is lowered for is compiled.
    """

    def first_true(*ops):  # XLA:GPU makes the predicated form
        return jax.lax.cond(jnp.logical_not(pred), usual, rare, *ops)

    def first_false(*ops):  # XLA:CPU keeps the indexed one, ``lax.cond``'s false branch first
        return jax.lax.cond(pred, rare, usual, *ops)

    return jax.lax.platform_dependent(
        *operands, cuda=first_true, rocm=first_true, default=first_false
    )


def decomposed(cma: cmaes.State, params: cmaes.Params, rows: jax.Array) -> cmaes.State:
    """``cma`` with the ``rows`` structures' C decomposed afresh (one batched eigh)."""
    return where_rows(rows, jax.vmap(cmaes.decompose)(cma, params), cma)


def decompose_rows(cma: cmaes.State, params: cmaes.Params, rows: jax.Array) -> cmaes.State:
    """`decomposed`, run only when a row asks for it."""
    return cond_rare(jnp.any(rows), lambda c: decomposed(c, params, rows), lambda c: c, cma)


def is_lazy(config: ExploitConfig) -> bool:
    """Whether the engine runs the lazy update: ``lazy_eigen`` > 0 with a full covariance (a
    diagonal run's spectrum costs O(P) and is always fresh: `kernels.sepcmaes`)."""
    return config.lazy_eigen > 0 and config.covariance == "full"


def lazy_decompose(
    cma: cmaes.State,
    params: cmaes.Params,
    age: jax.Array,
    updated: jax.Array,
    tick: jax.Array,
    factor: float,
) -> tuple[cmaes.State, jax.Array]:
    """The lazy update (``ExploitConfig.lazy_eigen``): ``(cma, age)`` after decomposing the
    ``updated`` structures that are due. ``age`` ``[S]`` counts each structure's C updates
    since its last decomposition, ``tick`` the engine iterations.

    A structure is due on the ticks that are multiples of its period
    (`kernels.cmaes.eigen_period`, a power of two within pycma's interval), so the due
    structures of a batch come together and the one batched ``eigh`` runs only on the
    multiples of the smallest period: every 2nd tick or less often at pycma's factor. Per
    structure phases (due once ``age`` reaches the interval) made some structure of a
    mixed batch due on nearly every tick. A structure that missed its tick (not updated
    then, e.g. scoring a pruning trial) or that restarted its age off the grid (a pruning
    attempt decomposes afresh) is due again once ``age`` reaches its period.
    """
    age = age + updated
    period = jax.vmap(cmaes.eigen_period, in_axes=(0, None))(params, factor)
    due = updated & ((tick % period == 0) | (age >= period))
    return decompose_rows(cma, params, due), jnp.where(due, 0, age)
