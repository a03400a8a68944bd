"""The EANT2 loop (paper section III, figures 3 and 5): one function per box of the figure.

::

    initialise          minimal networks (one neuron per output, no hidden neurons)
      -> exploit        batched CMA-ES of every new structure (+ pruning), exploitation.run
      -> repeat:
           explore      offspring by structural mutation (weight-0 joins), exploration.mutate
           exploit      batched CMA-ES of the offspring (+ parents if ``reexploit``)
           select       rank-based greedy with the diversity rules, exploration.select

Everything a run does flows from one PRNG key and an `EANT2Config`: generation ``g``
uses ``fold_in(key, g)``, split into a mutation key (seeding a NumPy generator for the host
side) and an exploitation key. The whole state after a generation is a small JSON document
(`RunState.to_json`), so a run resumes from its last complete generation and, on CPU,
ends with exactly the result of an uninterrupted run.

The library never prints: progress goes to ``callback(event: dict)``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import distributed
from .compiler import GENE_FLOOR, NEURON_FLOOR, Bucket, bucket_for, bucket_size
from .config import EANT2Config
from .exploration import OPERATORS, initial_genome, mutate, select
from .genome import Genome
from .genomefile import GenomeFile
from .pruning import PruneAttempt
from .rundir import RunDir, RunDirError
from .tasks import check_task, spec_of
from .tasks import make as make_task
from .tasks.base import Task
from .tuning import tune

__all__ = [
    "EANT2Config",
    "GenerationRecord",
    "Individual",
    "RunResult",
    "RunState",
    "resume",
    "run",
]


@dataclasses.dataclass(frozen=True)
class Individual:
    """A member of the population: its genome (with tuned weights) and its cost."""

    genome: Genome
    cost: float
    origin: str = "init"  # the operator that made it, or "init"

    def to_json(self) -> dict:
        return {"genome": str(self.genome), "cost": self.cost, "origin": self.origin}

    @classmethod
    def from_json(cls, d: dict) -> Individual:
        return cls(Genome.parse(d["genome"]), float(d["cost"]), d.get("origin", "init"))


@dataclasses.dataclass(frozen=True)
class RunState:
    """Everything needed to continue a run after a completed generation."""

    generation: int
    population: tuple[Individual, ...]
    next_id: int
    evaluations: int
    key: tuple[int, ...]  # raw key data of the run's PRNG key
    wall_s: float = 0.0

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["population"] = [ind.to_json() for ind in self.population]
        d["key"] = list(self.key)
        return d

    @classmethod
    def from_json(cls, d: dict) -> RunState:
        return cls(
            generation=int(d["generation"]),
            population=tuple(Individual.from_json(x) for x in d["population"]),
            next_id=int(d["next_id"]),
            evaluations=int(d["evaluations"]),
            key=tuple(int(k) for k in d["key"]),
            wall_s=float(d.get("wall_s", 0.0)),
        )

    def best(self) -> Individual:
        return self.population[0]


@dataclasses.dataclass(frozen=True)
class GenerationRecord:
    """One completed generation, as the run directory's ``generations.jsonl`` holds it.

    Attributes:
      generation: its number (0: the initial population).
      best_cost, best_size, best_neurons, best_genome: the best individual after selection
        (size = number of genes = weights).
      mean_size: mean size of the population.
      evaluations: cost evaluations of the run so far.
      wall_s: wall time of the run so far; generation_s: of this generation.
      prune_attempts, prune_accepted: pruning attempts in this generation, and accepted ones.
      population: individuals kept; exploited: structures tuned in this generation.
    """

    generation: int
    best_cost: float
    best_size: int
    mean_size: float
    best_neurons: int
    evaluations: int
    wall_s: float
    prune_attempts: int
    prune_accepted: int
    population: int
    exploited: int
    generation_s: float
    best_genome: str

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> GenerationRecord:
        return cls(**d)


class RunResult(NamedTuple):
    """What `run` returns.

    Attributes:
      population: the final population, best first.
      best: the best genome.
      generations: one `GenerationRecord` per generation.
      pruning: one `PruneAttempt` per pruning attempt.
    """

    population: list[Individual]
    best: Genome
    generations: list[GenerationRecord]
    pruning: list[PruneAttempt]


def _key_data(key: jax.Array) -> tuple[int, ...]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return tuple(int(k) for k in np.asarray(key, dtype=np.uint32).ravel())


def _key_from_data(data: Sequence[int]) -> jax.Array:
    """A typed PRNG key from its raw data (as stored in checkpoints and config.json)."""
    return jax.random.wrap_key_data(jnp.asarray(np.array(data, dtype=np.uint32)))


def _initialise(task: Task, key: jax.Array, config: EANT2Config) -> tuple[list[Genome], int]:
    rng = np.random.default_rng(_key_data(key))
    genomes, seen = [], set()
    for _ in range(config.population):
        g = initial_genome(
            rng,
            task.n_inputs,
            task.n_outputs,
            connectivity=config.init_connectivity,
            weight_scale=config.init_weight_scale,
        )
        # Identical structures are not evaluated twice (with full connectivity, all are).
        if g.structure_key() not in seen:
            seen.add(g.structure_key())
            genomes.append(g)
    return genomes, task.n_outputs


def _explore(
    rng: np.random.Generator,
    population: Sequence[Individual],
    task: Task,
    next_id: int,
    config: EANT2Config,
) -> tuple[list[Individual], int]:
    """Make offspring by structural mutation; duplicates of existing structures are dropped."""
    want = config.offspring or config.population
    seen = {ind.genome.structure_key() for ind in population}
    p = np.asarray(config.operator_weights) / sum(config.operator_weights)
    children: list[Individual] = []
    for _ in range(20 * want):  # give up on duplicates after a while
        if len(children) == want:
            break
        parent = population[int(rng.integers(len(population)))]
        op = OPERATORS[int(rng.choice(len(OPERATORS), p=p))]
        child = mutate(
            rng,
            parent.genome,
            op,
            n_inputs=task.n_inputs,
            next_id=next_id,
            input_fraction=config.input_fraction,
            weight_scale=config.new_weight_scale,
        )
        if child is None or child.structure_key() in seen:
            continue
        if op == "add_subnetwork":
            next_id += 1
        seen.add(child.structure_key())
        children.append(Individual(child, parent.cost, op))
    return children, next_id


def _generation_record(
    state: RunState, evaluated: int, prune: list[PruneAttempt], t: float
) -> GenerationRecord:
    best = state.best()
    sizes = [ind.genome.n_params for ind in state.population]
    return GenerationRecord(
        generation=state.generation,
        best_cost=best.cost,
        best_size=best.genome.n_params,
        mean_size=float(np.mean(sizes)),
        best_neurons=best.genome.n_neurons,
        evaluations=state.evaluations,
        wall_s=state.wall_s,
        prune_attempts=len(prune),
        prune_accepted=sum(r.accepted for r in prune),
        population=len(state.population),
        exploited=evaluated,
        generation_s=t,
        best_genome=str(best.genome),
    )


def grow_bucket(genomes: Sequence[Genome], current: Bucket | None) -> Bucket:
    """The bucket a generation compiles into: ``current`` while the genomes fit, else one
    with headroom, the smallest bucket for one more neuron, gene and sweep than they need
    (at least two sweeps: a first hidden neuron adds one).

    Each new bucket is a new program to compile (seconds on a CPU, more on a GPU), while the
    padding costs little (a generation is latency-bound: docs/benchmarks.md). Results do not
    depend on it: a structure's CMA-ES is independent of its padding."""
    need = bucket_for(genomes)
    if current is not None and (
        need.neurons <= current.neurons
        and need.genes <= current.genes
        and need.sweeps <= current.sweeps
    ):
        return current
    return Bucket(
        neurons=bucket_size(max(g.n_neurons for g in genomes) + 1, NEURON_FLOOR),
        genes=bucket_size(max(g.n_params for g in genomes) + 1, GENE_FLOOR),
        sweeps=bucket_size(max(max(g.depth() for g in genomes) + 1, 2)),
    )


