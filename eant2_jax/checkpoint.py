"""A run's checkpoints: what a run directory commits after each generation, and how a
directory is checked, trusted and rewound before a run goes on in it.

* `validate`: a run directory's committed contents typed and cross-checked (the
  configuration, the key, the records, the checkpoint's state against the last record),
  changing nothing;
* `task_for`: the task a resume runs on. Only a registered task is rebuilt from
  ``config.json`` by itself; a user's task (``module:factory``, ``file.py:factory``) is
  code, and code is never run because a data file names it: the caller names it again
  (docs/reliability.md, "Trust");
* `resumed`: what a resume may change (the budgets and stopping options, `RESUMABLE`),
  checked, and the ``config.json`` that records it;
* `rewind` and `commit`: the directory cut back to its last commit, and one more
  generation committed (`eant2_jax.rundir.RunDir` does the files);
* `task_file_sha256` and `task_file_changed`: the SHA-256 of a user's task file, recorded
  when a run starts and compared when it is resumed.

The files themselves, their crash safety and their checksums are `eant2_jax.rundir`'s.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax

from .config import EANT2Config
from .genome import Genome
from .genomefile import GenomeFile
from .jsonio import dumps
from .pruning import PruneAttempt
from .records import GenerationRecord, RunState, check_key, key_data, key_from_data
from .rundir import CONFIG, Committed, RunDir, RunDirError
from .tasks import is_registered, spec_of
from .tasks import make as make_task
from .tasks.base import Task

__all__ = [
    "RESUMABLE",
    "Validated",
    "check_fits",
    "commit",
    "create",
    "resumed",
    "rewind",
    "run_meta",
    "task_file_changed",
    "task_file_sha256",
    "task_for",
    "validate",
    "validated",
]

# The configuration fields a resume may change: budgets and stopping options (with the total
# of generations, config.json's ``generations``). Everything else is the run's own: a
# resumed run is the run it was, allowed to go further or to stop sooner.
RESUMABLE = tuple(
    name
    for name in ("target_cost", "max_evaluations", "stop_when_solved")
    if name in {f.name for f in dataclasses.fields(EANT2Config)}
)


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
    """Check a run directory as `eant2_jax.resume` does, changing nothing.

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
        v = validated(rundir)
        if task is not None:
            check_fits(rundir.path, v, task)
        return v


def _fail(path: Path, name: str, reason: str):
    raise RunDirError(f"{path / name}: {reason}")


def _config_of(path: Path, c: Committed) -> tuple[EANT2Config, int, tuple[int, ...]]:
    """``config.json``'s configuration, total generations and key data, checked."""
    meta = c.config
    if not isinstance(meta.get("config"), dict):
        _fail(path, CONFIG, "no configuration object ('config')")
    try:
        config = EANT2Config.from_dict(meta["config"], complete=c.strict)
    except (TypeError, ValueError) as e:
        _fail(path, CONFIG, f"bad configuration: {e}")
    total = meta.get("generations")
    if isinstance(total, bool) or not isinstance(total, int) or total < 0:
        _fail(path, CONFIG, f"generations must be an integer >= 0, got {total!r:.40}")
    try:
        key = check_key(meta.get("key"), "key")
    except (TypeError, ValueError) as e:
        _fail(path, CONFIG, f"bad key: {e}")
    return config, total, key


def validated(rundir: RunDir) -> Validated:
    """`RunDir.read` of an open run directory, typed and cross-checked (no task needed:
    nothing here runs code the directory names)."""
    path, c = rundir.path, rundir.read()
    config, total, key = _config_of(path, c)
    try:
        records = [GenerationRecord.from_json(r) for r in c.generations]
    except (TypeError, ValueError) as e:
        _fail(path, "generations.jsonl", f"corrupt record: {e}")
    try:
        pruning = [PruneAttempt.from_json(r) for r in c.pruning]
    except (TypeError, ValueError) as e:
        _fail(path, "pruning.jsonl", f"corrupt record: {e}")
    state = None
    if c.checkpoint is not None:
        try:
            state = RunState.from_json(c.checkpoint["state"])
        except (TypeError, ValueError) as e:
            _fail(path, "checkpoint.json", f"corrupt state: {e}")
        if state.key != key:
            _fail(path, "checkpoint.json", "its key is not the run's key in config.json")
        _check_state(path, state, config, records, pruning)
    elif records or pruning:
        _fail(path, "checkpoint.json", "missing, but the logs hold committed records")
    for r in records:
        try:
            Genome.parse(r.best_genome)
        except ValueError as e:
            _fail(path, "generations.jsonl", f"generation {r.generation}: {e}")
    key = key_from_data(key if state is None else state.key)
    return Validated(c, config, total, state, key, records, pruning)


