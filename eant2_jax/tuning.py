"""The handover between host and device: "tune these genomes on this task", in one place.

Every caller that tunes genomes — `optimize`, the EANT2 loop, the benchmarks, the
tests — goes through `tune`, which does the whole round trip once:

1. compile the genomes into one padded batch (`eant2_jax.compiler.compile_genomes`);
2. choose the population size with ONE rule (`popsize_for`);
3. start the engine (`eant2_jax.exploitation.init`) with one key per structure;
4. build the pruner's tables (`eant2_jax.pruning.tables_for`);
5. run the engine (`eant2_jax.exploitation.run`), optionally over a device mesh;
6. gather the result to the host and turn each structure back into a genome, with the
   pruned genes dropped (`eant2_jax.pruning.prune_genome`);
7. on a noisy task (``task.noisy``), score each tuned genome again on fresh episodes: the
   best cost seen during a search is the best of many draws, an optimistic estimate. The
   distribution mean is scored too, and the lower of the two kept
   (``ExploitConfig.recommend``, ``ExploitConfig.rescore``).

`cost` is the other host entry point: the task's cost of genomes as they stand.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import distributed, programs, rescoring, spare
from . import exploitation as ex
from .compiler import Bucket, CompiledBatch, batch_rows, compile_genomes
from .evaluate import as_genomes
from .genome import Genome
from .pruning import PruneAttempt, attempt_records, prune_genome, tables_for
from .tasks.base import Task, check_task
from .warmstart import Search as Search
from .warmstart import align as align
from .warmstart import inherited as inherited
from .watch import Watch

__all__ = [
    "OptimizeResult",
    "Search",
    "Tuned",
    "check_task",
    "cost",
    "optimize",
    "popsize_for",
    "prepare",
    "tune",
]


def popsize_for(
    config: ex.ExploitConfig, batch: CompiledBatch, rows: int | None = None, task: Any = None
) -> int:
    """The population size of a batch, the one rule (docs/algorithm.md, "Batch width"):
    ``config.popsize`` if set; else ``max(default, width // rows)`` with ``config.width`` or
    the ``task``'s ``default_width`` for `jax.default_backend()` (none: the default alone),
    ``default`` the CMA-ES default (`eant2_jax.exploitation.default_popsize`) of the batch's
    padded gene count.

    ``rows``: the batch's rows, padding included, as one device would hold them (default: the
    batch's own). `prepare` passes the rows before they are rounded up to a multiple of a
    mesh's size: ``width`` counts the whole batch's networks, on every device together.

    The default follows the gene bucket rather than each structure's own size so that every
    batch of one bucket shares one compiled program; within a bucket the padded count
    exceeds a structure's own by at most a half, which changes ``4 + floor(3 ln n)`` by at
    most one candidate. Every batch of one bucket and row count gets one popsize, so a program
    compiled ahead for a guessed bucket (`eant2_jax.programs.guesses`) is the one it runs.
    """
    if config.popsize is not None:
        return config.popsize
    default = ex.default_popsize(batch.bucket.genes)
    width = config.width or getattr(task, "default_width", {}).get(jax.default_backend())
    rows = batch.layout.slot.shape[0] if rows is None else rows
    return default if width is None else max(default, width // rows)


class Prepared(NamedTuple):
    """Steps 1-4 of `tune`: everything the engine needs, nothing run yet."""

    batch: CompiledBatch
    state: ex.ExploitState
    tables: Any  # eant2_jax.kernels.pruning.Tables [rows, P]
    popsize: int


@functools.partial(jax.jit, static_argnums=1)
def start_keys(key: jax.Array, rows: int) -> jax.Array:
    """``[rows]`` keys ``fold_in(key, i)``: row ``i``'s start key in a batch that `tune`
    starts with ``key`` (`eant2_jax.run_lockstep` builds its rows from the same rule). One
    program: eagerly, the index vector, its conversion and the ``fold_in`` compile one
    small program each, a fraction of a second apiece on a GPU when the cache is cold."""
    return jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, jnp.arange(rows))


def prepare(
    genomes: Sequence[Genome],
    task: Task,
    *,
    key: jax.Array,
    config: ex.ExploitConfig,
    keys: jax.Array | None = None,
    bucket: Bucket | None = None,
    min_rows: int = 1,
    pad_count: bool = True,
    multiple_of: int = 1,
    start: Sequence[Search | None] | None = None,
    abstract: bool = False,
    mesh: jax.sharding.Mesh | None = None,
) -> Prepared:
    """Compile, choose the popsize, build the tables and start the engine (no iteration).

    Args: as for `tune`; ``multiple_of`` rounds the rows up (the devices they will split
    over); ``abstract``: the start keys and the engine state as shapes only
    (`jax.eval_shape`: nothing computed, no program compiled; ``key`` may be a shape too);
    ``mesh``: the batch is made on this device mesh, split along the structure axis as
    `eant2_jax.exploitation.run` holds it: the host's arrays go straight to their devices
    and each device starts its own structures' CMA-ES, so nothing is moved between devices
    afterwards (docs/design.md, "Many devices"). Not with ``abstract``.
    """
    if mesh is not None and abstract:
        raise ValueError("prepare: a mesh needs arrays, not shapes (abstract=True)")
    if start is not None and len(start) != len(genomes):
        raise ValueError(f"start: {len(start)} searches for {len(genomes)} genomes")
    batch = compile_genomes(
        genomes,
        task.n_inputs,
        bucket=bucket,
        min_rows=min_rows,
        pad_count=pad_count,
        multiple_of=multiple_of,
        mesh=mesh,
    )
    rows = batch.layout.slot.shape[0]
    # The rows one device would hold: a mesh does not change the popsize (`popsize_for`).
    popsize = popsize_for(
        config, batch, batch_rows(len(genomes), min_rows=min_rows, pad_count=pad_count), task
    )
    if keys is None:
        keys = jax.eval_shape(start_keys, key, rows) if abstract else start_keys(key, rows)
    elif keys.shape[0] != rows:
        raise ValueError(f"keys: {keys.shape[0]} keys for a batch of {rows} rows")
    # Made on the host (`jnp` would compile two programs); `init` places it (on a mesh, each
    # device its own rows).
    active = np.arange(rows) < batch.count
    cov = sigma = None
    if start is not None and any(w is not None for w in start):
        width = batch.weights.shape[-1]
        dtype = np.dtype(config.dtype)  # float32 by default: rows x P x P of it
        cov = np.broadcast_to(np.eye(width, dtype=dtype), (rows, width, width)).copy()
        sigma = np.full(rows, config.sigma0)
        for i, (g, w) in enumerate(zip(genomes, start, strict=True)):
            if w is not None:
                w.check(g.n_params, f"start[{i}]")
                cov[i, : g.n_params, : g.n_params] = w.cov
                sigma[i] = w.sigma
    init = functools.partial(ex.init, config=config, popsize=popsize, mesh=mesh)
    init = functools.partial(jax.eval_shape, init) if abstract else init
    st = init(keys, batch.weights, batch.layout.gene_mask, active=active, cov=cov, sigma=sigma)
    return Prepared(batch, st, tables_for(genomes, batch.bucket.genes, rows, mesh), popsize)


def compile_ahead(
    genomes: Sequence[Genome],
    task: Task,
    *,
    key: jax.Array,
    config: ex.ExploitConfig,
    bucket: Bucket | None = None,
    min_rows: int = 1,
) -> bool:
    """Start compiling, in a background thread, the engine program that ``tune(genomes,
    task, key=key, config=config, bucket=bucket, min_rows=min_rows)`` will run, from shapes
    alone: no key is split and no engine state is made (`jax.eval_shape`), so it needs
    none of the small programs `prepare` runs first (on a GPU with a cold cache a few
    tenths of a second each to compile); those then compile while this one does. The
    program is the one `tune` would compile, so results do not change; `tune` waits for it
    instead of compiling it again. Returns whether a compilation was started (not on a
    CPU, see `eant2_jax.programs.ahead_enabled`; not with a warm start).
    """
    if not programs.ahead_enabled():
        return False
    genomes = list(genomes)
    check_task(task, genomes)
    init_key, run_key = jax.eval_shape(lambda k: tuple(jax.random.split(k)), key)
    prep = prepare(genomes, task, key=init_key, config=config, bucket=bucket,
                   min_rows=min_rows, abstract=True)  # fmt: skip
    return ex.compile_ahead(
        prep.state, prep.batch.layout, task, key=run_key, config=config, tables=prep.tables
    )


@dataclasses.dataclass(frozen=True)
class Tuned:
    """What `tune` returns.

    Attributes:
      genomes: the tuned genomes (best weights, pruned genes dropped), in input order; a
        structure that never saw a finite cost is returned unchanged.
      costs: each one's cost (inf where none was finite): the best cost of its search, or
        on a noisy task its cost on fresh episodes (`tune`, step 7).
      evaluations: each one's cost evaluations (pruning trials and the re-evaluation on a
        noisy task included).
      stop_reasons: why each one stopped (see ``exploitation.STOP_REASONS``).
      history: the engine's `StepRecord` of
        ``[ticks, rows]`` arrays (padding rows included).
      pruning: one `PruneAttempt` per attempt; ``structure``
        is the index in ``genomes``.
      state: the engine's final state (on device).
      search_costs: the best cost each search saw (equal to ``costs`` on a task that is
        not noisy).
      solution: the index of the structure whose best network passed ``solution_test``
        (its entry in ``genomes`` is that network), or None.
      picked: which point of each search the entry in ``genomes`` is: ``"best"`` (the
        best candidate seen) or, on a noisy task with ``config.recommend`` other than
        "best", ``"mean"`` (the distribution mean scored lower on the fresh episodes).
      searches: with ``keep_search``, each structure's final search distribution on the
        genes of its entry in ``genomes`` (None where no cost was finite, or where the
        network is the solution found mid-search); else None.
    """

    genomes: list[Genome]
    costs: list[float]
    evaluations: list[int]
    stop_reasons: list[str]
    history: ex.StepRecord
    pruning: list[PruneAttempt]
    state: ex.ExploitState
    search_costs: list[float]
    solution: int | None = None
    searches: list[Search | None] | None = None
    picked: list[str] | None = None


def tune(
    genomes: Sequence[Genome],
    task: Task,
    *,
    key: jax.Array,
    config: ex.ExploitConfig,
    keys: jax.Array | None = None,
    bucket: Bucket | None = None,
    min_rows: int = 1,
    pad_count: bool = True,
    on_chunk: Callable[[dict], None] | None = None,
    mesh: jax.sharding.Mesh | None = None,
    on_compile: Callable[[dict], None] | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
    start: Sequence[Search | None] | None = None,
    keep_search: bool = False,
) -> Tuned:
    """Tune (and prune) a batch of structures together: ONE batched CMA-ES run.

    Args:
      genomes: the structures, with their starting weights.
      task: the task.
      key: PRNG key; split into an engine-start key and the task's key. Structure ``i``
        starts from ``fold_in(start_key, i)`` unless ``keys`` is given.
      config: the exploitation configuration.
      keys: optional ``[rows]`` start keys, one per batch row (padding rows included).
      bucket: pad to these sizes (default: the smallest that fits, ``compiler.bucket_for``).
      min_rows: pad the batch to at least this many structures (one program per bucket).
      pad_count: round the rows up the bucket series (see ``compile_genomes``).
      on_chunk: progress callback (see `eant2_jax.exploitation.run`).
      mesh: split the structures over these devices (see `eant2_jax.distributed`).
      on_compile: called before a program is compiled (see
        `eant2_jax.exploitation.run`).
      solution_test: a host-side test of a network (a genome with its weights): after each
        chunk of ``config.chunk`` iterations, every structure whose best network is one
        not tested yet is tested (in batch order); the first that passes halts every structure
        (`eant2_jax.exploitation.halted`) and is returned as ``Tuned.solution``. The
        evaluations are those spent until then; the test's own work is not counted.
      start: optional warm starts, one per genome (None: ``sigma0`` and ``C = I``): each
        search starts at ``N(weights, sigma^2 cov)`` (`Search`; e.g. `inherited`).
      keep_search: also return each structure's final search (``Tuned.searches``).

    Returns:
      `Tuned`.
    """
    genomes = list(genomes)
    check_task(task, genomes)
    count = len(genomes)
    if config.spare_rows == "restarts":  # every padding row searches again (`spare`)
        rows = batch_rows(count, min_rows=min_rows, pad_count=pad_count)
        genomes, start = spare.spread(genomes, start, rows)
    init_key, run_key = jax.random.split(key)
    prep = prepare(genomes, task, key=init_key, config=config, keys=keys, bucket=bucket,
                   min_rows=min_rows, pad_count=pad_count, start=start, mesh=mesh)  # fmt: skip
    watch = None if solution_test is None else Watch(genomes, solution_test)
    rescorer = None
    if getattr(task, "noisy", False):
        rescorer = rescoring.Rescorer(
            genomes, task, key, config,
            rows=prep.batch.layout.slot.shape[0], bucket=prep.batch.bucket, pad_count=pad_count,
        )  # fmt: skip
    st, hist = ex.run(prep.state, prep.batch.layout, task, key=run_key, config=config,
                      tables=prep.tables, on_chunk=on_chunk, mesh=mesh, on_compile=on_compile,
                      halt=watch)  # fmt: skip
    res = _handed_back(genomes, st, hist, config, watch, rescorer, keep_search)
    return res if len(genomes) == count else spare.best_of(res, count)


def _handed_back(genomes, st, hist, config, watch, rescorer, keep_search) -> Tuned:
    """`tune`'s steps 6 and 7: the engine's final state gathered to the host and turned
    back into genomes (the network that passed ``solution_test`` in its place), rescored
    on a noisy task."""
    best_x, best_cost, mask, spent, stop = distributed.gather(
        (st.cma.best_x, st.cma.best_cost, st.cma.mask, st.evals, st.stop)
    )
    best_x, best_cost = np.asarray(best_x, np.float64), np.asarray(best_cost, np.float64)
    tuned, costs = _tuned_genomes(genomes, best_x, best_cost, mask)
    searches = _final_searches(genomes, st, best_cost, mask) if keep_search else None
    solution = None
    if watch is not None and watch.found is not None:
        # The network that passed: a structure halted in a pruning re-fit is otherwise
        # returned as it was before the attempt.
        solution, network, cost_found = watch.found
        tuned[solution], costs[solution] = network, cost_found
        if searches is not None:  # the search went on past that network, or was restored
            searches[solution] = None
    count = len(genomes)
    evaluations = [int(e) for e in spent[:count]]
    search_costs = list(costs)
    picked = ["best"] * count
    if rescorer is not None:
        mean = None
        if config.recommend != "best":
            mean = np.asarray(distributed.gather(st.cma.mean), np.float64)
        tuned, costs, evaluations, picked = rescoring.rescore(
            genomes, tuned, costs, evaluations, mean, mask, solution, config, rescorer
        )
    return Tuned(
        genomes=tuned,
        costs=costs,
        evaluations=evaluations,
        stop_reasons=[ex.STOP_REASONS[int(s)] for s in stop[:count]],
        history=hist,
        pruning=attempt_records(hist.prune, genomes, config.pruner),
        state=st,
        search_costs=search_costs,
        solution=solution,
        searches=searches,
        picked=picked,
    )


def _tuned_genomes(genomes, best_x, best_cost, mask) -> tuple[list[Genome], list[float]]:
    """`tune`'s step 6: each structure's best network, its pruned genes dropped, and its
    cost; a structure that never saw a finite cost comes back as it was, at cost inf."""
    tuned, costs = [], []
    for i, g in enumerate(genomes):
        n = g.n_params
        if np.isfinite(best_cost[i]):
            tuned.append(prune_genome(g, mask[i, :n], best_x[i, :n]))
            costs.append(float(best_cost[i]))
        else:  # never saw a finite cost: keep the structure, rank it last
            tuned.append(g)
            costs.append(float("inf"))
    return tuned, costs


def _final_searches(genomes, st, best_cost, mask) -> list[Search | None]:
    """Each structure's final search on the genes it kept (None where it is not finite)."""
    cov, sigma = distributed.gather((st.cma.C, st.cma.sigma))
    cov, sigma = np.asarray(cov, np.float64), np.asarray(sigma, np.float64)
    searches = []
    for i, g in enumerate(genomes):
        keep = np.flatnonzero(np.asarray(mask[i, : g.n_params]))
        ok = np.isfinite(best_cost[i]) and np.isfinite(sigma[i]) and sigma[i] > 0
        c = cov[i][np.ix_(keep, keep)]
        c = 0.5 * (c + c.T)
        ok = ok and bool(np.all(np.isfinite(c)))
        searches.append(Search(float(sigma[i]), c) if ok else None)
    return searches


