"""The peers' runs on the servo task (bench/bench_peers.py): each method tunes until it has spent
its evaluation budget and records its best cost against evaluations and wall time (`Curve`):
evosax's CMA-ES and pycma on a fixed network written as an EANT2 genome, neat-python scored by
the task's own cost of its outputs, and this project's EANT2 loop."""

from __future__ import annotations

import configparser
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from bench.common import evosax_start
from eant2_jax import exploitation as ex
from eant2_jax import loop
from eant2_jax.compiler import compile_genomes
from eant2_jax.genome import Gene, GeneKind, Genome
from eant2_jax.kernels import network as kn

__all__ = [
    "Curve",
    "fixed_genome",
    "neat_outputs",
    "outputs_cost",
    "run_eant2",
    "run_evosax",
    "run_neat",
    "run_pycma",
]


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