def _generation(
    task: Task,
    state: RunState | None,
    key: jax.Array,
    config: EANT2Config,
    callback,
    mesh=None,
    bucket: Bucket | None = None,
) -> tuple[RunState, GenerationRecord, list[PruneAttempt], Bucket | None]:
    """One generation (generation 0 initialises); returns the new state, its records and
    the bucket it compiled into (:func:`grow_bucket` of ``bucket``)."""
    t0 = time.perf_counter()
    gen = 0 if state is None else state.generation + 1
    gkey = jax.random.fold_in(key, gen)
    mut_key, exp_key = jax.random.split(gkey)

    def progress(info):
        if callback is not None:
            callback({"event": "exploit", "generation": gen, **info})

    def compiling(info):
        if callback is not None:
            callback({"event": "compiling", "generation": gen, **info})

    if state is None:
        genomes, next_id = _initialise(task, mut_key, config)
        parents: list[Individual] = []
        new = [Individual(g, float("inf")) for g in genomes]
        evaluations = 0
    else:
        rng = np.random.default_rng(_key_data(mut_key))
        parents = list(state.population)
        new, next_id = _explore(rng, parents, task, state.next_id, config)
        evaluations = state.evaluations
        if config.reexploit:
            new = parents + new
            parents = []
    if new:
        bucket = grow_bucket([ind.genome for ind in new], bucket)
        res = tune(
            [ind.genome for ind in new],
            task,
            key=exp_key,
            config=config.exploit,
            bucket=bucket,
            on_chunk=progress,
            on_compile=compiling,
            mesh=mesh,
            # Every generation's batch gets the same number of rows: one program per bucket.
            min_rows=(config.offspring or config.population)
            + (config.population if config.reexploit else 0),
        )
        new = [
            Individual(g, c, ind.origin)
            for g, c, ind in zip(res.genomes, res.costs, new, strict=True)
        ]
        evals = sum(res.evaluations)
        prune = [dataclasses.replace(r, generation=gen) for r in res.pruning]
    else:
        evals, prune = 0, []
    pool = parents + new
    keep = select(
        [ind.genome for ind in pool],
        [ind.cost for ind in pool],
        config.population,
        similar_limit=config.similar_limit,
        prefer_smaller=config.prefer_smaller,
        size_tolerance=config.size_tolerance,
        size_atol=config.size_atol,
    )
    dt = time.perf_counter() - t0
    state = RunState(
        generation=gen,
        population=tuple(pool[i] for i in keep),
        next_id=next_id,
        evaluations=evaluations + evals,
        key=_key_data(key) if state is None else state.key,
        wall_s=(0.0 if state is None else state.wall_s) + dt,
    )
    return state, _generation_record(state, len(new), prune, dt), prune, bucket


