"""Multi-device scaling of a servo generation's exploitation (weak and strong).

One exploitation batch — S random structures, a fixed number of CMA-ES iterations, 1023
moves each, pruning on — is timed on 1, 2, 4, ... devices of a 1-D mesh along the structure
axis. Weak scaling: S grows with the device count (``--per-device`` structures each); strong
scaling: S is fixed (``--strong``). Each case is timed after a warm-up call that compiles.

Run: ``python -m bench scaling [--devices 1 2 4] [--quick] [--out PATH]``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

import jax

from bench.common import (
    Column,
    default_out,
    environment,
    markdown_table,
    random_population,
    write_results,
)
from eant2_jax import distributed, loop, tasks
from eant2_jax import exploitation as ex


def time_case(task, genomes, config, devices: int, repeats: int) -> tuple[float, float]:
    mesh = distributed.make_mesh(devices) if devices > 1 else None
    key = jax.random.key(0)
    t0 = time.perf_counter()
    loop.exploit(genomes, task, key=key, config=config, mesh=mesh)
    first = time.perf_counter() - t0
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        loop.exploit(genomes, task, key=jax.random.fold_in(key, r + 1), config=config, mesh=mesh)
        times.append(time.perf_counter() - t0)
    return first, sorted(times)[len(times) // 2]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(prog="python -m bench scaling", description=__doc__)
    p.add_argument("--devices", type=int, nargs="+", default=None)
    p.add_argument("--per-device", type=int, default=32)
    p.add_argument("--strong", type=int, default=128)
    p.add_argument("--genes", type=int, default=50)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--moves", type=int, default=1023)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.quick:
        args.per_device, args.strong, args.iters, args.moves, args.repeats = 2, 4, 4, 8, 1
    counts = args.devices or [d for d in (1, 2, 4, 8) if d <= jax.device_count()]
    task = tasks.make("servo", n_starts=args.moves)
    config = ex.ExploitConfig(
        max_iters=args.iters, chunk=args.iters, patience=10**6, sigma_tol=0.0,
        pruner="covariance", prune_window=50,
    )  # fmt: skip
    rows = []
    for kind in ("weak", "strong"):
        base = None
        for d in counts:
            s = args.per_device * d if kind == "weak" else args.strong
            genomes = random_population(1, s, args.genes)
            first, t = time_case(task, genomes, config, d, args.repeats)
            base = base or (t, s)
            # Speed-up in structures processed per second relative to 1 device.
            speedup = (s / t) / (base[1] / base[0])
            rows.append(
                {
                    "scaling": kind,
                    "devices": d,
                    "structures": s,
                    "first_s": first,
                    "seconds": t,
                    "structures_per_s": s / t,
                    "speedup": speedup,
                }
            )
    payload = {"environment": environment(), "config": vars(args), "rows": rows}
    md = f"Device: {payload['environment']['device_kind']} x {jax.device_count()}.\n\n"
    md += markdown_table(
        rows,
        [
            Column("scaling", "scaling"),
            Column("devices", "devices"),
            Column("structures", "structures"),
            Column("first_s", "first call s", "{:.1f}"),
            Column("seconds", "s / generation", "{:.3f}"),
            Column("structures_per_s", "structures/s", "{:.1f}"),
            Column("speedup", "speed-up", "{:.2f}x"),
        ],
    )
    write_results(args.out or default_out("scaling"), payload, md)
    print(md)
    return payload


if __name__ == "__main__":  # pragma: no cover
    main()
