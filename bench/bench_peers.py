"""Peers on the servo task: the same cost and the same evaluation budget for every method.

Each method tunes controllers for the servo task (1023 start poses, kinematic mode, one move
per start: ``tasks.make("servo")``) until it has spent ``--budget`` evaluations (one
evaluation = one network scored on all 1023 starts). Every cost is the task's own JAX cost:

* ``cmaes-h{H}`` (evosax ``CMA_ES``): a FIXED fully connected ``10-H-3`` network written as an
  EANT2 genome (`bench.peer_methods.fixed_genome`), compiled once; ``ask``, the batched
  ``task.cost`` of the population and ``tell`` are one jitted step.
* ``pycma-h{H}``: the same networks tuned by pycma (NumPy, host), each population scored by the
  same jitted ``task.cost`` placed on the CPU (``--pycma-device``): the "original EANT2 on a
  CPU" reference. pycma restarts (same start, new seed) if it meets a stop criterion.
* ``neat``: neat-python (pop 150, 10 inputs, 3 outputs). With one move per start the 1023
  inputs are fixed data (``task.x_start``), so each genome's outputs over all starts are
  computed on the host (`bench.peer_methods.neat_outputs`, vectorised over starts) and scored
  on device by `bench.peer_methods.outputs_cost` (the servo move from each start, exactly what
  ``Servo.episode`` does for one move). One evaluation per genome, as NEAT counts.
* ``eant2``: this project (``eant2_jax.loop.run``, covariance pruning; none with
  ``--quick``); its evaluations come from its generation records, so its curve has one point
  per generation and it may overshoot the budget by part of a generation (the best cost *at*
  the budget is taken from the last generation within it).

For each method: best cost against evaluations and against wall time (a point every
``--every`` evaluations; wall time from the method's start, XLA compilation included),
the final best cost within the budget, and the evaluations and wall time at which it first
reached the final best cost of the fixed-network evosax CMA-ES (the largest ``H`` run).

Run: ``python -m bench peers [--quick] [--budget N] [--methods ...]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

import jax

from bench import harness
from bench.common import Column, eant2_pruner, environment, markdown_table
from bench.peer_methods import Curve, run_eant2, run_evosax, run_neat, run_pycma
from eant2_jax import exploitation as ex
from eant2_jax import loop, tasks

__all__ = ["main"]


# ---------------------------------------------------------------------------- the suite
def _summary(name: str, curve: Curve, budget: int, target: float | None) -> dict:
    within = [p for p in curve.points if p["evaluations"] <= budget]
    final = within[-1]["best_cost"] if within else None
    reach = None
    if target is not None:
        reach = next((p for p in curve.points if p["best_cost"] <= target), curve.reached)
        if reach is not None and reach["evaluations"] > budget:
            reach = None
    return {
        "method": name,
        "best_cost_at_budget": final,
        "best_cost_end": curve.best,
        "evaluations_used": curve.evals,
        "evals_to_target": None if reach is None else reach["evaluations"],
        "wall_to_target_s": None if reach is None else reach["wall_s"],
        "total_wall_s": curve.points[-1]["wall_s"] if curve.points else None,
        "curve": curve.points,
    }


COLUMNS = [
    Column("method", "method"),
    Column("best_cost_at_budget", "best cost at budget", "{:.5f}"),
    Column("evaluations_used", "evals used"),
    Column(
        lambda r: r["evals_to_target"] if r["evals_to_target"] is not None else "not reached",
        "evals to target",
    ),
    Column("wall_to_target_s", "wall to target s", "{:.1f}"),
    Column("total_wall_s", "total wall s", "{:.1f}"),
]


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--budget", type=int, default=20_000, help="evaluations per method")
    p.add_argument("--every", type=int, default=None, help="curve spacing (default budget/50)")
    p.add_argument("--hidden", type=int, nargs="+", default=[0, 5, 10])
    p.add_argument(
        "--methods",
        nargs="+",
        default=["cmaes", "pycma", "neat", "eant2"],
        choices=["cmaes", "pycma", "neat", "eant2"],
    )
    harness.run_options(p, seed=0)
    p.add_argument("--sigma0", type=float, default=0.5)
    p.add_argument("--n-starts", type=int, default=1023)
    p.add_argument("--pycma-device", default="cpu", help="cpu or default")
    p.add_argument("--neat-pop", type=int, default=150)
    p.add_argument("--eant2-population", type=int, default=10)
    p.add_argument("--eant2-max-iters", type=int, default=100)
    p.add_argument("--eant2-patience", type=int, default=30)
    p.add_argument("--eant2-prune-window", type=int, default=30)
    p.add_argument(
        "--compilation-cache",
        default=None,
        metavar="DIR",
        help="JAX's persistent compilation cache (as the eant2 CLI uses); a second run with "
        "the same DIR measures wall times without compilation",
    )


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.budget, args.n_starts, args.hidden = 100, 8, [2]
        args.neat_pop, args.eant2_population, args.eant2_max_iters = 30, 2, 3
        args.eant2_patience, args.eant2_prune_window = 5, 3


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    """Every method to the budget, one after another; the payload."""
    if args.compilation_cache:
        jax.config.update("jax_compilation_cache_dir", args.compilation_cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    every = args.every or max(args.budget // 50, 1)
    task = tasks.make("servo", n_starts=args.n_starts, mode="kinematic")
    eant2_config = loop.EANT2Config(
        population=args.eant2_population,
        exploit=ex.ExploitConfig(
            pruner=eant2_pruner(args.quick),
            max_iters=args.eant2_max_iters,
            patience=args.eant2_patience,
            prune_window=args.eant2_prune_window,
            chunk=min(10, args.eant2_max_iters),
        ),
    )
    runs: list[tuple[str, Callable[[], Curve]]] = []
    if "cmaes" in args.methods:
        for h in args.hidden:
            runs.append(
                (
                    f"cmaes-h{h}",
                    lambda h=h: run_evosax(task, h, args.budget, every, args.seed, args.sigma0),
                )
            )
    if "pycma" in args.methods:
        for h in args.hidden:
            runs.append(
                (
                    f"pycma-h{h}",
                    lambda h=h: run_pycma(
                        task, h, args.budget, every, args.seed, args.sigma0, args.pycma_device
                    ),
                )
            )
    if "neat" in args.methods:
        runs.append(("neat", lambda: run_neat(task, args.budget, every, args.seed, args.neat_pop)))
    if "eant2" in args.methods:
        runs.append(("eant2", lambda: run_eant2(task, args.budget, every, args.seed, eant2_config)))

    curves = {name: fn() for name, fn in runs}
    # Target: the final best of the fixed-network evosax CMA-ES with the most hidden neurons.
    ref = next(
        (f"cmaes-h{h}" for h in sorted(args.hidden, reverse=True) if f"cmaes-h{h}" in curves), None
    )
    target = None
    if ref is not None:
        target = _summary(ref, curves[ref], args.budget, None)["best_cost_at_budget"]
    rows = [_summary(name, c, args.budget, target) for name, c in curves.items()]
    payload = {
        **environment(),
        "suite": "peers",
        "config": {
            **harness.settings(args),
            "every": every,
            "eant2": eant2_config.to_dict(),
        },
        "baselines": task.baselines(),
        "target_method": ref,
        "target_cost": target,
        "rows": rows,
    }
    return payload


def render(payload: dict[str, Any]) -> str:
    cfg = payload["config"]
    return (
        f"Servo (kinematic, {cfg['n_starts']} starts), budget {cfg['budget']} evaluations per "
        f"method; target = final best of {payload['target_method']} ({payload['target_cost']})."
        "\n\n" + markdown_table(payload["rows"], COLUMNS)
    )


SUITE = harness.Suite(
    name="peers",
    title="Peers on the servo task at an equal evaluation budget",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
