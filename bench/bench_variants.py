"""CMA-ES variants for larger networks: evaluations to a target (docs/protocol.md section 10).

Issue 41 asks for a limited-memory CMA-ES (LM-MA-ES) beside the full and separable kernels
"if measured worth it", and for the separable one by default above a documented size. On
brax an evaluation is a 1,000-step episode and the CMA-ES update a small part of an
iteration (protocol section 10 gives the measured shares), so the question is evaluations:
how many does each variant need where the full one is the paper's?

Each case is a fresh function per seed ``s`` (``--first-seed``, ``--seeds``) of dimension n
(``--dims``), its optimum ``x*`` drawn in [-1, 1]^n, every method starting at the origin
with step size 1 and ``lambda = 4 + floor(3 ln n)`` candidates:

* ``rotated``: ``f(x) = sum_i cond^{i/(n-1)} (R (x - x*))_i^2``, ``R`` a random rotation
  (`bench.bench_cmaes.ellipsoid_data`), ``cond`` = ``--cond``: the weights matter jointly;
* ``separable``: the same without ``R``: the control where the diagonal variant must do well.

Methods: ``full`` and ``diagonal`` are `eant2_jax.kernels.cmaes` (``Params.diagonal``; the
full one with the engine's lazy decomposition, ``lazy_eigen`` 0.5), float32, run from
``jax.random.key(s)``; ``lm-ma-es`` is `bench.lmmaes` (NumPy, float64, from the paper's
Algorithm 1, generator seed ``s``); ``evosax-lm-ma-es`` is evosax's ``LM_MA_ES`` as shipped
(its update of the direction vectors weights the candidates' normals in population order,
not by rank: ``update_M`` in ``evosax/algorithms/distribution_based/lm_ma_es.py``, 0.3.2).
A run counts the evaluations until its best cost is below ``--target`` (every candidate of
the last iteration counted), or never within ``--max-evals``.

A row gives the runs that reached the target, the median evaluations with a percentile
bootstrap 95% interval (10,000 resamples, key 0; a run that never reached counts as
infinite), the ratio of that median to ``full``'s on the same functions with its interval,
and the seconds the case took on this machine (not a claim: the methods run on different
engines). Run: ``python -m bench variants [--dims 32 128] [--seeds 10]``.
"""

from __future__ import annotations

import argparse
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.bench_cmaes import ellipsoid, ellipsoid_data
from bench.common import BenchInputError, Column, environment, markdown_table
from bench.field_stats import median_interval
from bench.lmmaes import lmmaes_evals_to_target, lmmaes_params
from eant2_jax.exploitation import default_popsize
from eant2_jax.kernels import cmaes

METHODS = ("full", "diagonal", "lm-ma-es", "evosax-lm-ma-es")
FUNCTIONS = ("rotated", "separable")
LAZY_EIGEN = 0.5  # ExploitConfig.lazy_eigen's default


def functions(kind: str, n: int, cond: float, seeds: list[int]) -> dict[str, np.ndarray]:
    """Per seed: rotation ``[S, n, n]`` (the identity for ``separable``), axis scales
    ``[S, n]`` and optimum ``[S, n]``, float64."""
    rots, scales, opts = [], [], []
    for s in seeds:
        rot, scale = ellipsoid_data(n, cond, s)
        rots.append(rot if kind == "rotated" else np.eye(n))
        scales.append(scale)
        opts.append(np.random.default_rng([s, n]).uniform(-1, 1, n))
    return {k: np.asarray(v, np.float64) for k, v in
            (("rot", rots), ("scale", scales), ("opt", opts))}  # fmt: skip


def cost(rot, scale, opt, x):
    """``f`` of candidates ``x`` ``[K, n]`` (NumPy or JAX arrays)."""
    return ellipsoid(rot, scale, x - opt[None, :])


