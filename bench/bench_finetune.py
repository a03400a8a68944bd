"""Gradient fine-tuning (optax, `eant2_jax.finetune`) against CMA-ES alone, at equal wall time.

Question: on a task whose cost is differentiable in the weights, given the same wall-clock
budget per batch of structures, which tunes the weights of EANT2 structures to a lower
cost: the batched CMA-ES (the exploitation engine, no pruning), the gradient stage, or one
after the other?

Protocol (written before the run):

* **Problems.** ``xor`` (the XOR task; 2 inputs, 1 output), ``sine`` (regression of
  ``sin(pi x)`` on 64 points of [-1, 1]; 1 input, 1 output), ``servo`` (the kinematic visual
  servoing task, its 1023 training starts; 10 inputs, 3 outputs).
* **Structures.** Per seed, ``--structures`` (16) random structures drawn with
  ``numpy.random.default_rng(seed)``: for xor and sine, each output neuron reads 1-4
  (xor) or 1-6 (sine) hidden tanh neurons (each reading every input and a bias), a bias and
  each input with probability 1/2; for servo, `bench.common.random_genome` of 33-60 genes
  (hidden neurons, forward and recurrent jumpers). Weights N(0, 1) (servo: N(0, 0.5^2), the
  generator's). Every arm starts from the same weights; the batch of 16 is tuned together
  (one padded program, as an EANT2 generation tunes its offspring); every seed's batch is
  padded to one bucket, so nothing compiles while a budget runs.
* **Arms**, each given the problem's budget ``T`` of wall time per batch (compilation
  excluded: every program is compiled by a warm-up call before any timing):
  ``cma``: the exploitation engine (``ExploitConfig(pruner="none", max_iters=10**6,
  chunk=10)``, its own stop rules kept; halted at ``T`` between chunks); ``grad``: the
  gradient stage (Adam, chunks of 50 steps until ``T``); ``cma+grad``: CMA-ES for ``T/2``
  (or until it stops), then the gradient stage for the rest; ``grad+cma``: the other order.
  A result is never worse than its start point (each arm's final network is compared with
  the start weights, as ``eant2_jax.optimize`` does).
* **Settings chosen on other seeds.** The learning rate of Adam is chosen from
  ``--learning-rates`` by the median final cost of the ``grad`` arm on seeds 100, 101, 102
  (``--choose-seeds``); the table reports fresh seeds 0 .. ``--seeds``-1 with that rate.
  The learning rate is a traced hyper-parameter (``optax.inject_hyperparams``), so every
  rate runs the same compiled program.
* **Reported** per problem and arm: the final cost (the task's cost of the returned
  networks, one program for all arms) over all structures of all report seeds: median and
  quartiles; ``wins``: the fraction of structures whose final cost is below the ``cma``
  arm's for the same structure (``cma`` itself: ties excluded, so 0); the wall time used
  (mean per batch); for xor, ``solved``: the fraction whose four outputs are on the right
  side of 0.5.

Run: ``python -m bench finetune [--problems xor sine servo] [--seeds 5] [--budgets xor=1
sine=1 servo=3] [--commit HASH]``; ``--quick`` is a smoke test (xor, tiny budgets).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from bench import harness
from bench.common import BenchInputError, Column, environment, git_commit, random_genome
from eant2_jax import evaluate, tasks, tuning
from eant2_jax import exploitation as ex
from eant2_jax.compiler import Bucket, bucket_for, compile_genomes
from eant2_jax.finetune import init, run_chunk, score
from eant2_jax.genome import Gene, GeneKind, Genome
from eant2_jax.rescoring import cost_batch

PROBLEMS = ("xor", "sine", "servo")
ARMS = ("cma", "grad", "cma+grad", "grad+cma")
BUDGETS = {"xor": 1.0, "sine": 1.0, "servo": 3.0}
LEARNING_RATES = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)
GRAD_CHUNK = 50
CMA = ex.ExploitConfig(pruner="none", max_iters=10**6, chunk=10)
# One optimiser object: the learning rate is state (set per run), not part of the program.
ADAM = optax.inject_hyperparams(optax.adam)(learning_rate=1e-2)


# ------------------------------------------------------------------------------ problems
def hidden_layer_genome(
    rng: np.random.Generator, n_inputs: int, n_outputs: int, max_hidden: int
) -> Genome:
    """Each output neuron reads 1..max_hidden hidden neurons (every input and a bias each),
    a bias and each input with probability 1/2; weights N(0, 1)."""
    genes, next_id = [], n_outputs
    for o in range(n_outputs):
        body, reads = [], 0
        for _ in range(int(rng.integers(1, max_hidden + 1))):
            body.append(Gene(GeneKind.NEURON, next_id, float(rng.normal()), n_inputs + 1))
            body += [Gene(GeneKind.INPUT, j, float(rng.normal())) for j in range(n_inputs)]
            body.append(Gene(GeneKind.BIAS, -1, float(rng.normal())))
            next_id, reads = next_id + 1, reads + 1
        for j in range(n_inputs):
            if rng.random() < 0.5:
                body.append(Gene(GeneKind.INPUT, j, float(rng.normal())))
                reads += 1
        body.append(Gene(GeneKind.BIAS, -1, float(rng.normal())))
        genes += [Gene(GeneKind.NEURON, o, float(rng.normal()), reads + 1), *body]
    return Genome(genes)


def make_task(name: str):
    if name == "xor":
        return tasks.xor()
    if name == "sine":
        x = np.linspace(-1, 1, 64)[:, None]
        return tasks.regression(x, np.sin(np.pi * x))
    return tasks.make("servo")


def structures(name: str, seed: int, count: int) -> list[Genome]:
    rng = np.random.default_rng(seed)
    if name == "servo":
        return [
            random_genome(rng, int(rng.integers(33, 61)), n_inputs=10, n_outputs=3)
            for _ in range(count)
        ]
    n_in, top = (2, 4) if name == "xor" else (1, 6)
    return [hidden_layer_genome(rng, n_in, 1, top) for _ in range(count)]


# ---------------------------------------------------------------------------------- arms
def _with(genomes: list[Genome], weights: np.ndarray) -> list[Genome]:
    return [g.with_weights(weights[i, : g.n_params]) for i, g in enumerate(genomes)]


def cma_stage(genomes, task, key, budget: float, bucket: Bucket) -> tuple[list[Genome], int]:
    """CMA-ES on the batch until its own stop rules or ``budget`` seconds (checked between
    chunks); each structure's best point and the evaluations spent."""
    deadline = time.perf_counter() + budget
    init_key, run_key = jax.random.split(key)
    prep = tuning.prepare(genomes, task, key=init_key, config=CMA, bucket=bucket)
    st, _ = ex.run(
        prep.state, prep.batch.layout, task, key=run_key, config=CMA,
        halt=lambda _: time.perf_counter() >= deadline,
    )  # fmt: skip
    best_x, best_cost = np.asarray(st.cma.best_x, np.float64), np.asarray(st.cma.best_cost)
    out = [
        g.with_weights(best_x[i, : g.n_params]) if np.isfinite(best_cost[i]) else g
        for i, g in enumerate(genomes)
    ]
    return out, int(np.sum(np.asarray(st.evals)[: len(genomes)]))