class OptimizeResult(NamedTuple):
    """What `optimize` returns.

    Attributes:
      genome: the genome with its best weights.
      cost: the best cost found (of ``genome``'s weights); on a noisy task (``task.noisy``)
        its cost on fresh episodes, which the search never saw.
      history: `StepRecord` of ``[ticks]`` arrays, one per
        engine iteration it ran (``sigma``, ``sigma_bar``, ``cond``, ``cond_bounded``,
        ``best_cost``, ``evaluations``, ``nonfinite``, ``running``, ``phase``: a pruning
        attempt's iterations have ``phase`` > 0; ``prune`` with a pruner).
      stop_reason: why the run stopped (see ``STOP_REASONS``).
      pruning: one `PruneAttempt` per pruning attempt; empty
        without a pruner.
    """

    genome: Genome
    cost: float
    history: ex.StepRecord
    stop_reason: str
    pruning: list[PruneAttempt]


def optimize(genome: Genome | str, task: Task, *, key: jax.Array, **options: Any) -> OptimizeResult:
    """Tune one genome's weights on a task with CMA-ES, starting from its current weights,
    and prune it with `ExploitConfig`'s default pruner (covariance); ``pruner="none"`` gives
    plain CMA-ES.

    Args:
      genome: the structure (and its initial weights).
      task: a task (see `eant2_jax.tasks`).
      key: PRNG key.
      **options: fields of `ExploitConfig` (popsize, sigma0,
        max_iters, pruner, ...).

    Returns:
      `OptimizeResult`.
    """
    (genome,) = as_genomes(genome)
    config = ex.ExploitConfig.from_options(options)
    init_key, _ = jax.random.split(key)
    # One structure starts from the start key itself (not fold_in(start, 0)): the seeded
    # results of optimize() predate the batch rule and are kept.
    res = tune([genome], task, key=key, config=config, keys=init_key[None], pad_count=False)
    best, best_cost = res.genomes[0], res.costs[0]
    # The start point is a candidate too (CMA-ES never evaluates its mean): a search that
    # found nothing better, or no finite cost (a large sigma0), returns where it started.
    start_cost = _start_cost(genome, task, key, config)
    if not best_cost <= start_cost:
        best, best_cost = genome, start_cost
    return OptimizeResult(
        best,
        best_cost,
        res.history.structure(0),
        res.stop_reasons[0],
        res.pruning,
    )


def _start_cost(genome: Genome, task: Task, key: jax.Array, config: ex.ExploitConfig) -> float:
    """The start point's cost as `optimize` compares it with the search's result: on a
    noisy task on the fresh draws that `tune` scores its result on, else the task's cost."""
    draws = config.rescore if getattr(task, "noisy", False) else 1
    fn, args = rescoring.fresh_cost_call([genome], task, key, draws)
    cost = float(np.asarray(fn(*args), np.float64)[0])
    return cost if math.isfinite(cost) else math.inf


def cost(
    genomes: Genome | str | Sequence[Genome | str], task: Task, *, key: jax.Array
) -> np.ndarray:
    """The task's cost of each genome as it stands (its own weights), ``float[len(genomes)]``."""
    genomes = as_genomes(genomes)
    check_task(task, genomes)
    batch = compile_genomes(genomes, task.n_inputs)
    return np.asarray(rescoring.cost_batch(batch.layout, batch.weights, task, key))[: batch.count]
