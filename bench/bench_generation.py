"""Whole EANT2 generations on the servo task, pruning overhead, and scaling.

Four parts, each optional:

* ``generation``: an EANT2 run (default 20 structures, 1023 moves, kinematic mode) for a few
  generations; per generation its wall time, evaluations, moves per second and the number of
  XLA compilations, counted through ``jax.monitoring``. After the warm-up generations the
  compilations must stop growing beyond one per new padding bucket.
* ``pruning``: the cost of one pruning attempt (every structure tries, batched) relative to
  one CMA-ES iteration of the same batch.
* ``scaling``: one exploitation batch of random genomes for a fixed number of iterations,
  against the number of structures, the number of moves and the network size (without a
  pruner unless ``--scaling-pruner`` names one; ``--lazy-eigen`` applies).
* ``eigh``: one batched decomposition of S covariances of P x P, as the engine's lazy update
  and a pruning attempt run it (``vmap`` of `eant2_jax.kernels.cmaes.eigen`, the
  eigendecomposition with its masking and condition bound): milliseconds per call, each call
  waiting for the device, against S and P (``--eigh-structures``, ``--eigh-genes``; not in
  the default parts). On a GPU JAX's ``eigh`` calls cuSOLVER (Jacobi up to P = 32,
  ``syevd`` above); on an H100 a call cost about the same whatever S (docs/benchmarks.md).

Run: ``python -m bench generation [--parts generation,pruning,scaling,eigh] [--quick]``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import Column, CompileClock, environment, random_population, time_call
from eant2_jax import exploitation as ex
from eant2_jax import loop, tasks, tuning
from eant2_jax.kernels import cmaes


def bench_generations(args, clock: CompileClock) -> list[dict]:
    if args.task == "servo":
        task = tasks.make("servo", mode=args.mode, n_starts=args.moves)
    else:
        task = tasks.make(args.task)
    # Record the padding bucket of every exploitation batch (wrapping the handover's compiler).
    buckets: list[tuple] = []
    compile_batch = tuning.compile_genomes

    def recording(*a, **k):
        batch = compile_batch(*a, **k)
        buckets.append((batch.bucket.genes, batch.bucket.neurons, batch.bucket.sweeps))
        return batch

    tuning.compile_genomes = recording
    config = loop.EANT2Config(
        population=args.population,
        exploit=ex.ExploitConfig(
            max_iters=args.max_iters, pruner=args.pruner, lazy_eigen=args.lazy_eigen
        ),
    )
    rows: list[dict] = []
    marks = {"compiles": clock.compiles, "t": time.perf_counter()}

    def on_event(event):
        if event["event"] != "generation":
            return
        now = time.perf_counter()
        rows.append(
            {
                "generation": event["generation"],
                "seconds": now - marks["t"],
                "exploited": event["exploited"],
                "evaluations": event["evaluations"],
                "compiles": clock.compiles - marks["compiles"],
                "best_cost": event["best_cost"],
                "best_size": event["best_size"],
                "bucket": buckets[-1] if buckets else None,
                "buckets_so_far": len(set(buckets)),
            }
        )
        marks["t"], marks["compiles"] = now, clock.compiles

    loop.run(
        task,
        key=jax.random.key(args.seed),
        config=config,
        generations=args.generations,
        callback=on_event,
    )
    prev = 0
    for r in rows:
        r["new_evaluations"] = r["evaluations"] - prev
        prev = r["evaluations"]
        r["evals_per_s"] = r["new_evaluations"] / r["seconds"]
        r["moves_per_s"] = r["evals_per_s"] * args.moves
    return rows


def exploit_batch(genomes, task, config: ex.ExploitConfig, seed: int = 0):
    """``(batch, state, tables)``: the genomes compiled unpadded and their engine state
    (the handover's first steps, :func:`eant2_jax.tuning.prepare`)."""
    keys = jax.random.split(jax.random.key(seed), len(genomes))
    prep = tuning.prepare(
        genomes, task, key=jax.random.key(seed), config=config, keys=keys, pad_count=False
    )
    return prep.batch, prep.state, prep.tables


def _batch(seed: int, count: int, n_genes: int, task, config: ex.ExploitConfig):
    genomes = random_population(seed, count, n_genes)
    return (genomes, *exploit_batch(genomes, task, config, seed))


def _pruning_case(args, task, n_genes: int) -> dict:
    config = ex.ExploitConfig(pruner="covariance", max_iters=1, chunk=1)
    _, batch, st, tables = _batch(args.seed, args.population, n_genes, task, config)
    plain = config.replace(pruner="none")
    key = jax.random.key(0)
    step = jax.jit(lambda s: ex.step(s, batch.layout, tables, task, key, plain)[0])
    trigger = jnp.ones(st.stop.shape, bool)
    # A whole attempt (the shifted means' evaluation and the re-fit, max_iters = 1
    # iteration of it), through the engine's own iterations.
    attempt = jax.jit(lambda s: ex.attempt(s, trigger, batch.layout, tables, task, key, config)[0])
    t_step = time_call(lambda: step(st.replace(attempt=None)), repeats=args.repeats).median_s
    t_prune = time_call(lambda: attempt(st), repeats=args.repeats).median_s
    return {
        "structures": args.population,
        "genes": n_genes,
        "P": batch.bucket.genes,
        "iteration_ms": 1e3 * t_step,
        "attempt_ms": 1e3 * t_prune,
        "ratio": t_prune / t_step,
    }


def bench_pruning(args) -> list[dict]:
    """One pruning attempt of every structure vs one CMA-ES iteration, same batch."""
    task = tasks.make("servo", mode=args.mode, n_starts=args.moves)
    return [_pruning_case(args, task, n) for n in args.scaling_genes]


def bench_scaling(args) -> list[dict]:
    """Time of ``iters`` exploitation iterations against structures, moves and size."""
    rows = []
    cases = [(s, args.moves, args.scaling_genes[0]) for s in args.scaling_structures]
    cases += [(args.population, m, args.scaling_genes[0]) for m in args.scaling_moves]
    cases += [(args.population, args.moves, g) for g in args.scaling_genes[1:]]
    for structures, moves, n_genes in dict.fromkeys(cases):
        task = tasks.make("servo", mode=args.mode, n_starts=moves)
        config = ex.ExploitConfig(
            pruner=args.scaling_pruner,
            lazy_eigen=args.lazy_eigen,
            max_iters=args.scaling_iters,
            chunk=args.scaling_iters,
            patience=10**6,
            sigma_tol=0.0,
            tolfun=None,
        )
        _, batch, st, tables = _batch(args.seed, structures, n_genes, task, config)
        popsize = st.params.weights.shape[-1]

        def go(st=st, batch=batch, task=task, config=config, tables=tables):
            return ex.run(
                st, batch.layout, task, key=jax.random.key(1), config=config, tables=tables
            )

        t0 = time.perf_counter()
        final, history = go()
        jax.block_until_ready(final)
        first = time.perf_counter() - t0
        # Engine iterations in which anything ran (a pruner's attempts at the budget stop
        # add some past scaling_iters).
        ticks = int(np.sum(np.any(history.running, axis=1)))
        t = time_call(go, warmup=1, repeats=max(1, args.repeats // 3)).median_s
        evals = int(np.sum(np.asarray(final.evals)))
        rows.append(
            {
                "structures": structures,
                "moves": moves,
                "genes": n_genes,
                "P": batch.bucket.genes,
                "popsize": popsize,
                "first_s": first,
                "iterations": ticks,
                "iteration_ms": 1e3 * t / ticks,
                "moves_per_s": evals * moves / t,
            }
        )
    return rows


def bench_eigh(args) -> list[dict]:
    """Milliseconds per batched decomposition of S random covariances of P x P."""
    rows = []
    rng = np.random.default_rng(args.seed)
    decompose = jax.jit(jax.vmap(cmaes.eigen, in_axes=(0, 0, None)))
    for genes in args.eigh_genes:
        for structures in args.eigh_structures:
            # A covariance as CMA-ES leaves it: SPD and ill-conditioned (its axes' scales
            # span two decades), its last quarter of axes padding (as in a bucket), a fresh
            # draw per (S, P).
            n = max(1, genes - genes // 4)
            a = rng.normal(size=(structures, n, n)) * np.logspace(0, 2, n)
            cov = np.zeros((structures, genes, genes), np.float32)
            cov[:, :n, :n] = a @ a.transpose(0, 2, 1) / n
            mask = np.broadcast_to(np.arange(genes) < n, (structures, genes))
            args_ = (jnp.asarray(cov), jnp.asarray(mask), jnp.float32(1e14))
            t = time_call(lambda a=args_: decompose(*a), repeats=args.repeats)
            rows.append(
                {
                    "structures": structures,
                    "P": genes,
                    "valid": n,
                    "first_s": t.first_call_s,
                    "call_ms": 1e3 * t.median_s,
                    "per_matrix_us": 1e6 * t.median_s / structures,
                }
            )
    return rows


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--parts", default="generation,pruning,scaling")
    harness.run_options(p, task="servo", population=20, generations=4, seed=0)
    p.add_argument("--max-iters", type=int, default=300)
    p.add_argument("--moves", type=int, default=1023)
    p.add_argument("--mode", default="kinematic")
    p.add_argument("--pruner", default="covariance")
    p.add_argument(
        "--lazy-eigen",
        type=float,
        default=ex.ExploitConfig.lazy_eigen,
        help="ExploitConfig.lazy_eigen (default: its default; 0: eager)",
    )
    p.add_argument("--scaling-structures", type=int, nargs="+", default=[8, 20, 40, 80])
    p.add_argument("--scaling-moves", type=int, nargs="+", default=[256, 1023, 4092])
    p.add_argument("--scaling-genes", type=int, nargs="+", default=[40, 80, 160])
    p.add_argument("--scaling-iters", type=int, default=50)
    p.add_argument(
        "--scaling-pruner",
        default="none",
        help="the scaling batch's pruner (its triggers fire as in a run; default none)",
    )
    p.add_argument("--eigh-structures", type=int, nargs="+", default=[1, 8, 24, 48])
    p.add_argument("--eigh-genes", type=int, nargs="+", default=[16, 32, 48, 64, 128])


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.population, args.generations, args.max_iters, args.moves = 3, 1, 20, 16
        args.scaling_structures, args.scaling_moves, args.scaling_genes = [2], [16], [34]
        args.scaling_iters, args.repeats = 5, 2
        args.eigh_structures, args.eigh_genes = [2], [8, 40]


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    clock = CompileClock()
    parts = set(args.parts.split(","))
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args)}
    for part, bench in (
        ("generation", lambda: bench_generations(args, clock)),
        ("pruning", lambda: bench_pruning(args)),
        ("scaling", lambda: bench_scaling(args)),
        ("eigh", lambda: bench_eigh(args)),
    ):
        if part in parts:
            payload[part] = bench()
            save(payload)
    return payload


def render(payload: dict[str, Any]) -> str:
    return harness.sections(payload, [
        ("generation", f"EANT2 generations on {payload['config'].get('task', 'servo')}", [
            Column("generation", "gen"), Column("seconds", "wall s", "{:.2f}"),
            Column("exploited", "structures"), Column("new_evaluations", "evaluations"),
            Column("moves_per_s", "moves/s", "{:.3g}"), Column("compiles", "XLA compiles"),
            Column(lambda r: r.get("bucket") and tuple(r["bucket"]), "bucket (P, H, sweeps)"),
            Column("buckets_so_far", "buckets so far"),
            Column("best_cost", "best cost", "{:.4g}"), Column("best_size", "size"),
        ]),
        ("pruning", "Pruning attempt vs one CMA-ES iteration", [
            Column("structures", "S"), Column("genes", "genes"), Column("P", "P"),
            Column("iteration_ms", "iteration ms", "{:.3g}"),
            Column("attempt_ms", "attempt ms", "{:.3g}"), Column("ratio", "ratio", "{:.2f}"),
        ]),
        ("scaling", "Scaling of one exploitation batch", [
            Column("structures", "S"), Column("moves", "moves"), Column("genes", "genes"),
            Column("P", "P"), Column("popsize", "popsize"),
            Column("first_s", "first call s", "{:.2f}"), Column("iterations", "iterations"),
            Column("iteration_ms", "ms / iteration", "{:.3g}"),
            Column("moves_per_s", "moves/s", "{:.3g}"),
        ]),
        ("eigh", "One batched decomposition of S covariances (cmaes.eigen, vmapped)", [
            Column("structures", "S"), Column("P", "P"), Column("valid", "valid axes"),
            Column("first_s", "first call s", "{:.2f}"),
            Column("call_ms", "ms / call", "{:.3g}"),
            Column("per_matrix_us", "us / matrix", "{:.3g}"),
        ]),
    ])  # fmt: skip


SUITE = harness.Suite(
    name="generation",
    title="EANT2 generations, pruning and scaling",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
    repeats=9,
)

main = SUITE.main
