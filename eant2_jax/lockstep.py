"""Independent EANT2 runs in lock-step: every generation of every run tuned in ONE batch.

A small generation is latency-bound on a GPU: the device waits on the host between short
kernels, and one device runs one program at a time, so runs side by side in threads
(`eant2_jax.run_many`'s workers) overlap little. In lock-step the runs' new structures of a
generation go into one `eant2_jax.tuning.tune` call instead: fewer, larger programs, one
padding bucket and fewer compilations per group. How much that saves depends on how full
one run's batch already keeps the device: on the servo task 200 structures fill an H100,
and ten runs in lock-step took 485 s against 510 s as ten threads (docs/benchmarks.md,
"Many runs on one GPU").

Each run keeps its own key, state, records and run directory; only the tuning is shared.
A structure's CMA-ES starts from the key it would get in the run alone and draws its own
random numbers (per-row keys, `eant2_jax.exploitation`), so on a task that is not noisy a
run in lock-step is the run `eant2_jax.run` makes alone with the same padding bucket, up to
the float rounding of wider padded sums (tests/test_lockstep.py). The bucket is the group's
(it grows with the largest structure of any run), and the default CMA-ES popsize follows it
(`eant2_jax.tuning.popsize_for`), so a run in a group can differ from the same key run
alone. On a noisy task the episodes of an iteration are shared by the
whole batch, so a run's result also depends on the group it ran in.

A killed group resumes exactly (on a task that is not noisy): the group's bucket is the
largest its members' checkpoints hold, and runs a generation behind the others (killed
between two commits) catch up first.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp

from . import distributed
from .compiler import Bucket, batch_rows
from .config import EANT2Config
from .loop import (
    RunResult,
    RunState,
    _breed,
    _commit,
    _compile_next_bucket,
    _conclude,
    _create,
    _key_data,
    _key_from_data,
    _rewind,
    _rows,
    _run_meta,
    _stopped,
    _Tuned,
    _validate,
    compile_first_ahead,
    grow_bucket,
)
from .rundir import RunDir
from .tasks import check_task
from .tasks.base import Task
from .tuning import start_keys, tune

__all__ = ["run_lockstep"]


class _Member:
    """One run of the group: its key, state, records and directory."""

    def __init__(self, index, key, total, rundir, meta, state=None, records=(), pruning=()):
        self.index, self.key, self.total, self.rundir, self.meta = index, key, total, rundir, meta
        self.state: RunState | None = state
        self.records, self.pruning = list(records), list(pruning)

    @property
    def generation(self) -> int:
        """Its last complete generation (-1 before generation 0)."""
        return -1 if self.state is None else self.state.generation

    def done(self, config: EANT2Config) -> bool:
        st = self.state
        return st is not None and (st.generation >= self.total or _stopped(st, config))


def run_lockstep(
    task: Task,
    keys: Sequence[jax.Array],
    *,
    config: EANT2Config | None = None,
    generations: int,
    outs: Sequence[str | None] | None = None,
    callback: Callable[[dict], None] | None = None,
    meta: dict | None = None,
    resume: bool = False,
    devices: int | str | Sequence[jax.Device] | None = None,
) -> list[RunResult]:
    """Independent runs of one configuration, tuned together generation by generation.

    Args:
      task: the task, shared by all runs.
      keys: one PRNG key per run.
      config: the configuration of every run (its ``devices`` must be None: pass
        ``devices``).
      generations: as for `eant2_jax.run`.
      outs: optional run directory per run (None entries write nothing); each is an
        ordinary run directory (`eant2_jax.resume` continues one alone).
      callback: progress events, with ``run`` (the run's index in ``keys``) added;
        ``exploit`` and ``compiling`` events are the group's and carry ``runs`` (the indices
        of the runs in the batch) instead.
      meta: extra ``config.json`` fields for every run directory.
      resume: a run whose directory in ``outs`` exists continues it (a finished run is read
        back, a stopped one goes on from its last complete generation); its configuration
        must be ``config``.
      devices: split each batch over these devices (`eant2_jax.distributed.make_mesh`);
        None: JAX's default device.

    Returns:
      One `eant2_jax.RunResult` per key, in order. A run solved by a ``solution_test`` is
      not supported here (it halts the whole batch): use `eant2_jax.run`.
    """
    config = EANT2Config() if config is None else config
    keys = list(keys)
    outs = [None] * len(keys) if outs is None else list(outs)
    if len(outs) != len(keys):
        raise ValueError(f"run_lockstep: {len(keys)} keys but {len(outs)} outs")
    if not keys:
        raise ValueError("run_lockstep: no keys")
    if generations < 0:
        raise ValueError(f"generations must be >= 0, got {generations}")
    if config.devices is not None:
        raise ValueError("run_lockstep places its batches itself: leave config.devices None")
    check_task(task)
    base_meta = _run_meta(task, meta)
    mesh = distributed.make_mesh(devices)
    with contextlib.ExitStack() as stack:
        members = []
        for i, (key, out) in enumerate(zip(keys, outs, strict=True)):
            key = _key_from_data(_key_data(key))
            if out is None:
                members.append(_Member(i, key, generations, None, base_meta))
            elif resume and Path(out).exists():
                members.append(_reopen(stack, i, out, task, config))
            else:
                rundir = stack.enter_context(_create(out, base_meta, generations, key, config))
                members.append(_Member(i, key, generations, rundir, base_meta))
        if mesh is None and all(m.state is None for m in members):
            # Generation 0's program, from shapes, while its keys and start are made.
            compile_first_ahead(task, members[0].key, config, runs=len(members))
        _loop(task, members, config, callback, mesh)
    return [
        RunResult(list(m.state.population), m.state.best().genome, m.records, m.pruning, None)
        for m in members
    ]


def _reopen(stack, index, out, task, config) -> _Member:
    """A run directory to go on with, checked and rewound as `eant2_jax.resume` does."""
    rundir = stack.enter_context(RunDir.open(out))
    v = _validate(rundir, rundir.read(), task)
    if v.config != config:
        raise ValueError(f"{out}: its configuration is not the group's; resume it alone")
    _rewind(rundir, v, task)
    meta = v.committed.config
    return _Member(index, v.key, v.generations, rundir, meta, v.state, v.records, v.pruning)


def _group_bucket(members: Sequence[_Member]) -> Bucket | None:
    """The largest bucket the members' checkpoints hold (a group shares one)."""
    held = [m.state.bucket for m in members if m.state is not None and m.state.bucket]
    if not held:
        return None
    return Bucket(*(max(b[i] for b in held) for i in range(3)))


