"""Evaluations to solve double pole balancing with EANT2, next to the published figures.

For each of ``--tasks`` (``dpv``: with velocities, balanced-steps fitness; ``dpnv``: without,
Gruau's damping fitness) and each of ``--seeds`` seeds, one ``eant2_jax.loop.run`` (EANT2
with covariance pruning) with :func:`eant2_jax.tasks.pole.solved` as its ``solution_test``
(100,000 steps; for dpnv also the 625-start generalisation test): the loop tests the best
network of every structure it is tuning whenever that network improves, after every
``--chunk`` CMA-ES iterations (default 1: every iteration), and stops at the first that
passes. A run whose evaluations pass ``--budget`` at the end of a generation is a failure.
The tasks in ``--recurrent-start`` (default dpnv) start from the recurrent-ready minimal
network (``EANT2Config.init_recurrent``: the output neuron reads its own previous output
through a weight-0 jumper).

**Accounting** (as Gomez, Schmidhuber & Miikkulainen 2008 count, and NEAT and ESP): one
evaluation = one network run by the task's cost during evolution: every CMA-ES candidate
and every network a pruning attempt evaluates, of every structure in the batch (the
structures of a generation are tuned together, in lock-step), up to and including the
iteration after which the solution test passed. The solution test's own runs (the
100,000-step run and the 625 starts) are not counted.

Reported per task: success rate, mean and median evaluations over solved runs, the mean with
failures charged the budget, the generalisation scores (of 625) of the solutions, and wall
time per solved run (compilation included: the first seed pays most of it), next to Gomez
et al. (2008), tables 3-4.

Seeds can run concurrently (``--workers``: threads of one process, sharing the device and
its compiled programs; a run's result does not depend on it), be split over processes or
machines (``--first-seed``) and the result files merged afterwards (``--merge``); a merge
refuses files whose settings or devices differ, or that share a seed. On a CPU, threads
share XLA's CPU thread pool, where concurrent programs can deadlock it (jaxlib's batched
LAPACK map; `eant2_jax.run_many` runs one at a time on CPUs for that reason): two workers
on the 2-core machine ran the pole suite fine, but for many seeds on a large CPU prefer
several processes (``--first-seed``) and ``--merge``.

**The protocol's runs** (docs/protocol.md, section 4): ``--protocol`` runs six variants on
seeds 5000-5019 (``--first-seed``/``--seeds`` move them), with the settings above: dpv, dpnv
from the recurrent-ready start and dpnv from the paper's minimal start, each under two rules
of the solution test (``EANT2Config.solution_rule``): ``champion``, the generation's champion
alone once per generation, as the published methods test, and ``structure``, the library's
test of every structure's improved best. Evaluations are counted alike (every network run
during evolution; the test not counted). Reported per variant: solved runs with a Wilson 95%
interval, the median evaluations to solve over all seeds (an unsolved run never reaches a
solution) with its percentile bootstrap interval (`eant2_jax.app.report_stats`, key
``jax.random.key(0)``, 10,000 resamples), the mean over solved runs, the solutions found in
generation 0 and the solution tests called per run. Default output
``bench/results/pole-protocol-<device tag>.json``.

Run: ``python -m bench pole [--quick] [--seeds N] [--first-seed K] [--tasks dpv dpnv]
[--solution-rule RULE] [--workers W] [--out PATH]``, then ``python -m bench pole --merge
A.json B.json ... --out PATH``; ``python -m bench pole --protocol [--variants V ...]``.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import json
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax

from bench import harness
from bench.common import BenchInputError, default_out, eant2_pruner, environment
from bench.pole_tables import (
    ACCOUNTING,
    PROTOCOL,
    PROTOCOL_ACCOUNTING,
    protocol_row,
    render,
    task_row,
)
from eant2_jax import exploitation as ex
from eant2_jax import loop
from eant2_jax.compiler import networks
from eant2_jax.genome import Genome
from eant2_jax.tasks import pole

__all__ = [
    "main",
    "solution_test",
    "solve_once",
    "task_config",
    "test_device",
]

PROTOCOL_SEEDS = (5000, 20)  # first seed, count (docs/protocol.md: 5000-5019)


class _OverBudget(Exception):
    pass


def solution_test(
    task, passed: list | None = None, device: jax.Device | None = None
) -> Callable[[Genome], bool]:
    """The bench's ``solution_test``: `pole.solved` of one genome, screened first.

    The screen is `pole.solved` with a 1,000-step long run (the 625 starts included): a
    network that fails it fails the full test, which then runs only for the rest (its
    100,000-step run is the slow part, seconds on a GPU). Neither is counted as evaluations.
    A genome that passes is appended to ``passed`` with its full check (`pole.solved`'s
    dict). ``device``: where the test runs (the task and the network are put there;
    default: JAX's default device).
    """
    if device is not None:
        task = jax.device_put(task, device)

    def test(genome: Genome) -> bool:
        with _on(device):
            net = jax.tree.map(lambda a: a[0], networks([genome], task.n_inputs))
            if not pole.solved(task, net, long_steps=1000)["solved"]:
                return False
            check = pole.solved(task, net)
        if check["solved"] and passed is not None:
            passed.append((genome, check))
        return check["solved"]

    return test


def _on(device: jax.Device | None):
    """``jax.default_device(device)``, or nothing for None."""
    return contextlib.nullcontext() if device is None else jax.default_device(device)


def test_device(name: str) -> jax.Device | None:
    """``--test-device``: ``cpu`` (the host's CPU; also on a GPU machine) or ``default``."""
    return None if name == "default" else jax.devices("cpu")[0]


def solve_once(
    task, seed: int, config: loop.EANT2Config, budget: int, device: jax.Device | None = None
) -> dict:
    """One EANT2 run until its solution test passes or ``budget`` evaluations; its record.

    A run is solved when a network passes the test with at most ``budget`` evaluations
    spent; an unsolved run stops after the first generation that ends past the budget.
    """
    t0 = time.perf_counter()
    info: dict[str, Any] = {"seed": seed, "solved": False, "evaluations": None, "generations": 0}
    passed: list[tuple[Genome, dict]] = []
    check = solution_test(task, passed, device)
    info["tests"] = 0

    def counted(genome: Genome) -> bool:
        info["tests"] += 1
        return check(genome)

    def on_event(event):
        if event["event"] != "generation":
            return
        info["generations"] = event["generation"]
        info["evaluations"] = event["evaluations"]
        info["best_cost"] = event["best_cost"]
        if event["evaluations"] >= budget and not passed:
            raise _OverBudget

    try:
        result = loop.run(
            task,
            key=jax.random.key(seed),
            config=config,
            generations=10**6,
            callback=on_event,
            solution_test=counted,
        )
    except _OverBudget:
        result = None
    if result is not None and result.solution is not None and info["evaluations"] <= budget:
        genome = result.solution.genome
        # The solution is the genome that passed the test, which checked it in full.
        found = next(c for g, c in passed if str(g) == str(genome))
        info.update(solved=True, genome=str(genome), check=found)
        info["solution_cost"] = result.solution.cost
    info["wall_s"] = time.perf_counter() - t0
    return info


def _options(p: argparse.ArgumentParser) -> None:
    harness.run_options(p, seeds=None, first_seed=None, population=10)
    p.add_argument("--tasks", nargs="+", default=["dpv", "dpnv"], choices=["dpv", "dpnv"])
    p.add_argument("--budget", type=int, default=40_000, help="evaluations before failure")
    p.add_argument(
        "--offspring", type=int, default=None, help="EANT2Config.offspring (default: population)"
    )
    p.add_argument(
        "--recurrent-start",
        nargs="*",
        default=["dpnv"],
        choices=["dpv", "dpnv"],
        help="tasks that start from the recurrent-ready minimal network "
        "(EANT2Config.init_recurrent; default: dpnv)",
    )
    p.add_argument(
        "--solution-rule",
        choices=["structure", "champion"],
        default="structure",
        help="which networks the solution test tests (EANT2Config.solution_rule): every "
        "structure's improved best (default) or the generation's champion alone",
    )
    p.add_argument(
        "--protocol",
        action="store_true",
        help="the protocol's six variants (docs/protocol.md, section 4) on seeds 5000-5019 "
        "unless --first-seed/--seeds say otherwise; --tasks, --recurrent-start and "
        "--solution-rule are then the variants'",
    )
    p.add_argument(
        "--variants",
        nargs="+",
        choices=list(PROTOCOL),
        default=None,
        help="with --protocol: run only these variants (default all, dpnv first)",
    )
    p.add_argument(
        "--inherit-search",
        action="store_true",
        help="children start from their parent's covariance (EANT2Config.inherit_search)",
    )
    p.add_argument(
        "--reexploit", action="store_true", help="tune surviving parents again (EANT2Config)"
    )
    p.add_argument("--popsize", type=int, default=16, help="CMA-ES candidates per iteration")
    p.add_argument("--sigma0", type=float, default=1.0, help="CMA-ES initial step size")
    p.add_argument("--max-iters", type=int, default=50)
    p.add_argument("--patience", type=int, default=10)
    p.add_argument("--prune-window", type=int, default=30)
    p.add_argument(
        "--chunk",
        type=int,
        default=1,
        help="CMA-ES iterations between solution tests (ExploitConfig.chunk; default 1)",
    )
    p.add_argument(
        "--workers", type=int, default=1, help="runs in flight at once (threads; default 1)"
    )
    p.add_argument(
        "--test-device",
        choices=["cpu", "default"],
        default="cpu",
        help="where the solution test runs: the host's CPU (default; on a GPU machine the "
        "evolution stays on the GPU) or JAX's default device",
    )
    p.add_argument(
        "--merge",
        nargs="+",
        metavar="JSON",
        help="merge result files of this suite (same settings and device) instead of running",
    )


def _prepare(args: argparse.Namespace) -> None:
    first, count = PROTOCOL_SEEDS if args.protocol else (0, 20)
    args.first_seed = first if args.first_seed is None else args.first_seed
    args.seeds = count if args.seeds is None else args.seeds
    if args.variants is not None and not args.protocol:
        raise BenchInputError("--variants needs --protocol")
    if args.protocol:
        args.variants = list(args.variants or PROTOCOL)
        args.tasks = sorted({PROTOCOL[v][0] for v in args.variants})
        if args.out is None and not args.render and not args.merge:
            args.out = str(default_out("pole-protocol"))
    if args.merge:
        if args.out is None:
            raise BenchInputError("--merge needs --out (the merged file)")
        if any(Path(args.out).resolve() == Path(m).resolve() for m in args.merge):
            raise BenchInputError(f"--out {args.out} is one of the merged files")
    elif args.quick:
        # A budget that generation 0 spends: every seed's run stops there, in the one padding
        # bucket of the minimal networks, so that runs of other seeds compile nothing new.
        args.seeds, args.budget, args.tasks = 1, 10, ["dpv"]
        args.population, args.max_iters, args.patience, args.prune_window = 2, 3, 2, 2
        args.popsize = 4


# Settings that may differ between the files of one merge.
_PER_PART = ("seeds", "first_seed", "tasks", "variants", "out", "merge", "workers")


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
        return {k: v for k, v in p["config"].items() if k not in (*_PER_PART, "eant2")}

    runs: dict[str, list[dict]] = {}
    for path, p in zip(paths, payloads, strict=True):
        if p.get("suite") != "pole":
            raise BenchInputError(f"{path} is not a result file of the pole suite")
        if settings(p) != settings(first):
            diff = sorted(k for k in settings(p) if settings(p)[k] != settings(first).get(k))
            raise BenchInputError(f"{path} differs from {paths[0]} in its settings: {diff}")
        # The EANT2 configurations (derived from the settings) of the tasks both files ran.
        ours, theirs = p["config"].get("eant2", {}), first["config"].get("eant2", {})
        if any(ours[t] != theirs[t] for t in set(ours) & set(theirs)):
            raise BenchInputError(f"{path} differs from {paths[0]} in its EANT2 configuration")
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
    # A file cut off before a group's first run holds it empty: nothing to merge.
    return first, {name: r for name, r in runs.items() if r}


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """Run the seeds (saving after each), or merge the files of ``--merge``; the payload."""
    if args.merge:
        first, merged = merge(args.merge)
        args = argparse.Namespace(**{**first["config"], "merge": args.merge})
        args.seeds = sum(len(r) for r in merged.values())
        if getattr(args, "protocol", False):
            args.variants = list(merged)
        else:
            args.tasks = list(merged)
    else:
        merged = None
    rows, runs = [], {}
    protocol = getattr(args, "protocol", False)
    row = protocol_row if protocol else task_row

    # A merge keeps the environment (device, versions, date) of the runs it merges.
    env = environment() if merged is None else {k: first[k] for k in environment()}
    # The groups of runs: the protocol's variants, or the tasks.
    groups = (
        {
            v: (PROTOCOL[v][0], task_config(args, PROTOCOL[v][0], PROTOCOL[v][1:]))
            for v in args.variants
        }
        if protocol
        else {name: (name, task_config(args, name)) for name in args.tasks}
    )
    configs = {name: config for name, (_, config) in groups.items()}

    def payload() -> dict:
        return {
            **env,
            "suite": "pole",
            "config": {
                **harness.settings(args, "merge"),
                "eant2": {name: c.to_dict() for name, c in configs.items()},
            },
            "published_source": "Gomez, Schmidhuber & Miikkulainen 2008 (JMLR 9), tables 3-4",
            "accounting": PROTOCOL_ACCOUNTING if protocol else ACCOUNTING,
            "rows": rows,
            "runs": runs,
        }

    if merged is not None:
        runs.update(merged)
        rows[:] = [row(n, r, args.budget) for n, r in runs.items()]
        return payload()
    # Results are saved after every run, so a run cut off by a time limit keeps them.
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    jobs = [(name, s) for name in groups for s in seeds]
    made = {t: pole.dpv() if t == "dpv" else pole.dpnv() for t, _ in groups.values()}
    for name in groups:
        runs[name] = []
    lock = threading.Lock()
    device = test_device(args.test_device)

    def one(job):
        name, s = job
        info = solve_once(made[groups[name][0]], s, configs[name], args.budget, device)
        with lock:
            runs[name].append(info)
            runs[name].sort(key=lambda r: r["seed"])
            rows[:] = [row(n, r, args.budget) for n, r in runs.items() if r]
            save(payload())

    t0 = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max(1, args.workers)) as pool:
        for f in [pool.submit(one, job) for job in jobs]:
            f.result()
    env["wall_total_s"] = time.perf_counter() - t0
    return payload()


def task_config(
    args: argparse.Namespace, name: str, variant: tuple[bool, str] | None = None
) -> loop.EANT2Config:
    """The EANT2 configuration of one task from the suite's options; ``variant``: a
    protocol variant's ``(recurrent-ready start, solution rule)`` in place of the options'."""
    recurrent, rule = variant or (
        name in args.recurrent_start,
        getattr(args, "solution_rule", "structure"),
    )
    return loop.EANT2Config(
        population=args.population,
        offspring=args.offspring,
        init_recurrent=recurrent,
        solution_rule=rule,
        inherit_search=getattr(args, "inherit_search", False),
        reexploit=getattr(args, "reexploit", False),
        exploit=ex.ExploitConfig(
            # The protocol's variants keep their pruner in a quick run too.
            pruner=eant2_pruner(
                getattr(args, "quick", False) and not getattr(args, "protocol", False)
            ),
            popsize=args.popsize,
            sigma0=args.sigma0,
            max_iters=args.max_iters,
            patience=args.patience,
            prune_window=args.prune_window,
            chunk=min(args.chunk, args.max_iters),
        ),
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
