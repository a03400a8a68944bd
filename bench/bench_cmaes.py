"""CMA-ES iterations per second for S structures at once: the batched masked engine vs loops.

One *iteration* advances every one of the S structures by one CMA-ES generation (ask,
evaluate ``popsize`` candidates, tell). The structures have different dimensions (spread over
``--dims``, default 20..200) and each minimises its own rotated ellipsoid
``f(x) = sum_i cond^{i/(n-1)} (R x)_i^2`` (``--cond``, default 1e6). Engines:

* ``batched-P<size>``: :mod:`eant2_jax.kernels.cmaes`, all S structures padded into one size
  (default 256) and advanced by ONE jit-compiled ``vmap(ask) -> evaluate -> vmap(tell)``;
* ``batched-buckets``: the same, the structures grouped into power-of-two buckets
  (32, 64, 128, 256), one compiled step per bucket per iteration (dispatched asynchronously);
* ``batched-P<size>-scan<K>``: as ``batched-P<size>``, K iterations per call in ``lax.scan``
  (how the exploitation engine runs); reported per iteration;
* ``batched-P<size>-scan<K>-lazy<F>``: as the scan variant with the lazy update of the
  engine's ``ExploitConfig.lazy_eigen = F`` (``--lazy-eigen``): ``tell`` keeps the last
  decomposition, and a structure's C is decomposed on the iterations that are multiples of
  its period, the largest power of two within ``ceil(F / (n (c_1 + c_mu)))`` (pycma's
  interval at F = 0.5), the batched ``eigh`` running only where some structure is due, by
  the engine's own code;
* ``evosax-loop``: a Python loop over the S structures, each stepped by a jit-compiled
  evosax ``CMA_ES`` step (ask, evaluate, tell) compiled once per distinct dimension;
* ``pycma``: a Python loop over S ``cma.CMAEvolutionStrategy`` instances (NumPy, CPU), the
  reference implementation (``pip install -e ".[bench]"``).

All engines use the same popsize (``--popsize``, default ``4 + floor(3 ln 200) = 19``, the
default of the largest dimension) so that an iteration does the same work. For each engine
and S: ``compile_s`` is the first iteration minus a steady one (tracing + XLA compilation, 0
for pycma), ``median_s`` the median of ``--repeats`` timed iterations after ``--warmup``
untimed ones, each waiting for the device (``block_until_ready``).

Run from the repository root::

    python -m bench cmaes                       # S = 1, 8, 32, 128 (sized for a GPU)
    python -m bench cmaes --structures 1 8 32   # a smaller sweep
    python -m bench cmaes --quick --out /tmp/c.json
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    environment,
    evosax_start,
    markdown_table,
    time_call,
)
from eant2_jax.kernels import cmaes

BUCKETS = (32, 64, 128, 256)


# ----------------------------------------------------------------------------- the problems
def dimensions(s_count: int, grid: Sequence[int]) -> list[int]:
    """Dimensions of S structures: evenly over ``grid`` (S = 1 takes its middle value)."""
    k = len(grid)
    return [int(grid[min(int((s + 0.5) * k / s_count), k - 1)]) for s in range(s_count)]


def ellipsoid_data(n: int, cond: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``[n, n]`` and axis scales ``[n]`` of a rotated ellipsoid (float32)."""
    rot, _ = np.linalg.qr(np.random.default_rng(seed).standard_normal((n, n)))
    scale = cond ** (np.arange(n) / max(n - 1, 1))
    return rot.astype(np.float32), scale.astype(np.float32)


def ellipsoid(rot: jax.Array, scale: jax.Array, x: jax.Array) -> jax.Array:
    """Costs ``[K]`` of candidates ``x`` ``[K, n]``; padded rows/scales of 0 ignore padding."""
    return ((x @ rot.T) ** 2) @ scale


def _pad(a: np.ndarray, size: int) -> np.ndarray:
    out = np.zeros((size,) * a.ndim, a.dtype)
    out[tuple(slice(0, d) for d in a.shape)] = a
    return out