def _until_target(start, step):
    """A jitted ``(seeds, rot, scale, opt, target, max_gens) -> generations to target``
    (``-1``: never), vmapped over the seeds. ``start(key)`` is a search's state from
    ``jax.random.key(seed)``, which also starts the loop's key; ``step(state, key, f)``
    returns ``(state, best cost of its candidates or so far, key)`` for costs ``f``."""

    def one(seed, rot, scale, opt, target, max_gens):
        f = functools.partial(cost, rot, scale, opt)

        def body(c):
            state, g, hit, key = c
            state, best, key = step(state, key, f)
            hit = jnp.where((hit < 0) & (best < target), g + 1, hit)
            return state, g + 1, hit, key

        key = jax.random.key(seed)
        init = (start(key), 0, -1, key)
        return jax.lax.while_loop(lambda c: (c[2] < 0) & (c[1] < max_gens), body, init)[2]

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None, None)))


@functools.cache
def _kernel_run(n: int, method: str):
    """`_until_target` of the library's kernel, and its popsize."""
    popsize = default_popsize(n)
    params = cmaes.default_params(n, popsize, diagonal=method == "diagonal")
    period = cmaes.eigen_period(params, LAZY_EIGEN)

    def step(state, key, f):
        key, sub = jax.random.split(key)
        x, state = cmaes.ask(sub, state, params)
        state = cmaes.tell(state, x, f(x), params, decompose=False)
        due = (state.generation % period) == 0
        state = jax.lax.cond(due, lambda s: cmaes.decompose(s, params), lambda s: s, state)
        return state, state.best_cost, key

    def start(key):
        return cmaes.init(jnp.zeros(n), 1.0, jnp.ones(n, bool), params)

    return _until_target(start, step), popsize


@functools.cache
def _evosax_run(n: int):
    """As `_kernel_run` for evosax's ``LM_MA_ES`` (its default parameters, step size 1)."""
    from evosax.algorithms import LM_MA_ES

    popsize = default_popsize(n)
    es = LM_MA_ES(popsize, jnp.zeros(n))
    params = es.default_params.replace(std_init=1.0)

    def step(state, key, f):
        key, k_ask, k_tell = jax.random.split(key, 3)
        x, state = es.ask(k_ask, state, params)
        cost_x = f(x)
        state, _ = es.tell(k_tell, x, cost_x, state, params)
        return state, jnp.min(cost_x), key

    def start(key):
        state = es.init(key, jnp.zeros(n), params)
        return jax.tree.map(lambda a: jnp.asarray(a, a.dtype), state)

    return _until_target(start, step), popsize


