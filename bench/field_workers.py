"""The field protocol's processes: one training run per (environment, seed, method), each in
a fresh process timed from its start, and one judging process per (environment, seed) that
puts both methods' networks through the champion rule on one task object
(bench/field_champions.py). ``python -m bench.field_workers train|judge ...``; the
orchestration is bench/field_protocol.py.

A training run writes its JSON after every generation (a killed run keeps what it measured):
``curve`` (per generation: evaluations, wall seconds from process start, best training
return, the archive of `TOP` candidates as ``[id, training return]``), ``candidates`` (id ->
the network: eant2_jax's genome text, TensorNEAT's node and connection rows) and ``kind``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import field_tnstate
from bench.field_settings import (
    ENVS,
    NORM_EPISODES,
    NORM_SEED,
    NORMALIZE,
    SPARE_ROWS,
    TOP,
    budgets,
)

__all__ = [
    "Log",
    "eant2_config",
    "judge",
    "main",
    "method_networks",
    "protocol_task",
    "resume_log",
    "train_eant2",
]


class Log:
    """A result file rewritten whole after every point; ``paused`` seconds (the protocol's
    own bookkeeping inside a run) are left out of the wall times."""

    def __init__(self, path: str | Path, t0: float, meta: dict):
        self.path, self.t0, self.paused = Path(path), t0, 0.0
        self.data = {**meta, "curve": [], "done": False}

    def wall(self) -> float:
        return time.time() - self.t0 - self.paused

    def point(self, **point: Any) -> None:
        self.data["curve"].append({"wall_s": self.wall(), **point})
        self.write()

    def write(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data))
        os.replace(tmp, self.path)


def protocol_task(env: dict[str, Any], episodes: int, normalize: str | None = None):
    """The environment's task object with eant2_jax's input convention: its frozen one
    (`ENVS`: gymnax's ``normalize``, brax's raw observations) or a trial's ``normalize``
    (``"random"``: statistics of `NORM_EPISODES` random-policy episodes from
    ``jax.random.key(NORM_SEED)``, frozen into the task; docs/protocol.md section 8)."""
    from eant2_jax import tasks

    options: dict[str, Any] = {"episodes": episodes, "max_steps": env["max_steps"]}
    if env["family"] == "gymnax":
        options["normalize"] = env["eant2"]["normalize"]
    else:
        options["backend"] = env["backend"]
    if normalize is not None:
        options["normalize"] = normalize
    if options.get("normalize") == "random":
        options.update(norm_episodes=NORM_EPISODES, norm_seed=NORM_SEED)
    return tasks.make(f"{env['family']}:{env['name']}", **options)


def eant2_config(env: dict[str, Any], *, budget: int, population: int | None = None,
                 max_iters: int | None = None, width: int | None = None,
                 spare_rows: str | None = None):  # fmt: skip
    """The protocol's `eant2_jax.EANT2Config` for ``env`` (its frozen settings), a trial's
    ``population``, ``max_iters``, ``width`` or ``spare_rows`` in their place where given
    (``width`` sets ``ExploitConfig.width`` and leaves the popsize to its rule; so does the
    settings' ``width``, where they have one)."""
    import eant2_jax

    s = env["eant2"]
    exploit = eant2_jax.ExploitConfig(
        pruner=s["pruner"], max_iters=max_iters or s["max_iters"], rescore=s["rescore"],
        popsize=None if width else s["popsize"], width=width or s["width"],
        spare_rows=spare_rows or s.get("spare_rows", "idle"),
    )  # fmt: skip
    return eant2_jax.EANT2Config(
        population=population or s["population"], max_evaluations=budget,
        reexploit=s["reexploit"], inherit_search=s["reexploit"],
        min_bucket=tuple(s["min_bucket"]) if s["min_bucket"] else None, stop_when_solved=False,
        exploit=exploit,
    )  # fmt: skip


def train_eant2(env: dict[str, Any], *, seed: int, budget: int, log: Log, top: int = TOP,
                population: int | None = None, max_iters: int | None = None,
                width: int | None = None, rundir: str | Path | None = None,
                normalize: str | None = None, spare_rows: str | None = None) -> None:  # fmt: skip
    """The protocol's eant2_jax run: ``eant2_jax.run`` with the frozen settings; after each
    generation its population after selection (read from the run directory, the time not
    counted) offered to the archive.

    With ``rundir`` the run directory is kept there, and a run whose directory holds a
    committed generation goes on from it (``eant2_jax.resume``, the same run to the bit)
    with ``log`` as `resume_log` reopened it: a run longer than one device call finishes
    over several. Its wall times go on from the last one logged, so the cold start of each
    new process counts against it."""
    import jax

    import eant2_jax
    from bench.field_champions import Archive
    from eant2_jax import checkpoint

    task = protocol_task(env, env["episodes"], normalize)
    config = eant2_config(env, budget=budget, population=population, max_iters=max_iters,
                          width=width, spare_rows=spare_rows)  # fmt: skip
    log.data.update(kind="eant2", settings=config.to_dict())
    if normalize is not None:
        log.data["normalize"] = normalize
    archive, candidates = Archive(top), log.data.setdefault("candidates", {})
    curve = log.data["curve"]
    for ident, fitness in curve[-1]["archive"] if curve else []:
        archive.offer(ident, fitness)

    def offer(out: str, generation: int, evaluations: int, size: int | None) -> None:
        t = time.time()
        for ind in checkpoint.validate(out, lock=False).state.population:
            text = str(ind.genome)
            if archive.offer(text, -float(ind.cost)):
                candidates.setdefault(text, text)
        log.paused += time.time() - t
        log.point(generation=generation, evaluations=evaluations, train_return=archive.best(),
                  size=size, archive=archive.entries())  # fmt: skip

    def on_event(e: dict) -> None:
        if e["event"] == "generation":
            offer(out, e["generation"], e["evaluations"], e["best_size"])

    with contextlib.ExitStack() as stack:
        if rundir is None:
            out = str(Path(stack.enter_context(tempfile.TemporaryDirectory())) / "run")
        else:
            out = str(rundir)
        state = _committed(out)
        if state is None:
            shutil.rmtree(out, ignore_errors=True)  # nothing committed: from the start
            eant2_jax.run(task, key=jax.random.key(seed), config=config, generations=10**9,
                          out=out, callback=on_event)  # fmt: skip
        else:
            if not curve or state.generation > curve[-1]["generation"]:
                offer(out, state.generation, state.evaluations, None)  # committed, not logged
            eant2_jax.resume(out, task, callback=on_event)
    keep = {i for p in log.data["curve"] for i, _ in p["archive"]}
    log.data["candidates"] = {i: g for i, g in candidates.items() if i in keep}


def _committed(out: str):
    """The run directory's committed state, or None (no directory, nothing committed)."""
    from eant2_jax import checkpoint
    from eant2_jax.rundir import RunDirError

    if not Path(out).is_dir():
        return None
    try:
        return checkpoint.validate(out, lock=False).state
    except RunDirError:
        return None


def resume_log(path: str | Path, t0: float, meta: dict) -> Log:
    """A training run's log, reopened from ``path`` when a killed process left it: its
    curve and candidates kept, its wall times going on from the last one logged."""
    log = Log(path, t0, meta)
    if Path(path).is_file():
        before = json.loads(Path(path).read_text())
        if before.get("curve"):
            last = before["curve"][-1]["wall_s"]
            log.paused = -last
            log.data.update(curve=before["curve"], candidates=before.get("candidates", {}),
                            resumed_at_s=[*before.get("resumed_at_s", []), last])  # fmt: skip
    return log


def method_networks(task, run: dict[str, Any]):
    """``(ids, nets)``: a training run's candidates as one batch of the library's networks."""
    ids = sorted(run["candidates"])
    if run["kind"] == "eant2":
        from eant2_jax.compiler import networks
        from eant2_jax.genome import Genome

        return ids, networks([Genome.parse(run["candidates"][i]) for i in ids], task.n_inputs)
    from bench.field_tnet import input_affine, stack, tensorneat_net

    n_in = task.n_inputs
    # A task that feeds raw observations has no affine (brax's obs_offset is None).
    lib_off, lib_scale = getattr(task, "obs_offset", None), getattr(task, "obs_scale", None)
    lib_off = np.zeros(n_in) if lib_off is None else np.asarray(lib_off)
    lib_scale = np.ones(n_in) if lib_scale is None else np.asarray(lib_scale)
    off, scale = input_affine(lib_off, lib_scale, run.get("obs_mean"), run.get("obs_std"))
    nets = [tensorneat_net(np.asarray(run["candidates"][i]["nodes"]).reshape(-1, 4),
                           np.asarray(run["candidates"][i]["conns"]).reshape(-1, 3),
                           n_inputs=n_in, n_outputs=task.n_outputs,
                           activations=run["activations"], in_offset=off, in_scale=scale)
            for i in ids]  # fmt: skip
    return ids, stack(nets)


def judge(env_name: str, runs: dict[str, dict[str, Any]], budget_list: list[int] | None = None,
          *, test_keys=None, normalize: str | None = None) -> dict[str, Any]:  # fmt: skip
    """Both methods' runs of one (environment, seed) under the champion rule, through one
    task object; refused when their test episodes start from different states.

    Args:
      runs: method -> its training run's JSON.
      budget_list: the reporting budgets (default: the protocol's, `budgets`).
      test_keys: method -> test key (default: the protocol's for all; a test's override).
      normalize: the trial's input convention eant2_jax trained with (`protocol_task`);
        TensorNEAT's networks take the task's inputs through `bench.field_tnet.input_affine`.
    """
    from bench.field_champions import Judge, check_same_starts, judge_run, starts_digest

    env = ENVS[env_name]
    task = protocol_task(env, 1, normalize)
    judges = {}
    for m, run in runs.items():
        if not run.get("curve"):
            continue
        ids, nets = method_networks(task, run)
        judges[m] = Judge(task, nets, ids, test_key=(test_keys or {}).get(m))
    drawn = {m: j.starts() for m, j in judges.items()}
    check_same_starts(drawn)
    out = {}
    for m, j in judges.items():
        out[m] = judge_run(j, runs[m]["curve"], budget_list or budgets(env))
        out[m]["starts_sha256"] = starts_digest(drawn[m])
    return out


def _train(args: argparse.Namespace) -> None:
    env = ENVS[args.env]
    meta = {"method": args.method, "env": args.env, "seed": args.seed}
    # A run goes on from its log where its rundir holds what it needs (eant2_jax's run
    # directory; TensorNEAT's kept state, else its run starts again).
    resumes = args.rundir is not None and (
        args.method == "eant2" or (Path(args.rundir) / field_tnstate.FILE).is_file()
    )
    log = resume_log(args.out, args.t0, meta) if resumes else Log(args.out, args.t0, meta)
    log.data.setdefault("start_s", log.wall())
    budget = env["tensorneat"]["pop_size"] * env["tensorneat"]["generations"]
    if args.generations:
        budget = (args.pop or env["tensorneat"]["pop_size"]) * args.generations
    log.data["budget"] = budget
    if args.method == "eant2":
        train_eant2(env, seed=args.seed, budget=budget, log=log, population=args.population,
                    max_iters=args.max_iters, width=args.width, rundir=args.rundir,
                    normalize=args.normalize, spare_rows=args.spare_rows)  # fmt: skip
    else:
        from bench.field_tensorneat import train

        task = protocol_task(env, 1)
        train(env, seed=args.seed, src=args.tensorneat, n_inputs=task.n_inputs,
              n_outputs=task.n_outputs, log=log, top=TOP, pop=args.pop,
              generations=args.generations, deadline_s=args.deadline_s,
              rundir=args.rundir)  # fmt: skip
    log.data["done"] = True
    log.write()


def main(argv: list[str]) -> int:
    """``train --method M --env E --seed S --out F --t0 T [...]`` or ``judge --env E --out F
    --budgets B ... --runs RUN.json ...``."""
    p = argparse.ArgumentParser(prog="python -m bench.field_workers")
    p.add_argument("what", choices=("train", "judge"))
    p.add_argument("--env", choices=sorted(ENVS), required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--method", default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--t0", type=float, default=None)
    p.add_argument("--tensorneat", default=None)
    p.add_argument("--pop", type=int, default=None, help="a trial's TensorNEAT population")
    p.add_argument("--generations", type=int, default=None, help="a trial's TN generations")
    p.add_argument("--population", type=int, default=None, help="a trial's eant2 population")
    p.add_argument("--max-iters", type=int, default=None, help="a trial's eant2 iterations")
    p.add_argument("--width", type=int, default=None, help="a trial's eant2 batch width")
    p.add_argument("--normalize", choices=NORMALIZE, default=None,
                   help="a trial's eant2 input convention (protocol_task)")  # fmt: skip
    p.add_argument("--spare-rows", choices=SPARE_ROWS, default=None,
                   help="a trial's eant2 ExploitConfig.spare_rows")  # fmt: skip
    p.add_argument("--deadline-s", type=float, default=math.inf)
    p.add_argument("--rundir", default=None, help="keep (and go on from) the run's state here")
    p.add_argument("--budgets", type=int, nargs="+", default=None, help="reporting budgets")
    p.add_argument("--runs", nargs="+", default=[], help="the training runs' JSON files")
    args = p.parse_args(argv)
    if args.what == "train":
        _train(args)
        return 0
    runs = {}
    for path in args.runs:
        run = json.loads(Path(path).read_text())
        runs[run["method"]] = run
    judged = judge(args.env, runs, args.budgets, normalize=args.normalize)
    Path(args.out).write_text(json.dumps(judged))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
