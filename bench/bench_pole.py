"""Evaluations to solve double pole balancing with EANT2, next to the published figures.

For each of ``--tasks`` (``dpv``: with velocities, balanced-steps fitness; ``dpnv``: without,
Gruau's damping fitness) and each of ``--seeds`` seeds, one ``eant2_jax.loop.run`` (EANT2
with covariance pruning) from the minimal network. After every generation the best genome is
checked with :func:`eant2_jax.tasks.pole.solved` (100,000 steps; for dpnv also the 625-start
generalisation test); the run stops at the first solved generation or when its evaluations
pass ``--budget`` (a failure). Evaluations are counted as the task module says (every
network run by the cost during evolution, CMA-ES candidates and pruning trials; the
``solved`` checks are tests and are not counted), at generation granularity: a run that
finds a solution mid-generation is charged the whole generation (its CMA-ES runs continue
until their stop rules fire, at most ``patience`` iterations after the last improvement).

Reported per task: success rate, mean and median evaluations over solved runs, the mean with
failures charged the budget, and wall time per solved run (compilation included: the first
seed pays most of it), next to Gomez, Schmidhuber & Miikkulainen (2008), tables 3-4.

Seeds can be split over processes or machines (``--first-seed``) and the result files
merged afterwards (``--merge``); a merge refuses files whose settings or devices differ, or
that share a seed.

Run: ``python -m bench pole [--quick] [--seeds N] [--first-seed K] [--tasks dpv dpnv]
[--out PATH]``, then ``python -m bench pole --merge A.json B.json ... --out PATH``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax

from bench import harness
from bench.common import BenchInputError, Column, environment, markdown_table
from eant2_jax import exploitation as ex
from eant2_jax import loop
from eant2_jax.compiler import networks
from eant2_jax.genome import Genome
from eant2_jax.tasks import pole

__all__ = ["PUBLISHED", "main", "solve_once"]

# Gomez, Schmidhuber & Miikkulainen (2008), JMLR 9: table 3 (DPV) and table 4 (DPNV, damping
# fitness); mean evaluations to solve.
PUBLISHED = {
    "dpv": {"NEAT": 3600, "ESP": 3800, "CMA-ES": 895, "CoSyNE": 954},
    "dpnv": {"NEAT": 6929, "ESP": 26342, "CMA-ES": 6061, "CoSyNE": 3416},
}


class _Solved(Exception):
    pass


def solve_once(task, seed: int, config: loop.EANT2Config, budget: int) -> dict:
    """One EANT2 run until ``solved`` or ``budget`` evaluations; its record."""
    t0 = time.perf_counter()
    info: dict[str, Any] = {"seed": seed, "solved": False, "evaluations": None, "generations": 0}

    def on_event(event):
        if event["event"] != "generation":
            return
        info["generations"] = event["generation"]
        info["evaluations"] = event["evaluations"]
        info["best_cost"] = event["best_cost"]
        genome = Genome.parse(event["best_genome"])
        net = jax.tree.map(lambda a: a[0], networks([genome], task.n_inputs))
        check = pole.solved(task, net)
        if check["solved"]:
            info.update(solved=True, genome=event["best_genome"], check=check)
            raise _Solved
        if event["evaluations"] >= budget:
            raise _Solved

    try:
        loop.run(
            task, key=jax.random.key(seed), config=config, generations=10**6, callback=on_event
        )
    except _Solved:
        pass
    info["wall_s"] = time.perf_counter() - t0
    return info


def _row(name: str, runs: list[dict], budget: int) -> dict:
    ok = [r for r in runs if r["solved"]]
    evals = [r["evaluations"] for r in ok]
    charged = [r["evaluations"] if r["solved"] else budget for r in runs]
    return {
        "task": name,
        "seeds": len(runs),
        "success_rate": len(ok) / len(runs),
        "mean_evals_solved": statistics.mean(evals) if evals else None,
        "median_evals_solved": statistics.median(evals) if evals else None,
        "mean_evals_failures_as_budget": statistics.mean(charged),
        "median_evals_failures_as_budget": statistics.median(charged),
        "wall_per_solved_s": (sum(r["wall_s"] for r in runs) / len(ok)) if ok else None,
        "median_wall_solved_s": statistics.median([r["wall_s"] for r in ok]) if ok else None,
        **{f"published_{k}": v for k, v in PUBLISHED[name].items()},
    }


COLUMNS = [
    Column("task", "task"),
    Column("seeds", "seeds"),
    Column("success_rate", "solved", "{:.0%}"),
    Column("mean_evals_solved", "mean evals (solved)", "{:.0f}"),
    Column("median_evals_solved", "median evals (solved)", "{:.0f}"),
    Column("mean_evals_failures_as_budget", "mean evals (fail = budget)", "{:.0f}"),
    Column("wall_per_solved_s", "wall s / solved run", "{:.1f}"),
    Column("published_NEAT", "NEAT"),
    Column("published_ESP", "ESP"),
    Column("published_CMA-ES", "CMA-ES"),
    Column("published_CoSyNE", "CoSyNE"),
]


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seeds", type=int, default=20, help="number of seeds")
    p.add_argument("--first-seed", type=int, default=0, help="seeds K, K+1, ...")
    p.add_argument("--tasks", nargs="+", default=["dpv", "dpnv"], choices=["dpv", "dpnv"])
    p.add_argument("--budget", type=int, default=40_000, help="evaluations before failure")
    p.add_argument("--population", type=int, default=10)
    p.add_argument("--max-iters", type=int, default=50)
    p.add_argument("--patience", type=int, default=10)
    p.add_argument("--prune-window", type=int, default=30)
    p.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="merge result files of this suite (same settings and device) instead of running",
    )


def _prepare(args: argparse.Namespace) -> None:
    if args.merge:
        if args.out is None:
            raise BenchInputError("--merge needs --out (the merged file)")
        if any(Path(args.out).resolve() == Path(m).resolve() for m in args.merge):
            raise BenchInputError(f"--out {args.out} is one of the merged files")
    elif args.quick:
        args.seeds, args.budget, args.tasks = 1, 50, ["dpv"]
        args.population, args.max_iters, args.patience, args.prune_window = 2, 3, 2, 2


# Settings that may differ between the files of one merge.
_PER_PART = ("seeds", "first_seed", "tasks", "out", "merge")


def merge(paths: Sequence[str]) -> tuple[dict, dict[str, list[dict]]]:
    """The runs of several result files of this suite, per task, checked to be one experiment.

    Returns:
      ``(first payload, runs per task)``.

    Raises:
      BenchInputError: naming the file whose settings or device differ from the first file's, or
        a seed that two files both ran.
    """
    payloads = []
    for path in paths:
        try:
            with open(path) as f:
                payloads.append(json.load(f))
        except (OSError, json.JSONDecodeError) as e:
            raise BenchInputError(f"cannot read {path}: {e}") from e
    first = payloads[0]

    def settings(p: dict) -> dict:
        return {k: v for k, v in p["config"].items() if k not in _PER_PART}

    runs: dict[str, list[dict]] = {}
    for path, p in zip(paths, payloads, strict=True):
        if p.get("suite") != "pole":
            raise BenchInputError(f"{path} is not a result file of the pole suite")
        if settings(p) != settings(first):
            diff = sorted(k for k in settings(p) if settings(p)[k] != settings(first).get(k))
            raise BenchInputError(f"{path} differs from {paths[0]} in its settings: {diff}")
        if p["device_kind"] != first["device_kind"]:
            raise BenchInputError(
                f"{path} ran on {p['device_kind']!r}, {paths[0]} on {first['device_kind']!r}"
            )
        for name, task_runs in p["runs"].items():
            seen = {r["seed"] for r in runs.get(name, [])}
            again = sorted(seen & {r["seed"] for r in task_runs})
            if again:
                raise BenchInputError(f"{path} repeats {name} seed(s) {again}")
            runs.setdefault(name, []).extend(task_runs)
    for task_runs in runs.values():
        task_runs.sort(key=lambda r: r["seed"])
    return first, runs


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """Run the seeds (saving after each), or merge the files of ``--merge``; the payload."""
    if args.merge:
        first, merged = merge(args.merge)
        args = argparse.Namespace(**{**first["config"], "merge": args.merge})
        args.seeds, args.tasks = sum(len(r) for r in merged.values()), list(merged)
    else:
        merged = None
    config = loop.EANT2Config(
        population=args.population,
        exploit=ex.ExploitConfig(
            pruner="covariance",
            max_iters=args.max_iters,
            patience=args.patience,
            prune_window=args.prune_window,
            chunk=min(10, args.max_iters),
        ),
    )
    rows, runs = [], {}

    # A merge keeps the environment (device, versions, date) of the runs it merges.
    env = environment() if merged is None else {k: first[k] for k in environment()}

    def payload() -> dict:
        return {
            **env,
            "suite": "pole",
            "config": {**harness.settings(args, "merge"), "eant2": config.to_dict()},
            "published_source": "Gomez, Schmidhuber & Miikkulainen 2008 (JMLR 9), tables 3-4",
            "rows": rows,
            "runs": runs,
        }

    if merged is not None:
        runs.update(merged)
        rows[:] = [_row(n, r, args.budget) for n, r in runs.items()]
        return payload()
    # Results are saved after every seed, so a run cut off by a time limit keeps them.
    for name in args.tasks:
        task = pole.dpv() if name == "dpv" else pole.dpnv()
        task_config = config
        if name == "dpv":
            # dpv's cost is -(steps balanced): a candidate at -max_steps balanced the whole
            # trial, so its CMA-ES stops there (pycma's ftarget) instead of running more
            # 100,000-step trials until its patience runs out. Evaluations are unchanged up
            # to that point; the solution check then runs as before.
            exploit = dataclasses.replace(config.exploit, target_cost=-float(task.max_steps))
            task_config = dataclasses.replace(config, exploit=exploit)
        runs[name] = []
        for s in range(args.first_seed, args.first_seed + args.seeds):
            runs[name].append(solve_once(task, s, task_config, args.budget))
            rows[:] = [_row(n, r, args.budget) for n, r in runs.items()]
            save(payload())
    return payload()


def render(payload: dict[str, Any]) -> str:
    seeds = ", ".join(f"{k} {len(v)}" for k, v in payload["runs"].items())
    return (
        f"EANT2 (covariance pruning) to solve double pole balancing; seeds per task: {seeds}; "
        f"budget {payload['config']['budget']} evaluations (failures charged the budget in the "
        "fail = budget column). Published columns: mean evaluations, Gomez et al. 2008.\n\n"
        + markdown_table(payload["rows"], COLUMNS)
    )


SUITE = harness.Suite(
    name="pole",
    title="Double pole balancing",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
