"""The EANT2 loop: the one driver of K >= 1 runs of the strategy (`eant2_jax.strategy`).

::

    init / ask     the brood of each run's next generation
    exploit        the broods of the runs at that generation in ONE batched tuning
    tell           selection: each run's new state and records
    commit         each run's records and checkpoint into its run directory, if any
    stopped?       generations done, target cost or evaluation budget reached

`run` is a group of one; `run_lockstep` is a group of K (each generation of every run
tuned in one batch: fewer, larger programs on a GPU, see below); `resume` goes on with a
run directory (`eant2_jax.checkpoint` checks it first); `eant2_jax.run_many` spreads
such runs and groups over devices.

Everything a run does flows from one PRNG key and an `EANT2Config`: generation ``g``
uses ``fold_in(key, g)``, split into a mutation key (seeding a NumPy generator for the host
side) and an exploitation key. The whole state after a generation is a small JSON document
(`RunState.to_json`), so a run resumes from its last complete generation and, on CPU,
ends with exactly the result of an uninterrupted run.

In lock-step each run keeps its own key, state, records and run directory; only the
tuning is shared. A structure's CMA-ES starts from the key it would get in the run alone
and draws its own random numbers (per-row keys, `eant2_jax.exploitation`), so on a task
that is not noisy a run in lock-step is the run `run` makes alone with the same padding
bucket, up to the float rounding of wider padded sums (tests/test_lockstep.py). The bucket
is the group's (it grows with the largest structure of any run), and the default CMA-ES
popsize follows it (`eant2_jax.tuning.popsize_for`), so a run in a group can differ from
the same key run alone; with ``ExploitConfig.width`` the width is shared by the group's rows,
so a run in a group of K gets about K times fewer candidates than alone. On a noisy task
the episodes of an iteration are shared by the whole batch, so a run's result also depends
on the group it ran in. A killed group resumes
exactly (on a task that is not noisy): the group's bucket is the largest its members'
checkpoints hold, and runs a generation behind the others (killed between two commits)
catch up first. How much a group saves depends on how full one run's batch already keeps
the device (the lock-step measurement of 2026-11-23 is in git history with the brax
results: ``git log -- 'bench/results/brax-*'``).

The library never prints: progress goes to ``callback(event: dict)``.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax

from . import distributed, strategy
from .checkpoint import (
    Validated,
    check_fits,
    commit,
    create,
    resumed,
    rewind,
    run_meta,
    task_for,
    validate,
    validated,
)
from .compiler import Bucket
from .config import EANT2Config
from .genome import Genome
from .programs import guesses
from .programs.guesses import compile_first_ahead, grow_bucket
from .records import (
    RUN_DEPENDENT,
    GenerationRecord,
    Individual,
    RunResult,
    RunState,
    key_data,
    key_from_data,
)
from .rundir import RunDir
from .tasks import check_task
from .tasks.base import Task

# The records and the checkpoint's checks live in their own modules; their names are
# imported here for the callers of the loop.
__all__ = [
    "RUN_DEPENDENT",
    "EANT2Config",
    "GenerationRecord",
    "Individual",
    "RunResult",
    "RunState",
    "Validated",
    "as_key",
    "compile_first_ahead",
    "grow_bucket",
    "resume",
    "run",
    "run_lockstep",
    "validate",
]


def as_key(key, what: str = "key") -> jax.Array:
    """A run's PRNG key: a JAX key as given (typed, or raw ``uint32`` data), or an int
    seed in [0, 2**32) as ``jax.random.key(seed)`` (the key ``eant2 run --seed`` uses).

    Raises:
      ValueError: one line naming ``what``: a seed out of range, a bool, or neither.
    """
    import numbers

    if isinstance(key, bool) or (isinstance(key, numbers.Integral) and not 0 <= key < 2**32):
        raise ValueError(f"{what}: an int seed must be in [0, 2**32), got {key!r:.40}")
    if isinstance(key, numbers.Integral):
        return jax.random.key(int(key))
    if not hasattr(key, "dtype"):
        raise ValueError(
            f"{what} must be a jax.random.key(...) or an int seed, got {type(key).__name__}"
        )
    return key


class _Member:
    """One run of a group: its key, state, records and directory."""

    def __init__(self, index, key, total, rundir, meta, state=None, records=(), pruning=()):
        self.index, self.key, self.total, self.rundir, self.meta = index, key, total, rundir, meta
        self.state: RunState | None = state
        self.records, self.pruning = list(records), list(pruning)
        self.solution: Individual | None = None

    @property
    def generation(self) -> int:
        """Its last complete generation (-1 before generation 0)."""
        return -1 if self.state is None else self.state.generation

    def done(self, config: EANT2Config) -> bool:
        st = self.state
        if self.solution is not None:
            return True
        return st is not None and (st.generation >= self.total or strategy.stopped(st, config))

    def result(self) -> RunResult:
        st = self.state
        return RunResult(
            list(st.population), st.best().genome, self.records, self.pruning, self.solution
        )


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
      key: the run's PRNG key (``jax.random.key(seed)``; an int seed is taken as that,
        `as_key`); the same key and config give the same run.
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
        `resume` can rebuild it (a registered task by itself, a user's when named again).
      solution_test: for a task with a success test of its own, separate from its cost
        (e.g. `eant2_jax.tasks.pole.solved`): ``solution_test(genome) -> bool``, called on
        the best network of each newly exploited structure whenever it improves (after each
        chunk of ``config.exploit.chunk`` CMA-ES iterations, see `eant2_jax.tuning.tune`).
        The first that passes stops the exploitation and the run after that generation is
        completed (selected, committed, reported); it is `RunResult.solution`, and a
        ``solution`` event follows the generation's. The generation's evaluations are
        those spent until then; the test's own work is not counted. With
        ``config.solution_rule="champion"`` it is called once per generation instead, on
        the champion after selection, and a run it passes stops there (all the
        generation's evaluations counted).

    Returns:
      `RunResult`.
    """
    config = EANT2Config() if config is None else config
    if generations < 0:
        raise ValueError(f"generations must be >= 0, got {generations}")
    check_task(task)  # before anything is written
    # the target it runs to, recorded; with a solution test, the test decides
    config = strategy.resolved(config, task, tested=solution_test is not None)
    meta = run_meta(task, meta)
    key = key_from_data(key_data(as_key(key)))
    mesh = distributed.make_mesh(config.devices)  # every check before anything is created
    with contextlib.ExitStack() as stack:
        rundir = None
        if out is not None:
            rundir = stack.enter_context(create(out, meta, generations, key, config))
        member = _Member(0, key, generations, rundir, meta)
        _drive(task, [member], config, callback, mesh, solution_test, grouped=False)
    return member.result()


