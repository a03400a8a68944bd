"""Episode throughput against batch width on brax locomotion (issue 41): network-episodes
per second and environment steps per second, eant2_jax and TensorNEAT side by side in one
process on one device.

* **eant2_jax**: for each environment (``--envs``, default ``hopper`` and ``halfcheetah``,
  the field's settings: ``bench/field_settings.py``, spring backend, one episode of at most
  1,000 steps) and each width ``W`` (``--widths``), ``W`` random networks of the
  environment's inputs and outputs (`bench.common.random_population` of seed ``--seed``,
  each the minimal network grown by ``--extra-genes`` genes: a few hidden neurons and
  jumpers, as the field's genomes; the result records their sizes) compiled into ONE batch,
  and the engine's evaluator of their costs timed: ``task.cost(key, nets)`` under
  ``jax.jit``, compiled ahead (``lower().compile()``, its seconds reported apart), then one
  untimed call and the median of ``--repeats`` calls, each waiting for the device.
* **TensorNEAT** (only with ``--tensorneat SRC``, the folder holding its ``tensorneat``
  package, as ``bench field`` takes it): for each population in ``--tn-pops`` (default
  1,000, its examples', and 10,000, its paper's), NEAT with its example's settings for the
  environment (`bench.field_tensorneat`), set up as ``Pipeline.setup`` does (halfcheetah's
  observation statistics from random episodes included, not timed), and the evaluation part
  of ``Pipeline.step`` timed the same way: ``ask``, ``transform`` and ``problem.evaluate``
  of the whole generation-0 population, vmapped as ``Pipeline.step`` does.

Rates: network-episodes/s = networks x episodes per evaluation / seconds per batch; env
steps/s = the steps the episodes lived (counted, see below) / seconds per batch; steps
computed/s counts what the device stepped, ended episodes included.

Early termination (read from the code, not measured): both evaluators mask an episode once
it ends, but neither stops stepping its physics while other episodes of the batch go on.
eant2_jax's `eant2_jax.tasks.episodic.rollout` runs blocks of ``chunk`` steps in one
``lax.while_loop``; vmapped over the batch it is one loop that stops when EVERY episode of
the batch has ended (checked per block); an ended episode's reward and step count stop,
its physics keeps stepping. TensorNEAT's ``RLEnv._evaluate_once`` is a ``lax.while_loop``
of single steps while ``~done & count < max_step``; vmapped over the population it runs
until the population's longest episode ends, stepping the ended ones too. halfcheetah
never ends early; random hopper networks fall within tens of steps, so hopper's rates at
generation 0 are not those of a trained population.

Steps lived are counted by untimed calls: eant2_jax's episode lengths
(``EpisodicTask.episode``'s second result, keys split as ``cost`` splits them) of the widest
batch's networks, the first ``W`` of them for width ``W`` (each network's episode does not
depend on its batch); TensorNEAT's by its evaluation with the reward of every step replaced
by 1 (its return is then the episode's length; the dynamics are the same).

Run: ``python -m bench throughput [--tensorneat SRC] [--widths 256 1024 4096 10000]``;
``--quick`` is a CPU smoke test (20-step episodes, widths 4 and 8, one repeat).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import math
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    environment,
    git_commit,
    markdown_table,
    random_population,
    time_call,
)
from bench.field_settings import ENVS
from eant2_jax import tasks
from eant2_jax.compiler import networks
from eant2_jax.genome import GeneKind
from eant2_jax.tasks.base import map_networks
from eant2_jax.tasks.brax_task import calling_brax

BRAX = tuple(k for k, v in ENVS.items() if v["family"] == "brax")
WIDTHS = (256, 1024, 4096, 10000)
TN_POPS = (1000, 10000)
# What the result says about ended episodes (from the code: the module docstring).
EARLY_END = (
    "Neither evaluator stops stepping an episode that has ended while others of its batch "
    "go on. eant2_jax (tasks.episodic.rollout): blocks of `chunk` steps in one "
    "lax.while_loop, vmapped over the batch, that stops once every episode of the batch has "
    "ended; an ended episode's reward and length stop counting, its physics is still "
    "computed. TensorNEAT (RLEnv._evaluate_once): a lax.while_loop of single steps while "
    "~done & count < max_step, vmapped over the population: it runs until the population's "
    "longest episode ends, computing the ended ones too."
)
QUICK = {"max_steps": 20, "widths": [4, 8], "tn_pops": [40], "repeats": 1}


# ----------------------------------------------------------------------------- measuring
def _timed(call, repeats: int) -> dict[str, Any]:
    """One untimed call, then the median of ``repeats`` timed ones (`bench.common.time_call`)."""
    t = time_call(call, warmup=0, repeats=repeats)
    return {"batch_s": t.median_s, "batch_min_s": t.min_s, "times_s": list(t.times_s)}


def _rates(row: dict[str, Any], lengths: np.ndarray, *, computed_per_episode: int) -> None:
    """Add the rates of a row measured on ``row["episodes"]`` episodes of ``lengths``."""
    t = row["batch_s"]
    row.update(
        steps_lived=int(lengths.sum()),
        mean_length=float(lengths.mean()),
        max_length=int(lengths.max()),
        steps_computed=row["episodes"] * computed_per_episode,
        episodes_per_s=row["episodes"] / t,
        steps_per_s=int(lengths.sum()) / t,
    )
    row["computed_steps_per_s"] = row["steps_computed"] / t


def _cost(task, key, nets):
    return task.cost(key, nets)


def _lengths(task, key, nets):
    """Episode lengths ``[W, episodes]`` of the episodes ``task.cost(key, nets)`` plays."""
    keys = jax.random.split(key, task.episodes)
    return map_networks(lambda n: jax.vmap(task.episode, in_axes=(None, 0))(n, keys)[1], nets)


def eant2_rows(name: str, args: argparse.Namespace, save, payload) -> None:
    """The eant2_jax rows of one environment, one per width, saved as they come."""
    env = ENVS[name]
    task = tasks.make(f"brax:{name}", episodes=env["episodes"], max_steps=args.max_steps,
                      backend=args.backend or env["backend"])  # fmt: skip
    t0 = time.perf_counter()
    n_min = task.n_outputs * (task.n_inputs + 1)  # the minimal network's genes
    genomes = random_population(args.seed, max(args.widths), n_min + args.extra_genes,
                                n_inputs=task.n_inputs, n_outputs=task.n_outputs)  # fmt: skip
    harness.log(f"throughput: {name}: {len(genomes)} random genomes in "
                f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
    key = jax.random.key(args.seed)
    t0 = time.perf_counter()
    widest = networks(genomes, task.n_inputs)
    widest_s = time.perf_counter() - t0
    lengths = np.asarray(jax.jit(_lengths)(task, key, widest)).reshape(len(genomes), -1)
    block = min(task.chunk, task.max_steps)
    for w in args.widths:
        harness.log(f"throughput: {name} eant2_jax width {w}")
        sizes = genomes[:w]
        t0 = time.perf_counter()
        nets = widest if w == len(genomes) else networks(sizes, task.n_inputs)
        build_s = widest_s if w == len(genomes) else time.perf_counter() - t0
        t0 = time.perf_counter()
        compiled = jax.jit(_cost).lower(task, key, nets).compile()
        row = {"env": name, "method": "eant2_jax", "width": w, "episodes": w * task.episodes,
               "build_s": build_s, "compile_s": time.perf_counter() - t0,
               "genes_mean": float(np.mean([len(g) for g in sizes])),
               "hidden_mean": float(np.mean([g.n_neurons - g.n_outputs for g in sizes])),
               "jumpers_mean": float(np.mean([_jumpers(g) for g in sizes])),
               "neuron_slots": int(nets.bias.shape[-1]), "chunk": task.chunk}  # fmt: skip
        row.update(_timed(lambda c=compiled, n=nets: c(task, key, n), args.repeats))
        mine = lengths[:w]
        # The batch's loop runs whole blocks until its longest episode has ended.
        _rates(row, mine, computed_per_episode=block * math.ceil(int(mine.max()) / block))
        payload["rows"].append(row)
        save(payload)


def _jumpers(genome) -> int:
    return sum(g.kind in (GeneKind.FORWARD, GeneKind.RECURRENT) for g in genome.genes)


# ----------------------------------------------------------------------------- TensorNEAT
def tensorneat_rows(name: str, args: argparse.Namespace, save, payload) -> None:
    """The TensorNEAT rows of one environment, one per population."""
    from bench import field_tensorneat as ftn

    ftn.import_from(args.tensorneat)
    from tensorneat.pipeline import Pipeline

    env = ENVS[name]
    tn, backend = env["tensorneat"], args.backend or env["backend"]
    probe = tasks.make(f"brax:{name}", max_steps=args.max_steps, backend=backend)
    n_in, n_out = probe.n_inputs, probe.n_outputs
    # brax's own warnings silenced (TensorNEAT makes its environment and traces its steps).
    with calling_brax():
        for pop in args.tn_pops:
            harness.log(f"throughput: {name} tensorneat population {pop}")
            algo = ftn.algorithm(n_in, n_out, pop=pop, output=tn["output"],
                                 activation=tn["activation"], max_nodes=tn["max_nodes"],
                                 max_conns=tn["max_conns"])  # fmt: skip
            prob = ftn.problem("brax", name, n_inputs=n_in, n_outputs=n_out,
                               max_steps=args.max_steps, repeat=env["episodes"], backend=backend,
                               obs_norm_episodes=tn["obs_norm_episodes"])  # fmt: skip
            pipeline = Pipeline(algorithm=algo, problem=prob, seed=args.seed,
                                generation_limit=1, fitness_target=math.inf)  # fmt: skip
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(sys.stderr):  # its progress lines; stdout has tables
                state = pipeline.setup()
            setup_s = time.perf_counter() - t0

            evaluate = _evaluation(algo, pop)
            t0 = time.perf_counter()
            compiled = jax.jit(functools.partial(evaluate, problem=prob)).lower(state).compile()
            row = {"env": name, "method": "tensorneat", "width": pop,
                   "episodes": pop * env["episodes"], "setup_s": setup_s,
                   "compile_s": time.perf_counter() - t0,
                   "hidden_mean": _tn_hidden(algo.ask(state), n_in, n_out)}  # fmt: skip
            row.update(_timed(lambda c=compiled, s=state: c(s), args.repeats))
            counting = functools.partial(evaluate, problem=_counting(prob))
            mean_len = np.asarray(jax.jit(counting)(state))
            # The field's brax evaluations are one episode each: a genome's length is its
            # episode's, and the population's loop steps every episode as long as the longest.
            lengths = np.rint(mean_len).astype(np.int64)
            _rates(row, lengths, computed_per_episode=int(lengths.max()))
            payload["rows"].append(row)
            save(payload)


def _evaluation(algo, pop: int):
    """``evaluate(state, problem) -> fitness [pop]``: the evaluation part of TensorNEAT's
    ``Pipeline.step`` (its keys, ``ask``, ``transform`` and ``problem.evaluate``, vmapped)."""

    def evaluate(state, problem):
        randkey, _ = jax.random.split(state.randkey)
        keys = jax.random.split(randkey, pop)
        nets = jax.vmap(algo.transform, in_axes=(None, 0))(state, algo.ask(state))
        return jax.vmap(problem.evaluate, in_axes=(None, 0, None, 0))(
            state, keys, algo.forward, nets)  # fmt: skip

    return evaluate


def _counting(prob):
    """A copy of a TensorNEAT problem whose reward is 1 every step: the same episodes, each
    returning its length."""
    import jax.numpy as jnp

    counter = copy.copy(prob)

    def ones(randkey, env_state, action, step=prob.step):
        obs, st, reward, done, info = step(randkey, env_state, action)
        return obs, st, jnp.ones_like(reward), done, info

    counter.step = ones  # RLEnv._evaluate_once calls self.step
    return counter


def _tn_hidden(population, n_in: int, n_out: int) -> float:
    """Mean hidden nodes of a TensorNEAT population (its nodes' used rows)."""
    nodes = np.asarray(population[0])
    return float(np.mean((~np.isnan(nodes[..., 0])).sum(-1) - n_in - n_out))


# ----------------------------------------------------------------------------- the suite
def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "commit": git_commit(),
                               "config": harness.settings(args), "early_termination": EARLY_END,
                               "rows": []}  # fmt: skip
    for name in args.envs:
        eant2_rows(name, args, save, payload)
        if args.tensorneat:
            tensorneat_rows(name, args, save, payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--envs", nargs="+", choices=BRAX, default=list(BRAX),
                   help="brax environments of the field (default: all)")  # fmt: skip
    p.add_argument(
        "--widths",
        nargs="+",
        type=int,
        default=None,
        help=f"eant2_jax batch widths, networks per batch (default {WIDTHS})",
    )
    p.add_argument("--tn-pops", nargs="+", type=int, default=None,
                   help=f"TensorNEAT populations (default {TN_POPS})")  # fmt: skip
    p.add_argument("--max-steps", type=int, default=None,
                   help="steps per episode at most (default the field's, 1000)")  # fmt: skip
    p.add_argument(
        "--backend",
        default=None,
        help="brax physics backend, both methods (default the field's, spring)",
    )
    p.add_argument(
        "--extra-genes",
        type=int,
        default=12,
        help="genes each random network has beyond the minimal one (default 12)",
    )
    harness.run_options(p, seed=0)
    p.add_argument("--tensorneat", default=None,
                   help="folder holding TensorNEAT's tensorneat package (its src/); "
                   "without it only eant2_jax is measured")  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        for k, v in QUICK.items():
            if k == "repeats" or getattr(args, k) is None:
                setattr(args, k, v)
    args.widths = list(WIDTHS) if args.widths is None else args.widths
    args.tn_pops = list(TN_POPS) if args.tn_pops is None else args.tn_pops
    if args.max_steps is None:
        args.max_steps = max(ENVS[n]["max_steps"] for n in args.envs)
    for option, values in (("--widths", args.widths), ("--tn-pops", args.tn_pops)):
        bad = [v for v in values if v < 1]
        if bad:
            raise BenchInputError(f"{option} must be positive integers, got {bad[0]}")
    if args.max_steps < 1 or args.extra_genes < 0:
        raise BenchInputError("--max-steps must be at least 1 and --extra-genes at least 0")
    if args.tensorneat and not (Path(args.tensorneat) / "tensorneat" / "pipeline.py").is_file():
        raise BenchInputError(
            "--tensorneat must name the folder holding TensorNEAT's tensorneat package "
            f"(its src/), got {args.tensorneat!r}"
        )


