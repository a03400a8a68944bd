"""Peers on the servo task: the same cost and the same evaluation budget for every method.

Each method tunes controllers for the servo task (1023 start poses, kinematic mode, one move
per start: ``tasks.make("servo")``) until it has spent ``--budget`` evaluations (one
evaluation = one network scored on all 1023 starts). Every cost is the task's own JAX cost:

* ``cmaes-h{H}`` (evosax ``CMA_ES``): a FIXED fully connected ``10-H-3`` network written as an
  EANT2 genome (:func:`fixed_genome`), compiled once; ``ask``, the batched
  ``task.cost`` of the population and ``tell`` are one jitted step.
* ``pycma-h{H}``: the same networks tuned by pycma (NumPy, host), each population scored by the
  same jitted ``task.cost`` placed on the CPU (``--pycma-device``): the "original EANT2 on a
  CPU" reference. pycma restarts (same start, new seed) if it meets a stop criterion.
* ``neat``: neat-python (pop 150, 10 inputs, 3 outputs). With one move per start the 1023
  inputs are fixed data (``task.x_start``), so each genome's outputs over all starts are
  computed on the host (:func:`neat_outputs`, vectorised over starts) and scored on device by
  :func:`outputs_cost` (the servo move from each start, exactly what ``Servo.episode`` does
  for one move). One evaluation per genome, as NEAT counts.
* ``eant2``: this project (``eant2_jax.loop.run``, covariance pruning); its evaluations come
  from its generation records, so its curve has one point per generation and it may overshoot
  the budget by part of a generation (the best cost *at* the budget is taken from the last
  generation within it).

For each method: best cost against evaluations and against wall time (a point every
``--every`` evaluations; wall time from the method's start, XLA compilation included),
the final best cost within the budget, and the evaluations and wall time at which it first
reached the final best cost of the fixed-network evosax CMA-ES (the largest ``H`` run).

Run: ``python -m bench peers [--quick] [--budget N] [--methods ...]``.
"""

from __future__ import annotations

import argparse
import configparser
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import Column, environment, evosax_start, markdown_table
from eant2_jax import exploitation as ex
from eant2_jax import loop, tasks
from eant2_jax.compiler import compile_genomes
from eant2_jax.genome import Gene, GeneKind, Genome
from eant2_jax.kernels import network as kn

__all__ = ["Curve", "fixed_genome", "main", "neat_outputs", "outputs_cost"]


# ------------------------------------------------------------------------------ the curve
class Curve:
    """Best cost so far against evaluations and wall time, sampled every ``every`` evals."""

    def __init__(self, budget: int, every: int):
        self.budget, self.every = budget, max(int(every), 1)
        self.t0 = time.perf_counter()
        self.evals, self.best = 0, float("inf")
        self.points: list[dict] = []  # {"evaluations", "best_cost", "wall_s"}
        self._next = 0
        self.reached: dict | None = None  # first point at or below the target
        self.target: float | None = None

    def add(self, n_evals: int, costs: np.ndarray | float) -> None:
        costs = np.asarray(costs, np.float64).reshape(-1)
        finite = costs[np.isfinite(costs)]
        self.evals += int(n_evals)
        if finite.size:
            self.best = min(self.best, float(finite.min()))
        now = time.perf_counter() - self.t0
        point = {"evaluations": self.evals, "best_cost": self.best, "wall_s": now}
        if self.target is not None and self.reached is None and self.best <= self.target:
            self.reached = point
        if self.evals >= self._next or self.done:
            self.points.append(point)
            while self._next <= self.evals:
                self._next += self.every

    @property
    def done(self) -> bool:
        return self.evals >= self.budget


# --------------------------------------------------------------------- fixed networks
def fixed_genome(
    rng: np.random.Generator,
    hidden: int,
    *,
    n_inputs: int = 10,
    n_outputs: int = 3,
    scale: float = 0.1,
) -> Genome:
    """A fully connected ``n_inputs-hidden-n_outputs`` network as an EANT2 linear genome.

    Each hidden neuron (ids ``n_outputs ..``) reads every input and a bias; each output neuron
    reads every hidden neuron, every input and a bias. The hidden neurons are written inside
    the LAST output's subtree; the other outputs read them through forward jumpers (a forward
    jumper must point to a neuron to its right). Every neuron gene's own weight is a parameter
    too (the weight of its output connection; for a root, a scale), as in every EANT2 genome.
    Weights ``N(0, scale^2)``.
    """

    def w() -> float:
        return float(rng.normal(scale=scale))

    def direct() -> list[Gene]:
        return [Gene(GeneKind.INPUT, j, w()) for j in range(n_inputs)] + [
            Gene(GeneKind.BIAS, -1, w())
        ]

    hid = list(range(n_outputs, n_outputs + hidden))
    genes: list[Gene] = []
    for r in range(n_outputs):
        if r < n_outputs - 1:
            kids = [Gene(GeneKind.FORWARD, k, w()) for k in hid] + direct()
            genes += [Gene(GeneKind.NEURON, r, w(), len(kids)), *kids]
        else:
            genes.append(Gene(GeneKind.NEURON, r, w(), hidden + n_inputs + 1))
            for k in hid:
                genes += [Gene(GeneKind.NEURON, k, w(), n_inputs + 1), *direct()]
            genes += direct()
    return Genome(genes)


