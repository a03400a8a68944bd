"""Run directories as the report reads them: loading (checked as resume checks them), the
setting runs must share to be compared, and reading a run up to a generation.

Runs are only compared when they ran the same task with the same options and the same
configuration, pruning apart (the arms differ in it): anything else is a `MixedRunsError`
naming the difference.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

from ..loop import GenerationRecord
from ..pruning import PruneAttempt

__all__ = [
    "LoadedRun",
    "MixedRunsError",
    "check_comparable",
    "load_runs",
    "mixed_message",
    "setting",
    "upto",
]


class MixedRunsError(ValueError):
    """Run directories that differ in their task or configuration (beyond pruning)."""


@dataclasses.dataclass(frozen=True)
class LoadedRun:
    """One run directory as the report reads it.

    Attributes:
      dir: its path; arm: its arm label (the pruner unless the run names one); task: the
      task's name (None if not recorded); seed: the seed (None if not recorded).
      generations: its `GenerationRecord`s; pruning: its `PruneAttempt`s.
      setting: what must agree between runs that are compared (`setting`).
      budget: generations asked for (None if not recorded); target_cost: the run's stop
      target (None if none).
    """

    dir: str
    arm: str
    task: str | None
    seed: int | None
    generations: list[GenerationRecord]
    pruning: list[PruneAttempt]
    setting: dict = dataclasses.field(default_factory=dict)
    budget: int | None = None
    target_cost: float | None = None


# Fields of config.json that may differ between compared runs: the arms differ in pruning,
# runs in their seed, and devices are placement only (the results are identical).
# A resume's history (``resumed``) may differ too: what it set is compared where it is.
_FREE = {"format", "seed", "key", "arm", "devices", "resumed"}


def setting(meta: dict) -> dict:
    """What a run's ``config.json`` says that runs compared in one report must share: the task,
    its options, the generations asked for and the configuration, pruning fields, seed and
    devices left out. Flat ``{"config.exploit.max_iters": 1000, ...}``."""
    flat: dict = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict) and prefix != "task_options":
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        else:
            flat[prefix] = value

    walk("", {k: v for k, v in meta.items() if k not in _FREE})
    flat.setdefault("task", None)
    flat.setdefault("task_options", {})
    flat.pop("config.devices", None)
    for k in [k for k in flat if k.startswith("config.exploit.") and "prune" in k]:
        del flat[k]  # pruner, prune_window, ...: what the arms compare
    return flat


def check_comparable(runs: Sequence[LoadedRun]) -> list[str]:
    """The fields in which ``runs`` differ (empty: they may be compared)."""
    fields = sorted({k for r in runs for k in r.setting}, key=lambda k: (k != "task", k))
    return [f for f in fields if len({json.dumps(r.setting.get(f)) for r in runs}) > 1]


def mixed_message(runs: Sequence[LoadedRun], fields: list[str]) -> str:
    """The one-line error of runs that differ in ``fields`` (`check_comparable`); values
    are shown as JSON, so a string read from a file cannot break the line."""
    first = fields[0]
    a = runs[0]
    b = next(
        r for r in runs if json.dumps(r.setting.get(first)) != json.dumps(a.setting.get(first))
    )
    more = ""
    if len(fields) > 1:
        more = f" (and {len(fields) - 1} more: {', '.join(map(_one_line, fields[1:4]))})"
    name = _one_line(first.removeprefix("config.").removeprefix("exploit."))
    return (
        f"runs differ in {name}: {a.dir} has {json.dumps(a.setting.get(first))}, {b.dir} has "
        f"{json.dumps(b.setting.get(first))}{more}; pass --allow-mixed to report them together"
    )


def _one_line(name: str) -> str:
    """A field name read from a file, its control characters and non-ASCII escaped."""
    return json.dumps(name)[1:-1]


def load_runs(dirs: Sequence[str | Path]) -> list[LoadedRun]:
    """Read run directories: config, generation records and arm label of each."""
    from ..loop import validate

    runs = []
    for d in dirs:
        # Checked as resume checks it, reading only what was committed (so a live run is
        # read consistently, without its lock).
        v = validate(str(d), lock=False)
        meta = v.committed.config
        if not v.records:
            raise ValueError(f"{d}: no completed generation to report")
        config = meta.get("config", {})
        arm = meta.get("arm", v.config.exploit.pruner)
        task, seed = meta.get("task", meta.get("task_type", "?")), meta.get("seed")
        if not isinstance(arm, str) or not isinstance(task, str):
            raise ValueError(f"{d}: config.json's arm and task must be names")
        budget = meta.get("generations")
        target = config.get("target_cost") if isinstance(config, dict) else None
        runs.append(
            LoadedRun(
                dir=str(d),
                arm=arm,
                task=task,
                seed=seed if isinstance(seed, int) else None,
                generations=v.records,
                pruning=v.pruning,
                setting=setting(meta),
                budget=budget if isinstance(budget, int) else None,
                target_cost=target if isinstance(target, int | float) else None,
            )
        )
    return runs


def upto(run: LoadedRun, generation: int) -> LoadedRun:
    """``run`` read up to ``generation``, as if it had stopped there (``eant2 report
    --upto``); ValueError if it has not reached it."""
    if isinstance(generation, bool) or not isinstance(generation, int) or generation < 0:
        raise ValueError(f"upto must be a generation >= 0, got {generation!r}")
    last = run.generations[-1].generation
    if last < generation:
        raise ValueError(f"{run.dir}: its last generation is {last}, before {generation}")
    return dataclasses.replace(
        run,
        generations=[g for g in run.generations if g.generation <= generation],
        pruning=[p for p in run.pruning if p.generation is None or p.generation <= generation],
    )