# ------------------------------------------------------------------------------- engines
def batched_engine(
    dims: Sequence[int],
    size: int,
    popsize: int,
    cond: float,
    seed: int,
    chunk: int = 1,
    lazy: float = 0.0,
) -> Callable[[], jax.Array]:
    """One iteration (or ``chunk`` in a scan) of S structures padded into ``size``; with
    ``lazy`` > 0 the lazy eigendecomposition of the exploitation engine."""
    from eant2_jax.exploitation import lazy_decompose  # the engine's own lazy step

    s_count = len(dims)
    data = [ellipsoid_data(n, cond, seed + s) for s, n in enumerate(dims)]
    rot = jnp.asarray(np.stack([_pad(r, size) for r, _ in data]))
    scale = jnp.asarray(np.stack([_pad(a, size) for _, a in data]))
    mask = np.arange(size)[None, :] < np.asarray(dims)[:, None]

    @jax.jit
    def setup(mask):  # one compilation instead of many eager vmapped ops
        params = jax.vmap(lambda n: cmaes.default_params(n, popsize))(jnp.sum(mask, axis=1))
        states = jax.vmap(lambda m, p: cmaes.init(m.astype(jnp.float32), 1.0, m, p))(mask, params)
        return params, states

    params, states = setup(mask)
    keys = jax.random.split(jax.random.key(seed), s_count)

    def one(carry, params, it):
        states, age = carry
        ks = jax.vmap(jax.random.fold_in, in_axes=(0, None))(keys, it)
        xs, states = jax.vmap(cmaes.ask)(ks, states, params)
        costs = jax.vmap(ellipsoid)(rot, scale, xs)
        tell = functools.partial(cmaes.tell, decompose=not lazy)
        states = jax.vmap(tell)(states, xs, costs, params)
        if lazy:
            every = jnp.ones(s_count, bool)
            states, age = lazy_decompose(states, params, age, every, it, lazy)
        return states, age

    @jax.jit
    def step(carry, params, it):
        if chunk == 1:
            return one(carry, params, it)
        body = lambda i, s: one(s, params, i)  # noqa: E731
        return jax.lax.fori_loop(it * chunk, (it + 1) * chunk, body, carry)

    holder = {"carry": (states, jnp.zeros(s_count, jnp.int32)), "it": 0}

    def iteration():
        holder["carry"] = step(holder["carry"], params, holder["it"])
        holder["it"] += 1
        return holder["carry"][0].sigma

    return iteration


def bucketed_engine(
    dims: Sequence[int], popsize: int, cond: float, seed: int
) -> Callable[[], list[jax.Array]]:
    """One iteration: one compiled batched step per power-of-two bucket."""
    groups: dict[int, list[int]] = {}
    for n in dims:
        groups.setdefault(next(b for b in BUCKETS if b >= n), []).append(n)
    engines = [
        batched_engine(g, size, popsize, cond, seed + 1000 * i)
        for i, (size, g) in enumerate(sorted(groups.items()))
    ]

    def iteration():
        return [e() for e in engines]  # asynchronous dispatch: the buckets overlap

    return iteration


def evosax_loop_engine(
    dims: Sequence[int], popsize: int, cond: float, seed: int
) -> Callable[[], list[jax.Array]]:
    """A Python loop over S evosax CMA-ES states, one compiled step per distinct dimension."""
    from evosax.algorithms import CMA_ES

    steps: dict[int, Callable] = {}
    for n in sorted(set(dims)):
        es = CMA_ES(popsize, jnp.zeros(n))
        es_params = jax.jit(lambda es=es: es.default_params)()  # one compilation, not eager ops

        def step(state, key, rot, scale, es=es, es_params=es_params):
            k1, k2 = jax.random.split(key)
            # evosax broadcasts [n] against [popsize, n]; allow it whatever the global config.
            with jax.numpy_rank_promotion("allow"):
                x, state = es.ask(k1, state, es_params)
                state, _ = es.tell(k2, x, ellipsoid(rot, scale, x), state, es_params)
            return state

        steps[n] = (es, es_params, jax.jit(step))

    structures = []
    for s, n in enumerate(dims):
        es, es_params, step = steps[n]
        rot, scale = (jnp.asarray(a) for a in ellipsoid_data(n, cond, seed + s))
        state = evosax_start(es, jax.random.key(seed), jnp.ones(n), es_params)
        structures.append([step, state, rot, scale, jax.random.key(seed + s)])

    holder = {"it": 0}

    def iteration():
        out = []
        for st in structures:
            step, state, rot, scale, key = st
            st[1] = step(state, jax.random.fold_in(key, holder["it"]), rot, scale)
            out.append(st[1].std)
        holder["it"] += 1
        return out

    return iteration


