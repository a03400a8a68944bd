"""The paper's experiments (section V), reproducible with one call.

* `reproduce`: EANT2 runs with and without pruning (V.B, figure 8), several seeds per
  arm, spread over the devices; then the condition experiment (V.A, figure 7) on the best
  unpruned network; then the report.
* `condition_experiment`: prune an evolved network, re-initialise it and its pruned
  version with random weights, and record cond(C) of a CMA-ES run on each (no pruning).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..compiler import networks
from ..config import ExploitConfig
from ..exploitation import run as run_engine
from ..genome import Genome
from ..kernels.pruning import PRUNERS
from ..loop import EANT2Config, compile_first_ahead
from ..multirun import chosen_devices, run_many
from ..pruning import kept_genes, reduce, where_rows
from ..rundir import RunDirError, write_atomic
from ..tasks.base import ReportingTask, Task
from ..tuning import optimize, prepare, tune
from .report import report

__all__ = ["MANIFEST", "arm_config", "condition_experiment", "reproduce", "resume_reproduction"]

# What `reproduce` writes first into its directory: its settings, so that
# `resume_reproduction` (``eant2 resume DIR``) can finish a reproduction that was killed.
MANIFEST = "reproduce.json"
_MANIFEST_VERSION = 1


def condition_experiment(
    genome: Genome,
    task: Task,
    *,
    key: jax.Array,
    prune_iters: int = 2000,
    prune_window: int = 100,
    prune_sigma0: float = 0.1,
    rounds: int = 10,
    prune_candidates: int = 4,
    iters: int = 10_000,
    inits: int = 5,
    sigma0: float = 0.5,
    weight_scale: float = 0.5,
    dtype: str = "float64",
    max_condition: float = 1e17,
    evolved_warmup: int = 0,
) -> dict:
    """Paper V.A: cond(C) of a network against its pruned version.

    First the network is pruned in rounds (each a CMA-ES run from its current weights, until
    a round removes nothing). Then the original and the pruned network each start from
    ``inits`` random weight vectors (the pruned one from the same draws on the genes it
    kept), and all ``2 * inits`` CMA-ES runs go as ONE batch, without pruning or early stop,
    recording cond(C) every iteration. The paper ran one initialisation of each, limited cond
    at about 1e17, and reports 1.8e17 against 9e13; a float32 state cannot resolve such
    condition numbers, hence ``dtype="float64"`` (JAX's x64 mode must be on).

    Args:
      genome: an evolved network (with tuned weights).
      task: its task.
      key: PRNG key.
      prune_iters: CMA-ES budget of each pruning round (from the current weights).
      prune_window: W of the pruning trigger in those rounds.
      prune_sigma0: initial step size of those rounds (small: the weights are tuned).
      rounds: at most this many pruning rounds; they stop when one removes nothing.
      prune_candidates: candidates tested per attempt.
      iters: CMA-ES budget of each run from random weights.
      inits: random initialisations of each network.
      sigma0: initial step size of those runs.
      weight_scale: std of the random initial weights.
      dtype: the CMA-ES state's dtype in those runs.
      max_condition: the bound on cond(C) in those runs.
      evolved_warmup: if > 0, also the variant that continues from an EVOLVED covariance
        instead of restarting at C = I: the original network's CMA-ES runs ``evolved_warmup``
        iterations from its tuned weights (``inits`` runs, step size ``prune_sigma0``); then
        each run goes on ``iters`` iterations twice, as it is and with the pruned genes
        removed (C conditioned on them, the pruned network's weights), from the same state
        and the same random numbers. Results under ``evolved``.

    Returns:
      ``before``/``after``: ``[inits][iters]`` cond(C) per run and iteration;
      ``peak_before``/``peak_after``: the peak of each run; ``cost_before``/``cost_after``:
      each run's best cost; ``size_before``/``size_after``; ``genome_before``/
      ``genome_after``; ``removed``: accepted pruning records.
    """
    k_prune, k_init, k_run = jax.random.split(key, 3)
    current, removed = genome, []
    for r in range(rounds):
        res = optimize(
            current,
            task,
            key=jax.random.fold_in(k_prune, r),
            pruner="covariance",
            prune_window=prune_window,
            max_iters=prune_iters,
            patience=prune_iters,
            sigma0=prune_sigma0,
            prune_candidates=prune_candidates,
        )
        accepted = [dict(x.to_json(), round=r) for x in res.pruning if x.accepted]
        removed += accepted
        current = res.genome
        if not accepted:
            break
    rng = np.random.default_rng(np.asarray(jax.random.key_data(k_init)))
    starts_a, starts_b = [], []
    for _ in range(inits):
        w = rng.normal(0, weight_scale, genome.n_params)
        starts_a.append(genome.with_weights(w))
        # The pruned network starts from the same draw on the genes it kept.
        starts_b.append(current.with_weights(w[_kept_genes(genome, current)]))
    config = ExploitConfig(
        sigma0=sigma0,
        max_iters=iters,
        chunk=min(iters, 500),
        patience=iters,
        sigma_tol=0.0,
        tolfun=None,
        sigma_up=1e30,
        bound_patience=iters + 1,
        max_condition=max_condition,
        dtype=dtype,
        lazy_eigen=0.0,  # cond(C) is recorded per iteration: decompose every iteration
    )
    res = tune(starts_a + starts_b, task, key=k_run, config=config, pad_count=False)
    cond = np.asarray(res.history.cond, np.float64).T  # [runs, iters]
    before, after = cond[:inits], cond[inits:]
    evolved = None
    if evolved_warmup > 0:
        evolved = _from_evolved(
            genome, current, task, jax.random.fold_in(k_run, 1), config, inits, evolved_warmup,
            prune_sigma0,
        )  # fmt: skip
    return {
        "before": before.tolist(),
        "after": after.tolist(),
        "peak_before": before.max(axis=1).tolist(),
        "peak_after": after.max(axis=1).tolist(),
        "cost_before": res.costs[:inits],
        "cost_after": res.costs[inits:],
        "size_before": genome.n_params,
        "size_after": current.n_params,
        "genome_before": str(genome),
        "genome_after": str(current),
        "dtype": dtype,
        "max_condition": max_condition,
        "removed": removed,
        "evolved": evolved,
    }


def _from_evolved(genome, pruned, task, key, config, inits, warmup, sigma0) -> dict:
    """The condition experiment continuing from an evolved covariance (see
    `condition_experiment`): rows ``[0, inits)`` the original network, rows
    ``[inits, 2 inits)`` the same states with the pruned genes removed."""
    kept = _kept_genes(genome, pruned)
    w = np.zeros(genome.n_params)
    w[kept] = pruned.weights
    warm = config.replace(sigma0=sigma0, max_iters=warmup, patience=warmup + 1, tolfun=None)
    # Row i and row inits + i share their key: the same evolution up to the branch, the
    # same random numbers after it.
    keys = jax.random.split(key, inits)
    prep = prepare([genome] * (2 * inits), task, key=key, config=warm,
                   keys=jnp.concatenate([keys, keys]), pad_count=False)  # fmt: skip
    st, _ = run_engine(prep.state, prep.batch.layout, task, key=key, config=warm)
    p = prep.batch.bucket.genes
    remove = np.zeros((2 * inits, p), bool)
    remove[inits:, : genome.n_params] = ~np.isin(np.arange(genome.n_params), kept)
    means = np.asarray(st.cma.mean).copy()
    means[inits:, : genome.n_params] = w
    cma, params = jax.jit(reduce)(
        st.cma, st.params, jnp.asarray(remove), jnp.asarray(means, st.cma.mean.dtype),
        jnp.full(2 * inits, jnp.inf),
    )  # fmt: skip
    branch = jnp.arange(2 * inits) >= inits
    st = st.replace(
        cma=where_rows(branch, cma, st.cma),
        params=where_rows(branch, params, st.params),
        stop=jnp.zeros_like(st.stop),
        since_improve=jnp.zeros_like(st.since_improve),
    )
    go_on = config.replace(max_iters=warmup + config.max_iters, patience=warmup + config.max_iters)
    st, hist = run_engine(st, prep.batch.layout, task, key=jax.random.fold_in(key, 1),
                          config=go_on)  # fmt: skip
    cond = np.asarray(hist.cond, np.float64).T
    before, after = cond[:inits], cond[inits:]
    best = np.asarray(st.cma.best_cost, np.float64)
    return {
        "warmup": warmup,
        "before": before.tolist(),
        "after": after.tolist(),
        "peak_before": before.max(axis=1).tolist(),
        "peak_after": after.max(axis=1).tolist(),
        "cost_before": best[:inits].tolist(),
        "cost_after": best[inits:].tolist(),
    }


def _kept_genes(original: Genome, pruned: Genome) -> np.ndarray:
    """`eant2_jax.pruning.kept_genes`, refusing a genome that is not a pruned copy."""
    kept = kept_genes(original, pruned)
    if len(kept) != len(pruned):
        raise ValueError("the pruned genome is not a sub-sequence of the original")
    return np.asarray(kept, np.int64)


def arm_config(base: EANT2Config, arm: str) -> EANT2Config:
    """The configuration of one arm of `reproduce`: a pruner's name (``none``,
    ``covariance``, ``obs``, ...) with the default tentative attempt, or ``NAME-literal``
    for that pruner under the paper's rule as written (`ExploitConfig.literal`)."""
    name, _, variant = arm.partition("-")
    if name not in PRUNERS or variant not in ("", "literal") or (name == "none" and variant):
        known = ", ".join(p for p in PRUNERS) + " (and NAME-literal)"
        raise ValueError(f"unknown arm {arm!r}; arms are {known}")
    options = {"pruner": name}
    if variant == "literal":
        options.update(prune_refit=0, prune_reference="mean", prune_at_stop=False)
    return dataclasses.replace(base, exploit=dataclasses.replace(base.exploit, **options))


def reproduce(
    task: Task,
    out: str | Path,
    *,
    task_meta: dict,
    runs: int = 10,
    generations: int = 15,
    pruners: Sequence[str] = ("covariance",),
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
    _resume: bool = False,
) -> Path:
    """Run the paper's experiments and write the report.

    The settings go first into ``out/reproduce.json``; a reproduction that was killed (or
    crashed) goes on with `resume_reproduction` (``eant2 resume OUT``), losing at most each
    run's current generation.

    Args:
      task: the task (the paper's: ``tasks.make("servo")``).
      out: a new directory (must not exist or be empty); it receives one run directory per
        arm and seed (``ARM-sSEED``), ``condition.json`` and ``report/``.
      task_meta: ``{"task": name, "task_options": {...}}`` stored with each run.
      runs: runs per arm (seeds ``seed .. seed+runs-1``; the same seeds in every arm).
      generations: generations per run.
      pruners: the pruning arms; an arm without pruning (``none``) is always added.
      config: base EANT2 configuration (its pruner is set per arm).
      seed: first seed.
      devices: devices to spread the runs over (see `eant2_jax.run_many`).
      workers_per_device: concurrent runs per device (overlaps one run's host work with
        another's device work).
      lockstep: an arm's runs go in lock-step, each generation of all of them tuned in one
        batch (`eant2_jax.run_lockstep`; one group per device); False: each run alone, in
        ``workers_per_device`` threads per device. On one H100 the servo arm took 485 s in
        lock-step against 510 s in threads (docs/benchmarks.md); a run then shares its
        padding bucket with its arm.
      condition: also run the V.A condition experiment.
      condition_iters: CMA-ES budget of each run of that experiment from random weights.
      condition_inits: random initialisations of each network in it.
      condition_dtype: the CMA-ES state's dtype in it; ``float64`` turns on JAX's x64 mode
        for that experiment alone (``jax.enable_x64``, once the evolution runs are done:
        they stay in float32).
      overlap_condition: run the condition experiment in a background thread while the
        pruning arms run (the arm without pruning goes first: the experiment starts from its
        best network), and the baselines' costs while the first arm runs. The experiment is
        a chain of small, latency-bound programs that leaves an accelerator mostly idle, so
        the overlap hides most of it (81 s of the default reproduction on an H100); the
        results are the same either way. ``None`` (default): on unless the default backend
        is a CPU, where two programs at once can deadlock XLA's CPU thread pool
        (`eant2_jax.multirun`).
      callback: progress events: ``generation`` events with ``run`` and ``arm``; a
        ``condition`` event with ``phase`` ``"start"`` or ``"done"`` (and ``wall_s``).

    Returns:
      The path of ``report/report.md``.
    """
    out = Path(out)
    base = config or EANT2Config()
    arms = [p for p in pruners if p != "none"] + ["none"]
    jobs = [(arm, seed + i) for arm in arms for i in range(runs)]
    configs = [arm_config(base, arm) for arm, _ in jobs]
    dirs = [out / f"{arm}-s{s}" for arm, s in jobs]
    if not _resume:
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise RunDirError(
                f"{out} already exists and is not an empty directory; not overwriting"
            )
        manifest = {
            "version": _MANIFEST_VERSION,
            "task_meta": task_meta,
            "runs": runs,
            "generations": generations,
            "pruners": list(pruners),
            "config": base.to_dict(),
            "seed": seed,
            "devices": devices,
            "workers_per_device": workers_per_device,
            "lockstep": lockstep,
            "condition": condition,
            "condition_iters": condition_iters,
            "condition_inits": condition_inits,
            "condition_dtype": condition_dtype,
        }
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")  # whole or absent
    t0 = time.perf_counter()

    def progress(event):
        if callback is not None:
            callback({**event, "arm": jobs[event["run"]][0]})

    if overlap_condition is None:
        overlap_condition = jax.default_backend() != "cpu"
    done = out / "condition.json"
    cond_cached = condition and _resume and done.is_file()  # written whole, at its end
    background: _Background | None = None
    # The reference controllers' costs need nothing from the runs: with the overlap they
    # are computed in the background while the first arm runs.
    reporting = isinstance(task, ReportingTask)
    baselines = None
    if reporting and overlap_condition:
        baselines = _Background("eant2-baselines", task.baselines)

    def run_condition(best: Genome) -> dict:
        """The condition experiment (V.A) on ``best``; writes ``condition.json``."""
        t = time.perf_counter()
        if callback is not None:
            callback({"event": "condition", "phase": "start", "size": best.n_params})
        # x64 for this experiment alone: the mode is global JAX state (thread-local under
        # this context manager), and the evolution runs, and a run started after this call
        # (a second reproduction in one process), must not see it.
        x64 = jax.enable_x64(True) if condition_dtype == "float64" else contextlib.nullcontext()
        with x64:
            result = condition_experiment(
                best,
                task,
                key=jax.random.key(seed + 10_000),
                iters=condition_iters,
                # The pruning rounds from the tuned weights need no more than the runs from
                # random weights (and a short setting stays short).
                prune_iters=min(condition_iters, 2000),
                inits=condition_inits,
                dtype=condition_dtype,
            )
        write_atomic(done, json.dumps(result) + "\n")
        if callback is not None:
            callback({"event": "condition", "phase": "done", "wall_s": time.perf_counter() - t})
        return result

    results: list = [None] * len(jobs)
    # The arm without pruning runs first: the condition experiment needs its best network
    # and can then overlap the other arms. The order changes no result (each run has its
    # own key) and not the report's (``jobs``' order).
    order = ["none"] + [a for a in arms if a != "none"]
    if lockstep and not _resume and len(chosen_devices(devices)) == 1:
        # Each later arm is one lock-step group: its generation-0 program (10-12 s of
        # compiling on an H100) compiles in the background while the first arm runs.
        for arm in order[1:]:
            first = next(i for i, (a, _) in enumerate(jobs) if a == arm)
            key = jax.eval_shape(jax.random.key, jobs[first][1])
            compile_first_ahead(task, key, configs[first], runs=runs)
    for arm in order:  # one meta per arm
        idx = [i for i, (a, _) in enumerate(jobs) if a == arm]
        arm_results = run_many(
            task,
            [jax.random.key(jobs[i][1]) for i in idx],
            config=[configs[i] for i in idx],
            generations=generations,
            outs=[str(dirs[i]) for i in idx],
            devices=devices,
            workers_per_device=workers_per_device,
            callback=None
            if callback is None
            else (lambda e, idx=idx: progress({**e, "run": idx[e["run"]]})),
            meta={**task_meta, "arm": arm},
            resume=_resume,
            lockstep=lockstep,
        )
        for i, r in zip(idx, arm_results, strict=True):
            results[i] = r
        if arm == "none" and condition and not cond_cached and overlap_condition:
            background = _Background(
                "eant2-condition", run_condition, _best_unpruned(jobs, results)
            )
    wall = time.perf_counter() - t0
    extra: dict = {"wall_s": wall, "device": jax.devices()[0].device_kind}
    if _resume:
        extra["resumed"] = True
    if reporting:
        extra["baselines"] = task.baselines() if baselines is None else baselines.result()
        gen: dict[str, list[float]] = {}
        # All best networks in one padded batch: one program, where one per network's shape
        # took about 20 s of compiling on an H100 (14.5 s against 2.4 s on a 2-core CPU).
        # Padding changes a float32 sum's order, not its terms: on the networks of the H100
        # reproduction the costs moved by at most 5.6e-9 (about 2e-7 relative).
        nets = networks([r.best for r in results], task.n_inputs)
        costs = np.asarray(task.generalisation(nets), np.float64)
        for (arm, _), c in zip(jobs, costs, strict=True):
            gen.setdefault(arm, []).append(float(c))
        extra["generalisation"] = gen
    cond = None
    if cond_cached:
        cond = json.loads(done.read_text(encoding="utf-8"))
    elif background is not None:
        cond = background.result()
    elif condition:
        cond = run_condition(_best_unpruned(jobs, results))
    extra["notes"] = _claims(dirs, cond)
    return report([str(d) for d in dirs], out / "report", extra=extra, condition=cond)


def _best_unpruned(jobs: Sequence[tuple[str, int]], results: Sequence) -> Genome:
    """The best network of the arm without pruning (by its last generation's cost)."""
    unpruned = [r for (arm, _), r in zip(jobs, results, strict=True) if arm == "none"]
    return min(unpruned, key=lambda r: r.generations[-1].best_cost).best


class _Background:
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


def resume_reproduction(out: str | Path, *, callback: Callable[[dict], None] | None = None) -> Path:
    """Finish a reproduction that `reproduce` started in ``out`` and that was stopped: with
    the settings of its ``reproduce.json``, finished runs are read back, interrupted ones
    resume from their last complete generation, missing ones start, then the condition
    experiment (unless its result is there) and the report follow. The result equals an
    uninterrupted reproduction's where a resumed run equals an uninterrupted one (on a CPU,
    or a GPU with deterministic ops).

    Raises:
      RunDirError: ``out`` holds no readable reproduction.
    """
    from .. import tasks

    out = Path(out)
    path = out / MANIFEST
    try:
        m = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise RunDirError(f"{out}: not a reproduction ({MANIFEST}: {e})") from None
    keys = ("task_meta", "runs", "generations", "pruners", "config", "seed", "devices",
            "workers_per_device", "condition", "condition_iters", "condition_inits",
            "condition_dtype")  # fmt: skip
    if (
        not isinstance(m, dict)
        or m.get("version") != _MANIFEST_VERSION
        or any(k not in m for k in keys)
    ):
        raise RunDirError(
            f"{path}: not a reproduce.json of version {_MANIFEST_VERSION} with {', '.join(keys)}"
        )
    meta = m["task_meta"]
    task = tasks.make(meta["task"], **meta["task_options"])
    return reproduce(
        task,
        out,
        task_meta=meta,
        config=EANT2Config.from_dict(m["config"], complete=True),
        callback=callback,
        _resume=True,
        # Reproductions written before lock-step existed ran each run alone.
        lockstep=bool(m.get("lockstep", False)),
        **{k: m[k] for k in keys if k not in ("task_meta", "config")},
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
        same = v["p_fitness"] is None or v["p_fitness"] > 0.05
        lines.append(
            f"- **Size reduction at equal fitness ({arm})**: size {v['size_mean']:.1f} vs "
            f"{none['size_mean']:.1f} without pruning ({v['size_reduction_pct']:.1f}% smaller; "
            f"paper: 59.8 vs 73.6, 23%); fitness {v['fitness_mean']:.4g} vs "
            f"{none['fitness_mean']:.4g} (paper: -0.2277 vs -0.2267); "
            + ("no significant fitness difference" if same else "the fitness DIFFERS")
            + (f" (p = {v['p_fitness']:.3g})." if v["p_fitness"] is not None else ".")
        )
    if cond is not None:
        before = float(np.median(cond["peak_before"]))
        after = float(np.median(cond["peak_after"]))
        lines.append(
            f"- **Better conditioning**: over {len(cond['peak_before'])} random initialisations "
            f"({cond['dtype']} CMA-ES state, bound {cond['max_condition']:.0e}), the median "
            f"peak cond(C) was {before:.3g} for the original network and {after:.3g} for the "
            f"pruned one, {before / after:.3g}x (paper: 1.8e17 vs 9e13, one run each); "
            + (
                "pruning lowered it at least 100x."
                if after * 100 <= before
                else "pruning lowered it, but less than 100x."
                if after < before
                else "pruning did NOT lower it."
            )
        )
    return "\n".join(lines)