def grad_stage(genomes, task, key, budget: float, bucket: Bucket, lr: float):
    """Adam (rate ``lr``) on the batch, chunks of `GRAD_CHUNK` steps until ``budget``
    seconds; each structure's best point and the steps taken."""
    deadline = time.perf_counter() + budget
    batch = compile_genomes(genomes, task.n_inputs, bucket=bucket)
    st = init(batch.weights, ADAM)
    hyper = dict(st.opt_state.hyperparams, learning_rate=jnp.full((batch.weights.shape[0],), lr))
    st = st._replace(opt_state=st.opt_state._replace(hyperparams=hyper))
    while True:
        st, _ = run_chunk(st, batch.layout, task, key, optimizer=ADAM, steps=GRAD_CHUNK)
        st.best_cost.block_until_ready()
        if time.perf_counter() >= deadline:
            break
    st = score(st, batch.layout, task, key)
    best = np.asarray(st.best_weights, np.float64)
    finite = np.isfinite(np.asarray(st.best_cost))
    out = [g.with_weights(best[i, : g.n_params]) if finite[i] else g for i, g in enumerate(genomes)]
    return out, int(st.step)


def run_arm(arm: str, genomes, task, key, budget: float, bucket: Bucket, lr: float) -> dict:
    t0 = time.perf_counter()
    first_key, second_key = jax.random.split(key)
    work = {"evaluations": 0, "steps": 0}
    stages = arm.split("+")
    for n, stage in enumerate(stages):
        left = budget - (time.perf_counter() - t0)
        share = left if n == len(stages) - 1 else budget / len(stages)
        k = first_key if n == 0 else second_key
        if stage == "cma":
            genomes, evals = cma_stage(genomes, task, k, max(share, 0.0), bucket)
            work["evaluations"] += evals
        else:
            genomes, steps = grad_stage(genomes, task, k, max(share, 0.0), bucket, lr)
            work["steps"] += steps
    return {"genomes": genomes, "seconds": time.perf_counter() - t0, **work}