def _fixed_cost_fn(task, genome: Genome):
    """``(costs(x [K, n]) -> [K], n, x0 [n])``: the task cost of weight vectors of ``genome``."""
    batch = compile_genomes([genome], task.n_inputs, pad_count=False)
    layout = jax.tree.map(lambda a: a[0], batch.layout)
    n = genome.n_params
    pad = batch.weights.shape[-1]

    def costs(task, x):
        full = jnp.zeros((x.shape[0], pad), x.dtype).at[:, :n].set(x)
        nets = jax.vmap(kn.network, in_axes=(None, 0))(layout, full)
        return task.cost(None, nets)

    return costs, n, np.asarray(genome.weights, np.float64)


def run_evosax(task, hidden: int, budget: int, every: int, seed: int, sigma0: float) -> Curve:
    from evosax.algorithms import CMA_ES

    genome = fixed_genome(np.random.default_rng(seed), hidden)
    costs, n, x0 = _fixed_cost_fn(task, genome)
    popsize = ex.default_popsize(n)
    es = CMA_ES(popsize, jnp.zeros(n))
    params = es.default_params.replace(std_init=sigma0)

    @jax.jit
    def step(key, state, task):
        k1, k2 = jax.random.split(key)
        # evosax broadcasts [n] against [popsize, n]; allow it whatever the global config.
        with jax.numpy_rank_promotion("allow"):
            x, state = es.ask(k1, state, params)
            c = costs(task, x)
            state, _ = es.tell(k2, x, c, state, params)
        return state, c

    curve = Curve(budget, every)
    key = jax.random.key(seed)
    state = evosax_start(es, key, jnp.asarray(x0, jnp.float32), params)
    i = 0
    while not curve.done:
        state, c = step(jax.random.fold_in(key, i), state, task)
        curve.add(popsize, np.asarray(c))
        i += 1
    return curve


def run_pycma(
    task, hidden: int, budget: int, every: int, seed: int, sigma0: float, device: str
) -> Curve:
    import cma

    genome = fixed_genome(np.random.default_rng(seed), hidden)
    costs, n, x0 = _fixed_cost_fn(task, genome)
    dev = jax.devices(device)[0] if device != "default" else jax.devices()[0]
    task_d = jax.device_put(task, dev)
    cost_jit = jax.jit(costs)
    popsize = ex.default_popsize(n)
    curve = Curve(budget, every)
    restart = 0
    while not curve.done:
        opts = {"popsize": popsize, "seed": seed + 1 + restart, "verbose": -9}
        es = cma.CMAEvolutionStrategy(x0, sigma0, opts)
        while not curve.done and not es.stop():
            xs = es.ask()
            x = jax.device_put(np.asarray(xs, np.float32), dev)
            c = np.asarray(cost_jit(task_d, x), np.float64)
            es.tell(xs, [float(v) if np.isfinite(v) else 1e10 for v in c])
            curve.add(popsize, c)
        restart += 1
    return curve


# ---------------------------------------------------------------------------------- NEAT
@jax.jit
def outputs_cost(task, y: jax.Array) -> jax.Array:
    """Task costs ``[G]`` of controllers given their raw outputs ``y`` ``[G, N, 3]`` at the N
    start poses (one move per start): ``dq = max_step * tanh(y)``, then ``Servo.move`` from
    each start at rest, mean move cost over starts (what ``Servo.cost`` does for a network)."""
    if task.moves_per_start != 1:
        raise ValueError("outputs_cost needs moves_per_start == 1 (open-loop, fixed inputs)")

    def one_start(q, y1):
        return task.move(q, jnp.zeros_like(q), task.max_step * jnp.tanh(y1))[3]

    return jax.vmap(lambda yg: jnp.mean(jax.vmap(one_start)(task.q_start, yg)))(y)


def _neat_tanh(z: np.ndarray) -> np.ndarray:
    # neat.activations.tanh_activation, vectorised.
    return np.tanh(np.clip(2.5 * z, -60.0, 60.0))


def neat_outputs(net, x: np.ndarray) -> np.ndarray:
    """Outputs ``[N, n_out]`` of a ``neat.nn.FeedForwardNetwork`` on inputs ``x`` ``[N, n_in]``.

    Same arithmetic as ``FeedForwardNetwork.activate`` (``act(bias + response * sum(w v))``,
    sum aggregation), vectorised over the N rows; hidden nodes use NEAT's tanh, output nodes
    identity (the servo task applies its own tanh), whatever activation the genome names.
    """
    values = {k: x[:, i] for i, k in enumerate(net.input_nodes)}
    outputs = set(net.output_nodes)
    zero = np.zeros(x.shape[0])
    for node, _act, _agg, bias, response, links in net.node_evals:
        s = zero.copy()
        for i, w in links:
            s += w * values.get(i, zero)
        z = bias + response * s
        values[node] = z if node in outputs else _neat_tanh(z)
    return np.stack([values.get(k, zero) for k in net.output_nodes], axis=-1)