COLUMNS = [
    Column("env", "env"),
    Column("method", "method"),
    Column("width", "width / population", "{:,}"),
    Column("compile_s", "compile s", "{:.1f}"),
    Column("batch_s", "s per batch", "{:.3f}"),
    Column("episodes_per_s", "network-episodes/s", "{:,.0f}"),
    Column("steps_per_s", "env steps/s (lived)", "{:,.0f}"),
    Column("computed_steps_per_s", "steps computed/s", "{:,.0f}"),
    Column("mean_length", "mean episode length", "{:.1f}"),
    Column("hidden_mean", "hidden neurons (mean)", "{:.1f}"),
]


def render(payload: dict[str, Any]) -> str:
    cfg = payload["config"]
    head = (f"Commit {payload.get('commit')}; {cfg['max_steps']}-step episodes, "
            f"{cfg.get('backend') or 'spring'} backend, median of {cfg['repeats']} "
            "batch(es) after one untimed call; compile timed apart. Env steps lived: "
            "steps before each episode ended; steps computed: what the device stepped "
            "(ended episodes ride along until the batch's longest ends).\n\n")  # fmt: skip
    tail = f"\nEarly termination: {payload.get('early_termination', EARLY_END)}\n"
    return head + markdown_table(payload["rows"], COLUMNS) + tail


SUITE = harness.Suite(
    name="throughput",
    title="Episode throughput against batch width",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
    repeats=3,
)

main = SUITE.main