def costs_of(genomes, task, bucket: Bucket) -> np.ndarray:
    batch = compile_genomes(genomes, task.n_inputs, bucket=bucket)
    out = cost_batch(batch.layout, batch.weights, task, jax.random.key(0))
    return np.asarray(out, np.float64)[: len(genomes)]


def xor_solved(genomes) -> np.ndarray:
    x = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]])[None]
    y = np.asarray(evaluate(genomes, x))[:, 0, :, 0]
    return np.all(np.abs(y - np.array([0.0, 1.0, 1.0, 0.0])) < 0.5, axis=1)


# ------------------------------------------------------------------------------ the suite
def _options(p: argparse.ArgumentParser) -> None:
    harness.run_options(p, seeds=5)
    p.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=PROBLEMS)
    p.add_argument("--structures", type=int, default=16, help="structures per seed (one batch)")
    p.add_argument("--budgets", nargs="+", default=[f"{k}={v}" for k, v in BUDGETS.items()],
                   help="PROBLEM=SECONDS of wall time per batch and arm")  # fmt: skip
    p.add_argument("--learning-rates", nargs="+", type=float, default=list(LEARNING_RATES))
    p.add_argument("--choose-seeds", nargs="+", type=int, default=[100, 101, 102])
    p.add_argument("--commit", default=None, help="the commit measured (default: git's HEAD)")


def _prepare(args: argparse.Namespace) -> None:
    budgets = {}
    for item in args.budgets:
        name, _, value = item.partition("=")
        try:
            budgets[name] = float(value)
        except ValueError:
            raise BenchInputError(f"--budgets: {item!r} is not PROBLEM=SECONDS") from None
    args.budgets = {**BUDGETS, **budgets}
    if args.quick:
        args.problems, args.structures, args.seeds = ["xor"], 4, 1
        args.budgets = {"xor": 0.2}
        args.learning_rates, args.choose_seeds = [1e-2, 1e-1], [100]
    if min(args.choose_seeds) < args.seeds:
        raise BenchInputError("--choose-seeds must not overlap the report seeds 0..seeds-1")
    if args.commit is None:
        args.commit = git_commit()


