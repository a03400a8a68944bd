"""Where the time of an EANT2 run on the servo task goes: a profile, not a guess.

Three parts (``--parts``), each optional:

* ``cold``: an EANT2 run in a fresh process (nothing compiled yet) for ``--generations``
  generations. Per generation: wall time, the number of XLA compilations and the seconds
  spent tracing, lowering and compiling them (``jax.monitoring`` events), and what is left.
* ``trace``: the same run again, same key, in the same process (so every program is already
  compiled), under ``jax.profiler.trace`` with a Perfetto trace. The trace is analysed here:
  per generation the wall time, the device's busy time (union of its kernel intervals), the
  host-device copies (count, seconds), and over the whole run the device ops that take the
  most time and the ``eant2_jax`` Python functions that take the most host time. The trace
  file itself is kept (``--trace-dir``) for Perfetto / TensorBoard.
* ``compile``: the exploitation program (``exploitation.run_chunk``) of one bucket,
  lowered and compiled without a pruner and with the covariance pruner, for minimal servo
  networks and for random ones of ``--compile-genes`` genes, with the compiler options the
  library uses (XLA's defaults, "shipped") and with ``--compiler-options`` alternatives,
  each case in a fresh process: what each piece costs to compile and to run.

Run: ``python -m bench profile [--quick] [--parts cold,trace,compile] [--trace-dir DIR]``.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from bench import harness
from bench.bench_generation import exploit_batch
from bench.common import (
    Column,
    CompileClock,
    environment,
    minimal_genome,
    random_population,
)
from eant2_jax import exploitation as ex
from eant2_jax import loop, tasks
from eant2_jax.genome import Genome

__all__ = ["analyse_trace", "main", "traced"]

_MARK = "eant2-bench-generation-end"


def _servo_run(args, on_generation) -> None:
    task = tasks.make("servo", mode=args.mode, n_starts=args.moves)
    config = loop.EANT2Config(
        population=args.population,
        exploit=ex.ExploitConfig(max_iters=args.max_iters, pruner=args.pruner),
    )

    def on_event(event):
        if event["event"] == "generation":
            on_generation(event)

    loop.run(
        task,
        key=jax.random.key(args.seed),
        config=config,
        generations=args.generations,
        callback=on_event,
    )


def bench_cold(args, clock: CompileClock) -> list[dict]:
    jax.clear_caches()  # cold even if this process compiled the same programs before
    rows: list[dict] = []
    mark = {"t": time.perf_counter(), **clock.snapshot()}

    def on_generation(event):
        now, snap = time.perf_counter(), clock.snapshot()
        row = {"generation": event["generation"], "wall_s": now - mark["t"]}
        for k in snap:
            row[k] = snap[k] - mark[k]
        row["other_s"] = row["wall_s"] - row["trace_s"] - row["lower_s"] - row["compile_s"]
        row["evaluations"] = event["evaluations"]
        rows.append(row)
        mark.update(t=time.perf_counter(), **clock.snapshot())

    _servo_run(args, on_generation)
    return rows


# -------------------------------------------------------------------------- trace analysis
def _union_seconds(intervals: list[tuple[float, float]]) -> float:
    """Total length (s) of the union of ``(start_us, end_us)`` intervals."""
    total, end = 0.0, -np.inf
    for a, b in sorted(intervals):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total * 1e-6


_PY_EVENT = re.compile(r"^\$(?P<file>[\w.]+\.py):\d+ (?P<func>[\w<>]+)$")


def analyse_trace(path: str | Path, ours: Sequence[str], top: int = 12) -> dict[str, Any]:
    """Summarise a Perfetto JSON trace written by ``jax.profiler.trace``.

    Args:
      path: ``perfetto_trace.json.gz``.
      ours: Python file names whose functions are reported (e.g. ``loop.py``).
      top: how many device ops and Python functions to list.

    Returns:
      ``windows`` (one per interval between ``_MARK`` instants: wall, device busy, copies),
      ``device_ops`` (name, count, seconds; over the whole trace), ``python`` (our functions'
      inclusive host seconds; nested calls of one function counted once), ``devices`` and
      ``per_device`` (each device's busy seconds, op count and the span from its first op's
      start to its last op's end, over the whole trace: devices that wait on each other
      show spans much longer than their busy time).
    """
    with gzip.open(path, "rt") as f:
        data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    names = {
        e["pid"]: e["args"]["name"]
        for e in events
        if e.get("ph") == "M" and e.get("name") == "process_name"
    }
    device_pids = {pid for pid, name in names.items() if name.startswith("/device:")}
    spans = [e for e in events if e.get("ph") == "X" and "dur" in e]
    marks = sorted(e["ts"] for e in events if e.get("name") == _MARK)
    start = min((e["ts"] for e in spans), default=0.0)
    bounds = [start, *marks]
    device = [e for e in spans if e["pid"] in device_pids]
    copies = [e for e in device if "memcpy" in e["name"].lower()]
    windows = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        inside = [(e["ts"], e["ts"] + e["dur"]) for e in device if a <= e["ts"] < b]
        cp = [e for e in copies if a <= e["ts"] < b]
        windows.append(
            {
                "wall_s": (b - a) * 1e-6,
                "device_busy_s": _union_seconds(inside),
                "device_ops": len(inside),
                "copies": len(cp),
                "copy_s": sum(e["dur"] for e in cp) * 1e-6,
                "h2d": sum("h2d" in e["name"].lower() for e in cp),
                "d2h": sum("d2h" in e["name"].lower() for e in cp),
            }
        )
    ops: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    for e in device:
        ops[e["name"]][0] += 1
        ops[e["name"]][1] += e["dur"] * 1e-6
    device_ops = [
        {"op": k, "count": c, "seconds": s}
        for k, (c, s) in sorted(ops.items(), key=lambda kv: -kv[1][1])[:top]
    ]
    # Inclusive host time of our Python functions (outermost call per thread only).
    per_func: dict[str, list[tuple[float, float, Any]]] = collections.defaultdict(list)
    for e in spans:
        m = _PY_EVENT.match(e["name"])
        if m and m["file"] in ours:
            per_func[f"{m['file']}:{m['func']}"].append((e["ts"], e["ts"] + e["dur"], e["tid"]))
    python = []
    for func, iv in per_func.items():
        by_thread = collections.defaultdict(list)
        for a, b, tid in iv:
            by_thread[tid].append((a, b))
        secs = sum(_union_seconds(v) for v in by_thread.values())
        python.append({"function": func, "calls": len(iv), "seconds": secs})
    python.sort(key=lambda r: -r["seconds"])
    per_device = []
    for pid in sorted(device_pids, key=lambda p: names[p]):
        iv = [(e["ts"], e["ts"] + e["dur"]) for e in device if e["pid"] == pid]
        span = (max(b for _, b in iv) - min(a for a, _ in iv)) * 1e-6 if iv else 0.0
        per_device.append(
            {"device": names[pid], "busy_s": _union_seconds(iv), "ops": len(iv), "span_s": span}
        )
    return {
        "windows": windows,
        "device_ops": device_ops,
        "python": python[:top],
        "devices": sorted(names[p] for p in device_pids),
        "per_device": per_device,
    }


_OURS = (
    "loop.py", "exploitation.py", "exploration.py", "compiler.py", "pruning.py",
    "rundir.py", "evaluate.py", "genome.py", "servo.py", "cmaes.py", "network.py",
)  # fmt: skip


def traced(call: Callable[[], Any], trace_dir: str | Path) -> tuple[Any, str]:
    """``call()`` under ``jax.profiler.trace`` into ``trace_dir``: its result and the
    Perfetto trace file it wrote."""
    trace_dir = Path(trace_dir)
    trace_dir.mkdir(parents=True, exist_ok=True)
    pattern = str(trace_dir / "**" / "perfetto_trace.json.gz")
    before = set(glob.glob(pattern, recursive=True))
    with jax.profiler.trace(str(trace_dir), create_perfetto_trace=True):
        out = call()
    new = sorted(set(glob.glob(pattern, recursive=True)) - before)
    if not new:
        raise RuntimeError(f"jax.profiler wrote no perfetto trace under {trace_dir}")
    return out, new[-1]


def bench_trace(args) -> dict[str, Any]:
    def on_generation(event):
        with jax.profiler.TraceAnnotation(_MARK):
            pass

    _, path = traced(lambda: _servo_run(args, on_generation), args.trace_dir)
    summary = analyse_trace(path, _OURS)
    for g, w in enumerate(summary["windows"]):
        w["generation"] = g
        w["device_busy_fraction"] = w["device_busy_s"] / w["wall_s"] if w["wall_s"] else None
    summary["trace_file"] = path
    return summary


# ------------------------------------------------------------------------------ compile
def _genome_sets(args, task) -> dict[str, list[Genome]]:
    rng = np.random.default_rng(args.seed)
    sets = {
        "minimal": [
            Genome(minimal_genome(rng, task.n_inputs, task.n_outputs))
            for _ in range(args.population)
        ]
    }
    for n_genes in args.compile_genes:
        sets[f"random {n_genes} genes"] = random_population(
            args.seed, args.population, n_genes, n_inputs=task.n_inputs, n_outputs=task.n_outputs
        )
    return sets


def _compile_case(args, networks: str, pruner: str, option: str) -> dict:
    """Lower, compile and run the exploitation program once, in this (fresh) process."""
    task = tasks.make("servo", mode=args.mode, n_starts=args.moves)
    genomes = _genome_sets(args, task)[networks]
    options = {} if option == "shipped" else dict([_parse_option(option)])
    config = ex.ExploitConfig(pruner=pruner, max_iters=10, chunk=10)
    batch, st, tables = exploit_batch(genomes, task, config, args.seed)
    call = (st, batch.layout, tables, task, jax.random.key(1), config)
    jax.block_until_ready(call)
    t0 = time.perf_counter()
    lowered = ex.run_chunk.lower(*call, 10)
    t1 = time.perf_counter()
    compiled = lowered.compile(compiler_options=options or None)
    t2 = time.perf_counter()
    jax.block_until_ready(compiled(*call))
    t3 = time.perf_counter()
    for _ in range(3):
        jax.block_until_ready(compiled(*call))
    t4 = time.perf_counter()
    return {
        "networks": networks,
        "pruner": pruner,
        "options": option,
        "structures": len(genomes),
        "P": batch.bucket.genes,
        "lower_s": t1 - t0,
        "compile_s": t2 - t1,
        "first_run_s": t3 - t2,
        "chunk_ms": (t4 - t3) / 3 * 1e3,
        "hlo_lines": lowered.as_text().count("\n"),
    }


def bench_compile(args) -> list[dict]:
    """Each case in a fresh process: XLA keeps compiled kernels and autotuning results for
    the life of a process, so a second compile of similar programs in one process is
    charged less (seen here: whichever variant went second looked up to 2x cheaper)."""
    task = tasks.make("servo", mode=args.mode, n_starts=args.moves)
    names = list(_genome_sets(args, task))
    rows = []
    for networks in names:
        for pruner in ("none", "covariance"):
            for option in ["shipped", *args.compiler_options]:
                case = json.dumps({"networks": networks, "pruner": pruner, "option": option})
                argv = [sys.executable, "-m", "bench", "profile", "--compile-case", case]
                argv += _shared_argv(args)
                # This process already holds most of the GPU's memory (JAX preallocates).
                env = {**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
                done = subprocess.run(argv, capture_output=True, text=True, check=False, env=env)
                if done.returncode:
                    raise RuntimeError(f"compile case {case} failed:\n{done.stderr[-2000:]}")
                rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows


def _shared_argv(args) -> list[str]:
    out = ["--population", str(args.population), "--moves", str(args.moves)]
    out += ["--mode", args.mode, "--seed", str(args.seed), "--compile-genes"]
    return out + [str(n) for n in args.compile_genes]


def _parse_option(text: str) -> tuple[str, Any]:
    name, _, value = text.partition("=")
    return name, _parse_value(value)


def _parse_value(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


# --------------------------------------------------------------------------------- main
def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--parts", default="cold,trace,compile")
    harness.run_options(p, population=20, generations=4, seed=0)
    p.add_argument("--max-iters", type=int, default=300)
    p.add_argument("--moves", type=int, default=1023)
    p.add_argument("--mode", default="kinematic")
    p.add_argument("--pruner", default="covariance")
    p.add_argument(
        "--compiler-options",
        nargs="*",
        default=["xla_gpu_autotune_level=0"],
        help="NAME=VALUE XLA options compared with the shipped ones (XLA's defaults) in the "
        "compile part",
    )
    p.add_argument(
        "--compile-genes",
        type=int,
        nargs="*",
        default=[160],
        help="sizes of random networks compiled in the compile part (besides minimal ones)",
    )
    p.add_argument("--compile-case", default=None, help=argparse.SUPPRESS)
    p.add_argument("--trace-dir", default="/tmp/eant2-profile")


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.population, args.generations, args.max_iters, args.moves = 3, 2, 10, 16
        args.compile_genes = [34]


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """The parts of ``--parts``, each saved as soon as it is done."""
    clock = CompileClock()
    parts = set(args.parts.split(","))
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args)}
    if "cold" in parts:
        payload["cold"] = bench_cold(args, clock)
        save(payload)
    if "trace" in parts:
        if "cold" not in parts:  # compile everything first, so the trace shows steady state
            _servo_run(args, lambda event: None)
        payload["trace"] = bench_trace(args)
        save(payload)
    if "compile" in parts:
        payload["compile"] = bench_compile(args)
    return payload


_G3 = "{:.3f}"
COLD = [
    Column("generation", "gen"), Column("wall_s", "wall s", "{:.2f}"),
    Column("compiles", "XLA compiles"), Column("trace_s", "tracing s", "{:.2f}"),
    Column("lower_s", "lowering s", "{:.2f}"), Column("compile_s", "compiling s", "{:.2f}"),
    Column("other_s", "rest s", "{:.2f}"),
]  # fmt: skip
WINDOWS = [
    Column("generation", "gen"), Column("wall_s", "wall s (traced)", _G3),
    Column("device_busy_s", "device busy s", _G3),
    Column("device_busy_fraction", "busy", "{:.0%}"), Column("device_ops", "device ops"),
    Column("h2d", "H2D copies"), Column("d2h", "D2H copies"), Column("copy_s", "copy s", "{:.4f}"),
]  # fmt: skip
COMPILE = [
    Column("networks", "networks"), Column("pruner", "pruner"),
    Column("options", "compiler options"), Column("P", "P"),
    Column("hlo_lines", "StableHLO lines"), Column("lower_s", "lowering s", "{:.2f}"),
    Column("compile_s", "compiling s", "{:.2f}"), Column("chunk_ms", "10 iterations ms", "{:.2f}"),
]  # fmt: skip


def render(payload: dict[str, Any]) -> str:
    trace = payload.get("trace") or {}
    parts = [("cold", "Cold run: wall time against compilation, per generation", COLD)]
    if trace:
        parts += [
            ("windows", "Warm run under the profiler, per generation", WINDOWS),
            ("device_ops", "Device ops by total time (whole warm run)", [
                Column(lambda r: r["op"][:60], "op"), Column("count", "count"),
                Column("seconds", "s", "{:.4f}"),
            ]),
            ("python", "eant2_jax Python functions by inclusive host time", [
                Column("function", "function"), Column("calls", "calls"),
                Column("seconds", "s", _G3),
            ]),
        ]  # fmt: skip
    parts.append(("compile", "Compiling the exploitation program (one bucket)", COMPILE))
    return harness.sections({**payload, **trace}, parts)


SUITE = harness.Suite(
    name="profile",
    title="Profile of an EANT2 servo run",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command-line entry point; returns the payload it wrote."""
    args = harness.parse_args(SUITE, argv)
    if args.compile_case:  # one case of the compile part, in its own process; no files
        row = _compile_case(args, **json.loads(args.compile_case))
        print(json.dumps(row))
        return row
    return harness.execute(SUITE, args)
