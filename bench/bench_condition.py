"""The paper's condition experiment (V.A) on one evolved network, in float64.

The network (``--genome-file``: a genome in text form, e.g. a run directory's
``best.genome``) is pruned in rounds, then the original and the pruned network each run
``--inits`` CMA-ES runs from random weights without pruning (one batch), recording cond(C)
every iteration: :func:`eant2_jax.app.experiments.condition_experiment`. The CMA-ES state is
float64 (JAX's x64 mode), with cond(C) bounded at ``--max-condition``.

Run: ``python -m bench condition --genome-file runs/.../best.genome [--iters 10000]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from bench import harness
from bench.common import BenchInputError, Column, environment, markdown_table


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--genome-file", required=True)
    harness.run_options(p, task="servo", seed=0)
    p.add_argument("--iters", type=int, default=10_000)
    p.add_argument("--inits", type=int, default=5)
    p.add_argument("--max-condition", type=float, default=1e17)
    p.add_argument("--prune-iters", type=int, default=2000)
    p.add_argument(
        "--evolved-warmup", type=int, default=0,
        help="also continue from an evolved C: CMA-ES iterations of the original before the "
        "branch (0: only the restart at C = I)",
    )  # fmt: skip
    p.add_argument("--n-starts", type=int, default=None, help="servo start poses (default all)")


def _prepare(args: argparse.Namespace) -> None:
    if not Path(args.genome_file).is_file():
        raise BenchInputError(f"--genome-file {args.genome_file}: no such file")
    if args.quick:
        args.iters, args.inits, args.prune_iters, args.n_starts = 50, 2, 50, 16
        args.evolved_warmup = min(args.evolved_warmup, 30)


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    import eant2_jax
    from eant2_jax.app.experiments import condition_experiment

    eant2_jax.enable_x64()
    genome = eant2_jax.Genome.parse(Path(args.genome_file).read_text().strip())
    options = {} if args.n_starts is None else {"n_starts": args.n_starts}
    task = eant2_jax.tasks.make(args.task, **options)
    t0 = time.perf_counter()
    cond = condition_experiment(
        genome,
        task,
        key=jax.random.key(args.seed),
        iters=args.iters,
        inits=args.inits,
        prune_iters=args.prune_iters,
        max_condition=args.max_condition,
        evolved_warmup=args.evolved_warmup,
    )
    wall = time.perf_counter() - t0
    rows = [
        {
            "network": name,
            "size": cond[f"size_{key}"],
            "median_peak": float(np.median(cond[f"peak_{key}"])),
            "peaks": ", ".join(f"{p:.3g}" for p in cond[f"peak_{key}"]),
            "median_cost": float(np.median(cond[f"cost_{key}"])),
        }
        for name, key in (("original", "before"), ("pruned", "after"))
    ]
    if cond["evolved"] is not None:
        ev = cond["evolved"]
        rows += [
            {
                "network": f"{name}, from the evolved C",
                "size": cond[f"size_{key}"],
                "median_peak": float(np.median(ev[f"peak_{key}"])),
                "peaks": ", ".join(f"{p:.3g}" for p in ev[f"peak_{key}"]),
                "median_cost": float(np.median(ev[f"cost_{key}"])),
            }
            for name, key in (("original", "before"), ("pruned", "after"))
        ]
        cond["evolved"] = {k: v for k, v in ev.items() if k not in ("before", "after")}
    small = {k: v for k, v in cond.items() if k not in ("before", "after")}
    return {
        "environment": environment(),
        "config": harness.settings(args),
        "wall_s": wall,
        "rows": rows,
        "ratio": rows[0]["median_peak"] / rows[1]["median_peak"],
        "ratio_evolved": rows[2]["median_peak"] / rows[3]["median_peak"] if len(rows) > 2 else None,
        "condition": small,
    }


COLUMNS = [
    Column("network", "network"),
    Column("size", "weights"),
    Column("median_peak", "median peak cond(C)", "{:.3g}"),
    Column("peaks", "peak per initialisation"),
    Column("median_cost", "median best cost", "{:.4g}"),
]


def render(payload: dict[str, Any]) -> str:
    return (
        markdown_table(payload["rows"], COLUMNS)
        + f"\nRatio of the medians: {payload['ratio']:.3g}x"
        + (
            f" (from the evolved C: {payload['ratio_evolved']:.3g}x)"
            if payload.get("ratio_evolved")
            else ""
        )  # fmt: skip
        + f"; wall {payload['wall_s']:.0f} s.\n"
    )


SUITE = harness.Suite(
    name="condition",
    title="Condition experiment (paper V.A), float64",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
