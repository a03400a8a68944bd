"""The paper's experiments (section V), reproducible with one call.

* `reproduce`: EANT2 runs with and without pruning (V.B, figure 8), several seeds per
  arm, spread over the devices; then the condition experiment (V.A, figure 7,
  `eant2_jax.app.condition`) on the best unpruned network; then the report.
* `resume_reproduction`: finish one that was stopped, from its ``reproduce.json``
  (`eant2_jax.app.manifest`: checked field by field before anything runs).
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import jax
import numpy as np

from ..compiler import networks
from ..genome import Genome
from ..jsonio import dumps
from ..loop import EANT2Config, compile_first_ahead
from ..multirun import chosen_devices, run_many
from ..rundir import RunDirError
from ..tasks.base import ReportingTask, Task
from . import outputs
from .arms import arm_overrides
from .condition import condition_experiment
from .heldout import held_out_costs
from .manifest import (
    CONDITION,
    MANIFEST,
    MANIFEST_VERSION,
    ManifestError,
    arm_config,
    arm_order,
    check_condition,
    check_manifest,
    read_json,
    read_manifest,
    resume_task,
)
from .report import escape, report

__all__ = [
    "MANIFEST",
    "Background",
    "ManifestError",
    "arm_config",
    "condition_experiment",
    "reproduce",
    "resume_reproduction",
]


def reproduce(
    task: Task,
    out: str | Path,
    *,
    task_meta: dict,
    runs: int = 10,
    generations: int = 15,
    pruners: Sequence[str] = ("covariance",),
    arm_runs: Mapping[str, int] | None = None,
    config: EANT2Config | None = None,
    seed: int = 0,
    devices: int | str = "all",
    workers_per_device: int = 1,
    lockstep: bool = True,
    condition: bool = True,
    condition_iters: int = 10_000,
    condition_inits: int = 5,
    condition_dtype: str = "float64",
    overlap_condition: bool | None = None,
    callback: Callable[[dict], None] | None = None,
) -> Path:
    """Run the paper's experiments and write the report; returns the path of
    ``report/report.md`` (docs/reproduce.md).

    The settings are checked (`eant2_jax.app.manifest.check_manifest`: the limits a manifest
    read back must meet) and go first into ``out/reproduce.json``: `resume_reproduction`
    (``eant2 resume OUT``) finishes a killed one, losing at most each run's current generation.

    Args:
      task: the task (the paper's: ``tasks.make("servo")``).
      out: a new or empty directory; it receives one run directory per arm and seed
        (``ARM-sSEED``), ``condition.json`` and ``report/``.
      task_meta: ``{"task": name, "task_options": {...}}`` stored with each run.
      runs: runs per arm (seeds ``seed .. seed+runs-1``; the same seeds in every arm).
      generations: generations per run.
      pruners: the arms, by name (`eant2_jax.app.arms`: a protocol arm such as ``default`` or
        ``no-refit``, a pruner's name, or ``NAME-literal``); ``none`` (no pruning) is added.
      arm_runs: runs of the arms whose count is not ``runs`` (``{"none": 20}``), from ``seed``.
      config: base EANT2 configuration (each arm sets its pruning fields: `arm_overrides`).
      seed: first seed.
      devices: devices to spread the runs over (see `eant2_jax.run_many`).
      workers_per_device: concurrent runs per device (host work overlaps device work).
      lockstep: an arm's runs go in lock-step, each generation of all of them tuned in one
        batch, one group per device (`eant2_jax.run_lockstep`: a run shares its padding
        bucket with its arm); False: each run alone, ``workers_per_device`` per device.
      condition: also run the V.A condition experiment.
      condition_iters: CMA-ES budget of each run of that experiment from random weights.
      condition_inits: random initialisations of each network in it.
      condition_dtype: the CMA-ES state's dtype in it; ``float64`` turns on JAX's x64 mode
        for that experiment alone (the evolution runs, done by then, stay in float32).
      overlap_condition: run the condition experiment in a background thread while the
        pruning arms run, and the baselines' costs while the first arm runs (the results are
        the same either way). ``None`` (default): on unless the default backend is a CPU.
      callback: progress events: ``generation`` events with ``run`` and ``arm``; a
        ``condition`` event with ``phase`` ``"start"`` or ``"done"`` (and ``wall_s``).

    Raises:
      ManifestError: a setting out of its range (one line naming it); nothing is created.
      RunDirError: ``out`` exists and is not an empty directory.
    """
    out = Path(out)
    manifest = {
        "version": MANIFEST_VERSION,
        "task_meta": task_meta,
        "runs": runs,
        "generations": generations,
        "pruners": list(pruners),
        "config": (config or EANT2Config()).to_dict(),
        "seed": seed,
        "devices": devices,
        "workers_per_device": workers_per_device,
        "lockstep": lockstep,
        "condition": condition,
        "condition_iters": condition_iters,
        "condition_inits": condition_inits,
        "condition_dtype": condition_dtype,
    }
    settings = _create(out, _with_arms(manifest, pruners, runs, arm_runs))
    settings["config"] = config or EANT2Config()
    return _reproduce(task, out, settings, overlap_condition, callback, resume=False)


def _with_arms(manifest: dict, pruners: Sequence[str], runs: int, arm_runs) -> dict:
    """``manifest`` with its arms' run counts (with ``arm_runs``) and overrides; an unknown
    arm is left to `check_manifest`, which names it in its own words."""
    arms = arm_order(list(pruners)) if isinstance(pruners, Sequence) else []
    if arm_runs:
        manifest["arm_runs"] = {**{a: runs for a in arms}, **dict(arm_runs)}
    try:
        manifest["arm_overrides"] = {a: arm_overrides(a) for a in arms}
    except ValueError:
        pass
    return manifest


def _create(out: Path, manifest: dict) -> dict:
    """The checked settings of ``manifest`` (one rule for a start and a resume), written
    into the new directory ``out``; nothing is created if a setting or ``out`` is wrong."""
    settings = check_manifest(manifest, "reproduce")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise RunDirError(f"{out} already exists and is not an empty directory; not overwriting")
    outputs.make_folder(out)
    outputs.write_text(out / MANIFEST, dumps(manifest, indent=2) + "\n")  # whole or absent
    return settings


def resume_reproduction(
    out: str | Path,
    *,
    callback: Callable[[dict], None] | None = None,
    task: Task | None = None,
) -> Path:
    """Finish a reproduction that `reproduce` started in ``out`` and that was stopped: with
    the settings of its ``reproduce.json``, finished runs are read back, interrupted ones
    resume from their last complete generation, missing ones start, then the condition
    experiment (unless its result is there) and the report follow. The result equals an
    uninterrupted reproduction's where a resumed run equals an uninterrupted one (on a CPU,
    or a GPU with deterministic ops).

    Args:
      out: the reproduction's directory.
      callback: progress events, as `reproduce`'s.
      task: the task, given again by the caller. Without it the manifest's task is rebuilt
        only when it is registered (`eant2_jax.tasks.is_registered`); a user task
        (``module:factory``, ``file.py``) named by the file is never imported.

    Raises:
      RunDirError: ``out`` holds no readable reproduction (`ManifestError`: one line naming
        the manifest's field that is wrong, before anything runs).
    """
    out = Path(out)
    settings = read_manifest(out)
    if task is None:
        task = resume_task(settings["task_meta"], str(out / MANIFEST))
    return _reproduce(task, out, settings, None, callback, resume=True)


def _reproduce(task, out: Path, settings: dict, overlap, callback, *, resume: bool) -> Path:
    """The reproduction of checked ``settings`` (`check_manifest`'s) in ``out``, whose
    manifest is written: the arms, the condition experiment, the report."""
    s = settings
    arms = arm_order(s["pruners"])
    jobs = [(arm, s["seed"] + i) for arm in arms for i in range(s["arm_runs"][arm])]
    dirs = [out / f"{arm}-s{seed}" for arm, seed in jobs]
    t0 = time.perf_counter()
    # The condition experiment is a chain of small, latency-bound programs that leaves an
    # accelerator mostly idle, so overlapping it with the arms hides most of it; on a CPU two
    # programs at once can deadlock XLA's CPU thread pool (`eant2_jax.multirun`).
    if overlap is None:
        overlap = jax.default_backend() != "cpu"
    done = out / CONDITION
    cond_cached = s["condition"] and resume and (done.exists() or done.is_symlink())
    # The reference controllers' costs need nothing from the runs: with the overlap they
    # are computed in the background while the first arm runs.
    reporting = isinstance(task, ReportingTask)
    baselines = Background("eant2-baselines", task.baselines) if reporting and overlap else None
    experiment = _Condition(task, s, done, callback)
    start_condition = None
    if s["condition"] and not cond_cached and overlap:
        start_condition = experiment.start
    results = _run_arms(task, s, jobs, dirs, callback, resume, start_condition)
    extra: dict = {"wall_s": time.perf_counter() - t0, "device": jax.devices()[0].device_kind}
    if resume:
        extra["resumed"] = True
    if reporting:
        extra["baselines"] = task.baselines() if baselines is None else baselines.result()
        extra["generalisation"] = _generalisation(task, jobs, results)
    fresh = _held_out(task, jobs, results)
    if fresh is not None:
        extra["held_out"] = fresh
    cond = None
    if cond_cached:
        cond = check_condition(read_json(done, strict=False), str(done))
    elif s["condition"]:
        cond = experiment.result(_best_unpruned(jobs, results))
    extra["notes"] = _claims(dirs, cond)
    return report([str(d) for d in dirs], out / "report", extra=extra, condition=cond)


def _run_arms(task, s: dict, jobs, dirs, callback, resume: bool, start_condition) -> list:
    """Run every arm (the one without pruning first: the condition experiment needs its best
    network and can then overlap the other arms; the order changes no result, each run has
    its own key, and not the report's); each arm's results in ``jobs``' order."""
    base = s["config"]
    configs = [arm_config(base, arm) for arm, _ in jobs]
    order = ["none"] + [a for a in dict.fromkeys(a for a, _ in jobs) if a != "none"]
    if s["lockstep"] and not resume and len(chosen_devices(s["devices"])) == 1:
        # Each later arm is one lock-step group: its generation-0 program compiles in the
        # background while the first arm runs.
        for arm in order[1:]:
            first = next(i for i, (a, _) in enumerate(jobs) if a == arm)
            key = jax.eval_shape(jax.random.key, jobs[first][1])
            compile_first_ahead(task, key, configs[first], runs=s["arm_runs"][arm])
    results: list = [None] * len(jobs)
    for arm in order:  # one meta per arm
        idx = [i for i, (a, _) in enumerate(jobs) if a == arm]

        def progress(e, idx=idx):
            run = idx[e["run"]]
            callback({**e, "run": run, "arm": jobs[run][0]})

        arm_results = run_many(
            task,
            [jax.random.key(jobs[i][1]) for i in idx],
            config=[configs[i] for i in idx],
            generations=s["generations"],
            outs=[str(dirs[i]) for i in idx],
            devices=s["devices"],
            workers_per_device=s["workers_per_device"],
            callback=None if callback is None else progress,
            meta={**s["task_meta"], "arm": arm},
            resume=resume,
            lockstep=s["lockstep"],
        )
        for i, r in zip(idx, arm_results, strict=True):
            results[i] = r
        if arm == "none" and start_condition is not None:
            start_condition(_best_unpruned(jobs, results))
    return results


class _Condition:
    """The condition experiment (V.A) of one reproduction: inline (`result` of the best
    network) or started in a background thread (`start`, then `result`)."""

    def __init__(self, task, s: dict, done: Path, callback):
        self._task, self._s, self._done, self._callback = task, s, done, callback
        self._background: Background | None = None

    def start(self, best: Genome) -> None:
        self._background = Background("eant2-condition", self._run, best)

    def result(self, best: Genome) -> dict:
        if self._background is not None:
            return self._background.result()
        return self._run(best)

    def _run(self, best: Genome) -> dict:
        """The experiment on ``best``; writes ``condition.json`` whole at its end."""
        s, callback = self._s, self._callback
        t = time.perf_counter()
        if callback is not None:
            callback({"event": "condition", "phase": "start", "size": best.n_params})
        # x64 for this experiment alone: the mode is global JAX state (thread-local under
        # this context manager), and the evolution runs, and a run started after this call
        # (a second reproduction in one process), must not see it.
        dtype = s["condition_dtype"]
        x64 = jax.enable_x64(True) if dtype == "float64" else contextlib.nullcontext()
        with x64:
            result = condition_experiment(
                best,
                self._task,
                key=jax.random.key(s["seed"] + 10_000),
                iters=s["condition_iters"],
                # The pruning rounds from the tuned weights need no more than the runs from
                # random weights (and a short setting stays short).
                prune_iters=min(s["condition_iters"], 2000),
                inits=s["condition_inits"],
                dtype=dtype,
            )
        outputs.write_text(self._done, json.dumps(result) + "\n")
        if callback is not None:
            callback({"event": "condition", "phase": "done", "wall_s": time.perf_counter() - t})
        return result


def _generalisation(task, jobs, results) -> dict[str, list[float]]:
    """Each run's best network's cost on the task's held-out set, per arm. All best
    networks go in one padded batch: one program, where one per network's shape compiled
    for far longer. Padding changes a float32 sum's order, not its terms (costs moved by
    about 2e-7 relative on the networks of docs/reproduce.md)."""
    gen: dict[str, list[float]] = {}
    nets = networks([r.best for r in results], task.n_inputs)
    costs = np.asarray(task.generalisation(nets), np.float64)
    for (arm, _), c in zip(jobs, costs, strict=True):
        gen.setdefault(arm, []).append(float(c))
    return gen


def _held_out(task, jobs, results) -> dict[str, list[float]] | None:
    """Each run's best network's cost on new start poses from the protocol's key, per arm
    (`eant2_jax.app.heldout`); None where the task has no rule for them."""
    nets = networks([r.best for r in results], task.n_inputs)
    costs = held_out_costs(task, nets)
    if costs is None:
        return None
    out: dict[str, list[float]] = {}
    for (arm, _), c in zip(jobs, costs, strict=True):
        out.setdefault(arm, []).append(float(c))
    return out


def _best_unpruned(jobs: Sequence[tuple[str, int]], results: Sequence) -> Genome:
    """The best network of the arm without pruning (by its last generation's cost)."""
    unpruned = [r for (arm, _), r in zip(jobs, results, strict=True) if arm == "none"]
    return min(unpruned, key=lambda r: r.generations[-1].best_cost).best


class Background:
    """``fn(*args)`` in a daemon thread named ``name``; `result` joins it and re-raises its
    error. A daemon (unlike a ``concurrent.futures`` worker, which the interpreter joins at
    exit), so that an interrupted reproduction exits without waiting for it (its output is
    written whole at its end or not at all)."""

    def __init__(self, name: str, fn: Callable, *args):
        self._out: dict = {}

        def target():
            try:
                self._out["value"] = fn(*args)
            except BaseException as e:  # noqa: BLE001 -- handed to the joining thread
                self._out["error"] = e

        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        if "error" in self._out:
            raise self._out["error"]
        return self._out["value"]


def _conditioning_claim(cond: dict) -> str:
    before = float(np.median(cond["peak_before"]))
    after = float(np.median(cond["peak_after"]))
    verdict = (
        "pruning lowered it at least 100x."
        if after * 100 <= before
        else "pruning lowered it, but less than 100x."
        if after < before
        else "pruning did NOT lower it."
    )
    return (
        f"- **Better conditioning**: over {len(cond['peak_before'])} random initialisations "
        f"({escape(cond['dtype'])} CMA-ES state, bound {cond['max_condition']:.0e}), the median "
        f"peak cond(C) was {before:.3g} for the original network and {after:.3g} for the "
        f"pruned one, {before / after:.3g}x (paper: 1.8e17 vs 9e13, one run each); " + verdict
    )


def _claims(dirs: Sequence[Path], cond: dict | None) -> str:
    """Plain statements of whether the paper's two claims hold in these runs."""
    from .report import load_runs, summarise

    s = summarise(load_runs([str(d) for d in dirs]))
    lines = ["## The paper's claims, checked on these runs", ""]
    none = s.get("none")
    for arm, v in s.items():
        if arm == "none" or none is None:
            continue
        p = v["p_fitness"]
        lines.append(
            f"- **Size and fitness ({escape(arm)})**: size {v['size_mean']:.1f} "
            f"vs {none['size_mean']:.1f} without pruning ({v['size_reduction_pct']:.1f}% "
            f"smaller; paper: 59.8 vs 73.6, 23%); fitness {v['fitness_mean']:.4g} vs "
            f"{none['fitness_mean']:.4g} (paper: -0.2277 vs -0.2267"
            + (f"; Welch p = {p:.3g}" if p is not None else "")
            + "). Whether the size is smaller and the fitness equivalent is decided by the "
            "verdicts above (a p-value above 0.05 is not equality)."
        )
    if cond is not None:
        lines.append(_conditioning_claim(cond))
    return "\n".join(lines)
