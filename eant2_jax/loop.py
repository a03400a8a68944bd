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
import threading
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import compilestats, distributed, exploitation, tuning
from .compiler import GENE_FLOOR, NEURON_FLOOR, Bucket, bucket_size
from .config import EANT2Config
from .exploration import OPERATORS, initial_genome, mutate, select
from .genome import Genome
from .genomefile import GenomeFile
from .pruning import PruneAttempt
from .rundir import Committed, RunDir, RunDirError, as_float, dumps, typed_fields
from .tasks import check_task, spec_of
from .tasks import make as make_task
from .tasks.base import Task
from .tuning import Search, inherited, tune

__all__ = [
    "EANT2Config",
    "GenerationRecord",
    "Individual",
    "RunResult",
    "RunState",
    "Validated",
    "resume",
    "run",
    "validate",
]


@dataclasses.dataclass(frozen=True)
class Individual:
    """A member of the population: its genome (with tuned weights) and its cost."""

    genome: Genome
    cost: float
    origin: str = "init"  # the operator that made it, or "init"
    # With EANT2Config.inherit_search: the final CMA-ES search of its tuning, on its genes.
    search: Search | None = dataclasses.field(default=None, compare=False, repr=False)

    def to_json(self) -> dict:
        d = {"genome": str(self.genome), "cost": self.cost, "origin": self.origin}
        if self.search is not None:
            d["search"] = self.search.to_json()
        return d

    @classmethod
    def from_json(cls, d: dict) -> Individual:
        if not isinstance(d, dict) or not isinstance(d.get("genome"), str):
            raise ValueError("an individual is not an object with a genome text")
        fields = {"genome", "cost", "origin", "search"}
        if not isinstance(d.get("origin", "init"), str) or set(d) - fields:
            raise ValueError(f"an individual has bad fields {sorted(d)}")
        genome = Genome.parse(d["genome"])
        search = None
        if "search" in d:
            search = Search.from_json(d["search"], genome.n_params, "an individual's search")
        return cls(genome, as_float(d.get("cost"), "cost"), d.get("origin", "init"), search)


@dataclasses.dataclass(frozen=True)
class RunState:
    """Everything needed to continue a run after a completed generation."""

    generation: int
    population: tuple[Individual, ...]
    next_id: int
    evaluations: int
    key: tuple[int, ...]  # raw key data of the run's PRNG key
    wall_s: float = 0.0
    # The padding bucket (neurons, genes, sweeps) the run has grown to (`grow_bucket`): the
    # default CMA-ES popsize follows it, so a resume must go on from it, not from scratch.
    # None in checkpoints written before it was recorded.
    bucket: tuple[int, int, int] | None = None

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["population"] = [ind.to_json() for ind in self.population]
        d["key"] = list(self.key)
        if self.bucket is None:
            del d["bucket"]
        else:
            d["bucket"] = list(self.bucket)
        return d

    @classmethod
    def from_json(cls, d: dict) -> RunState:
        """The state as `to_json` wrote it; a ValueError names a bad field."""
        if not isinstance(d, dict):
            raise ValueError("the state is not a JSON object")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"the state has unknown field(s) {unknown}")
        for name in ("generation", "next_id", "evaluations"):
            v = d.get(name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"the state's {name} must be an integer >= 0, got {v!r:.40}")
        pop = d.get("population")
        if not isinstance(pop, list) or not pop:
            raise ValueError("the state's population must be a non-empty list")
        return cls(
            generation=d["generation"],
            population=tuple(Individual.from_json(x) for x in pop),
            next_id=d["next_id"],
            evaluations=d["evaluations"],
            key=_check_key(d.get("key"), "the state's key"),
            wall_s=as_float(d.get("wall_s", 0.0), "wall_s"),
            bucket=_check_bucket(d.get("bucket")),
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
      compiles, compile_s, cache_hits, cache_misses: this generation's XLA programs
        compiled (or loaded from the persistent cache), the seconds spent tracing, lowering
        and compiling them, and the persistent cache's hits and misses
        (`eant2_jax.compilestats`; 0 in records written before they existed). Like the wall
        times they depend on the process, not on the run: ``RUN_DEPENDENT`` names them.
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
    compiles: int = 0
    compile_s: float = 0.0
    cache_hits: int = 0
    cache_misses: int = 0

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> GenerationRecord:
        """The record as `to_json` wrote it; a ValueError names a bad field."""
        return cls(**typed_fields(cls, d, "a generation record"))


# The record fields that depend on the process and machine (timing, compilation), not on
# the run: two runs of one key and config agree on every other field.
RUN_DEPENDENT = ("wall_s", "generation_s", "compiles", "compile_s", "cache_hits", "cache_misses")


class RunResult(NamedTuple):
    """What `run` returns.

    Attributes:
      population: the final population, best first.
      best: the best genome.
      generations: one `GenerationRecord` per generation.
      pruning: one `PruneAttempt` per pruning attempt.
      solution: the network that passed ``solution_test`` (the run stopped there; it need
        not be the best by cost), or None.
    """

    population: list[Individual]
    best: Genome
    generations: list[GenerationRecord]
    pruning: list[PruneAttempt]
    solution: Individual | None = None


def _key_data(key: jax.Array) -> tuple[int, ...]:
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return tuple(int(k) for k in np.asarray(key, dtype=np.uint32).ravel())


def _check_bucket(data) -> tuple[int, int, int] | None:
    """A checkpoint's bucket: absent (None), or three integers >= 1."""
    if data is None:
        return None
    if not (
        isinstance(data, list)
        and len(data) == 3
        and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in data)
    ):
        raise ValueError(
            f"the state's bucket must be [neurons, genes, sweeps] integers >= 1, got {data!r:.60}"
        )
    return tuple(data)