def _check_state(path, state: RunState, config: EANT2Config, records, pruning) -> None:
    """The checkpoint's state against the configuration and the committed records."""
    last, best = records[-1], state.best()
    if len(state.population) > config.population:
        _fail(
            path,
            "checkpoint.json",
            f"{len(state.population)} individuals, more than the population of {config.population}",
        )
    if last.best_genome != str(best.genome) or dumps(last.best_cost) != dumps(best.cost):
        _fail(path, "checkpoint.json", "its best individual is not the last generation record's")
    if last.evaluations != state.evaluations:
        _fail(path, "checkpoint.json", "its evaluations differ from the last generation record's")
    if sum(r.prune_attempts for r in records) != len(pruning):
        _fail(
            path,
            "pruning.jsonl",
            f"{len(pruning)} record(s) where the generation records "
            f"count {sum(r.prune_attempts for r in records)}",
        )
    if any(p.generation is None or not 0 <= p.generation <= state.generation for p in pruning):
        _fail(path, "pruning.jsonl", "a record of a generation the checkpoint has not committed")
    for i, ind in enumerate(state.population):
        g = ind.genome
        if max(g.neuron_ids) >= state.next_id:
            _fail(
                path,
                "checkpoint.json",
                f"individual {i} has neuron id {max(g.neuron_ids)} >= next_id {state.next_id}",
            )


def check_fits(path: Path, v: Validated, task: Task) -> None:
    """The directory's genomes against the task's input and output counts."""
    for i, ind in enumerate(() if v.state is None else v.state.population):
        g = ind.genome
        if g.n_outputs != task.n_outputs or g.n_inputs > task.n_inputs:
            _fail(
                path,
                "checkpoint.json",
                f"individual {i} has {g.n_outputs} outputs and reads {g.n_inputs} "
                f"inputs; the task has {task.n_outputs} and {task.n_inputs}",
            )
    for r in v.records:
        g = Genome.parse(r.best_genome)
        if g.n_outputs != task.n_outputs or g.n_inputs > task.n_inputs:
            _fail(
                path,
                "generations.jsonl",
                f"generation {r.generation}'s best genome does not fit "
                f"the task ({g.n_outputs} outputs, {g.n_inputs} inputs read)",
            )


def task_for(path: Path, meta: dict, task: Task | None) -> Task:
    """The task a run directory goes on with (docs/reliability.md, "Trust").

    With ``task`` None, the task ``config.json`` records is rebuilt only when it is a
    registered one (`eant2_jax.tasks.is_registered`): a ``module:factory`` or
    ``file.py:factory`` spec is user code, and nothing a data file names is imported or
    called; the caller names it again. A given ``task`` that `eant2_jax.tasks.make` built
    must have the recorded spec.

    Raises:
      RunDirError: one line: no spec, a user task not named again, or another task.
    """
    recorded = meta.get("task")
    if task is not None:
        given = spec_of(task)
        if given is not None and isinstance(recorded, str) and given["task"] != recorded:
            raise RunDirError(
                f"{path}: the task given, {given['task']!r:.80}, is not the run's "
                f"({recorded!r:.80} in config.json)"
            )
        return task
    if not isinstance(recorded, str):
        kind = meta.get("task_type", "unknown")
        raise RunDirError(
            f"{path}: config.json records no task spec (its task, {kind!s:.80}, was not built "
            f"by eant2_jax.tasks.make); pass the task to resume(), or start runs with "
            f"tasks.make('module:factory')"
        )
    if not is_registered(recorded):
        raise RunDirError(
            f"{path}: its task {recorded!r:.80} is user code, which is not run because a run "
            f"directory names it; name it again: eant2 resume DIR --task SPEC, or "
            f"resume(out, task=tasks.make(SPEC, **options)) in Python"
        )
    options = meta.get("task_options", {})
    if not isinstance(options, dict):
        raise RunDirError(f"{path}: config.json is corrupt: task_options is not a dict")
    try:
        return make_task(recorded, **options)
    except (TypeError, ValueError) as e:
        raise RunDirError(f"{path / CONFIG}: {e}") from None


def run_meta(task: Task, meta: dict | None) -> dict:
    """What ``config.json`` records of the task (and the caller's ``meta``); best.genome's
    header reads it too, in the run and after a resume alike. A user's task also records
    the SHA-256 of its file (`task_file_sha256`), for a resume to compare."""
    spec = spec_of(task) or {"task_type": f"{type(task).__module__}.{type(task).__qualname__}"}
    digest = task_file_sha256(task)
    return {**spec, **({"task_sha256": digest} if digest else {}), **(meta or {})}


