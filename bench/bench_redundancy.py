"""Known redundancy: does ``optimize(genome, task, pruner=...)`` remove what is redundant?

Four regression problems whose redundancy is known, each with identity and with tanh
output neurons. The targets are functions the network represents exactly, plus Gaussian
noise (std 0.05) over 16,384 samples, so that a redundant connection's extra capacity fits
the noise by about p / n (~0.02%), far below the paper's 0.1% tolerance, and a necessary
connection is not:

* ``parallel``: ``y = f(1.5 x0)``; the genome reads x0 twice and x1 once (any may go, x0
  must stay).
* ``no_effect``: ``y = f(x0 - x1)``; the genome also reads x2 (only x2 may go).
* ``duplicate``: ``y = f(1.2 tanh(x0 + x1))``; the genome has two hidden neurons reading x0
  and x1 (either neuron, or one of its inputs, may go; x0 and x1 must still be read).
* ``latent``: ten inputs that mix four latent variables, ``y = f(0.3 w.z)``; the genome
  reads all ten (six are redundant; any may go as long as the cost holds).

Per problem, output and seed: one ``optimize`` without pruning and one with the pruner and
settings under test (``--mode default``: the library's defaults; ``--mode literal``: the
paper's rule as written, :meth:`eant2_jax.ExploitConfig.literal`). A seed counts as
**removed** if at least one connection went, all of them allowed, no input that must stay
was lost, and the cost is at most 1% above the unpruned run's.

Run: ``python -m bench redundancy [--seeds 10] [--pruners covariance obs ...] [--modes
default literal]``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import numpy as np

from bench import harness
from bench.common import Column, environment, markdown_table
from eant2_jax import tasks, tuning
from eant2_jax.genome import GeneKind

N_SAMPLES, NOISE = 16_384, 0.05
LITERAL = dict(prune_refit=0, prune_reference="mean", prune_at_stop=False)


def problems(output: str, n: int = N_SAMPLES) -> dict[str, tuple]:
    """``name: (x, y, genome, genes that may go, inputs that must stay)``."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, 3))
    noise = NOISE * rng.normal(size=(n, 1))
    f = np.tanh if output == "tanh" else (lambda v: v)
    z = rng.normal(size=(n, 4))
    mix = z @ rng.normal(size=(4, 10))
    w = np.array([[1.0], [-0.5], [0.3], [0.8]])
    latent_genome = "N0/10*1 " + " ".join(f"I{i}*0.0" for i in range(10))
    return {
        "parallel": (x, f(1.5 * x[:, :1]) + noise, "N0/3*1 I0*0.7 I0*0.8 I1*0.5", {1, 2, 3}, {0}),
        "no_effect": (
            x, f(x[:, :1] - x[:, 1:2]) + noise, "N0/3*1 I0*0.5 I1*-0.5 I2*0.3", {3}, {0, 1}
        ),
        "duplicate": (
            x,
            f(1.2 * np.tanh(x[:, :1] + x[:, 1:2])) + noise,
            "N0/2*1 N1/2*0.6 I0*1.0 I1*1.0 N2/2*0.5 I0*0.9 I1*1.1",
            set(range(1, 7)),
            {0, 1},
        ),
        "latent": (mix, f(0.3 * (z @ w)) + noise, latent_genome, set(range(1, 11)), set()),
    }  # fmt: skip


def one(task, genome: str, may_go: set, must_stay: set, seed: int, pruner: str, mode: str,
        base: tuning.OptimizeResult):  # fmt: skip
    """One seed of one case; ``base``: the unpruned run of this seed (it depends on the case
    and seed only, not on the pruner)."""
    key = jax.random.key(seed)
    options = LITERAL if mode == "literal" else {}
    t0 = time.perf_counter()
    res = tuning.optimize(genome, task, key=key, pruner=pruner, **options)
    wall = time.perf_counter() - t0
    removed = [r.gene for r in res.pruning if r.accepted]
    reads = {g.ref for g in res.genome.genes if g.kind == GeneKind.INPUT}
    lost = not must_stay <= reads
    worse = res.cost > 1.01 * base.cost
    return {
        "removed_genes": removed,
        "size": res.genome.n_params,
        "cost": res.cost,
        "cost_unpruned": base.cost,
        "lost_necessary": lost,
        "worse_1pct": bool(worse),
        "success": bool(removed and set(removed) <= may_go and not lost and not worse),
        "attempts": len(res.pruning),
        "evaluations": int(res.history.evaluations[-1]),
        "evaluations_unpruned": int(base.history.evaluations[-1]),
        "stop": res.stop_reason,
        "wall_s": wall,
    }


def _mean(rows: list[dict], value) -> float:
    return float(np.mean([value(r) for r in rows]))


def _options(p: argparse.ArgumentParser) -> None:
    harness.run_options(p, seeds=10)
    p.add_argument("--pruners", nargs="+", default=["covariance"])
    p.add_argument("--modes", nargs="+", default=["default", "literal"])
    p.add_argument("--problems", nargs="+", default=None)


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.seeds, args.problems = 1, ["no_effect"]


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    runs, rows = [], []
    unpruned = {}  # (output, problem, seed) -> the unpruned run, shared by every arm
    payload = {"environment": environment(), "config": harness.settings(args)}
    # Every pruner's default rule first, then the literal ones (a partial run has whole arms).
    for mode in args.modes:
        for pruner in args.pruners:
            for output in ("identity", "tanh"):
                for name, (x, y, genome, may_go, must_stay) in problems(output).items():
                    if args.problems and name not in args.problems:
                        continue
                    task = tasks.regression(x, y, hidden="tanh", output=output)
                    case = []
                    for s in range(args.seeds):
                        base = unpruned.get((output, name, s))
                        if base is None:
                            base = tuning.optimize(genome, task, key=jax.random.key(s))
                            unpruned[output, name, s] = base
                        case.append(
                            {"pruner": pruner, "mode": mode, "output": output, "problem": name,
                             "seed": s,
                             **one(task, genome, may_go, must_stay, s, pruner, mode, base)}
                        )  # fmt: skip
                    runs += case
                    rows.append(
                        {
                            "pruner": pruner,
                            "mode": mode,
                            "output": output,
                            "problem": name,
                            "removed": f"{sum(r['success'] for r in case)}/{len(case)}",
                            "lost": sum(r["lost_necessary"] for r in case),
                            "worse": sum(r["worse_1pct"] for r in case),
                            "mean_removed": float(np.mean([len(r["removed_genes"]) for r in case])),
                            "evals_ratio": float(
                                np.mean(
                                    [r["evaluations"] / r["evaluations_unpruned"] for r in case]
                                )
                            ),
                        }
                    )
                    save({**payload, "rows": rows, "runs": runs})
    return {**payload, "rows": rows, "runs": runs}


COLUMNS = [
    Column("pruner", "pruner"),
    Column("mode", "rule"),
    Column("output", "output"),
    Column("problem", "problem"),
    Column("removed", "removed (seeds)"),
    Column("lost", "necessary lost"),
    Column("worse", "cost > 1% worse"),
    Column("mean_removed", "connections removed (mean)", "{:.1f}"),
    Column("evals_ratio", "evaluations vs unpruned", "{:.2f}x"),
]

SUITE = harness.Suite(
    name="redundancy",
    title="Known redundancy",
    description=__doc__,
    options=_options,
    run=run,
    render=lambda payload: markdown_table(payload["rows"], COLUMNS),
    prepare=_prepare,
)

main = SUITE.main