def _check_key(data, what: str) -> tuple[int, ...]:
    """Raw key data as JSON holds it: a non-empty list of uint32 words."""
    if (
        not isinstance(data, list)
        or not 1 <= len(data) <= 8
        or not all(isinstance(k, int) and not isinstance(k, bool) for k in data)
        or not all(0 <= k < 2**32 for k in data)
    ):
        raise ValueError(f"{what} must be a list of 1 to 8 integers in [0, 2**32)")
    return tuple(data)


def _key_from_data(data: Sequence[int]) -> jax.Array:
    """A typed PRNG key from its raw data (as stored in checkpoints and config.json)."""
    return jax.random.wrap_key_data(jnp.asarray(np.array(data, dtype=np.uint32)))


def _initialise(task: Task, key: jax.Array, config: EANT2Config) -> tuple[list[Genome], int]:
    """Generation 0's genomes and the next free neuron id: ``population`` minimal starts,
    each with ``init_mutations`` structural mutations (a diverse start when asked)."""
    rng = np.random.default_rng(_key_data(key))
    genomes, seen, next_id = [], set(), task.n_outputs
    # Without mutations one draw per slot, as before (with full connectivity every draw is
    # the same structure); with them, a slot draws again (20 times at most) when it meets a
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
                child, op = _mutate_once(rng, g, task, next_id + used, config)
                if child is not None:
                    g, used = child, used + (op == "add_subnetwork")
            # Identical structures are not evaluated twice.
            if g.structure_key() not in seen:
                seen.add(g.structure_key())
                genomes.append(g)
                next_id += used
                break
    return genomes, next_id


def _mutate_once(
    rng: np.random.Generator, genome: Genome, task: Task, next_id: int, config: EANT2Config
) -> tuple[Genome | None, str]:
    """One structural mutation with an operator drawn by ``operator_weights``; returns the
    child (None if the operator had nothing to act on) and the operator."""
    p = np.asarray(config.operator_weights) / sum(config.operator_weights)
    op = OPERATORS[int(rng.choice(len(OPERATORS), p=p))]
    child = mutate(
        rng,
        genome,
        op,
        n_inputs=task.n_inputs,
        next_id=next_id,
        input_fraction=config.input_fraction,
        weight_scale=config.new_weight_scale,
    )
    return child, op


def _explore(
    rng: np.random.Generator,
    population: Sequence[Individual],
    task: Task,
    next_id: int,
    config: EANT2Config,
) -> tuple[list[Individual], int, list[Individual]]:
    """Make offspring by structural mutation; duplicates of existing structures are dropped.
    Returns the children, the next free neuron id and each child's parent."""
    want = config.offspring or config.population
    seen = {ind.genome.structure_key() for ind in population}
    children: list[Individual] = []
    parents: list[Individual] = []
    for _ in range(20 * want):  # give up on duplicates after a while
        if len(children) == want:
            break
        parent = population[int(rng.integers(len(population)))]
        child, op = _mutate_once(rng, parent.genome, task, next_id, config)
        if child is None or child.structure_key() in seen:
            continue
        if op == "add_subnetwork":
            next_id += 1
        seen.add(child.structure_key())
        children.append(Individual(child, parent.cost, op))
        parents.append(parent)
    return children, next_id, parents