def pycma_engine(
    dims: Sequence[int], popsize: int, cond: float, seed: int
) -> Callable[[], list[float]]:
    """A Python loop over S pycma instances (NumPy on the CPU)."""
    import cma

    structures = []
    for s, n in enumerate(dims):
        rot, scale = (a.astype(np.float64) for a in ellipsoid_data(n, cond, seed + s))
        opts = {"popsize": popsize, "seed": seed + s + 1, "verbose": -9, "maxiter": 10**9}
        es = cma.CMAEvolutionStrategy(np.ones(n), 1.0, opts)
        structures.append((es, rot, scale))

    def iteration():
        for es, rot, scale in structures:
            x = np.asarray(es.ask())
            es.tell(list(x), list(((x @ rot.T) ** 2) @ scale))
        return [es.sigma for es, _, _ in structures]

    return iteration


# ------------------------------------------------------------------------------ the sweep
COLUMNS = [
    Column("engine", "engine"),
    Column("S", "S"),
    Column(lambda r: f"{r['dim_min']}-{r['dim_max']}", "dims"),
    Column("padding", "padded to"),
    Column("popsize", "popsize"),
    Column("compile_s", "compile s", "{:.2f}"),
    Column(lambda r: r["median_s"] * 1e3, "ms / iteration", "{:.3g}"),
    Column(lambda r: r["min_s"] * 1e3, "min ms", "{:.3g}"),
    Column("iters_per_s", "iterations/s", "{:.3g}"),
    Column("structure_iters_per_s", "structure-iterations/s", "{:.3g}"),
    Column("speedup_vs_evosax_loop", "x evosax loop", "{:.2f}"),
    Column("speedup_vs_pycma", "x pycma", "{:.2f}"),
]


