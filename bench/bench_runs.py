"""Many runs of one configuration on one device: in lock-step, in threads, one at a time.

Each mode runs the same ``--runs`` seeds of ``eant2_jax.run_many`` on the task in a fresh
process with no persistent compilation cache, timed from just before the process starts:

* ``lockstep``: `eant2_jax.run_lockstep` (each generation of every run tuned in one batch),
  the default of ``eant2 reproduce``;
* ``threads``: each run alone, ``--workers`` of them in flight (``--no-lockstep --workers``);
  on a CPU `run_many` runs one at a time whatever the workers (two programs at once can
  deadlock XLA's CPU thread pool), so this mode is ``sequential`` there;
* ``sequential``: each run alone, one after the other.

Reported per mode: seconds from process start to the end, the seconds of the runs alone
(after imports and task set-up), XLA programs compiled, and the runs' mean final best cost
and evaluations (lock-step shares the padding bucket between runs, so its runs may differ
from the others'; `eant2_jax.lockstep`).

Run: ``python -m bench runs [--task servo] [--runs 10] [--generations 3] [--population 20]``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import textwrap
import time
from typing import Any

from bench import harness
from bench.common import Column, child_env, eant2_pruner, environment, markdown_table
from eant2_jax.app.parser import task_options

_CHILD = textwrap.dedent(
    """
    import json, sys, time
    t_start = time.perf_counter()
    import jax
    import eant2_jax as E
    from eant2_jax.programs import stats as compilestats
    spec = json.loads(sys.argv[1])
    task = E.tasks.make(spec["task"], **spec["options"])
    exploit = {"pruner": spec["pruner"]}
    if spec["max_iters"] is not None:
        exploit["max_iters"] = spec["max_iters"]
    config = E.EANT2Config(population=spec["population"], exploit=E.ExploitConfig(**exploit))
    keys = [jax.random.key(s) for s in range(spec["seed"], spec["seed"] + spec["runs"])]
    before = compilestats.snapshot()
    t0 = time.perf_counter()
    res = E.run_many(task, keys, config=config, generations=spec["generations"],
                     workers_per_device=spec["workers"], lockstep=spec["lockstep"])
    t1 = time.perf_counter()
    done = compilestats.snapshot() - before
    print(json.dumps({
        "setup_s": t0 - t_start, "runs_s": t1 - t0, "compiles": done.programs,
        "compile_s": done.seconds,
        "best": [r.generations[-1].best_cost for r in res],
        "evaluations": [r.generations[-1].evaluations for r in res],
        "device": jax.devices()[0].device_kind,
    }))
    """
)

MODES = {"lockstep": (True, None), "threads": (False, "workers"), "sequential": (False, 1)}


def _one(args, mode: str) -> dict[str, Any]:
    lockstep, workers = MODES[mode]
    spec = {
        "task": args.task, "options": task_options(args.task_option), "runs": args.runs,
        "generations": args.generations, "population": args.population,
        "max_iters": args.max_iters, "seed": args.seed, "lockstep": lockstep,
        "workers": args.workers if workers == "workers" else 1,
        "pruner": eant2_pruner(args.quick),
    }  # fmt: skip
    env = child_env(EANT2_CACHE_DIR="", JAX_ENABLE_COMPILATION_CACHE="false")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(spec)], env=env,
                              cwd=tmp, capture_output=True, text=True)  # fmt: skip
        total = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"{mode} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"mode": mode, "total_s": total, **out,
            "best_mean": sum(out["best"]) / len(out["best"]),
            "evaluations_mean": sum(out["evaluations"]) / len(out["evaluations"])}  # fmt: skip


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    for mode in args.modes:
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; modes: {', '.join(MODES)}")
        payload["rows"].append(_one(args, mode))
        save(payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    harness.run_options(p, task="servo", population=20, generations=3, seed=0)
    p.add_argument("--task-option", action="append", default=[], metavar="KEY=VALUE",
                   help="as for eant2 run (VALUE is JSON or a string)")  # fmt: skip
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--max-iters", type=int, default=None)
    p.add_argument("--workers", type=int, default=10, help="runs in flight in 'threads'")
    p.add_argument("--modes", nargs="+", default=list(MODES))


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.task, args.runs, args.generations, args.population = "xor", 2, 1, 4
        args.max_iters, args.workers = 30, 2


COLUMNS = [
    Column("mode", "mode"),
    Column("total_s", "s from process start", "{:.1f}"),
    Column("runs_s", "s of the runs", "{:.1f}"),
    Column("compiles", "XLA programs"),
    Column("compile_s", "compiling s", "{:.1f}"),
    Column("best_mean", "mean final best cost", "{:.4g}"),
    Column("evaluations_mean", "mean evaluations", "{:,.0f}"),
]

SUITE = harness.Suite(
    name="runs",
    title="Many runs on one device: lock-step, threads, one at a time",
    description=__doc__,
    options=_options,
    run=run,
    render=lambda payload: markdown_table(payload["rows"], COLUMNS),
    prepare=_prepare,
)

main = SUITE.main