def run(
    task: Task,
    *,
    key: jax.Array,
    config: EANT2Config | None = None,
    generations: int,
    out: str | None = None,
    callback: Callable[[dict], None] | None = None,
    meta: dict | None = None,
) -> RunResult:
    """Run EANT2 on a task.

    Args:
      task: the task (see `eant2_jax.tasks`).
      key: the run's PRNG key; the same key and config give the same run.
      config: `EANT2Config` (default: its defaults, covariance pruning on).
      generations: generations after the initial one (generation 0 exploits the minimal
        networks; the result has ``generations + 1`` generation records).
      out: optional run directory to create (must not exist or be empty); a run written
        there continues with `resume` after a crash or a kill.
      callback: receives progress events: dicts with ``event`` = ``generation`` (a
        `GenerationRecord`'s fields), ``exploit`` (after each chunk of CMA-ES
        iterations) or ``compiling`` (before a program is first compiled).
        `eant2_jax.progress.ProgressReporter` prints them.
      meta: extra JSON fields for ``config.json``. A task built by
        `eant2_jax.tasks.make` records its spec and options there by itself, so that
        `resume` can rebuild it.

    Returns:
      `RunResult`.
    """
    config = EANT2Config() if config is None else config
    if generations < 0:
        raise ValueError(f"generations must be >= 0, got {generations}")
    check_task(task)  # before anything is written
    rundir = None
    # What config.json records of the task; best.genome's header reads it too, in this run
    # and after a resume alike.
    spec = spec_of(task) or {"task_type": f"{type(task).__module__}.{type(task).__qualname__}"}
    meta = {**spec, **(meta or {})}
    if out is not None:
        rundir = RunDir.create(
            out,
            {
                **meta,
                "generations": generations,
                "key": list(_key_data(key)),
                "config": config.to_dict(),
            },
        )
    key = _key_from_data(_key_data(key))
    return _loop(task, None, key, config, generations, rundir, callback, meta)


