"""Many independent EANT2 runs (seeds, or arms with different configs) spread over devices.

One worker thread per device (or several, to overlap one run's host-side work with another's
device work) takes runs from a queue; each run is pinned to its device with
``jax.default_device`` and is exactly the run `eant2_jax.loop.run` would make there.

CPU devices get one worker thread between them: XLA's CPU devices share one thread pool, and
two programs running at once in it can deadlock (jaxlib's batched LAPACK kernels, the
engine's ``eigh`` among them, wait inside the pool for work queued behind each other: a
two-core machine hung in ``jax::ParallelBatchMap`` with ``eant2 reproduce --workers 2`` on
the servo task). A CPU run already uses every core, so concurrency gains nothing there.
"""

from __future__ import annotations

import queue
import signal
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import jax

from .config import EANT2Config
from .loop import resume as resume_run
from .loop import run, run_lockstep
from .records import RunResult
from .tasks.base import Task

__all__ = ["run_many"]

# The worker threads' name prefix (the command line tells a Ctrl-C with runs still going).
WORKER = "eant2-run-worker"


def chosen_devices(devices: int | str | Sequence[jax.Device]) -> list[jax.Device]:
    """The devices `run_many` spreads over for ``devices``: ``"all"`` local ones, the first
    ``devices`` of them, or the given ones."""
    local = jax.local_devices()
    if devices == "all":
        return local
    if isinstance(devices, int):
        if not 1 <= devices <= len(local):
            raise ValueError(f"devices={devices}: this process has {len(local)} device(s)")
        return local[:devices]
    return list(devices)


def run_many(
    task: Task,
    keys: Sequence[jax.Array],
    *,
    config: EANT2Config | Sequence[EANT2Config] | None = None,
    generations: int,
    outs: Sequence[str | None] | None = None,
    devices: int | str | Sequence[jax.Device] = "all",
    workers_per_device: int = 1,
    callback: Callable[[dict], None] | None = None,
    meta: dict | None = None,
    resume: bool = False,
    lockstep: bool = False,
) -> list[RunResult]:
    """Independent runs (seeds, or arms with different configs) spread over devices.

    One worker thread per device takes runs from a queue; a run is pinned to its device
    with ``jax.default_device`` and is exactly the run `run` would make there.

    Args:
      task: the task, shared by all runs.
      keys: one PRNG key per run.
      config: one config for all runs, or one per run (their ``devices`` must be None).
      generations: as for `run`.
      outs: optional run directory per run (None entries write nothing).
      devices: ``"all"`` (this process's devices), a count, or explicit devices.
      workers_per_device: runs in flight per device (>1 overlaps one run's host-side work
        with another's device work). CPU devices run one run at a time between them (see
        the module's docstring); asking for more there warns.
      callback: progress events, with ``run`` (the run's index) added.
      meta: extra ``config.json`` fields for every run directory.
      resume: a run whose directory in ``outs`` exists continues it instead of starting
        (`eant2_jax.loop.resume`: a finished run is read back, a stopped one goes on from
        its last complete generation).
      lockstep: runs of equal configs go in lock-step (`eant2_jax.run_lockstep`: each
        generation of all of them tuned in one batch), split into one group per device;
        the groups are what the workers take. On a GPU this saves the most where one run's
        generation is too small to keep the device busy; a run then shares its padding
        bucket with its group (see `eant2_jax.loop`). ``exploit``/``compiling``
        events carry ``runs``.

    Returns:
      The results, in the order of ``keys``.
    """
    keys = list(keys)
    configs, outs = _per_run(config, keys, outs)
    if workers_per_device < 1:
        raise ValueError(f"workers_per_device must be >= 1, got {workers_per_device}")
    chosen = chosen_devices(devices)
    todo: queue.Queue = queue.Queue()
    for job in _jobs(configs, chosen, lockstep):
        todo.put(job)
    results: list[RunResult | None] = [None] * len(keys)
    errors: list[BaseException] = []
    relay = _Relay(callback)
    common = dict(task=task, generations=generations, meta=meta, resume=resume)

    def worker(device):
        # Ctrl-C goes to the main thread, which is waiting for these (see below).
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        while not errors:
            try:
                job = todo.get_nowait()
            except queue.Empty:
                return
            here = device if device is not None else chosen[job[0] % len(chosen)]
            try:
                with jax.default_device(here):
                    got = _run_job(job, keys, configs, outs, relay(job), lockstep, **common)
                for i, r in zip(job, got, strict=True):
                    results[i] = r
            except BaseException as e:  # re-raised in the caller's thread
                errors.append(e)

    threads = [
        threading.Thread(target=worker, args=(d,), daemon=True, name=f"{WORKER}-{k}")
        for k, d in enumerate(_slots(chosen, workers_per_device))
    ]
    _wait(threads, errors)
    return results