def _generation_record(
    state: RunState,
    evaluated: int,
    prune: list[PruneAttempt],
    t: float,
    compiled: compilestats.CompileStats,
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
        compiles=compiled.programs,
        compile_s=compiled.seconds,
        cache_hits=compiled.cache_hits,
        cache_misses=compiled.cache_misses,
        best_genome=str(best.genome),
    )


def grow_bucket(
    genomes: Sequence[Genome], current: Bucket | None, floor: Sequence[int] | None = None
) -> Bucket:
    """The bucket a generation compiles into: ``current`` while the genomes fit, else one
    with headroom, the smallest bucket for one more neuron, gene and sweep than they need
    (at least two sweeps: a first hidden neuron adds one) and at least ``floor``
    (`EANT2Config.min_bucket`: ``(neurons, genes, sweeps)``).

    Each new bucket is a new program to compile (seconds on a CPU, more on a GPU), while the
    padding costs little (a generation is latency-bound: docs/benchmarks.md). A structure's
    CMA-ES is independent of its padding except through the default popsize, which follows
    the gene bucket (`eant2_jax.tuning.popsize_for`); so the bucket is part of the checkpoint
    (`RunState.bucket`) and a resumed run goes on with it."""
    neurons = max(g.n_neurons for g in genomes)
    genes = max(g.n_params for g in genomes)
    depth = max(g.depth() for g in genomes)
    # A series value holds a size iff it is at least the size (every bucket is one).
    if current is not None and (
        neurons <= current.neurons and genes <= current.genes and depth <= current.sweeps
    ):
        return current
    need = (neurons + 1, genes + 1, max(depth + 1, 2))
    if floor is not None:
        need = tuple(max(n, f) for n, f in zip(need, floor, strict=True))
    return Bucket(
        neurons=bucket_size(need[0], NEURON_FLOOR),
        genes=bucket_size(need[1], GENE_FLOOR),
        sweeps=bucket_size(need[2]),
    )


class _Brood(NamedTuple):
    """A generation up to its tuning (`_breed`): what it tunes and what it keeps aside."""

    gen: int
    parents: list[Individual]  # kept untuned into selection
    new: list[Individual]  # to tune
    next_id: int
    evaluations: int  # of the run before this generation
    starts: list[Search | None] | None  # warm starts of ``new`` (inherit_search)
    exp_key: jax.Array
    t0: float
    compiled: compilestats.CompileStats


class _Tuned(NamedTuple):
    """The part of a `tuning.tune` result that belongs to one run's brood."""

    genomes: list[Genome]
    costs: list[float]
    evaluations: list[int]
    pruning: list[PruneAttempt]
    searches: list[Search | None] | None
    solution: int | None


@jax.jit
def _generation_keys(key: jax.Array, gen: int | jax.Array) -> tuple[jax.Array, jax.Array]:
    """``split(fold_in(key, gen))``: a generation's mutation and exploitation keys. One
    program: run eagerly, the same integer operations compile four (the conversion,
    ``fold_in``, ``split`` and the unpacking), each a fraction of a second on a GPU when the
    cache is cold."""
    mut_key, exp_key = jax.random.split(jax.random.fold_in(key, gen))
    return mut_key, exp_key


def _breed(task: Task, state: RunState | None, key: jax.Array, config: EANT2Config) -> _Brood:
    """A generation's start: the initial structures (generation 0), else the parents'
    offspring (and the parents themselves with ``reexploit``)."""
    t0 = time.perf_counter()
    compiled = compilestats.snapshot()
    gen = 0 if state is None else state.generation + 1
    mut_key, exp_key = _generation_keys(key, gen)
    starts: list[Search | None] | None = None  # warm starts (inherit_search)
    if state is None:
        genomes, next_id = _initialise(task, mut_key, config)
        return _Brood(
            gen, [], [Individual(g, float("inf")) for g in genomes], next_id, 0, None,
            exp_key, t0, compiled,
        )  # fmt: skip
    rng = np.random.default_rng(_key_data(mut_key))
    parents = list(state.population)
    new, next_id, made_from = _explore(rng, parents, task, state.next_id, config)
    if config.inherit_search:
        sigma0 = config.exploit.sigma0
        starts = [
            None if p.search is None else inherited(p.genome, p.search, c.genome, sigma0)
            for c, p in zip(new, made_from, strict=True)
        ]
    if config.reexploit:
        new = parents + new
        if starts is not None:  # their own C and sigma go on
            starts = [p.search for p in parents] + starts
        parents = []
    return _Brood(gen, parents, new, next_id, state.evaluations, starts, exp_key, t0, compiled)