def _options(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--structures", type=int, nargs="+", default=None, help="values of S")
    ap.add_argument(
        "--dims", type=int, nargs="+", default=None, help="dimension grid the S structures use"
    )
    ap.add_argument("--pad", type=int, default=None, help="common padded size (default 256)")
    ap.add_argument("--popsize", type=int, default=None, help="default 4 + 3 ln(max dim)")
    ap.add_argument("--cond", type=float, default=1e6, help="ellipsoid condition number")
    ap.add_argument("--chunk", type=int, default=10, help="K of the scan variant (0: skip)")
    ap.add_argument("--lazy-eigen", type=float, default=0.5,
                    help="F of the lazy scan variant (engine 'lazy')")  # fmt: skip
    ap.add_argument(
        "--engines",
        nargs="+",
        default=None,
        choices=["batched", "buckets", "scan", "lazy", "evosax", "pycma"],
        help="engines to run (default all)",
    )
    harness.run_options(ap, seed=0)


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        # Each batched engine is one XLA compilation (~2 s on a CPU), each distinct dimension
        # one evosax compilation: the smoke run keeps one of each.
        args.structures = args.structures or [2]
        args.dims = args.dims or [6]
        args.pad = args.pad or 8
        args.chunk = min(args.chunk, 2)
        args.warmup = min(args.warmup, 1)
        args.repeats = min(args.repeats, 3)
        args.engines = args.engines or ["batched", "evosax", "pycma"]
    else:
        args.structures = args.structures or [1, 8, 32, 128]
        args.dims = args.dims or list(range(20, 201, 20))
        args.pad = args.pad or 256
        args.engines = args.engines or ["batched", "buckets", "scan", "lazy", "evosax", "pycma"]
    if max(args.dims) > args.pad:
        raise BenchInputError(
            f"--pad {args.pad} is smaller than the largest dimension {max(args.dims)}"
        )
    args.popsize = args.popsize or 4 + int(math.floor(3 * math.log(max(args.dims))))
    if args.chunk <= 0:
        args.engines = [e for e in args.engines if e not in ("scan", "lazy")]
    if args.lazy_eigen <= 0:
        raise BenchInputError(f"--lazy-eigen must be > 0, got {args.lazy_eigen}")


def _cases(args: argparse.Namespace, dims: list[int]) -> list[tuple[str, str, Callable]]:
    p, k, seed = args.popsize, args.chunk, args.seed
    buckets = sorted({next(b for b in BUCKETS if b >= n) for n in dims})
    makers = {
        "batched": (
            f"batched-P{args.pad}",
            str(args.pad),
            lambda: batched_engine(dims, args.pad, p, args.cond, seed),
        ),
        "buckets": (
            "batched-buckets",
            "/".join(map(str, buckets)),
            lambda: bucketed_engine(dims, p, args.cond, seed),
        ),
        "scan": (
            f"batched-P{args.pad}-scan{k}",
            str(args.pad),
            lambda: batched_engine(dims, args.pad, p, args.cond, seed, chunk=k),
        ),
        "lazy": (
            f"batched-P{args.pad}-scan{k}-lazy{args.lazy_eigen:g}",
            str(args.pad),
            lambda: batched_engine(
                dims, args.pad, p, args.cond, seed, chunk=k, lazy=args.lazy_eigen
            ),  # fmt: skip
        ),
        "evosax": ("evosax-loop", "none", lambda: evosax_loop_engine(dims, p, args.cond, seed)),
        "pycma": ("pycma", "none", lambda: pycma_engine(dims, p, args.cond, seed)),
    }
    if max(dims) > BUCKETS[-1]:
        makers.pop("buckets")
    cases = [makers[e] for e in args.engines if e in makers]
    return cases


def _load() -> float | None:
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover - not available on every platform
        return None


def _payload(args: argparse.Namespace, env: dict, rows: list[dict], total_s: float) -> dict:
    env = dict(env)
    load_start = env.pop("loadavg_1m_start", None)
    return {
        "benchmark": "cmaes",
        "unit": "iterations per second (one CMA-ES generation of every one of the S structures)",
        **env,
        "config": {
            "quick": args.quick,
            "structures": args.structures,
            "dims_grid": args.dims,
            "pad": args.pad,
            "buckets": list(BUCKETS),
            "popsize": args.popsize,
            "problem": f"rotated ellipsoid, condition {args.cond:g}, one rotation per structure",
            "chunk": args.chunk,
            "engines": args.engines,
            "dtype": "float32 (pycma: float64)",
            "warmup": args.warmup,
            "repeats": args.repeats,
            "seed": args.seed,
        },
        # CPU timings are only as good as the machine is idle: record how busy it was.
        "host": {
            "cpu_count": os.cpu_count(),
            "loadavg_1m_start": load_start,
            "loadavg_1m_end": _load(),
        },
        "total_s": total_s,
        "rows": rows,
    }


def _add_speedups(rows: list[dict]) -> None:
    for r in rows:
        for name, ref in (("evosax_loop", "evosax-loop"), ("pycma", "pycma")):
            base = next((b for b in rows if b["engine"] == ref and b["S"] == r["S"]), None)
            r[f"speedup_vs_{name}"] = (
                r["iters_per_s"] / base["iters_per_s"] if base is not None else None
            )


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """Run the sweep described by parsed arguments; return the JSON payload."""
    env = environment() | {"loadavg_1m_start": _load()}
    rows: list[dict] = []
    t_start = time.perf_counter()
    for s_count in args.structures:
        dims = dimensions(s_count, args.dims)
        for engine, padding, make in _cases(args, dims):
            iteration = make()
            timing = time_call(iteration, warmup=args.warmup, repeats=args.repeats)
            k = args.chunk if "-scan" in engine else 1
            per_iter = timing.median_s / k
            row = {
                "engine": engine,
                "S": s_count,
                "dims": dims,
                "dim_min": min(dims),
                "dim_max": max(dims),
                "dim_mean": float(np.mean(dims)),
                "padding": padding,
                "popsize": args.popsize,
                "iterations_per_call": k,
                "first_call_s": timing.first_call_s,
                "compile_s": 0.0 if engine == "pycma" else timing.compile_s,
                "median_s": per_iter,
                "min_s": timing.min_s / k,
                "times_s": list(timing.times_s),
                "iters_per_s": 1.0 / per_iter,
                "structure_iters_per_s": s_count / per_iter,
                "evals_per_s": s_count * args.popsize / per_iter,
            }
            rows.append(row)
            _add_speedups(rows)
            harness.log(
                f"[cmaes] {engine} S={s_count} dims {min(dims)}-{max(dims)}: "
                f"compile {row['compile_s']:.2f}s, {per_iter * 1e3:.3g} ms/iteration"
            )
            save(_payload(args, env, rows, time.perf_counter() - t_start))
    _add_speedups(rows)
    return _payload(args, env, rows, time.perf_counter() - t_start)


def render(payload: dict[str, Any]) -> str:
    """The problem and the host's load, then the table."""
    cfg, host = payload["config"], payload["host"]
    head = (
        f"{cfg['problem']}; popsize {cfg['popsize']}; median of {cfg['repeats']} iterations. "
        f"Host: {host['cpu_count']} CPUs, 1-min load average {host['loadavg_1m_start']} at "
        f"start, {host['loadavg_1m_end']} at end.\n\n"
    )
    return head + markdown_table(payload["rows"], COLUMNS)


SUITE = harness.Suite(
    name="cmaes",
    title="CMA-ES throughput",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
    repeats=7,
    min_repeats=3,
    warmup=2,
)

main = SUITE.main