def task_file_sha256(task: Task) -> str | None:
    """The SHA-256 of the file that defines a user's task (``file.py:factory``: that file;
    ``module:factory``: the module's file), or None for a registered task, a task not built
    by `eant2_jax.tasks.make`, or a file that cannot be read. Reads the file already
    imported to build ``task``; imports nothing."""
    spec = spec_of(task)
    if spec is None or is_registered(spec["task"]):
        return None
    source = spec["task"].rsplit(":", 1)[0]
    if source.endswith(".py"):
        path = source
    else:
        path = getattr(sys.modules.get(source), "__file__", None)
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path else None
    except OSError:
        return None


def task_file_changed(meta: dict, task: Task) -> str | None:
    """A one-line warning when the file of the user's task ``task`` no longer holds what it
    held when the run in ``meta`` (its ``config.json``) started; None when it does, or when
    either side has no record (a registered task, a run from before the record)."""
    recorded, now = meta.get("task_sha256"), task_file_sha256(task)
    if not isinstance(recorded, str) or now is None or recorded == now:
        return None
    return (
        f"the file of task {meta.get('task')!s:.300} has changed since the run started "
        "(its SHA-256 differs): the resumed generations run the new code"
    )


def resumed(
    v: Validated,
    generations: int | None,
    changes: Mapping[str, Any] | None,
    resolve: Callable[[EANT2Config], EANT2Config] | None = None,
) -> tuple[EANT2Config, int, dict | None]:
    """What a resume goes on with: the configuration, the total of generations, and the
    new ``config.json`` object that records them (None when nothing changes).

    Args:
      v: the run directory, validated.
      generations: the new total (None: as recorded); not below the last completed one.
      changes: configuration fields to change, only those of `RESUMABLE`, checked by their
        specs. The object records them and appends ``{"after_generation", "generations",
        and the fields}`` to its ``resumed`` list.
      resolve: applied to a changed configuration, as a run's start applies it
        (`eant2_jax.strategy.resolved`: no target and the stop when solved on is the
        task's solved level); what it sets is recorded too.

    Raises:
      ValueError: one line naming the option that may not change or its bad value.
    """
    changes = dict(changes or {})
    for name in changes:
        if name not in RESUMABLE:
            raise ValueError(
                f"{name!s:.60} cannot change on resume (a run keeps its configuration); "
                f"a resume may change generations, {', '.join(RESUMABLE)}"
            )
    meta = v.committed.config
    done = -1 if v.state is None else v.state.generation
    total = v.generations if generations is None else generations
    if total < done:
        raise ValueError(
            f"generations {total}: the run has already completed generation {done}; a "
            "resume may only keep or raise the total"
        )
    data = copy.deepcopy(meta["config"])
    data.update(changes)
    config = EANT2Config.from_dict(data, complete=v.committed.strict)  # each field's checks
    if changes and resolve is not None:
        config = resolve(config)
    now, before = config.to_dict(), v.config.to_dict()
    values = {
        name: now[name]
        for name in RESUMABLE
        if name in changes or dumps(now[name]) != dumps(before[name])
    }
    if total == v.generations and all(dumps(before[k]) == dumps(x) for k, x in values.items()):
        return v.config, total, None
    history = meta.get("resumed") if isinstance(meta.get("resumed"), list) else []
    entry = {"after_generation": done, "generations": total, **values}
    new = {**meta, "generations": total, "config": {**meta["config"], **values}}
    return config, total, {**new, "resumed": [*history, entry]}


def create(out: str, meta: dict, generations: int, key: jax.Array, config: EANT2Config) -> RunDir:
    """A new run directory for a run of ``config`` from ``key``."""
    return RunDir.create(
        out,
        {
            **meta,
            "generations": generations,
            "key": list(key_data(key)),
            "config": config.to_dict(),
        },
    )


def rewind(rundir: RunDir, v: Validated, task: Task) -> None:
    """Cut a checked run directory back to what it committed (best.genome rewritten when it
    does not hold the checkpoint's best), before a run goes on in it."""
    best = None
    if v.state is not None and not _holds_best(v.committed.best, v.state):
        best = _best_text(v.state, task, v.committed.config)
    rundir.rewind(v.committed.offsets, best)


def commit(
    rundir: RunDir | None,
    task: Task,
    meta: dict,
    state: RunState,
    record: GenerationRecord,
    prune: list[PruneAttempt],
) -> None:
    """A completed generation into the run directory (if any): records, best, checkpoint."""
    if rundir is not None:
        rundir.commit(
            [record.to_json()],
            [r.to_json() for r in prune],
            _best_text(state, task, meta),
            state.to_json(),
        )


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