def evaluations(method: str, fn: dict[str, np.ndarray], seeds: list[int], target: float,
                max_evals: int) -> list[int]:  # fmt: skip
    """Evaluations to ``target`` per seed (``-1``: not within ``max_evals``)."""
    n = fn["opt"].shape[1]
    if method == "lm-ma-es":
        out = []
        for i, s in enumerate(seeds):
            f = functools.partial(cost, fn["rot"][i], fn["scale"][i], fn["opt"][i])
            out.append(lmmaes_evals_to_target(f, n, 1.0, target, max_evals, s))
        return out
    run, popsize = _evosax_run(n) if method == "evosax-lm-ma-es" else _kernel_run(n, method)
    with jax.numpy_rank_promotion("allow"):  # evosax broadcasts [n] against [popsize, n]
        gens = run(jnp.asarray(seeds), *(jnp.asarray(fn[k], jnp.float32) for k in ("rot",
                   "scale", "opt")), jnp.float32(target), max_evals // popsize)  # fmt: skip
    gens = np.asarray(gens)
    return [int(g) * popsize if g >= 0 else -1 for g in gens]


def _interval(values: list[int], reference: list[int] | None) -> tuple[float, ...]:
    """The median with its bootstrap interval, then (against ``reference``) the ratio of the
    medians with its interval; a run that never reached counts as infinite."""
    from eant2_jax.app.report_stats import bootstrap_interval, median

    def inf(v):
        return np.where(np.asarray(v) < 0, np.inf, np.asarray(v, np.float64))

    med = median_interval(inf(values))
    if reference is None:
        return med
    with np.errstate(invalid="ignore"):
        ratio = bootstrap_interval(
            [inf(values), inf(reference)], lambda a, b: median(a) / median(b)
        )
    return med + ratio


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    for n in args.dims:
        for kind in args.functions:
            fn = functions(kind, n, args.cond, seeds)
            full = None
            for method in args.methods:
                harness.log(f"variants: {kind} n={n} {method}")
                t0 = time.perf_counter()
                evals = evaluations(method, fn, seeds, args.target, args.max_evals)
                seconds = time.perf_counter() - t0
                full = evals if method == "full" else full
                stats = _interval(evals, None if method == "full" else full)
                row = {"function": kind, "n": n, "method": method, "evaluations": evals,
                       "reached": sum(e >= 0 for e in evals), "runs": len(evals),
                       "median": stats[0], "low": stats[1], "high": stats[2],
                       "seconds": seconds}  # fmt: skip
                if len(stats) == 6:
                    row.update(ratio=stats[3], ratio_low=stats[4], ratio_high=stats[5])
                payload["rows"].append(row)
                save(payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dims", type=int, nargs="+", default=[32, 128], help="n of each case")
    p.add_argument("--functions", nargs="+", default=list(FUNCTIONS), choices=FUNCTIONS)
    p.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        choices=METHODS,
        help="the ratios are to full's, which must then come first",
    )
    p.add_argument("--cond", type=float, default=1e4, help="the ellipsoids' condition number")
    p.add_argument("--target", type=float, default=1e-6, help="a run ends below this cost")
    p.add_argument("--max-evals", type=int, default=2_000_000, help="evaluations per run, at most")
    harness.run_options(p, seeds=10, first_seed=7100)  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.dims, args.seeds, args.max_evals, args.target = [32], 2, 60_000, 1e-3
    if "full" in args.methods and args.methods[0] != "full":
        raise BenchInputError("--methods: full, where given, must come first (the ratios')")
    if args.seeds < 1 or args.max_evals < 1 or args.cond < 1 or args.target <= 0:
        raise BenchInputError("--seeds and --max-evals must be >= 1, --cond >= 1, --target > 0")
    if "lm-ma-es" in args.methods or "evosax-lm-ma-es" in args.methods:
        for n in args.dims:
            try:
                lmmaes_params(n)
            except ValueError as e:
                raise BenchInputError(f"--dims {n}: {e}") from None
    elif min(args.dims) < 2:
        raise BenchInputError("--dims must be at least 2")


def _evals(v: float) -> str:
    return "never" if not np.isfinite(v) else f"{v:,.0f}"


def _render(payload: dict) -> str:
    def interval(r, a, lo, hi, fmt):
        if a not in r:
            return "—"
        return f"{fmt(r[a])} [{fmt(r[lo])}, {fmt(r[hi])}]"

    def ratio(v):  # nan: neither median finite
        return f"{v:.2f}x" if np.isfinite(v) else ("n/a" if np.isnan(v) else "inf")

    return markdown_table(payload["rows"], [
        Column("function", "function"),
        Column("n", "n"),
        Column("method", "method"),
        Column(lambda r: f"{r['reached']}/{r['runs']}", "reached"),
        Column(lambda r: interval(r, "median", "low", "high", _evals), "median evaluations [95%]"),
        Column(lambda r: interval(r, "ratio", "ratio_low", "ratio_high", ratio), "/ full [95%]"),
        Column(lambda r: f"{r['seconds']:.1f}", "s"),
    ])  # fmt: skip


SUITE = harness.Suite(
    name="variants",
    title="CMA-ES variants for larger networks",
    description=__doc__,
    options=_options,
    run=run,
    render=_render,
    prepare=_prepare,
)

main = SUITE.main