def resume(
    out: str,
    task: Task | None = None,
    *,
    generations: int | None = None,
    changes: Mapping[str, Any] | None = None,
    callback: Callable[[dict], None] | None = None,
    solution_test: Callable[[Genome], bool] | None = None,
) -> RunResult:
    """Continue a run directory from its last complete generation.

    The directory is locked for the whole run (a second resume of a live run is refused)
    and checked completely (`validate`) before anything in it is changed or any task is
    built.

    Args:
      out: the run directory.
      task: the task it was run on. None rebuilds a registered task from the spec in
        ``config.json`` (`eant2_jax.tasks.is_registered`); a user's task
        (``module:factory``, ``file.py:factory``) is never imported because a directory
        names it: pass it (``tasks.make(SPEC, **options)``; its spec must be the recorded
        one). docs/reliability.md, "Trust".
      generations: new total number of generations (default: the one in ``config.json``);
        not below the last completed generation.
      changes: budgets and stopping options to change, ``{"target_cost": 0.01,
        "max_evaluations": 10**6}`` (`eant2_jax.checkpoint.RESUMABLE`; any other field is
        refused in one line). A new total or change is checked by the fields' specs and
        recorded in ``config.json`` before the first new generation
        (`eant2_jax.checkpoint.resumed`; crash-safe, `eant2_jax.rundir.RunDir.replace_config`).
      callback: progress events, as for `run`.
      solution_test: as for `run`. The checkpoint's population is tested first (best
        first): a run that stopped on a solution, resumed with the same test, stops again
        at once if its solution survived selection.

    Raises:
      RunDirError: not a run directory, a corrupt one, no task given and none recorded, a
        user task not given, or a task given that is not the recorded one.
      ValueError: a change that is not allowed, or a bad value (one line naming it).
    """
    if generations is not None and (
        isinstance(generations, bool) or not isinstance(generations, int) or generations < 0
    ):
        raise ValueError(f"generations must be an integer >= 0, got {generations!r}")
    with RunDir.open(out) as rundir:
        v = validated(rundir)
        task = task_for(rundir.path, v.committed.config, task)
        check_task(task)
        check_fits(rundir.path, v, task)
        config, total, meta = resumed(
            v,
            generations,
            changes,
            lambda c: strategy.resolved(c, task, tested=solution_test is not None),
        )
        mesh = distributed.make_mesh(config.devices)
        rewind(rundir, v, task)
        if meta is not None:
            rundir.replace_config(meta, v.committed.checkpoint)
        meta = v.committed.config if meta is None else meta
        member = _Member(0, v.key, total, rundir, meta, v.state, v.records, v.pruning)
        _drive(task, [member], config, callback, mesh, solution_test, grouped=False)
    return member.result()


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
    if config.exploit.spare_rows != "idle" and len(keys) > 1:
        raise ValueError(
            f"run_lockstep: exploit.spare_rows={config.exploit.spare_rows!r} would give one run's "
            "spare rows to another run's structures: run them apart, or leave it 'idle'"
        )
    check_task(task)
    config = strategy.resolved(config, task)
    base_meta = run_meta(task, meta)
    mesh = distributed.make_mesh(devices)
    with contextlib.ExitStack() as stack:
        members = []
        for i, (key, out) in enumerate(zip(keys, outs, strict=True)):
            key = key_from_data(key_data(as_key(key, f"keys[{i}]")))
            if out is None:
                members.append(_Member(i, key, generations, None, base_meta))
            elif resume and Path(out).exists():
                members.append(_reopen(stack, i, out, task, config))
            else:
                rundir = stack.enter_context(create(out, base_meta, generations, key, config))
                members.append(_Member(i, key, generations, rundir, base_meta))
        _drive(task, members, config, callback, mesh)
    return [m.result() for m in members]


