"""Row invariance: does a row's result depend on how many rows its program holds?

Split over devices, each device's program holds fewer rows of a batch than one device's
does; where a compiled operation rounds a row differently by the number of rows around it,
the split changes the results (docs/design.md, "Many devices": "Results on a GPU"). This
suite runs each stage of an engine iteration, jitted alone, on ``--rows`` S rows and on the
first k of them (``--ks``), and compares the first k rows of the two results bit for bit:

* ``ask``, ``tell``, ``decompose``: the CMA-ES kernels (`eant2_jax.kernels.cmaes`), vmapped
  over S states of ``--genes`` P parameters with random covariances, ``--popsize`` candidates;
  ``tell-lazy`` is ``tell`` without its eigendecomposition (``decompose=False``, as the
  engine's lazy rule runs it), which parts the update's rounding from the decomposition's;
* ``cost``: the task's cost of S random networks of about P genes (`bench.common.random_genome`
  with the task's inputs and outputs; one draw, the same key for every row), as the engine
  evaluates a batch (`eant2_jax.rescoring.cost_batch`). ``--task brax:hopper --task-option
  max_steps=1000`` is the case where a long episode can turn a last-place difference into
  another return.

A row gives the stage, k, whether every leaf's first k rows are equal (``same``), and the
largest absolute difference. Nothing is timed.

Run: ``python -m bench rows [--rows 64] [--ks 1 2 3 4 8 32] [--task xor]``.
"""

from __future__ import annotations

import argparse
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import BenchInputError, Column, environment, markdown_table, random_population
from eant2_jax import tasks
from eant2_jax.app.taskoptions import task_options
from eant2_jax.compiler import compile_genomes
from eant2_jax.kernels import cmaes
from eant2_jax.rescoring import cost_batch

STAGES = ("ask", "tell", "tell-lazy", "decompose", "cost")


def _cmaes_args(rows: int, genes: int, popsize: int, seed: int) -> dict[str, tuple]:
    """Each CMA-ES stage's function and its ``[rows]`` arguments: random means and
    covariances (decomposed), per-row keys, candidates and costs."""
    rng = np.random.default_rng(seed)
    params = cmaes.default_params(genes, popsize)
    states = []
    for _ in range(rows):
        st = cmaes.init(jnp.asarray(rng.normal(size=genes), jnp.float32), 0.5,
                        jnp.ones(genes, bool), params)  # fmt: skip
        a = rng.normal(size=(genes, genes))
        cov = (a @ a.T / genes + np.eye(genes)).astype(np.float32)
        states.append(cmaes.decompose(st.replace(C=jnp.asarray(cov)), params))
    st = jax.tree.map(lambda *a: jnp.stack(a), *states)
    keys = jax.random.split(jax.random.key(seed), rows)
    x = jnp.asarray(rng.normal(size=(rows, popsize, genes)), jnp.float32)
    costs = jnp.asarray(rng.normal(size=(rows, popsize)), jnp.float32)
    return {
        "ask": (lambda k, s: jax.vmap(cmaes.ask, (0, 0, None))(k, s, params), (keys, st)),
        "tell": (
            lambda s, x, c: jax.vmap(cmaes.tell, (0, 0, 0, None))(s, x, c, params),
            (st, x, costs),
        ),  # fmt: skip
        "tell-lazy": (  # the update without its eigendecomposition (the engine's lazy rule)
            lambda s, x, c: jax.vmap(
                functools.partial(cmaes.tell, decompose=False), (0, 0, 0, None)
            )(s, x, c, params),
            (st, x, costs),
        ),  # fmt: skip
        "decompose": (lambda s: jax.vmap(cmaes.decompose, (0, None))(s, params), (st,)),
    }


def _cost_args(task: Any, rows: int, genes: int, seed: int) -> tuple:
    genomes = random_population(seed, rows, genes, n_inputs=task.n_inputs,
                                n_outputs=task.n_outputs)  # fmt: skip
    batch = compile_genomes(genomes, task.n_inputs, pad_count=False)
    key = jax.random.key(seed)
    return (lambda layout, w: cost_batch(layout, w, task, key)), (batch.layout, batch.weights)


