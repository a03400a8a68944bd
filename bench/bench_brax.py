"""brax tasks end to end: ``eant2 run brax:ENV`` and ``eant2 resume`` from process start,
then the best network's return on new episodes. A case may name another environment family
instead (``playground:CartpoleBalance ARGS...``: MuJoCo Playground).

Each case starts ``eant2 run brax:ENV ARGS...`` in a fresh process (as a user does, with an
empty compilation cache) and times it from just before the process starts to its exit; then
``eant2 resume`` of the run directory likewise (same cache); then, in this process, the run's
``best.genome`` plays ``--episodes`` new episodes (a key no run used) of the task the run
directory records. A case that outruns what is left of ``--budget-s`` is stopped and
reported as such, with whatever generations it had finished.

Run: ``python -m bench brax [--case "ENV ARGS..."]... [--budget-s 300]``; the default cases
(``CASES``, spring backend) are ``inverted_pendulum`` to its maximum return (1000) and a
short ``hopper`` run.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    eant2_argv,
    environment,
    markdown_table,
    unseen_key,
)
from eant2_jax.tasks.brax_task import PRECISIONS  # (brax itself is imported on first use)

# The spring backend: on an H100 (2026-11-23) a generalized-backend inverted_pendulum run did
# not finish its first generation in 262 s (bench/results/brax-generalized-gpu-h100.md, 3a13bcd);
# spring's step is one small loop with few scatters (generalized: 4 loops, 68 scatters).
CASES = (
    "inverted_pendulum --task-option backend=spring --population 10 --max-iters 50 "
    "--generations 2 --target-cost -1000",
    "hopper --task-option backend=spring --population 10 --max-iters 20 --generations 0",
)
# The quick case on spring too: on a 2-core CPU its programs compile in ~12% less time than
# the generalized backend's (the test suite runs it).
QUICK = ("inverted_pendulum --task-option backend=spring --population 2 --max-iters 3 "
         "--generations 0 --no-prune --task-option max_steps=20",)  # fmt: skip


def _cli(args: list[str], *, cwd: str, env: dict, timeout: float) -> tuple[str, float, str]:
    """``eant2 ARGS`` in a new process: ("ok" | "failed" | "timed out", seconds, stderr)."""
    cmd = eant2_argv(*args)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=max(timeout, 1.0))  # fmt: skip
    except subprocess.TimeoutExpired as e:
        err = e.stderr.decode() if isinstance(e.stderr, bytes) else (e.stderr or "")
        return "timed out", time.perf_counter() - t0, err
    return ("ok" if proc.returncode == 0 else "failed"), time.perf_counter() - t0, proc.stderr


def _last_generation(run_dir: Path) -> dict[str, Any]:
    path = run_dir / "generations.jsonl"
    lines = path.read_text().splitlines() if path.is_file() else []
    return json.loads(lines[-1]) if lines else {}


def _new_returns(run_dir: Path, episodes: int, seed: int, **options: Any) -> list[float]:
    """Returns of the run's best network on ``episodes`` new episodes, of the task the run
    recorded with ``options`` put over its own (e.g. another ``precision``)."""

    from eant2_jax import tasks
    from eant2_jax.compiler import networks
    from eant2_jax.genomefile import GenomeFile
    from eant2_jax.tasks.episodic import returns

    meta = json.loads((run_dir / "config.json").read_text())
    task = tasks.make(meta["task"], **{**meta["task_options"], **options})
    genome = GenomeFile.read(run_dir / "best.genome").genome
    nets = networks([genome], task.n_inputs)
    return returns(task, nets, key=unseen_key(seed), episodes=episodes)[0].tolist()


def _case(spec: str, args, deadline: float) -> dict[str, Any]:
    env_name, *extra = shlex.split(spec)
    # "ENV" is a brax environment; "playground:ENV" (any "NAMESPACE:NAME") is run as named.
    task = env_name if ":" in env_name else f"brax:{env_name}"
    row: dict[str, Any] = {"case": spec, "task": task, "seed": args.seed}
    with tempfile.TemporaryDirectory() as tmp:
        environ = dict(os.environ, EANT2_CACHE_DIR=str(Path(tmp) / "cache"))
        run_dir = Path(tmp) / "run"
        argv = ["run", row["task"], "--seed", str(args.seed), "--out", str(run_dir), *extra]
        status, seconds, err = _cli(argv, cwd=tmp, env=environ,
                                    timeout=deadline - time.perf_counter())  # fmt: skip
        last = _last_generation(run_dir)
        row.update(run=status, run_s=seconds, run_log=err.strip().splitlines()[-8:])
        for key in ("generation", "evaluations", "best_cost", "best_size", "best_genome"):
            row[key] = last.get(key)
        if status == "failed":
            row["error"] = err.strip().splitlines()[-1:] or ["?"]
            return row
        if not last:
            return row
        status, seconds, err = _cli(["resume", str(run_dir)], cwd=tmp, env=environ,
                                    timeout=deadline - time.perf_counter())  # fmt: skip
        after = _last_generation(run_dir)
        row.update(resume=status, resume_s=seconds, resume_log=err.strip().splitlines()[-4:],
                   resume_best_cost=after.get("best_cost"),
                   resume_generations=after.get("generation"))  # fmt: skip
        if status == "failed":
            row["error"] = err.strip().splitlines()[-1:] or ["?"]
        if args.episodes and time.perf_counter() < deadline:
            t0 = time.perf_counter()
            r = _new_returns(run_dir, args.episodes, args.seed)
            row.update(new_episodes=len(r), new_return_mean=sum(r) / len(r),
                       new_return_min=min(r), new_return_max=max(r),
                       new_eval_s=time.perf_counter() - t0)  # fmt: skip
            for precision in args.replay_precision:  # the same episodes, other physics
                r = _new_returns(run_dir, args.episodes, args.seed, precision=precision)
                row[f"new_return_mean_{precision}"] = sum(r) / len(r)
                row[f"new_return_min_{precision}"] = min(r)
    return row


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    deadline = time.perf_counter() + args.budget_s
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    for spec in args.case:
        if time.perf_counter() >= deadline:
            payload["rows"].append({"case": spec, "run": "not started (budget spent)"})
        else:
            payload["rows"].append(_case(spec, args, deadline))
        save(payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--case", action="append", default=None,
                   help='"ENV ARGS...": brax:ENV (or a task NAMESPACE:NAME, e.g. '
                   "playground:CartpoleBalance) and arguments of eant2 run (repeatable; "
                   "default: the two cases of the module docstring)")  # fmt: skip
    harness.run_options(p, seed=0)
    p.add_argument("--episodes", type=int, default=100,
                   help="new episodes the best network plays after the run (0: none)")  # fmt: skip
    p.add_argument("--budget-s", type=float, default=600.0,
                   help="wall time for all cases; a case running past it is stopped")  # fmt: skip
    p.add_argument("--replay-precision", action="append", default=[], choices=PRECISIONS,
                   help="the best network also plays the same new episodes with the brax "
                   "task's precision set to this (repeatable)")  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if args.case is None:
        args.case = list(QUICK if args.quick else CASES)
    if args.quick:
        args.episodes = min(args.episodes, 4)
    if args.episodes < 0 or args.budget_s <= 0:
        raise BenchInputError("--episodes must be >= 0 and --budget-s > 0")


COLUMNS = [
    Column("case", "brax:ENV and eant2 run arguments"),
    Column("run", "run"),
    Column("generation", "last generation"),
    Column("evaluations", "evaluations", "{:,}"),
    Column("run_s", "run s (from process start)", "{:.1f}"),
    Column("best_cost", "best cost (re-evaluated)", "{:g}"),
    Column("best_size", "size"),
    Column("resume", "resume"),
    Column("resume_s", "resume s", "{:.1f}"),
    Column("resume_best_cost", "best cost after resume", "{:g}"),
    Column("new_return_mean", "mean return, new episodes", "{:.1f}"),
    Column("new_return_min", "min", "{:g}"),
    Column("new_episodes", "episodes"),
]


def render(payload: dict[str, Any]) -> str:
    columns = list(COLUMNS)
    for precision in payload["config"].get("replay_precision") or []:
        columns += [
            Column(f"new_return_mean_{precision}", f"mean return, precision={precision}",
                   "{:.1f}"),
            Column(f"new_return_min_{precision}", "min", "{:g}"),
        ]  # fmt: skip
    out = markdown_table(payload["rows"], columns)
    genomes = [f"* `{r['case']}`: `{r['best_genome']}`" for r in payload["rows"]
               if r.get("best_genome")]  # fmt: skip
    return out + ("\nBest genomes:\n\n" + "\n".join(genomes) + "\n" if genomes else "")


SUITE = harness.Suite(
    name="brax",
    title="brax tasks, run and resume",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