def _next_bucket_guesses(
    runs: Sequence[tuple[RunState | None, _Brood]],
    task: Task,
    config: EANT2Config,
    bucket: Bucket,
) -> list[tuple[Bucket, list[Genome]]]:
    """The buckets the batch will likely grow into next, guessed during this generation,
    and genomes that fill each: among ``_GUESS_TRIES`` dry generations (offspring of this
    generation's structures and the current population of every run in ``runs``,
    ``(state, brood)`` each: one for a run alone, a lock-step group's for
    `eant2_jax.run_lockstep`, made with throwaway generators: the runs' own draws are
    untouched), the most frequent bucket that outgrows ``bucket``, and the second most
    frequent if at least two tries grew into it; none if no try outgrew ``bucket``. Only
    a guess (selection and pruning decide the real parents): on the XOR runs of
    tests/test_loop.py the first named 4 of 6 new buckets. The second was added for
    `eant2 reproduce`: with the first alone, its covariance arm (a lock-step group of 200
    structures) still waited 9-12 s for a new bucket's program in two generations on an
    H100."""
    pools = [list(st.population if st is not None else []) + list(b.new) for st, b in runs]
    gen = runs[0][1].gen
    grown: dict[Bucket, list[Genome]] = {}
    votes: dict[Bucket, int] = {}
    for t in range(_GUESS_TRIES):
        dry = []
        for i, pool in enumerate(pools):
            rng = np.random.default_rng([gen, t, i] if i else [gen, t])
            dry += [ind.genome for ind in _explore(rng, pool, task, 2**30, config)[0]]
        b = grow_bucket(dry, bucket, config.min_bucket) if dry else bucket
        if b != bucket:
            grown.setdefault(b, dry)
            votes[b] = votes.get(b, 0) + 1
    ranked = sorted(votes, key=votes.get, reverse=True)[:2]  # ties: the first grown
    return [(b, grown[b]) for i, b in enumerate(ranked) if i == 0 or votes[b] >= 2]


_GUESS_TRIES = 8


def _compile_next_bucket(runs, task, config, bucket, min_rows) -> threading.Thread | None:
    """On an accelerator, compile the engine programs of the guessed next buckets
    (`_next_bucket_guesses` of ``runs``) for batches of ``min_rows`` rows in the background
    while this generation runs (`eant2_jax.exploitation.compile_ahead`): a new
    bucket's program takes seconds to tens of seconds to compile there, which otherwise
    stall the generation that meets it. The program is the one that generation would
    compile, so results do not change."""
    if not exploitation.compile_ahead_enabled():
        return None

    def work():
        try:
            init_key, run_key = jax.random.split(runs[0][1].exp_key)
            for b, genomes in _next_bucket_guesses(runs, task, config, bucket):
                prep = tuning.prepare(genomes, task, key=init_key, config=config.exploit,
                                      bucket=b, min_rows=min_rows)  # fmt: skip
                exploitation.compile_ahead(prep.state, prep.batch.layout, task, key=run_key,
                                           config=config.exploit, tables=prep.tables)  # fmt: skip
        except Exception:  # noqa: BLE001 - a guess that fails costs nothing but itself
            return

    thread = threading.Thread(target=work, name="eant2-next-bucket", daemon=True)
    thread.start()
    exploitation.join_at_exit(thread)
    return thread


