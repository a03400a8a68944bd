"""Forward throughput of the compiled EANT2 networks, against a dense MLP of the same padded size.

One *network-step* is one network applied to one example at one time step; a call on ``G``
genomes over inputs ``[T, M, n_in]`` does ``G * T * M`` of them. For every population size
``G``, genome size (genes, hence neurons) and padding bucket, the benchmark times
:func:`eant2_jax.evaluate.rollout_batch` (the public forward pass):

* ``first_call_s``: the first call on fresh caches, tracing and XLA compilation included;
* ``median_s``: median of ``--repeats`` (>= 5) timed calls after ``--warmup`` untimed ones,
  each waiting for the device (``block_until_ready``);

and, in the same run, a baseline: ``jax.vmap`` over a plain dense MLP of the same padded size
(``n_in -> H`` tanh ``-> n_out``, ``H`` = the bucket's neuron count) on the same ``G``, ``T``,
``M``. The MLP carries no state between steps; it is the cost of the smallest dense network
with the same number of neuron slots, so the ratio shows what the general topology
(``sweeps`` dense passes over ``H x H``, recurrent weights) and the per-genome scatter cost.

Configurations: ``main`` is the servo task's shape, each network on ``M = 1023`` independent
one-step examples (``T = 1``); ``recurrent`` is ``T = 100`` steps of ``M = 64`` streams.
Padding: ``fit`` is the smallest bucket holding the population; ``2x`` doubles the neuron and
gene buckets (same sweeps) to show what over-padding costs.

Run from the repository root::

    python -m bench forward                      # full sweep (sized for a GPU)
    python -m bench forward --pops 32 256        # a CPU-sized sweep
    python -m bench forward --quick --out /tmp/f.json
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    environment,
    markdown_table,
    random_population,
    time_call,
)
from eant2_jax.compiler import Bucket, bucket_for, bucket_size, compile_genomes
from eant2_jax.evaluate import rollout_batch

N_INPUTS = 10
N_OUTPUTS = 3
HIDDEN, OUTPUT = "tanh", "identity"
# Same precision as the EANT2 kernel (kernels/network.py uses HIGHEST so that GPUs do not
# silently use TF32), so that the baseline does the same arithmetic per multiply-add.
_PRECISION = jax.lax.Precision.HIGHEST

CONFIGS = {"main": (1, 1023), "recurrent": (100, 64)}
QUICK_CONFIGS = {"main": (1, 16), "recurrent": (3, 4)}


# ------------------------------------------------------------------------------- baseline
def _mlp_one(w1: jax.Array, b1: jax.Array, w2: jax.Array, x: jax.Array) -> jax.Array:
    """Dense MLP on one example: ``[n_in] -> [H]`` tanh ``-> [n_out]``."""
    return jnp.dot(w2, jnp.tanh(jnp.dot(w1, x, precision=_PRECISION) + b1), precision=_PRECISION)


@jax.jit
def mlp_batch(w1: jax.Array, b1: jax.Array, w2: jax.Array, inputs: jax.Array) -> jax.Array:
    """G dense MLPs on shared inputs.

    Args:
      w1: ``[G, H, n_in]``; b1: ``[G, H]``; w2: ``[G, n_out, H]``.
      inputs: ``[T, M, n_in]``.

    Returns:
      ``[G, T, M, n_out]``, the layout :func:`rollout_batch` returns.
    """

    # The MLP has no state, so T and M flatten into one batch of examples: one batched
    # matmul per layer, the plainest form of the baseline.
    steps, streams, n_in = inputs.shape
    flat = inputs.reshape(steps * streams, n_in)

    def one(a, b, c):
        return jax.vmap(functools.partial(_mlp_one, a, b, c))(flat)

    ys = jax.vmap(one)(w1, b1, w2)
    return ys.reshape(ys.shape[0], steps, streams, ys.shape[-1])


# ------------------------------------------------------------------------------ one case
def _flops_per_step(h: int, sweeps: int) -> tuple[int, int]:
    """Multiply-add flops of one network-step as executed, for (EANT2 kernel, MLP)."""
    kernel = 2 * (h * N_INPUTS + h * h + sweeps * h * h + N_OUTPUTS * h)
    mlp = 2 * (h * N_INPUTS + N_OUTPUTS * h)
    return kernel, mlp


def bench_case(
    genomes: Sequence,
    *,
    config: str,
    steps: int,
    streams: int,
    pad: str,
    genes_target: int,
    seed: int,
    warmup: int,
    repeats: int,
) -> dict[str, Any]:
    """Time the EANT2 forward pass and the MLP baseline on one population and shape."""
    fit = bucket_for(genomes)
    if pad == "fit":
        bucket = fit
    elif pad == "2x":
        bucket = Bucket(neurons=2 * fit.neurons, genes=2 * fit.genes, sweeps=fit.sweeps)
    else:
        raise ValueError(f"unknown padding {pad!r}")

    t0 = time.perf_counter()
    batch = compile_genomes(genomes, N_INPUTS, bucket=bucket)
    host_compile_s = time.perf_counter() - t0
    g_rows = int(batch.weights.shape[0])
    h, p = bucket.neurons, bucket.genes

    rng = np.random.default_rng(seed)
    inputs = jnp.asarray(rng.normal(size=(steps, streams, N_INPUTS)), jnp.float32)
    params = jnp.asarray(rng.normal(scale=0.5, size=(g_rows, p)), jnp.float32)
    w1 = jnp.asarray(rng.normal(scale=0.5, size=(g_rows, h, N_INPUTS)), jnp.float32)
    b1 = jnp.asarray(rng.normal(scale=0.5, size=(g_rows, h)), jnp.float32)
    w2 = jnp.asarray(rng.normal(scale=0.5, size=(g_rows, N_OUTPUTS, h)), jnp.float32)

    # Fresh caches, so that each first call compiles (no two cases share a shape anyway).
    jax.clear_caches()
    kernel = time_call(
        lambda: rollout_batch(batch.layout, params, inputs, hidden=HIDDEN, output=OUTPUT),
        warmup=warmup,
        repeats=repeats,
    )
    jax.clear_caches()
    mlp = time_call(lambda: mlp_batch(w1, b1, w2, inputs), warmup=warmup, repeats=repeats)

    n_steps = g_rows * steps * streams
    flops_k, flops_m = _flops_per_step(h, bucket.sweeps)
    n_params = [g.n_params for g in genomes]
    n_neurons = [g.n_neurons for g in genomes]
    return {
        "config": config,
        "T": steps,
        "M": streams,
        "G": g_rows,
        "genes_target": genes_target,
        "genes_mean": float(np.mean(n_params)),
        "genes_max": int(max(n_params)),
        "neurons_mean": float(np.mean(n_neurons)),
        "neurons_max": int(max(n_neurons)),
        "depth_max": int(max(g.depth() for g in genomes)),
        "pad": pad,
        "bucket_neurons": h,
        "bucket_genes": p,
        "sweeps": bucket.sweeps,
        "neuron_fill": float(np.mean(n_neurons)) / h,
        "network_steps": n_steps,
        "host_compile_s": host_compile_s,
        "first_call_s": kernel.first_call_s,
        "compile_s": kernel.compile_s,
        "median_s": kernel.median_s,
        "min_s": kernel.min_s,
        "times_s": list(kernel.times_s),
        "steps_per_s": n_steps / kernel.median_s,
        "gflops_per_s": n_steps * flops_k / kernel.median_s / 1e9,
        "mlp_first_call_s": mlp.first_call_s,
        "mlp_compile_s": mlp.compile_s,
        "mlp_median_s": mlp.median_s,
        "mlp_min_s": mlp.min_s,
        "mlp_times_s": list(mlp.times_s),
        "mlp_steps_per_s": n_steps / mlp.median_s,
        "mlp_gflops_per_s": n_steps * flops_m / mlp.median_s / 1e9,
        "ratio_vs_mlp": mlp.median_s / kernel.median_s,
    }


# ---------------------------------------------------------------------------------- sweep
COLUMNS = [
    Column("config", "config"),
    Column(lambda r: f"{r['T']}x{r['M']}", "T x M"),
    Column("G", "G"),
    Column("genes_mean", "genes", "{:.0f}"),
    Column("neurons_mean", "neurons", "{:.1f}"),
    Column(
        lambda r: f"{r['bucket_neurons']}/{r['bucket_genes']}/{r['sweeps']}", "bucket H/P/sweeps"
    ),
    Column("pad", "pad"),
    Column("first_call_s", "first call s", "{:.2f}"),
    Column(lambda r: r["median_s"] * 1e3, "median ms", "{:.3g}"),
    Column(lambda r: r["steps_per_s"] / 1e6, "M steps/s", "{:.3g}"),
    Column("mlp_first_call_s", "MLP first s", "{:.2f}"),
    Column(lambda r: r["mlp_median_s"] * 1e3, "MLP median ms", "{:.3g}"),
    Column(lambda r: r["mlp_steps_per_s"] / 1e6, "MLP M steps/s", "{:.3g}"),
    Column("ratio_vs_mlp", "EANT2/MLP", "{:.2f}"),
]


def _options(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--pops", type=int, nargs="+", default=None, help="population sizes G")
    ap.add_argument("--genes", type=int, nargs="+", default=None, help="genome sizes (genes)")
    ap.add_argument(
        "--configs", nargs="+", choices=sorted(CONFIGS), default=None, help="shapes to run"
    )
    ap.add_argument(
        "--pad-genes",
        type=int,
        nargs="*",
        default=None,
        help="genome sizes also run with 2x padding (default: the middle size)",
    )
    harness.run_options(ap, seed=0)


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.pops = args.pops or [4]
        args.genes = args.genes or [30, 60]
        args.shapes = QUICK_CONFIGS
    else:
        args.pops = args.pops or [32, 256, 2048]
        args.genes = args.genes or [30, 100, 300]
        args.shapes = CONFIGS
    if args.configs:
        args.shapes = {k: v for k, v in args.shapes.items() if k in args.configs}
    if args.pad_genes is None:
        args.pad_genes = [sorted(args.genes)[len(args.genes) // 2]]


def _payload(args: argparse.Namespace, env: dict, rows: list[dict], total_s: float) -> dict:
    order = list(args.shapes)
    rows = sorted(
        rows, key=lambda r: (order.index(r["config"]), r["genes_target"], r["G"], r["pad"] != "fit")
    )
    return {
        "benchmark": "forward",
        "unit": "network-steps per second (one network on one example at one time step)",
        **env,
        "config": {
            "quick": args.quick,
            "shapes": {k: {"T": t, "M": m} for k, (t, m) in args.shapes.items()},
            "pops": args.pops,
            "genes": args.genes,
            "pad_genes": args.pad_genes,
            "n_inputs": N_INPUTS,
            "n_outputs": N_OUTPUTS,
            "hidden": HIDDEN,
            "output": OUTPUT,
            "precision": "float32, Precision.HIGHEST",
            "warmup": args.warmup,
            "repeats": args.repeats,
            "seed": args.seed,
            "baseline": "jax.vmap over dense MLP n_in -> H (tanh) -> n_out, H = bucket neurons",
        },
        "total_s": total_s,
        "rows": rows,
    }


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """Run the sweep described by parsed arguments; return the JSON payload."""
    env = environment()
    rows: list[dict] = []
    t_start = time.perf_counter()
    for genes in args.genes:
        # One pool per size; each population is its prefix, so sizes nest.
        pool = random_population(
            args.seed + genes, max(args.pops), genes, n_inputs=N_INPUTS, n_outputs=N_OUTPUTS
        )
        for config, (steps, streams) in args.shapes.items():
            for g in args.pops:
                # Keep G on the bucket series so that no padding rows inflate the count.
                if bucket_size(g) != g:
                    raise BenchInputError(f"population size {g} is not on the bucket series")
                pads = ["fit", "2x"] if genes in args.pad_genes else ["fit"]
                for pad in pads:
                    row = bench_case(
                        pool[:g],
                        config=config,
                        steps=steps,
                        streams=streams,
                        pad=pad,
                        genes_target=genes,
                        seed=args.seed,
                        warmup=args.warmup,
                        repeats=args.repeats,
                    )
                    rows.append(row)
                    harness.log(
                        f"[forward] {config} G={g} genes~{genes} pad={pad} "
                        f"H/P/S={row['bucket_neurons']}/{row['bucket_genes']}/{row['sweeps']}: "
                        f"first {row['first_call_s']:.2f}s, {row['median_s'] * 1e3:.3g} ms, "
                        f"{row['steps_per_s'] / 1e6:.3g} M steps/s "
                        f"(MLP {row['mlp_steps_per_s'] / 1e6:.3g})"
                    )
                    save(_payload(args, env, rows, time.perf_counter() - t_start))
    return _payload(args, env, rows, time.perf_counter() - t_start)


def render(payload: dict[str, Any]) -> str:
    return markdown_table(payload["rows"], COLUMNS)


SUITE = harness.Suite(
    name="forward",
    title="Forward throughput",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
    repeats=7,
    min_repeats=5,
    warmup=2,
)

main = SUITE.main