def resume(
    out: str,
    task: Task | None = None,
    *,
    generations: int | None = None,
    callback: Callable[[dict], None] | None = None,
) -> RunResult:
    """Continue a run directory from its last complete generation.

    Args:
      out: the run directory.
      task: the task it was run on; None rebuilds it from the spec in ``config.json``
        (recorded when the task came from `eant2_jax.tasks.make`: a registered name,
        ``module:factory`` or ``file.py:factory``).
      generations: new total number of generations (default: the one in ``config.json``).
      callback: progress events, as for `run`.

    Raises:
      RunDirError: not a run directory, a corrupt one, or no task given and none recorded.
    """
    rundir = RunDir.open(out)
    meta = rundir.config()
    if task is None:
        task = _task_from_meta(meta, rundir)
    check_task(task)
    try:
        config = EANT2Config.from_dict(meta["config"])
        total = int(meta["generations"] if generations is None else generations)
    except (KeyError, TypeError, ValueError) as e:
        raise RunDirError(f"{rundir.path}: config.json is corrupt: {e}") from None
    ckpt = rundir.checkpoint()
    try:
        state = None if ckpt is None else RunState.from_json(ckpt["state"])
    except (KeyError, TypeError, ValueError) as e:
        raise RunDirError(f"{rundir.path}: checkpoint.json is corrupt: {e}") from None
    rundir.rewind(None if ckpt is None else ckpt["offsets"])
    if state is None:
        key = _key_from_meta(meta, rundir)
    else:
        key = _key_from_data(state.key)
    return _loop(task, state, key, config, total, rundir, callback, meta)


def _task_from_meta(meta: dict, rundir: RunDir) -> Task:
    """Rebuild a run's task from the spec its ``config.json`` records."""
    if not isinstance(meta.get("task"), str):
        kind = meta.get("task_type", "unknown")
        raise RunDirError(
            f"{rundir.path}: config.json records no task spec (its task, {kind}, was not built "
            f"by eant2_jax.tasks.make); pass the task to resume(), or start runs with "
            f"tasks.make('module:factory')"
        )
    options = meta.get("task_options", {})
    if not isinstance(options, dict):
        raise RunDirError(f"{rundir.path}: config.json is corrupt: task_options is not a dict")
    return make_task(meta["task"], **options)


def _key_from_meta(meta: dict, rundir: RunDir) -> jax.Array:
    if "key" not in meta:
        raise RunDirError(f"{rundir.path}: config.json has no key; the run cannot be resumed")
    return _key_from_data(meta["key"])


def _loop(task, state, key, config, generations, rundir, callback, meta) -> RunResult:
    gen_records = (
        [] if rundir is None else [GenerationRecord.from_json(r) for r in rundir.generations()]
    )
    prune_records = [] if rundir is None else [PruneAttempt.from_json(r) for r in rundir.pruning()]
    mesh = distributed.make_mesh(config.devices)
    bucket = None  # grows, never shrinks: one program for as long as the genomes fit
    while state is None or state.generation < generations:
        if state is not None and config.target_cost is not None:
            if state.best().cost <= config.target_cost:
                break
        state, record, prune, bucket = _generation(task, state, key, config, callback, mesh, bucket)
        gen_records.append(record)
        prune_records.extend(prune)
        if rundir is not None:
            # best.genome carries what is needed to run it: activations, sizes, the task.
            best = GenomeFile.from_task(
                state.best().genome,
                task,
                name=meta.get("task"),
                options=meta.get("task_options"),
            )
            rundir.commit(
                [record.to_json()],
                [r.to_json() for r in prune],
                best.to_text().rstrip("\n"),  # commit adds the newline
                state.to_json(),
            )
        if callback is not None:
            callback({"event": "generation", **record.to_json()})
    return RunResult(list(state.population), state.best().genome, gen_records, prune_records)
