"""Multi-device scaling of a servo generation's exploitation (weak and strong).

One exploitation batch — S random structures, a fixed number of CMA-ES iterations, 1023
moves each, pruning on (off with ``--quick``) — is timed on 1, 2, 4, ... devices of a 1-D
mesh along the structure axis. Weak scaling: S grows with the device count (``--per-device``
structures each); strong scaling: S is fixed (``--strong``). Each case is timed after a
warm-up call that compiles.

Each row also times the engine alone (`eant2_jax.exploitation.run` on a batch that
`tuning.prepare` made on the devices, as `tune` makes it: the devices' loops, the host's one
read per chunk and whatever `run` still has to place), the loops alone (the same call on
arguments placed beforehand, the task too, so that engine minus loops is that placement)
and gives the rest of a generation, the host's handover (compiling the genomes, starting
the engine on the devices, turning the results back into genomes; ``start s`` times
`tuning.prepare` alone, ``hand-back s`` is the rest), which grows with the structures and is
not split over devices: where it is a large share, more devices cannot
help (docs/design.md, "Many devices"). ``loops speed-up`` is the loops' structures per
second against one device's: what the devices' programs alone scale by.

``--rounds R`` times every case R times, interleaved (all cases once, then again), so that
a drift of the machine reaches every device count alike. A row gives each timing's median
round, the median round's speed-up and the range of the R rounds' speed-ups: with 5 rounds
the chance that the range misses the median speed-up is 2 x 0.5^5, about 6%.

``--trace-dir DIR`` also runs each case's loops once more, in the first round, under
``jax.profiler.trace`` (a Perfetto trace per case under DIR) and gives each device's busy
time and the span from its first kernel's start to its last kernel's end
(`bench.bench_profile.analyse_trace`): devices whose spans exceed their busy time by more
than one device's do wait on each other or on the host.

Run: ``python -m bench scaling [--devices 1 2 4] [--quick] [--trace-dir DIR]``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import jax

from bench import harness
from bench.bench_profile import analyse_trace, traced
from bench.common import (
    BenchInputError,
    Column,
    eant2_pruner,
    environment,
    markdown_table,
    random_population,
    time_call,
)
from eant2_jax import distributed, tasks, tuning
from eant2_jax import exploitation as ex


def time_case(
    task, genomes, config, devices: int, repeats: int, trace_dir: Path | None = None
) -> tuple:
    """``(first call s, median s per tune, median s of the engine alone, median s of the
    loops alone, median s of the start)``: the engine alone is `exploitation.run` on a batch
    `tuning.prepare` made on the devices (the devices' loops, the host's one read per chunk
    and whatever `run` still places), the loops alone the same call on arguments placed
    beforehand; the rest of a tune is the host's handover, which the devices do not split:
    the start (`tuning.prepare`: compile the genomes, build the tables, start the engine on
    the devices) and the hand-back (gather the results, turn them back into genomes).
    With ``trace_dir``, a last item: the loops traced once more (`_traced`), else None."""
    mesh = distributed.make_mesh(devices) if devices > 1 else None
    key = jax.random.key(0)
    t0 = time.perf_counter()
    tuning.tune(genomes, task, key=key, config=config, mesh=mesh)
    first = time.perf_counter() - t0
    times = []
    # The keys are made before the clock starts: a first fold_in compiles a small program.
    keys = [jax.random.fold_in(key, r + 1) for r in range(repeats)]
    for k in keys:
        t0 = time.perf_counter()
        tuning.tune(genomes, task, key=k, config=config, mesh=mesh)
        times.append(time.perf_counter() - t0)
    init_key, run_key = jax.random.split(key)
    # Made on the devices as `tune` makes it (`tuning.prepare`'s mesh).
    prep = tuning.prepare(genomes, task, key=init_key, config=config, mesh=mesh)

    def engine_call(st, layout, tables, on):
        def call():
            return ex.run(st, layout, on, key=run_key, config=config, tables=tables, mesh=mesh)[0]

        return call

    def engine_s(st, layout, tables, on) -> float:
        return time_call(engine_call(st, layout, tables, on), warmup=0, repeats=repeats).median_s

    start = time_call(
        lambda: tuning.prepare(genomes, task, key=init_key, config=config, mesh=mesh).state,
        warmup=0,
        repeats=repeats,
    ).median_s
    engine = engine_s(prep.state, prep.batch.layout, prep.tables, task)
    # Placed as `run` places them: `run` then finds every array where it belongs already.
    placed = ex.placed(prep.state, prep.batch.layout, prep.tables, task, mesh)
    loops = engine_s(*placed)
    trace = None if trace_dir is None else _traced(engine_call(*placed), trace_dir)
    return first, statistics.median(times), engine, loops, start, trace


def _traced(call, trace_dir: Path) -> dict[str, Any]:
    """One ``call()`` (compiled already) under ``jax.profiler.trace`` into ``trace_dir``:
    its wall time and each device's busy time and span (`bench.bench_profile.analyse_trace`)."""

    def timed():
        t0 = time.perf_counter()
        jax.block_until_ready(call())
        return time.perf_counter() - t0

    wall, path = traced(timed, trace_dir)
    summary = analyse_trace(path, ())
    return {"trace_file": path, "trace_wall_s": wall, "per_device": summary["per_device"]}


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--devices", type=int, nargs="+", default=None)
    p.add_argument("--per-device", type=int, default=32)
    p.add_argument("--strong", type=int, default=128)
    p.add_argument("--genes", type=int, default=50)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--moves", type=int, default=1023)
    p.add_argument("--trace-dir", default=None,
                   help="also trace each case's loops once (first round) into this folder "
                        "and give each device's busy time and span")  # fmt: skip
    p.add_argument("--rounds", type=int, default=3,
                   help="times every case this often, interleaved; the rows give the "
                        "median round and the range of the speed-ups")  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if args.rounds < 1:
        raise BenchInputError(f"--rounds must be at least 1, got {args.rounds}")
    if args.quick:
        # One structure per device and a strong batch of one: the one-device cases are one
        # program, and so are the two-device ones (one structure padded to two rows), so
        # that the smoke test compiles two engine programs, not three.
        args.per_device, args.strong, args.iters, args.moves, args.repeats = 1, 1, 4, 8, 1
        args.rounds = 2


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    counts = args.devices or [d for d in (1, 2, 4, 8) if d <= jax.device_count()]
    task = tasks.make("servo", n_starts=args.moves)
    config = ex.ExploitConfig(
        max_iters=args.iters, chunk=args.iters, patience=10**6, sigma_tol=0.0,
        tolfun=None, pruner=eant2_pruner(args.quick), prune_window=50,
    )  # fmt: skip
    cases = [(kind, d, args.per_device * d if kind == "weak" else args.strong)
             for kind in ("weak", "strong") for d in counts]  # fmt: skip
    populations = {s: random_population(1, s, args.genes) for _, _, s in cases}
    # Every round times every case once, so that a drift of the machine's speed reaches
    # each device count alike; a round's speed-ups are against its own one-device case.
    rounds = []
    for r in range(args.rounds):
        timed = {}
        for c in cases:
            trace = None
            if args.trace_dir is not None and r == 0:
                trace = Path(args.trace_dir) / f"{c[0]}-{c[1]}dev-{c[2]}"
            times = time_case(task, populations[c[2]], config, c[1], args.repeats, trace)
            timed[c] = _timed(c, times)
        for c in cases:
            base = next(timed[b] for b in cases if b[0] == c[0])  # the scaling's first case
            for k, t in (("speedup", "seconds"), ("loops_speedup", "loops_s")):
                timed[c][k] = (c[2] / timed[c][t]) / (base["structures"] / base[t])
        rounds.append(timed)
    rows = []
    for c in cases:
        each = [r[c] for r in rounds]
        row = {k: statistics.median(x[k] for x in each) for k in _MEDIANS}
        row = {**each[0], **row}  # the case, and the first round's first call
        for k in ("speedup", "loops_speedup"):
            row[f"{k}_rounds"] = [x[k] for x in each]
            row[f"{k}_range"] = f"{min(row[f'{k}_rounds']):.2f}-{max(row[f'{k}_rounds']):.2f}x"
        rows.append(row)
    return {"environment": environment(), "config": harness.settings(args), "rows": rows}