def _reopen(stack, index, out, task, config) -> _Member:
    """A run directory to go on with, checked and rewound as `resume` does."""
    rundir = stack.enter_context(RunDir.open(out))
    v = validated(rundir)
    task_for(rundir.path, v.committed.config, task)  # the task given must be the run's
    check_fits(rundir.path, v, task)
    if v.config != config:
        raise ValueError(f"{out}: its configuration is not the group's; resume it alone")
    rewind(rundir, v, task)
    meta = v.committed.config
    return _Member(index, v.key, v.generations, rundir, meta, v.state, v.records, v.pruning)


def _group_bucket(members: Sequence[_Member]) -> Bucket | None:
    """The largest bucket the members' checkpoints hold (a group shares one)."""
    held = [m.state.bucket for m in members if m.state is not None and m.state.bucket]
    if not held:
        return None
    return Bucket(*(max(b[i] for b in held) for i in range(3)))


def _drive(task, members, config, callback, mesh, solution_test=None, grouped=True) -> None:
    """Generations of every member until each is done. ``grouped``: a lock-step group's
    events (``run`` and ``runs`` in them); a run alone's carry neither."""
    bucket = _group_bucket(members)
    if mesh is None and all(m.state is None for m in members):
        # Generation 0's program, from shapes, while its keys and start are made.
        guesses.compile_first_ahead(task, members[0].key, config, runs=len(members))
    # The solution test's rule (EANT2Config.solution_rule): every structure's improved best
    # during its tuning, or the generation's champion alone after selection.
    champion = config.solution_rule == "champion"
    if solution_test is not None:  # resumed: test what it holds
        for m in members:
            if m.state is not None:
                m.solution = _passed(m.state, solution_test, champion)
    while True:
        active = [m for m in members if not m.done(config)]
        if not active:
            return
        # Runs a generation behind (a kill between two commits) go first, alone.
        lowest = min(m.generation for m in active)
        group = [m for m in active if m.generation == lowest]
        broods = [
            strategy.init(m.key, task, config)
            if m.state is None
            else strategy.ask(m.key, m.state, task, config)
            for m in group
        ]
        during = None if champion else solution_test
        tuned = _exploit(task, group, broods, config, bucket, callback, mesh, during, grouped)
        bucket = tuned[0].bucket
        for m, brood, part in zip(group, broods, tuned, strict=True):
            m.state, record, prune, m.solution = strategy.tell(m.key, m.state, brood, part, config)
            if champion and solution_test is not None:
                m.solution = _passed(m.state, solution_test, champion)
            m.records.append(record)
            m.pruning.extend(prune)
            commit(m.rundir, task, m.meta, m.state, record, prune)
            if callback is None:
                continue
            run = {"run": m.index} if grouped else {}
            callback({"event": "generation", **run, **record.to_json()})
            if m.solution is not None:
                callback(
                    {
                        "event": "solution",
                        **run,
                        "generation": m.state.generation,
                        "evaluations": m.state.evaluations,
                        **m.solution.to_json(),
                    }
                )