NEAT_CONFIG = {
    "NEAT": {
        "fitness_criterion": "max",
        "fitness_threshold": "1.0",  # costs are >= 0: never reached, the budget stops runs
        "no_fitness_termination": "True",
        "pop_size": "150",
        "reset_on_extinction": "True",
    },
    "DefaultGenome": {
        "num_inputs": "10",
        "num_outputs": "3",
        "num_hidden": "0",
        "feed_forward": "True",
        "initial_connection": "full_direct",
        "compatibility_disjoint_coefficient": "1.0",
        "compatibility_weight_coefficient": "0.5",
        "conn_add_prob": "0.5",
        "conn_delete_prob": "0.5",
        "node_add_prob": "0.2",
        "node_delete_prob": "0.2",
        "activation_default": "tanh",
        "activation_options": "tanh",
        "activation_mutate_rate": "0.0",
        "aggregation_default": "sum",
        "aggregation_options": "sum",
        "aggregation_mutate_rate": "0.0",
        "bias_init_mean": "0.0",
        "bias_init_stdev": "1.0",
        "bias_init_type": "gaussian",
        "bias_max_value": "30.0",
        "bias_min_value": "-30.0",
        "bias_mutate_power": "0.5",
        "bias_mutate_rate": "0.7",
        "bias_replace_rate": "0.1",
        "response_init_mean": "1.0",
        "response_init_stdev": "0.0",
        "response_init_type": "gaussian",
        "response_max_value": "30.0",
        "response_min_value": "-30.0",
        "response_mutate_power": "0.0",
        "response_mutate_rate": "0.0",
        "response_replace_rate": "0.0",
        "weight_init_mean": "0.0",
        "weight_init_stdev": "1.0",
        "weight_init_type": "gaussian",
        "weight_max_value": "30",
        "weight_min_value": "-30",
        "weight_mutate_power": "0.5",
        "weight_mutate_rate": "0.8",
        "weight_replace_rate": "0.1",
        "enabled_default": "True",
        "enabled_mutate_rate": "0.01",
        "enabled_rate_to_true_add": "0.0",
        "enabled_rate_to_false_add": "0.0",
    },
    "DefaultSpeciesSet": {"compatibility_threshold": "3.0"},
    "DefaultStagnation": {
        "species_fitness_func": "max",
        "max_stagnation": "20",
        "species_elitism": "2",
    },
    "DefaultReproduction": {"elitism": "2", "survival_threshold": "0.2"},
}


def _neat_config(pop_size: int, seed: int):
    import neat

    cp = configparser.ConfigParser()
    cp.read_dict(NEAT_CONFIG)
    cp["NEAT"]["pop_size"] = str(pop_size)
    cp["NEAT"]["seed"] = str(seed)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "neat.cfg"
        with path.open("w") as f:
            cp.write(f)
        return neat.Config(
            neat.DefaultGenome,
            neat.DefaultReproduction,
            neat.DefaultSpeciesSet,
            neat.DefaultStagnation,
            str(path),
        )


def run_neat(task, budget: int, every: int, seed: int, pop_size: int) -> Curve:
    import random

    import neat

    random.seed(seed)
    config = _neat_config(pop_size, seed)
    x = np.asarray(task.x_start, np.float64)
    curve = Curve(budget, every)

    def evaluate(genomes, config):
        nets = [neat.nn.FeedForwardNetwork.create(g, config) for _, g in genomes]
        y = np.stack([neat_outputs(net, x) for net in nets]).astype(np.float32)
        c = np.asarray(outputs_cost(task, jnp.asarray(y)), np.float64)
        for (_, g), v in zip(genomes, c, strict=True):
            g.fitness = -float(v) if np.isfinite(v) else -1e10
        curve.add(len(genomes), c)

    pop = neat.Population(config)
    pop.run(evaluate, max(1, -(-budget // pop_size)))
    return curve


# --------------------------------------------------------------------------------- EANT2
class _Budget(Exception):
    pass


def run_eant2(task, budget: int, every: int, seed: int, config: loop.EANT2Config) -> Curve:
    curve = Curve(budget, every)
    curve.every = 1  # one point per generation: all of them

    def on_event(event):
        if event["event"] != "generation":
            return
        curve.add(event["evaluations"] - curve.evals, event["best_cost"])
        if curve.done:
            raise _Budget

    try:
        loop.run(
            task, key=jax.random.key(seed), config=config, generations=10**6, callback=on_event
        )
    except _Budget:
        pass
    return curve


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
            pruner="covariance",
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