_MEDIANS = ("seconds", "engine_s", "loops_s", "placement_s", "host_s", "start_s", "back_s",
            "structures_per_s", "speedup", "loops_speedup")  # fmt: skip


def _timed(case: tuple, timed: tuple) -> dict[str, Any]:
    """One case of one round (`time_case`'s timings), before its speed-ups."""
    kind, d, s = case
    first, t, engine, loops, start, trace = timed
    row = {"scaling": kind, "devices": d, "structures": s, "first_s": first, "seconds": t,
           "engine_s": engine, "loops_s": loops, "placement_s": engine - loops,
           "host_s": t - engine, "start_s": start, "back_s": t - engine - start,
           "structures_per_s": s / t}  # fmt: skip
    if trace is not None:
        row.update(trace)
        per = trace["per_device"]
        # No device tracks (a CPU trace): None, which the table prints as a dash.
        row["busy_text"] = ", ".join(f"{x['busy_s']:.3f}" for x in per) or None
        row["span_text"] = ", ".join(f"{x['span_s']:.3f}" for x in per) or None
    return row


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
    Column("start_s", "start s", "{:.3f}"),
    Column("back_s", "hand-back s", "{:.3f}"),
    Column("structures_per_s", "structures/s", "{:.1f}"),
    Column("speedup", "speed-up", "{:.2f}x"),
    Column("speedup_range", "range"),
    Column("loops_speedup", "loops speed-up", "{:.2f}x"),
    Column("loops_speedup_range", "range"),
]

TRACE_COLUMNS = [
    Column("trace_wall_s", "traced loops s", "{:.3f}"),
    Column("busy_text", "busy s per device"),
    Column("span_text", "span s per device"),
]


def _columns(rows: list[dict[str, Any]]) -> list[Column]:
    """The table's columns: the trace's only where the rows were traced (``--trace-dir``)."""
    return COLUMNS + (TRACE_COLUMNS if any("per_device" in r for r in rows) else [])


SUITE = harness.Suite(
    name="scaling",
    title="Multi-device scaling",
    description=__doc__,
    options=_options,
    run=run,
    render=lambda payload: markdown_table(payload["rows"], _columns(payload["rows"])),
    prepare=_prepare,
    repeats=3,
)

main = SUITE.main