def _passed(state, solution_test, champion) -> Individual | None:
    """The individual of ``state`` that passes ``solution_test``: its champion alone
    (``champion``), or the first of its population that does, best first."""
    tested = [state.best()] if champion else state.population
    return next((i for i in tested if solution_test(i.genome)), None)


def _exploit(
    task, group, broods, config, bucket, callback, mesh, solution_test, grouped
) -> list[strategy.Tuned]:
    """`strategy.exploit_together` of the group's broods with progress events and, once
    the generation's program runs, the guessed next bucket compiled in the background
    (`eant2_jax.programs.guesses`; unless every run of the group ends with it)."""
    gen = max(b.generation for b in broods)
    genomes = [ind.genome for b in broods for ind in b.new]
    if genomes:
        bucket = grow_bucket(genomes, bucket, config.min_bucket)
    ahead = any(b.generation < m.total for m, b in zip(group, broods, strict=True))
    runs = {"runs": [m.index for m in group]} if grouped else {}
    started = []  # the next bucket's compilation, started once this generation's program runs

    def progress(info):
        if ahead and not started and mesh is None:
            # After the first chunk: this generation's own program is compiled by then, so
            # the guess's tracing and compiling do not compete with it.
            pools = [
                [i.genome for i in (m.state.population if m.state is not None else ())]
                + [i.genome for i in b.new]
                for m, b in zip(group, broods, strict=True)
            ]
            rows = guesses.generation_rows(config) * len(group)
            started.append(
                guesses.compile_next_bucket(pools, gen, broods[0].key, task, config, bucket, rows)
            )
        if callback is not None:
            callback({"event": "exploit", "generation": gen, **runs, **info})

    def compiling(info):
        if callback is not None:
            callback({"event": "compiling", "generation": gen, **runs, **info})

    return strategy.exploit_together(
        broods, task, config, bucket, on_chunk=progress, on_compile=compiling, mesh=mesh,
        solution_test=solution_test,
    )  # fmt: skip