def _wait(threads: list[threading.Thread], errors: list[BaseException]) -> None:
    """Start the workers and wait for them; the first error of any is raised here."""
    for t in threads:
        t.start()
    try:
        for t in threads:
            # In short waits: a signal that a jax thread received is only acted on when the
            # main thread runs Python again (a plain join() kept Ctrl-C waiting for every
            # run to end).
            while t.is_alive():
                t.join(0.25)
    except KeyboardInterrupt:
        errors.append(KeyboardInterrupt())  # no worker starts another run
        raise
    if errors:
        raise errors[0]


def _per_run(config, keys, outs) -> tuple[list[EANT2Config], list[str | None]]:
    """One config and one output directory per run, checked."""
    configs = list(config) if isinstance(config, Sequence) else [config] * len(keys)
    configs = [EANT2Config() if c is None else c for c in configs]
    outs = [None] * len(keys) if outs is None else list(outs)
    if not (len(configs) == len(outs) == len(keys)):
        raise ValueError("run_many: keys, configs and outs must have the same length")
    if any(c.devices is not None for c in configs):
        raise ValueError("run_many places each run on one device: leave config.devices None")
    return configs, outs


def _jobs(configs, chosen, lockstep: bool) -> list[list[int]]:
    """What the workers take: one run each, or with ``lockstep`` the runs of equal configs
    in groups, one group per device."""
    if not lockstep:
        return [[i] for i in range(len(configs))]
    by_config: dict = {}
    for i, c in enumerate(configs):
        by_config.setdefault(c, []).append(i)
    parts = 1 if chosen[0].platform == "cpu" else len(chosen)
    return [g[k::parts] for g in by_config.values() for k in range(parts) if g[k::parts]]


class _Relay:
    """The caller's callback, serialised across workers, with each event's run index
    (and a group's ``runs``) mapped back to the index in ``keys``."""

    def __init__(self, callback):
        self.callback, self.lock = callback, threading.Lock()

    def __call__(self, job):
        if self.callback is None:
            return None

        def cb(event):
            # A lock-step group's events name their run by its index in the group (exploit
            # events the group, by "runs"); a run alone's carry no run.
            event = {**event, "run": job[event.get("run", 0)]}
            if "runs" in event:
                event["runs"] = [job[r] for r in event["runs"]]
            with self.lock:
                self.callback(event)

        return cb


def _run_job(job, keys, configs, outs, cb, lockstep, *, task, generations, meta, resume):
    """The runs of one job (a run alone, or a lock-step group), on the current device."""
    if lockstep:
        return run_lockstep(
            task, [keys[i] for i in job], config=configs[job[0]], generations=generations,
            outs=[outs[i] for i in job], callback=cb, meta=meta, resume=resume,
        )  # fmt: skip
    (i,) = job
    if resume and outs[i] is not None and Path(outs[i]).exists():
        return [resume_run(outs[i], task, callback=cb)]
    return [
        run(task, key=keys[i], config=configs[i], generations=generations, out=outs[i],
            callback=cb, meta=meta)
    ]  # fmt: skip


def _slots(chosen, workers_per_device: int) -> list:
    """One worker per slot: a device each (``workers_per_device`` per device), or on CPU
    devices one worker between them (device None: each run goes to ``chosen[i % len]``)."""
    if all(d.platform == "cpu" for d in chosen):
        if workers_per_device > 1:
            warnings.warn(
                f"workers_per_device={workers_per_device} on CPU devices: running one run at "
                "a time (concurrent programs can deadlock XLA's CPU thread pool)",
                stacklevel=3,
            )
        return [None]
    return [d for d in chosen for _ in range(workers_per_device)]