def compare(fn, args: tuple, ks: list[int]) -> list[dict[str, Any]]:
    """``fn`` jitted on ``args`` (leading axis: rows) and on their first k rows for each k:
    per k, whether every leaf's first k rows are equal to the bit and the largest absolute
    difference (NaN where both are NaN counts as equal)."""
    f = jax.jit(fn)
    full = [np.asarray(a) for a in jax.tree.leaves(f(*args))]
    out = []
    for k in ks:
        first = [a[:k] for a in jax.tree.leaves(args)]
        part = f(*jax.tree.unflatten(jax.tree.structure(args), first))
        part = [np.asarray(a) for a in jax.tree.leaves(part)]
        same, worst = True, 0.0
        for u, v in zip(full, part, strict=True):
            u = u[:k]
            if np.array_equal(u, v, equal_nan=True):
                continue
            same = False
            if np.issubdtype(u.dtype, np.floating):
                d = np.abs(u.astype(np.float64) - v.astype(np.float64))
                worst = max(worst, float(np.nanmax(d)) if np.isfinite(d).any() else np.inf)
            else:
                worst = np.inf
        out.append({"k": k, "same": same, "max_abs": worst})
    return out


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    try:
        task = tasks.make(args.task, **args.options)
    except (ValueError, TypeError) as e:  # a name or option the task does not take
        raise BenchInputError(f"--task {args.task}: {e}") from None
    cases = _cmaes_args(args.rows, args.genes, args.popsize, args.seed)
    cases["cost"] = _cost_args(task, args.rows, args.genes, args.seed)
    for stage in args.stages:
        fn, fargs = cases[stage]
        harness.log(f"rows: {stage}")
        for row in compare(fn, fargs, args.ks):
            payload["rows"].append({"stage": stage, "rows": args.rows, **row})
        save(payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rows", type=int, default=64, help="S, the rows of the full batch")
    p.add_argument("--ks", type=int, nargs="+", default=[1, 2, 3, 4, 8, 32],
                   help="the row counts compared with it")  # fmt: skip
    p.add_argument("--genes", type=int, default=48, help="P, parameters per row")
    p.add_argument("--popsize", type=int, default=40, help="CMA-ES candidates per row")
    p.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    p.add_argument("--task-option", action="append", default=[], metavar="KEY=VALUE",
                   help="an option of --task (VALUE is JSON or a string)")  # fmt: skip
    harness.run_options(p, task="xor", seed=0, helps={"task": "the cost stage's task"})


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.rows, args.ks, args.genes, args.popsize = 6, [1, 3], 12, 8
    bad = [k for k in args.ks if not 1 <= k <= args.rows]
    if bad or args.rows < 1:
        raise BenchInputError(f"--ks must lie in [1, --rows = {args.rows}]; got {bad}")
    if args.genes < 2 or args.popsize < 2:
        raise BenchInputError("--genes and --popsize must be at least 2")
    try:  # the eant2 command line's reading: JSON or text, checked against the defaults
        args.options = task_options(args.task_option, args.task)
    except ValueError as e:
        raise BenchInputError(str(e)) from None


def _render(payload: dict) -> str:
    return markdown_table(payload["rows"], [
        Column("stage", "stage"),
        Column("rows", "S"),
        Column("k", "k"),
        Column(lambda r: "same" if r["same"] else "**differs**", "first k rows"),
        Column(lambda r: "0" if r["same"] else f"{r['max_abs']:.3g}", "max abs difference"),
    ])  # fmt: skip


SUITE = harness.Suite(
    name="rows",
    title="Row invariance of the engine's stages",
    description=__doc__,
    options=_options,
    run=run,
    render=_render,
    prepare=_prepare,
)

main = SUITE.main