def compile_first_ahead(task: Task, key: jax.Array, config: EANT2Config, runs: int = 1) -> bool:
    """On an accelerator, start compiling generation 0's engine program at once, from
    shapes alone (`eant2_jax.tuning.compile_ahead`): the generation's keys, its engine start
    and their small programs then compile and run while it does, instead of before it
    (on a GPU with a cold cache those were 1.7 s of a servo run's first generation,
    docs/benchmarks.md, "Cold start"). Only where generation 0's structure does not depend
    on the run's draws: minimal starts of full connectivity without initial mutations
    (the defaults); their weights are the only draws, and they do not shape the program.

    `run` calls it first; a caller may call it sooner, before it has the run's key:
    ``key`` may be its shape (``jax.eval_shape(jax.random.key, seed)``), and `run` then
    finds the compilation under way. ``runs``: the runs tuned in one batch (a lock-step
    group's, `eant2_jax.run_lockstep`). Returns whether a compilation was started; one that
    fails to start returns False (generation 0 then compiles its program as usual)."""
    if not exploitation.compile_ahead_enabled():
        return False
    if config.init_mutations or config.init_connectivity < 1:
        return False
    try:
        rng = np.random.default_rng(0)  # weights only, see above
        genome = initial_genome(
            rng,
            task.n_inputs,
            task.n_outputs,
            connectivity=1.0,
            weight_scale=config.init_weight_scale,
            recurrent=config.init_recurrent,
        )
        bucket = grow_bucket([genome], None, config.min_bucket)
        exp_key = jax.eval_shape(_generation_keys, key, 0)[1]
        return tuning.compile_ahead(
            [genome], task, key=exp_key, config=config.exploit, bucket=bucket,
            min_rows=_rows(config) * runs,
        )  # fmt: skip
    except Exception:  # noqa: BLE001 - an ahead compile that fails costs nothing but itself
        return False


def _rows(config: EANT2Config) -> int:
    """Rows of every generation's batch of one run: one program per bucket."""
    return (config.offspring or config.population) + (config.population if config.reexploit else 0)


def _conclude(
    state: RunState | None,
    key: jax.Array,
    config: EANT2Config,
    brood: _Brood,
    res: _Tuned | None,
    bucket: Bucket | None,
) -> tuple[RunState, GenerationRecord, list[PruneAttempt], Individual | None]:
    """A generation's end: the tuned brood into selection, the new state and its record."""
    new = brood.new
    if res is not None:
        searches = res.searches or [None] * len(new)
        new = [
            Individual(g, c, ind.origin, w)
            for g, c, ind, w in zip(res.genomes, res.costs, new, searches, strict=True)
        ]
        solution = None if res.solution is None else new[res.solution]
        evals = sum(res.evaluations)
        prune = [dataclasses.replace(r, generation=brood.gen) for r in res.pruning]
    else:
        evals, prune, solution = 0, [], None
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
    state = RunState(
        generation=brood.gen,
        population=tuple(pool[i] for i in keep),
        next_id=brood.next_id,
        evaluations=brood.evaluations + evals,
        key=_key_data(key) if state is None else state.key,
        wall_s=(0.0 if state is None else state.wall_s) + dt,
        bucket=None if bucket is None else (bucket.neurons, bucket.genes, bucket.sweeps),
    )
    compiled = compilestats.snapshot() - brood.compiled
    record = _generation_record(state, len(new), prune, dt, compiled)
    return state, record, prune, solution


def _generation(
    task: Task,
    state: RunState | None,
    key: jax.Array,
    config: EANT2Config,
    callback,
    mesh=None,
    bucket: Bucket | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
    ahead: bool = True,
) -> tuple[RunState, GenerationRecord, list[PruneAttempt], Bucket | None, Individual | None]:
    """One generation (generation 0 initialises); returns the new state, its records, the
    bucket it compiled into (`grow_bucket` of ``bucket``) and the new structure whose best
    network passed ``solution_test`` (None if none did). ``ahead``: compile the guessed next
    bucket (False in a run's last generation)."""
    brood = _breed(task, state, key, config)
    gen = brood.gen
    started = []  # the next bucket's compilation, started once this generation's program runs

    def progress(info):
        if ahead and not started and mesh is None:
            # After the first chunk: this generation's own program is compiled by then, so
            # the guess's tracing and compiling do not compete with it (started at the
            # generation's start, they delayed its first chunk as much as they saved later).
            started.append(
                _compile_next_bucket([(state, brood)], task, config, bucket, _rows(config))
            )
        if callback is not None:
            callback({"event": "exploit", "generation": gen, **info})

    def compiling(info):
        if callback is not None:
            callback({"event": "compiling", "generation": gen, **info})

    part = None
    if brood.new:
        bucket = grow_bucket([ind.genome for ind in brood.new], bucket, config.min_bucket)
        res = tune(
            [ind.genome for ind in brood.new],
            task,
            key=brood.exp_key,
            config=config.exploit,
            bucket=bucket,
            on_chunk=progress,
            on_compile=compiling,
            mesh=mesh,
            min_rows=_rows(config),
            solution_test=solution_test,
            start=brood.starts,
            keep_search=config.inherit_search,
        )
        part = _Tuned(
            res.genomes, res.costs, res.evaluations, res.pruning, res.searches, res.solution
        )
    state, record, prune, solution = _conclude(state, key, config, brood, part, bucket)
    return state, record, prune, bucket, solution


