"""EANT2 as an ask/tell strategy: one generation as four pure steps (docs/algorithm.md).

The boxes of the paper's figure 3 (EANT2) and figure 5 (with pruning inside the
exploitation box), one function each::

    init      initialise          minimal networks (one neuron per output): the brood of
                                  generation 0
    ask       explore             offspring by structural mutation (weight-0 joins), with
                                  their parents' searches (``inherit_search``) and the
                                  parents themselves to tune again (``reexploit``)
    exploit   exploit (+ prune)   ONE batched CMA-ES run of a brood's new structures, with
                                  pruning (`eant2_jax.tuning.tune`)
    tell      select              rank-based greedy selection with the diversity rules: the
                                  new `RunState`, its `GenerationRecord`, its pruning records
    stopped   repeat?             target cost (by default the task's solved level,
                                  `resolved`) or evaluation budget reached

Each takes the run's PRNG key first (generation ``g`` draws from ``fold_in(key, g)``) and
is a function of its arguments: the same key, config and state give the same brood, the
same tuning and the same selection, so a driver of one's own makes exactly the run
`eant2_jax.run` makes. The only things read from the process are the timings and
compilation counts a `GenerationRecord` reports (``records.RUN_DEPENDENT``). A driver in
ten lines (the run of `eant2_jax.run` for ``generations``, without a run directory)::

    from eant2_jax import strategy

    config = strategy.resolved(config, task)  # the target: the task's solved level
    state, records, brood = None, [], strategy.init(key, task, config)
    while True:
        tuned = strategy.exploit(brood, task, config)
        state, record, pruning, _ = strategy.tell(key, state, brood, tuned, config)
        records.append(record)
        if state.generation >= generations or strategy.stopped(state, config):
            break
        brood = strategy.ask(key, state, task, config)
    best = state.best()

`eant2_jax.loop` is the library's driver of K >= 1 such runs (a run alone is a group of
one; `eant2_jax.run_lockstep` tunes the broods of K runs in one batch with
`exploit_together`), with run directories, progress events and compile-ahead around it.
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
from .compiler import Bucket, batch_rows
from .config import EANT2Config
from .exploration import initial_genome, mutate_once, offspring, select
from .genome import Genome
from .programs import stats
from .programs.guesses import generation_rows, grow_bucket
from .pruning import PruneAttempt
from .records import GenerationRecord, Individual, RunState, key_data
from .tasks.base import Task, solved_cost
from .tuning import Search, inherited, start_keys, tune

__all__ = [
    "Brood",
    "Told",
    "Tuned",
    "ask",
    "batch_fill",
    "exploit",
    "exploit_together",
    "init",
    "initialise",
    "resolved",
    "stopped",
    "tell",
]


class Brood(NamedTuple):
    """A generation up to its tuning (`init`, `ask`): what it tunes and what it keeps aside.

    Attributes:
      generation: the generation's number (0: the initial structures).
      parents: individuals that go into selection untuned (the population, unless
        ``reexploit``).
      new: the individuals to tune (their genomes hold the starting weights).
      next_id: the next free neuron id after this generation's mutations.
      evaluations: the run's cost evaluations before this generation.
      starts: warm starts of ``new`` (``inherit_search``), one per individual, or None.
      key: the generation's exploitation key (the second of ``split(fold_in(key, g))``).
      bucket: the padding bucket the run had grown to (None before generation 0).
      t0, compiled: when the generation started and the process's compilation counts then
        (for its record's timings only).
    """

    generation: int
    parents: list[Individual]
    new: list[Individual]
    next_id: int
    evaluations: int
    starts: list[Search | None] | None
    key: jax.Array
    bucket: Bucket | None
    t0: float
    compiled: stats.CompileStats


class Tuned(NamedTuple):
    """What `exploit` returns for one brood: its part of a `eant2_jax.tuning.tune` result
    (in the order of ``Brood.new``) and the bucket it was tuned in.

    Attributes:
      genomes, costs, evaluations: each new structure's tuned (and pruned) genome, its cost
        and its cost evaluations.
      pruning: the pruning attempts; ``structure`` is the index in ``genomes``.
      searches: each one's final search (``inherit_search``), or None.
      solution: the index of the structure whose network passed a ``solution_test``, or
        None.
      bucket: the padding bucket of the tuning (`grow_bucket`); the new state records it.
      fill: the batch's fill (`batch_fill`), or None where nothing was tuned.
    """

    genomes: list[Genome]
    costs: list[float]
    evaluations: list[int]
    pruning: list[PruneAttempt]
    searches: list[Search | None] | None
    solution: int | None
    bucket: Bucket | None
    fill: float | None = None


class Told(NamedTuple):
    """What `tell` returns: the state after the generation, its record, its pruning
    records (with their generation) and the individual that passed a ``solution_test``
    (None if none did)."""

    state: RunState
    record: GenerationRecord
    pruning: list[PruneAttempt]
    solution: Individual | None


def batch_fill(running) -> float | None:
    """The share of a batch's row-iterations that ran a search. ``running`` is the engine's
    ``[ticks, rows]`` record (`eant2_jax.exploitation.StepRecord`), every row of the batch
    included: padding rows, rows that round a batch up for a mesh and rows whose search has
    stopped count as idle (docs/algorithm.md, "Batch width"). The iterations counted are
    those the engine ran: up to the last in which a row ran (its last chunk's record goes on
    past it, iterations its loop never ran). None for a batch in which nothing ran."""
    running = np.asarray(running, bool)
    ran = np.flatnonzero(running.any(axis=1))
    return float(np.mean(running[: ran[-1] + 1])) if ran.size else None


@jax.jit
def _generation_keys(key: jax.Array, gen: int | jax.Array) -> tuple[jax.Array, jax.Array]:
    """``split(fold_in(key, gen))``: a generation's mutation and exploitation keys. One
    program: run eagerly, the same integer operations compile four (the conversion,
    ``fold_in``, ``split`` and the unpacking)."""
    mut_key, exp_key = jax.random.split(jax.random.fold_in(key, gen))
    return mut_key, exp_key


def initialise(key: jax.Array, task: Task, config: EANT2Config) -> tuple[list[Genome], int]:
    """Generation 0's genomes and the next free neuron id: ``population`` minimal starts,
    each with ``init_mutations`` structural mutations (a diverse start when asked),
    duplicates dropped. ``key`` seeds the host's generator (`init` passes generation 0's
    mutation key)."""
    rng = np.random.default_rng(key_data(key))
    genomes, seen, next_id = [], set(), task.n_outputs
    # Without mutations one draw per slot (with full connectivity every draw is the same
    # structure); with them, a slot draws again (20 times at most) when it meets a
    # structure already drawn.
    tries = 20 if config.init_mutations else 1
    for _ in range(config.population):
        for _ in range(tries):
            g = initial_genome(
                rng,
                task.n_inputs,
                task.n_outputs,
                connectivity=config.init_connectivity,
                weight_scale=config.init_weight_scale,
                recurrent=config.init_recurrent,
            )
            used = 0
            for _ in range(config.init_mutations):
                child, op = mutate_once(rng, g, task.n_inputs, next_id + used, config)
                if child is not None:
                    g, used = child, used + (op == "add_subnetwork")
            # Identical structures are not evaluated twice.
            if g.structure_key() not in seen:
                seen.add(g.structure_key())
                genomes.append(g)
                next_id += used
                break
    return genomes, next_id


def init(key: jax.Array, task: Task, config: EANT2Config) -> Brood:
    """The initialise box: generation 0's brood, the minimal structures to tune.

    Args:
      key: the run's PRNG key.
      task: the task (its input and output counts shape the networks).
      config: the run's configuration.
    """
    t0, compiled = time.perf_counter(), stats.snapshot()
    mut_key, exp_key = _generation_keys(key, 0)
    genomes, next_id = initialise(mut_key, task, config)
    new = [Individual(g, float("inf")) for g in genomes]
    return Brood(0, [], new, next_id, 0, None, exp_key, None, t0, compiled)


def ask(key: jax.Array, state: RunState, task: Task, config: EANT2Config) -> Brood:
    """The explore box: the brood of the generation after ``state``'s.

    Offspring of the population by structural mutation (`eant2_jax.exploration.offspring`),
    each with its parent's cost until tuned; with ``inherit_search`` each child's warm
    start from its parent's search (`eant2_jax.tuning.inherited`); with ``reexploit`` the
    parents go into the brood to be tuned again, from their own searches.

    Args:
      key: the run's PRNG key (the one `init` got).
      state: the state after the last generation (`tell`).
      task: the task; config: the run's configuration.
    """
    t0, compiled = time.perf_counter(), stats.snapshot()
    gen = state.generation + 1
    mut_key, exp_key = _generation_keys(key, gen)
    rng = np.random.default_rng(key_data(mut_key))
    parents = list(state.population)
    children, ops, made_from, next_id = offspring(
        rng, [p.genome for p in parents], task.n_inputs, state.next_id, config
    )
    new = [
        Individual(c, parents[i].cost, op)
        for c, op, i in zip(children, ops, made_from, strict=True)
    ]
    starts: list[Search | None] | None = None
    if config.inherit_search:
        sigma0 = config.exploit.sigma0
        starts = [
            None if p.search is None else inherited(p.genome, p.search, c, sigma0)
            for c, p in zip(children, (parents[i] for i in made_from), strict=True)
        ]
    if config.reexploit:
        new = parents + new
        if starts is not None:  # their own C and sigma go on
            starts = [p.search for p in parents] + starts
        parents = []
    bucket = None if state.bucket is None else Bucket(*state.bucket)
    return Brood(
        gen, parents, new, next_id, state.evaluations, starts, exp_key, bucket, t0, compiled
    )


def exploit(
    brood: Brood,
    task: Task,
    config: EANT2Config,
    *,
    on_chunk: Callable[[dict], None] | None = None,
    on_compile: Callable[[dict], None] | None = None,
    mesh: jax.sharding.Mesh | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
) -> Tuned:
    """The exploitation box (with pruning, figure 5): one batched CMA-ES run of the
    brood's new structures, padded to the run's bucket grown to fit them (`grow_bucket`).

    Args:
      brood: from `init` or `ask`.
      task: the task.
      config: the run's configuration.
      on_chunk: progress after each chunk of iterations (`eant2_jax.tuning.tune`).
      on_compile: called before a program is first compiled.
      mesh: split the batch over these devices.
      solution_test: a success test of a network (`eant2_jax.run`).
    """
    return exploit_together(
        [brood], task, config, brood.bucket, on_chunk=on_chunk, on_compile=on_compile,
        mesh=mesh, solution_test=solution_test,
    )[0]  # fmt: skip


def exploit_together(
    broods: Sequence[Brood],
    task: Task,
    config: EANT2Config,
    bucket: Bucket | None,
    *,
    on_chunk: Callable[[dict], None] | None = None,
    on_compile: Callable[[dict], None] | None = None,
    mesh: jax.sharding.Mesh | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
) -> list[Tuned]:
    """`exploit` of the broods of K >= 1 runs of one configuration in ONE batch (lock-step,
    `eant2_jax.run_lockstep`), padded to ``bucket`` grown to fit them all; each brood's part.

    Row j of a brood starts from the key it gets in its run alone (`eant2_jax.tuning.tune`:
    row j of a batch tuned with key k starts from ``fold_in(split(k)[0], j)``), so on a
    task that is not noisy a run tuned together is the run alone with the same bucket.
    ``solution_test`` halts the whole batch, so it is taken for one brood only.
    """
    genomes = [ind.genome for b in broods for ind in b.new]
    if not genomes:
        return [Tuned([], [], [], [], None, None, bucket) for _ in broods]
    if solution_test is not None and len(broods) > 1:
        raise ValueError("a solution_test halts the whole batch: tune one brood with it")
    bucket = grow_bucket(genomes, bucket, config.min_bucket)
    min_rows = generation_rows(config) * len(broods)
    starts = None
    if any(b.starts is not None for b in broods):
        starts = [s for b in broods for s in (b.starts or [None] * len(b.new))]
    keys = None  # one brood: tune derives the same row keys itself
    if len(broods) > 1:
        rows = batch_rows(len(genomes), min_rows=min_rows, multiple_of=distributed.size(mesh))
        # Padding rows start from the last brood's key, past its rows.
        counts = [len(b.new) for b in broods]
        counts[-1] += rows - len(genomes)
        init_keys = [jax.random.split(b.key)[0] for b in broods]
        keys = jnp.concatenate([start_keys(k, n) for k, n in zip(init_keys, counts, strict=True)])
    res = tune(
        genomes, task, key=broods[0].key, keys=keys, config=config.exploit, bucket=bucket,
        min_rows=min_rows, on_chunk=on_chunk, on_compile=on_compile, mesh=mesh,
        solution_test=solution_test, start=starts, keep_search=config.inherit_search,
    )  # fmt: skip
    fill = batch_fill(res.history.running)  # the batch's, shared by its broods
    parts, lo = [], 0
    for b in broods:
        hi = lo + len(b.new)
        pruning = [
            dataclasses.replace(r, structure=r.structure - lo)
            for r in res.pruning
            if lo <= r.structure < hi
        ]
        searches = None if res.searches is None else res.searches[lo:hi]
        solution = res.solution if len(broods) == 1 else None
        parts.append(
            Tuned(
                res.genomes[lo:hi],
                res.costs[lo:hi],
                res.evaluations[lo:hi],
                pruning,
                searches,
                solution,
                bucket,
                fill,
            )  # fmt: skip
        )
        lo = hi
    return parts


def tell(
    key: jax.Array, state: RunState | None, brood: Brood, tuned: Tuned, config: EANT2Config
) -> Told:
    """The select box: the tuned brood and its parents into selection
    (`eant2_jax.exploration.select`), the new state and the generation's records.

    Args:
      key: the run's PRNG key (recorded in the state of generation 0).
      state: the state the brood was asked from (None for generation 0's).
      brood: from `init` or `ask`; tuned: its `exploit`.
      config: the run's configuration.
    """
    searches = tuned.searches or [None] * len(brood.new)
    new = [
        Individual(g, c, ind.origin, w)
        for g, c, ind, w in zip(tuned.genomes, tuned.costs, brood.new, searches, strict=True)
    ]
    solution = None if tuned.solution is None else new[tuned.solution]
    prune = [dataclasses.replace(r, generation=brood.generation) for r in tuned.pruning]
    pool = brood.parents + new
    keep = select(
        [ind.genome for ind in pool],
        [ind.cost for ind in pool],
        config.population,
        similar_limit=config.similar_limit,
        prefer_smaller=config.prefer_smaller,
        size_tolerance=config.size_tolerance,
        size_atol=config.size_atol,
    )
    dt = time.perf_counter() - brood.t0
    bucket = tuned.bucket
    state = RunState(
        generation=brood.generation,
        population=tuple(pool[i] for i in keep),
        next_id=brood.next_id,
        evaluations=brood.evaluations + sum(tuned.evaluations),
        key=key_data(key) if state is None else state.key,
        wall_s=(0.0 if state is None else state.wall_s) + dt,
        bucket=None if bucket is None else (bucket.neurons, bucket.genes, bucket.sweeps),
    )
    compiled = stats.snapshot() - brood.compiled
    spent = state.evaluations - brood.evaluations
    record = _record(state, len(new), prune, dt, compiled, spent, tuned.fill)
    return Told(state, record, prune, solution)


def resolved(config: EANT2Config, task: Task, *, tested: bool = False) -> EANT2Config:
    """The configuration a run of ``task`` runs with: with no ``target_cost`` and
    ``stop_when_solved`` on, ``target_cost`` becomes the task's solved level (its
    ``solved_cost``, where it defines one). The one place the run's target is decided: a
    run directory records the configuration this returns, so a resume and a report read
    the target the run used. Resolving twice changes nothing.

    ``tested``: the run has a ``solution_test`` (`eant2_jax.run`). Such a run is solved
    when its test passes, not when its cost reaches the solved level: a training cost at
    that level whose network fails the test must not end it (docs/pole.md, "Under the
    published rule"), so only a ``target_cost`` given explicitly stops it."""
    if config.target_cost is not None or not config.stop_when_solved or tested:
        return config
    level = solved_cost(task)
    return config if level is None else dataclasses.replace(config, target_cost=level)


def stopped(state: RunState, config: EANT2Config) -> bool:
    """Whether a run stops before its next generation: ``target_cost`` (see `resolved`) or
    ``max_evaluations`` reached (docs/algorithm.md, "When a run stops")."""
    if config.target_cost is not None and state.best().cost <= config.target_cost:
        return True
    return config.max_evaluations is not None and state.evaluations >= config.max_evaluations


def _record(
    state: RunState,
    evaluated: int,
    prune: list[PruneAttempt],
    t: float,
    compiled: stats.CompileStats,
    spent: int,
    fill: float | None,
) -> GenerationRecord:
    best = state.best()
    sizes = [ind.genome.n_params for ind in state.population]
    mean_cost, cost_std = state.cost_stats()
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
        compiles=compiled.programs,
        compile_s=compiled.seconds,
        cache_hits=compiled.cache_hits,
        cache_misses=compiled.cache_misses,
        best_genome=str(best.genome),
        generation_evaluations=spent,
        mean_cost=mean_cost,
        cost_std=cost_std,
        batch_fill=fill,
    )