def _problem(name: str, args, save, payload) -> None:
    task, budget = make_task(name), args.budgets[name]
    seeds = [*args.choose_seeds, *range(args.seeds)]
    batches = {s: structures(name, s, args.structures) for s in seeds}
    bucket = bucket_for([g for b in batches.values() for g in b])
    warm = batches[seeds[0]]
    for arm in ARMS:  # compile every program before any timing
        run_arm(arm, warm, task, jax.random.key(0), 1e-3, bucket, 1e-2)
    costs_of(warm, task, bucket)
    choice = []
    for lr in args.learning_rates:
        finals = [
            costs_of(run_arm("grad", batches[s], task, jax.random.key(s), budget, bucket, lr)
                     ["genomes"], task, bucket)
            for s in args.choose_seeds
        ]  # fmt: skip
        choice.append({"problem": name, "learning_rate": lr,
                       "median_cost": float(np.median(np.concatenate(finals)))})  # fmt: skip
        harness.log(f"{name} choose lr={lr:g}: median {choice[-1]['median_cost']:.4g}")
    lr = min(choice, key=lambda r: r["median_cost"])["learning_rate"]
    payload["choice"] += choice
    finals: dict[str, list] = {arm: [] for arm in ARMS}
    extra: dict[str, dict] = {arm: {"seconds": [], "evaluations": [], "steps": [], "solved": []}
                              for arm in ARMS}  # fmt: skip
    for s in range(args.seeds):
        start = costs_of(batches[s], task, bucket)
        for arm in ARMS:
            res = run_arm(arm, batches[s], task, jax.random.key(s), budget, bucket, lr)
            got = costs_of(res["genomes"], task, bucket)
            keep = ~(got <= start)  # never worse than the start point
            genomes = [
                b if k else g for g, b, k in zip(res["genomes"], batches[s], keep, strict=True)
            ]
            finals[arm].append(np.where(keep, start, got))
            for field in ("seconds", "evaluations", "steps"):
                extra[arm][field].append(res[field])
            if name == "xor":
                extra[arm]["solved"].append(xor_solved(genomes))
            harness.log(f"{name} seed {s} {arm}: median {np.median(finals[arm][-1]):.4g} "
                        f"in {res['seconds']:.2f} s")  # fmt: skip
    cma = np.concatenate(finals["cma"])
    for arm in ARMS:
        c = np.concatenate(finals[arm])
        q1, med, q3 = np.percentile(c, [25, 50, 75])
        payload["rows"].append({
            "problem": name, "arm": arm, "budget_s": budget, "learning_rate": lr,
            "structures": int(c.size), "median": float(med), "q1": float(q1), "q3": float(q3),
            "wins": float(np.mean(c < cma)),
            "seconds": float(np.mean(extra[arm]["seconds"])),
            "evaluations": float(np.mean(extra[arm]["evaluations"])),
            "steps": float(np.mean(extra[arm]["steps"])),
            "solved": float(np.mean(np.concatenate(extra[arm]["solved"])))
            if extra[arm]["solved"] else None,
            "costs": [float(v) for v in c],
        })  # fmt: skip
    save(payload)


def run(args: argparse.Namespace, save) -> dict[str, Any]:
    payload: dict[str, Any] = {
        "environment": environment(),
        "commit": args.commit,
        "config": harness.settings(args),
        "choice": [],
        "rows": [],
    }
    for name in args.problems:
        _problem(name, args, save, payload)
    return payload


def render(payload: dict[str, Any]) -> str:
    rows = payload.get("rows", [])
    head = f"Commit {payload.get('commit')}; settings: `{payload.get('config')}`.\n\n"
    columns = [
        Column("problem", "problem"), Column("arm", "arm"), Column("budget_s", "budget s"),
        Column("learning_rate", "Adam rate", "{:g}"), Column("structures", "structures"),
        Column("median", "median cost", "{:.4g}"),
        Column(lambda r: f"{r['q1']:.3g} – {r['q3']:.3g}", "quartiles"),
        Column("wins", "below cma", "{:.0%}"), Column("solved", "solved", "{:.0%}"),
        Column("seconds", "s used", "{:.2f}"), Column("evaluations", "CMA-ES evals", "{:,.0f}"),
        Column("steps", "grad steps", "{:,.0f}"),
    ]  # fmt: skip
    choice = [
        Column("problem", "problem"), Column("learning_rate", "Adam rate", "{:g}"),
        Column("median_cost", "median cost (grad, choice seeds)", "{:.4g}"),
    ]  # fmt: skip
    return head + harness.sections(
        {"rows": rows, "choice": payload.get("choice", [])},
        [("rows", "Final cost at equal wall time", columns),
         ("choice", "Learning rate chosen on other seeds", choice)],
    )  # fmt: skip


SUITE = harness.Suite(
    name="finetune",
    title="Gradient fine-tuning against CMA-ES at equal wall time",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
