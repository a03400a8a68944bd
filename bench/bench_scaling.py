"""Multi-device scaling of a servo generation's exploitation (weak and strong).

One exploitation batch — S random structures, a fixed number of CMA-ES iterations, 1023
moves each, pruning on — is timed on 1, 2, 4, ... devices of a 1-D mesh along the structure
axis. Weak scaling: S grows with the device count (``--per-device`` structures each); strong
scaling: S is fixed (``--strong``). Each case is timed after a warm-up call that compiles.

Each row also times the engine alone (`eant2_jax.exploitation.run` on a prepared batch: the
batch's placement on the devices, the devices' loops and the host's one read per chunk), the
loops alone (the same call on a batch placed beforehand, so that engine minus loops is the
placement) and gives the rest of a generation, the host's handover (compiling the genomes,
the engine start, turning the results back into genomes), which grows with the structures
and is not split over devices: where it is a large share, more devices cannot help
(docs/design.md, "Many devices"). ``loops speed-up`` is the loops' structures per second
against one device's: what the devices' programs alone scale by.

Run: ``python -m bench scaling [--devices 1 2 4] [--quick]``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax

from bench import harness
from bench.common import Column, environment, markdown_table, random_population
from eant2_jax import distributed, tasks, tuning
from eant2_jax import exploitation as ex


def time_case(task, genomes, config, devices: int, repeats: int) -> tuple[float, ...]:
    """``(first call s, median s per tune, median s of the engine alone, median s of the
    loops alone)``: the engine alone is `exploitation.run` on a prepared batch (placing it
    on the devices, the devices' loops and the host's one read per chunk), the loops alone
    the same call on a batch placed beforehand; the rest of a tune is the host's handover
    (compile the genomes, start the engine, turn the results back into genomes), which the
    devices do not split."""
    mesh = distributed.make_mesh(devices) if devices > 1 else None
    key = jax.random.key(0)
    t0 = time.perf_counter()
    tuning.tune(genomes, task, key=key, config=config, mesh=mesh)
    first = time.perf_counter() - t0
    times, engine = [], []
    # The keys are made before the clock starts: a first fold_in compiles a small program.
    keys = [jax.random.fold_in(key, r + 1) for r in range(repeats)]
    for k in keys:
        t0 = time.perf_counter()
        tuning.tune(genomes, task, key=k, config=config, mesh=mesh)
        times.append(time.perf_counter() - t0)
    init_key, run_key = jax.random.split(key)
    prep = tuning.prepare(
        genomes, task, key=init_key, config=config, multiple_of=distributed.size(mesh)
    )
    # Placed as `run` places them: `run` then finds every array where it belongs already.
    st0, layout, tables, on_devices = ex.placed(
        prep.state, prep.batch.layout, prep.tables, task, mesh
    )
    loops = []
    for batch, out in (((prep.state, prep.batch.layout, prep.tables, task), engine),
                       ((st0, layout, tables, on_devices), loops)):  # fmt: skip
        for _ in range(repeats):
            t0 = time.perf_counter()
            st, _ = ex.run(
                batch[0], batch[1], batch[3], key=run_key, config=config, tables=batch[2],
                mesh=mesh,
            )  # fmt: skip
            jax.block_until_ready(st)
            out.append(time.perf_counter() - t0)
    return first, *(sorted(x)[len(x) // 2] for x in (times, engine, loops))


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--devices", type=int, nargs="+", default=None)
    p.add_argument("--per-device", type=int, default=32)
    p.add_argument("--strong", type=int, default=128)
    p.add_argument("--genes", type=int, default=50)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--moves", type=int, default=1023)


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.per_device, args.strong, args.iters, args.moves, args.repeats = 2, 4, 4, 8, 1


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    counts = args.devices or [d for d in (1, 2, 4, 8) if d <= jax.device_count()]
    task = tasks.make("servo", n_starts=args.moves)
    config = ex.ExploitConfig(
        max_iters=args.iters, chunk=args.iters, patience=10**6, sigma_tol=0.0,
        tolfun=None, pruner="covariance", prune_window=50,
    )  # fmt: skip
    rows = []
    for kind in ("weak", "strong"):
        base = None
        for d in counts:
            s = args.per_device * d if kind == "weak" else args.strong
            genomes = random_population(1, s, args.genes)
            first, t, engine, loops = time_case(task, genomes, config, d, args.repeats)
            base = base or (t, s, loops)
            # Speed-up in structures processed per second relative to 1 device.
            speedup = (s / t) / (base[1] / base[0])
            rows.append(
                {
                    "scaling": kind,
                    "devices": d,
                    "structures": s,
                    "first_s": first,
                    "seconds": t,
                    "engine_s": engine,
                    "loops_s": loops,
                    "placement_s": engine - loops,
                    "host_s": t - engine,
                    "structures_per_s": s / t,
                    "speedup": speedup,
                    "loops_speedup": (s / loops) / (base[1] / base[2]),
                }
            )
    return {"environment": environment(), "config": harness.settings(args), "rows": rows}


COLUMNS = [
    Column("scaling", "scaling"),
    Column("devices", "devices"),
    Column("structures", "structures"),
    Column("first_s", "first call s", "{:.1f}"),
    Column("seconds", "s / generation", "{:.3f}"),
    Column("engine_s", "engine s", "{:.3f}"),
    Column("loops_s", "loops s", "{:.3f}"),
    Column("placement_s", "placement s", "{:.3f}"),
    Column("host_s", "handover s", "{:.3f}"),
    Column("structures_per_s", "structures/s", "{:.1f}"),
    Column("speedup", "speed-up", "{:.2f}x"),
    Column("loops_speedup", "loops speed-up", "{:.2f}x"),
]

SUITE = harness.Suite(
    name="scaling",
    title="Multi-device scaling",
    description=__doc__,
    options=_options,
    run=run,
    render=lambda payload: markdown_table(payload["rows"], COLUMNS),
    prepare=_prepare,
    repeats=3,
)

main = SUITE.main