def _loop(task, members, config, callback, mesh) -> None:
    bucket = _group_bucket(members)
    while True:
        active = [m for m in members if not m.done(config)]
        if not active:
            return
        # Runs a generation behind (a kill between two commits) go first, alone.
        lowest = min(m.generation for m in active)
        group = [m for m in active if m.generation == lowest]
        broods = [_breed(task, m.state, m.key, config) for m in group]
        parts: list[_Tuned | None] = [None] * len(group)
        genomes = [ind.genome for b in broods for ind in b.new]
        if genomes:
            bucket = grow_bucket(genomes, bucket, config.min_bucket)
            # The guessed next bucket is compiled ahead unless every run of the group ends
            # with this generation.
            ahead = any(b.gen < m.total for m, b in zip(group, broods, strict=True))
            parts = _tune_together(
                task, group, broods, genomes, config, bucket, callback, mesh, ahead
            )
        for m, brood, part in zip(group, broods, parts, strict=True):
            m.state, record, prune, _ = _conclude(m.state, m.key, config, brood, part, bucket)
            m.records.append(record)
            m.pruning.extend(prune)
            _commit(m.rundir, task, m.meta, m.state, record, prune)
            if callback is not None:
                callback({"event": "generation", "run": m.index, **record.to_json()})


def _tune_together(
    task, group, broods, genomes, config, bucket, callback, mesh, ahead=False
) -> list[_Tuned | None]:
    """One `tune` of every brood's new structures (``genomes``, in brood order); each brood's
    part of the result. ``ahead``: compile the group's guessed next bucket in the
    background once this generation's program runs (`eant2_jax.loop._compile_next_bucket`,
    as a run alone does)."""
    runs = [m.index for m in group]
    gen = max(b.gen for b in broods)
    min_rows = _rows(config) * len(group)
    started = []

    def progress(info):
        if ahead and not started and mesh is None:
            pairs = [(m.state, b) for m, b in zip(group, broods, strict=True)]
            started.append(_compile_next_bucket(pairs, task, config, bucket, min_rows))
        if callback is not None:
            callback({"event": "exploit", "generation": gen, "runs": runs, **info})

    def compiling(info):
        if callback is not None:
            callback({"event": "compiling", "generation": gen, "runs": runs, **info})

    starts = None
    if any(b.starts is not None for b in broods):
        starts = [s for b in broods for s in (b.starts or [None] * len(b.new))]
    rows = batch_rows(len(genomes), min_rows=min_rows, multiple_of=distributed.size(mesh))
    # Row j of a brood starts from the key it gets in its run alone (`tuning.tune`: row j
    # of a batch tuned with key k starts from fold_in(split(k)[0], j)); padding rows from
    # the last brood's key, past its rows.
    counts = [len(b.new) for b in broods]
    counts[-1] += rows - len(genomes)
    init_keys = [jax.random.split(b.exp_key)[0] for b in broods]
    row_keys = jnp.concatenate([start_keys(k, n) for k, n in zip(init_keys, counts, strict=True)])
    res = tune(
        genomes,
        task,
        key=broods[0].exp_key,
        keys=row_keys,
        config=config.exploit,
        bucket=bucket,
        min_rows=min_rows,
        on_chunk=progress,
        on_compile=compiling,
        mesh=mesh,
        start=starts,
        keep_search=config.inherit_search,
    )
    parts: list[_Tuned | None] = []
    lo = 0
    for b in broods:
        hi = lo + len(b.new)
        if hi == lo:
            parts.append(None)
            continue
        pruning = [r for r in res.pruning if lo <= r.structure < hi]
        parts.append(
            _Tuned(
                res.genomes[lo:hi],
                res.costs[lo:hi],
                res.evaluations[lo:hi],
                [dataclasses.replace(r, structure=r.structure - lo) for r in pruning],
                None if res.searches is None else res.searches[lo:hi],
                None,
            )
        )
        lo = hi
    return parts