def run(
    task: Task,
    *,
    key: jax.Array,
    config: EANT2Config | None = None,
    generations: int,
    out: str | None = None,
    callback: Callable[[dict], None] | None = None,
    meta: dict | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
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
      solution_test: for a task with a success test of its own, separate from its cost
        (e.g. `eant2_jax.tasks.pole.solved`): ``solution_test(genome) -> bool``, called on
        the best network of each newly exploited structure whenever it improves (after each
        chunk of ``config.exploit.chunk`` CMA-ES iterations, see `eant2_jax.tuning.tune`).
        The first that passes stops the exploitation and the run after that generation is
        completed (selected, committed, reported); it is `RunResult.solution`, and a
        ``solution`` event follows the generation's. The generation's evaluations are
        those spent until then; the test's own work is not counted.

    Returns:
      `RunResult`.
    """
    config = EANT2Config() if config is None else config
    if generations < 0:
        raise ValueError(f"generations must be >= 0, got {generations}")
    check_task(task)  # before anything is written
    meta = _run_meta(task, meta)
    mesh = distributed.make_mesh(config.devices)  # every check before anything is created
    key = _key_from_data(_key_data(key))
    if out is None:
        return _loop(
            task, None, key, config, generations, None, callback, mesh, meta,
            solution_test=solution_test,
        )  # fmt: skip
    with _create(out, meta, generations, key, config) as rundir:
        return _loop(
            task, None, key, config, generations, rundir, callback, mesh, meta,
            solution_test=solution_test,
        )  # fmt: skip


def _run_meta(task: Task, meta: dict | None) -> dict:
    """What ``config.json`` records of the task (and the caller's ``meta``); best.genome's
    header reads it too, in the run and after a resume alike."""
    spec = spec_of(task) or {"task_type": f"{type(task).__module__}.{type(task).__qualname__}"}
    return {**spec, **(meta or {})}


def _create(out: str, meta: dict, generations: int, key: jax.Array, config: EANT2Config) -> RunDir:
    """A new run directory for a run of ``config`` from ``key``."""
    return RunDir.create(
        out,
        {
            **meta,
            "generations": generations,
            "key": list(_key_data(key)),
            "config": config.to_dict(),
        },
    )


def _rewind(rundir: RunDir, v: Validated, task: Task) -> None:
    """Cut a checked run directory back to what it committed (best.genome rewritten when it
    does not hold the checkpoint's best), before a run goes on in it."""
    best = None
    if v.state is not None and not _holds_best(v.committed.best, v.state):
        best = _best_text(v.state, task, v.committed.config)
    rundir.rewind(v.committed.offsets, best)


def _stopped(state: RunState, config: EANT2Config) -> bool:
    """Whether a run stops before its next generation: target cost or evaluations reached."""
    if config.target_cost is not None and state.best().cost <= config.target_cost:
        return True
    return config.max_evaluations is not None and state.evaluations >= config.max_evaluations


def _commit(rundir: RunDir | None, task: Task, meta: dict, state: RunState, record, prune):
    """A completed generation into the run directory (if any): records, best, checkpoint."""
    if rundir is not None:
        rundir.commit(
            [record.to_json()],
            [r.to_json() for r in prune],
            _best_text(state, task, meta),
            state.to_json(),
        )


def resume(
    out: str,
    task: Task | None = None,
    *,
    generations: int | None = None,
    callback: Callable[[dict], None] | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
) -> RunResult:
    """Continue a run directory from its last complete generation.

    The directory is locked for the whole run (a second resume of a live run is refused)
    and checked completely (`validate`) before anything in it is changed.

    Args:
      out: the run directory.
      task: the task it was run on; None rebuilds it from the spec in ``config.json``
        (recorded when the task came from `eant2_jax.tasks.make`: a registered name,
        ``module:factory`` or ``file.py:factory``).
      generations: new total number of generations (default: the one in ``config.json``).
      callback: progress events, as for `run`.
      solution_test: as for `run`. The checkpoint's population is tested first (best
        first): a run that stopped on a solution, resumed with the same test, stops again
        at once if its solution survived selection.

    Raises:
      RunDirError: not a run directory, a corrupt one, or no task given and none recorded.
    """
    if generations is not None and (
        isinstance(generations, bool) or not isinstance(generations, int) or generations < 0
    ):
        raise ValueError(f"generations must be an integer >= 0, got {generations!r}")
    with RunDir.open(out) as rundir:
        committed = rundir.read()
        if task is None:
            task = _task_from_meta(committed.config, rundir)
        check_task(task)
        v = _validate(rundir, committed, task)
        mesh = distributed.make_mesh(v.config.devices)
        _rewind(rundir, v, task)
        total = v.generations if generations is None else generations
        return _loop(
            task, v.state, v.key, v.config, total, rundir, callback, mesh, committed.config,
            v.records, v.pruning, solution_test,
        )  # fmt: skip


class Validated(NamedTuple):
    """A run directory's committed contents, typed and cross-checked (`validate`).

    Attributes:
      committed: the raw `Committed` contents.
      config: the run's configuration; generations: the total it asked for.
      state: the checkpoint's state (None before the first commit); key: the run's key.
      records, pruning: the committed generation and pruning records.
    """

    committed: Committed
    config: EANT2Config
    generations: int
    state: RunState | None
    key: jax.Array
    records: list[GenerationRecord]
    pruning: list[PruneAttempt]


def validate(out: str, task: Task | None = None, *, lock: bool = True) -> Validated:
    """Check a run directory as `resume` does, changing nothing.

    Args:
      out: the run directory.
      task: the task it runs (its input and output counts are checked against the
        genomes); None skips the task checks.
      lock: take the directory's lock while checking (refused on a live run); without it
        only the committed part is read, which is consistent on a live run too.

    Raises:
      RunDirError: one line naming the file and what is wrong.
    """
    with RunDir.open(out, lock=lock) as rundir:
        return _validate(rundir, rundir.read(), task)


def _validate(rundir: RunDir, c: Committed, task: Task | None) -> Validated:
    path = rundir.path

    def fail(name: str, reason: str):
        raise RunDirError(f"{path / name}: {reason}")

    meta = c.config
    if not isinstance(meta.get("config"), dict):
        fail("config.json", "no configuration object ('config')")
    try:
        config = EANT2Config.from_dict(meta["config"], complete=c.strict)
    except (TypeError, ValueError) as e:
        fail("config.json", f"bad configuration: {e}")
    total = meta.get("generations")
    if isinstance(total, bool) or not isinstance(total, int) or total < 0:
        fail("config.json", f"generations must be an integer >= 0, got {total!r:.40}")
    try:
        key_data = _check_key(meta.get("key"), "key")
        key = _key_from_data(key_data)
    except (TypeError, ValueError) as e:
        fail("config.json", f"bad key: {e}")
    try:
        records = [GenerationRecord.from_json(r) for r in c.generations]
    except (TypeError, ValueError) as e:
        fail("generations.jsonl", f"corrupt record: {e}")
    try:
        pruning = [PruneAttempt.from_json(r) for r in c.pruning]
    except (TypeError, ValueError) as e:
        fail("pruning.jsonl", f"corrupt record: {e}")
    state = None
    if c.checkpoint is not None:
        try:
            state = RunState.from_json(c.checkpoint["state"])
        except (TypeError, ValueError) as e:
            fail("checkpoint.json", f"corrupt state: {e}")
        last = records[-1]
        best = state.best()
        if state.key != key_data:
            fail("checkpoint.json", "its key is not the run's key in config.json")
        if len(state.population) > config.population:
            fail(
                "checkpoint.json",
                f"{len(state.population)} individuals, more than the "
                f"population of {config.population}",
            )
        if last.best_genome != str(best.genome) or dumps(last.best_cost) != dumps(best.cost):
            fail("checkpoint.json", "its best individual is not the last generation record's")
        if last.evaluations != state.evaluations:
            fail("checkpoint.json", "its evaluations differ from the last generation record's")
        if sum(r.prune_attempts for r in records) != len(pruning):
            fail(
                "pruning.jsonl",
                f"{len(pruning)} record(s) where the generation records "
                f"count {sum(r.prune_attempts for r in records)}",
            )
        if any(p.generation is None or not 0 <= p.generation <= state.generation for p in pruning):
            fail("pruning.jsonl", "a record of a generation the checkpoint has not committed")
        for i, ind in enumerate(state.population):
            g = ind.genome
            if max(g.neuron_ids) >= state.next_id:
                fail(
                    "checkpoint.json",
                    f"individual {i} has neuron id {max(g.neuron_ids)} >= next_id {state.next_id}",
                )
            if task is not None and (g.n_outputs != task.n_outputs or g.n_inputs > task.n_inputs):
                fail(
                    "checkpoint.json",
                    f"individual {i} has {g.n_outputs} outputs and reads {g.n_inputs} "
                    f"inputs; the task has {task.n_outputs} and {task.n_inputs}",
                )
    elif records or pruning:
        fail("checkpoint.json", "missing, but the logs hold committed records")
    for r in records:
        try:
            g = Genome.parse(r.best_genome)
        except ValueError as e:
            fail("generations.jsonl", f"generation {r.generation}: {e}")
        if task is not None and (g.n_outputs != task.n_outputs or g.n_inputs > task.n_inputs):
            fail(
                "generations.jsonl",
                f"generation {r.generation}'s best genome does not fit "
                f"the task ({g.n_outputs} outputs, {g.n_inputs} inputs read)",
            )
    if state is None:
        key = _key_from_data(key_data)
    else:
        key = _key_from_data(state.key)
    return Validated(c, config, total, state, key, records, pruning)


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
    try:
        return make_task(meta["task"], **options)
    except (TypeError, ValueError) as e:
        raise RunDirError(f"{rundir.path / 'config.json'}: {e}") from None


def _holds_best(text: str | None, state: RunState) -> bool:
    """Whether ``best.genome``'s text (as `RunDir.read` read it) already holds the
    checkpoint's best, with or without a header: a file from before headers is left as it
    is."""
    if text is None:
        return False
    try:
        return GenomeFile.parse(text).genome == state.best().genome
    except ValueError:
        return False


def _best_text(state: RunState, task: Task, meta: dict) -> str:
    """``best.genome``'s text: the best genome with a header that carries what is needed to
    run it (activations, sizes, the task); ``commit`` adds the final newline."""
    best = GenomeFile.from_task(
        state.best().genome, task, name=meta.get("task"), options=meta.get("task_options")
    )
    return best.to_text().rstrip("\n")


def _loop(
    task, state, key, config, generations, rundir, callback, mesh, meta,
    gen_records=(), prune_records=(), solution_test=None,
) -> RunResult:  # fmt: skip
    gen_records, prune_records = list(gen_records), list(prune_records)
    # Grows, never shrinks: one program for as long as the genomes fit; a resume goes on
    # from the checkpoint's.
    bucket = None if state is None or state.bucket is None else Bucket(*state.bucket)
    solution = None
    if state is None and mesh is None:
        compile_first_ahead(task, key, config)
    if state is not None and solution_test is not None:  # resumed: test what it holds
        solution = next((ind for ind in state.population if solution_test(ind.genome)), None)
    while solution is None and (state is None or state.generation < generations):
        if state is not None and _stopped(state, config):
            break
        last = (0 if state is None else state.generation + 1) >= generations
        state, record, prune, bucket, solution = _generation(
            task, state, key, config, callback, mesh, bucket, solution_test, ahead=not last
        )
        gen_records.append(record)
        prune_records.extend(prune)
        _commit(rundir, task, meta, state, record, prune)
        if callback is not None:
            callback({"event": "generation", **record.to_json()})
            if solution is not None:
                callback(
                    {
                        "event": "solution",
                        "generation": state.generation,
                        "evaluations": state.evaluations,
                        **solution.to_json(),
                    }
                )
    return RunResult(
        list(state.population), state.best().genome, gen_records, prune_records, solution
    )
