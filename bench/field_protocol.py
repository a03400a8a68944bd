"""``python -m bench field --protocol``: the field comparison as docs/protocol.md section 3
fixes it, with the frozen settings of bench/field_settings.py.

Per environment and seed: eant2_jax's and TensorNEAT's training runs, each in a fresh
process without a compilation cache and timed from its start (bench/field_workers.py), then
one judging process that puts both methods' candidates through the champion rule on one
task object (bench/field_champions.py). Each seed's judged record is appended to the
checkpoint (``--checkpoint``, default beside the result file: ``...checkpoint.jsonl``), and a
finished training run is kept in ``...checkpoint.jsonl.runs/`` until its seed is judged;
``--resume --force`` skips the seeds and runs already there. Each run keeps its state there
too (eant2_jax's run directory; TensorNEAT's state after each generation,
bench/field_tnstate.py), and a killed one goes on from its last generation (a device call's
time limit loses at most that), so a run longer than one call finishes over several. The summary
(bench/field_stats.py) and the result file ``bench/results/field-protocol-<device>.{json,md}``
are rewritten after every seed.

With ``--peer-runs DIR`` TensorNEAT's finished runs are also copied into DIR (kept there when
their seed is judged), and a later call with the same DIR judges a run found there, made with
the same TensorNEAT settings, in place of training TensorNEAT again (bench/field_peers.py):
the width candidates of docs/protocol.md section 6 train TensorNEAT once per seed. The
result file names the runs it reused (``reused_peer_runs``).

Without overrides it runs the protocol's seeds (4000-4009 gymnax, 4000-4004 brax). Any of
``--seeds/--first-seed/--budget/--population/--max-iters/--width/--tensorneat-pop`` makes it a
**trial**: written to ``field-protocol-trial-<device>`` and labelled as not the protocol's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bench import field_peers, harness
from bench.common import BenchInputError, default_out, environment
from bench.field_settings import ENVS, budgets, env_seeds, table

__all__ = [
    "METHODS",
    "add_options",
    "call_settings",
    "hold_no_device_memory",
    "prepare",
    "protocol_child_env",
    "render",
    "run",
    "trial_overrides",
]

TRIAL = ("budget", "population", "max_iters", "width", "normalize", "spare_rows", "tensorneat_pop")
# Trial options added after checkpoints existed: left out of a call's settings while unset,
# so that a checkpoint written before them still matches the call that resumes it.
_LATER = ("width", "normalize", "spare_rows")


def _tensorneat_size(args: argparse.Namespace, env: str) -> tuple[int, int]:
    """TensorNEAT's population and generations: the frozen ones, or a trial's ``--budget``
    (with ``--tensorneat-pop``, which alone changes nothing)."""
    tn = ENVS[env]["tensorneat"]
    if not args.budget:
        return tn["pop_size"], tn["generations"]
    pop = args.tensorneat_pop or tn["pop_size"]
    return pop, max(1, args.budget // pop)


def _train_argv(method: str, args: argparse.Namespace, env: str, seed: int, out: Path) -> list:
    argv = [sys.executable, "-m", "bench.field_workers", "train", "--method", method, "--env",
            env, "--seed", str(seed), "--out", str(out)]  # fmt: skip
    if args.budget:
        pop, generations = _tensorneat_size(args, env)
        argv += ["--pop", str(pop), "--generations", str(generations)]
    eant2 = (("--population", args.population), ("--max-iters", args.max_iters),
             ("--width", args.width), ("--normalize", args.normalize),
             ("--spare-rows", args.spare_rows))  # fmt: skip
    for flag, v in eant2:
        if v is not None and method == "eant2":
            argv += [flag, str(v)]
    if method == "tensorneat":
        argv += ["--tensorneat", str(args.tensorneat)]
    # Kept beside its log: a killed run goes on from it (eant2_jax's run directory,
    # TensorNEAT's state after its last generation: bench/field_tnstate.py).
    argv += ["--rundir", str(out.with_suffix(".rundir"))]
    return argv


# method -> argv of its training process; a test may add a stand-in with the same outputs.
METHODS = {"eant2": _train_argv, "tensorneat": _train_argv}


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--protocol", action="store_true", help="docs/protocol.md section 3")
    p.add_argument("--checkpoint", default=None,
                   help="--protocol: per-seed records (default: beside --out)")  # fmt: skip
    p.add_argument("--resume", action="store_true",
                   help="--protocol: skip the seeds and runs the checkpoint holds "
                        "(with --force)")  # fmt: skip
    p.add_argument("--peer-runs", default=None, metavar="DIR",
                   help="--protocol: share TensorNEAT's finished training runs through DIR "
                        "(reused where made with the same settings)")  # fmt: skip


def trial_overrides(args: argparse.Namespace) -> list[str]:
    given = [f"--{k.replace('_', '-')}" for k in TRIAL if getattr(args, k, None) is not None]
    if args.seeds is not None or args.first_seed is not None:
        given.append("--seeds/--first-seed")
    return given


def prepare(args: argparse.Namespace) -> None:
    """Check a ``--protocol`` call and fill its defaults (one line naming a bad option)."""
    if args.quick:
        raise BenchInputError("--protocol has no --quick sizes: a trial names --budget etc.")
    args.envs = args.envs or list(ENVS)
    bad = [e for e in args.envs if e not in ENVS]
    if bad:
        raise BenchInputError(f"--protocol runs {', '.join(ENVS)}; not {', '.join(bad)}")
    for name in ("seeds", "budget", "population", "max_iters", "width", "tensorneat_pop"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise BenchInputError(f"--{name.replace('_', '-')} must be at least 1")
    if args.first_seed is not None and args.first_seed < 0:
        raise BenchInputError("--first-seed must be at least 0")
    args.trial = bool(trial_overrides(args))
    if args.out is None:
        args.out = str(default_out("field-protocol-trial" if args.trial else "field-protocol"))
    if args.checkpoint is None:
        args.checkpoint = str(Path(args.out).with_suffix("")) + ".checkpoint.jsonl"
    if Path(args.checkpoint).exists() and not args.resume:
        raise BenchInputError(f"{args.checkpoint} exists: --resume --force goes on from it")
    if args.peer_runs is not None and Path(args.peer_runs).exists():
        if not Path(args.peer_runs).is_dir():
            raise BenchInputError(f"--peer-runs must name a folder, got {args.peer_runs}")


def _seeds(args: argparse.Namespace, env: str) -> list[int]:
    if args.seeds is None and args.first_seed is None:
        return env_seeds(env)
    first = 0 if args.first_seed is None else args.first_seed
    return list(range(first, first + (args.seeds or len(env_seeds(env)))))


def _budgets(args: argparse.Namespace) -> dict[str, list[int]]:
    if not args.budget:
        return {e: budgets(ENVS[e]) for e in args.envs}
    out = {}
    for e in args.envs:
        pop = args.tensorneat_pop or ENVS[e]["tensorneat"]["pop_size"]
        total = pop * max(1, args.budget // pop)
        out[e] = [round(f * total) for f in (0.25, 0.5, 1.0)]
    return out


def call_settings(args: argparse.Namespace) -> dict[str, Any]:
    """What a checkpoint must share with the call that resumes it: the frozen settings, the
    call's options and its seeds (not ``--peer-runs``: a reused run is the run it would
    train, and each record names its reused runs)."""
    keep = ("envs", "methods", "seeds", "first_seed", *TRIAL)
    given = {k: getattr(args, k) for k in keep if k not in _LATER or getattr(args, k) is not None}
    return {"frozen": table(args.envs), "args": given,
            "seed_lists": {e: _seeds(args, e) for e in args.envs}}  # fmt: skip


def _read_checkpoint(path: Path, settings: dict) -> list[dict]:
    """The checkpoint's seed records; refused if its settings are not this call's."""
    if not path.exists():
        return []
    lines = [json.loads(s) for s in path.read_text().splitlines() if s.strip()]
    if not lines or lines[0].get("settings") != json.loads(json.dumps(settings)):
        raise BenchInputError(f"{path} holds another call's settings; resume with the same ones")
    return lines[1:]


# The orchestrating process's own JAX (its bootstrap intervals) must not hold the device's
# memory while the training and judging processes run: with JAX's default preallocation it
# would take 75% of the GPU at its first array, and every later child would run out of memory.
_PREALLOCATE = "XLA_PYTHON_CLIENT_PREALLOCATE"
CHILD_PREALLOCATE: list[str | None] = []  # the caller's own setting, for the children


def hold_no_device_memory() -> None:
    """Keep this process from preallocating device memory (call before JAX starts its
    backends); the child processes get the caller's setting back (`protocol_child_env`)."""
    if not CHILD_PREALLOCATE:
        CHILD_PREALLOCATE.append(os.environ.get(_PREALLOCATE))
    os.environ[_PREALLOCATE] = "false"


def protocol_child_env() -> dict[str, str]:
    """A training or judging process's environment: cold (no compilation cache), the
    caller's device-memory setting, this checkout last on ``PYTHONPATH``."""
    environ = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    if CHILD_PREALLOCATE:
        environ.pop(_PREALLOCATE, None)
        if CHILD_PREALLOCATE[0] is not None:
            environ[_PREALLOCATE] = CHILD_PREALLOCATE[0]
    environ["EANT2_CACHE_DIR"] = ""  # cold: no persistent compilation cache on either side
    # The checkout goes last, for `bench` alone (as bench_field's workers).
    environ["PYTHONPATH"] = os.pathsep.join(
        filter(None, [environ.get("PYTHONPATH", ""), str(Path(__file__).resolve().parents[1])])
    )
    return environ


def _call(argv: list[str], timeout: float) -> str:
    """Run a child process; its last stderr line if it failed, else ''."""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, env=protocol_child_env(),
                              timeout=timeout)  # fmt: skip
    except subprocess.TimeoutExpired:
        return f"killed after {timeout:.0f} s"
    if proc.returncode != 0:
        return (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]
    return ""


def _train(method, args, env, seed, runs: Path, device: dict) -> dict:
    out = runs / f"{env}-s{seed}-{method}.json"
    share = args.peer_runs is not None and method == field_peers.METHOD
    if share:
        pop, generations = _tensorneat_size(args, env)
        want = field_peers.settings(env, seed, pop=pop, generations=generations,
                                    src=args.tensorneat, device=device)  # fmt: skip
    run = json.loads(out.read_text()) if out.is_file() else {}
    if not (run.get("done") or run.get("deadline")):  # else a finished (or stopped) run kept
        found = field_peers.find(args.peer_runs, env, seed, want) if share else None
        run = found or _launch(method, args, env, seed, out)
        if found:
            out.write_text(json.dumps(found))  # kept until judged, as a run trained here
    if share:
        field_peers.publish(args.peer_runs, run, want)
    return run


def _launch(method, args, env, seed, out: Path) -> dict:
    """A training run in its own process; the run's JSON with its ``process_s``."""
    t0 = time.time()
    err = _call([*METHODS[method](method, args, env, seed, out), "--t0", repr(t0)],
                args.deadline_s)  # fmt: skip
    run = json.loads(out.read_text()) if out.is_file() else {"method": method, "curve": []}
    run["process_s"] = time.time() - t0
    if err:
        # Stopped at --deadline-s: final, judged on the generations it completed.
        run["deadline" if err.startswith("killed after") else "error"] = err
    out.write_text(json.dumps(run))  # with process_s: a resuming call judges the same run
    return run


def _reused(records: list[dict]) -> list[dict]:
    """The training runs of ``records`` judged from a ``--peer-runs`` file."""
    return [{"env": r["env"], "seed": r["seed"], "method": m, "file": run["reused_from"]}
            for r in records for m, run in r["runs"].items() if run.get("reused_from")]  # fmt: skip


def judge_argv(args: argparse.Namespace, env: str, out: Path, budget_list: list[int],
               paths: list[Path]) -> list[str]:  # fmt: skip
    """The judging process's command: the runs ``paths`` at ``budget_list``, into ``out``,
    on the task eant2_jax trained on (a trial's ``--normalize``)."""
    argv = [sys.executable, "-m", "bench.field_workers", "judge", "--env", env,
            "--out", str(out), "--budgets", *map(str, budget_list), "--runs",
            *map(str, paths)]  # fmt: skip
    if args.normalize is not None:
        argv += ["--normalize", args.normalize]
    return argv


def _seed(args, env: str, seed: int, runs: Path, budget_list: list[int], device: dict) -> dict:
    trained = {m: _train(m, args, env, seed, runs, device) for m in args.methods}
    paths = [runs / f"{env}-s{seed}-{m}.json" for m in args.methods]
    judged_path = runs / f"{env}-s{seed}-judged.json"
    err = _call(judge_argv(args, env, judged_path, budget_list, paths), args.deadline_s)
    if err:
        raise BenchInputError(f"field protocol: judging {env} seed {seed} failed: {err}")
    judged = json.loads(judged_path.read_text())
    slim = {m: {k: v for k, v in r.items() if k != "candidates"} for m, r in trained.items()}
    for m, r in trained.items():  # the champions' networks, for the record
        champs = {b["champion"] for b in judged.get(m, {}).get("budgets", []) if b["champion"]}
        slim[m]["champions"] = {c: r["candidates"][c] for c in sorted(champs)}
    return {"env": env, "seed": seed, "runs": slim, "judged": judged}


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    from bench.field_stats import summarise

    settings = call_settings(args)
    ckpt = Path(args.checkpoint)
    records = _read_checkpoint(ckpt, settings) if args.resume else []
    if not ckpt.exists():
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        ckpt.write_text(json.dumps({"settings": settings}) + "\n")
    runs = Path(str(ckpt) + ".runs")
    runs.mkdir(exist_ok=True)
    all_budgets = _budgets(args)
    payload: dict[str, Any] = {"protocol": True, "trial": args.trial,
                               "overrides": trial_overrides(args), "environment": environment(),
                               "config": harness.settings(args), **settings,
                               "seeds": records, "reused_peer_runs": _reused(records)}  # fmt: skip
    done = {(r["env"], r["seed"]) for r in records}
    for env in args.envs:
        for seed in _seeds(args, env):
            if (env, seed) in done:
                continue
            harness.log(f"field protocol: {env} seed {seed}")
            rec = _seed(args, env, seed, runs, all_budgets[env], payload["environment"])
            with ckpt.open("a") as f:
                f.write(json.dumps(rec) + "\n")
            for m in args.methods:
                (runs / f"{env}-s{seed}-{m}.json").unlink(missing_ok=True)
                shutil.rmtree(runs / f"{env}-s{seed}-{m}.rundir", ignore_errors=True)
            payload["seeds"].append(rec)
            payload["reused_peer_runs"] = _reused(payload["seeds"])
            payload["summary"] = summarise(payload["seeds"], all_budgets)
            save(payload)
    payload["summary"] = summarise(payload["seeds"], all_budgets)
    return payload


def render(payload: dict[str, Any]) -> str:
    from bench.field_stats import render_summary, seed_counts, summarise

    budgets_ = payload.get("frozen", {}).get("budgets", {})
    if payload.get("args", {}).get("budget"):
        budgets_ = {r["env"]: [] for r in payload["seeds"]}
        for r in payload["seeds"]:
            for m in r["judged"].values():
                budgets_[r["env"]] = [b["budget"] for b in m["budgets"]]
    rows = summarise(payload.get("seeds", []), budgets_)
    head = ""
    if payload.get("trial"):
        head = ("**A trial, not the protocol's result** (overrides: "
                f"{', '.join(payload.get('overrides', []))}).\n\n")  # fmt: skip
    frozen = "```json\n" + json.dumps(payload.get("frozen", {}), indent=1) + "\n```\n"
    note = ("Test return: the champion's mean over 100 episodes from jax.random.key(9000), the "
            "same initial states for both methods (checked); champion: the best on 10 "
            "validation episodes (key 8000) of each method's 5 best by training fitness. "
            "Medians with percentile bootstrap 95% intervals (10,000 resamples, key 0); "
            "difference: eant2_jax minus TensorNEAT, same seed; a win or loss needs its "
            "interval to exclude 0, else a tie. Seeds with eant2_jax >= TensorNEAT (issue "
            "41's 'on most seeds': more than half): at TensorNEAT's evaluation count, the "
            "last budget's champions; at TensorNEAT's wall time, eant2_jax's last judged "
            "champion at or before TensorNEAT's last judged champion, against it.\n")  # fmt: skip
    stopped = [f"{r['env']} seed {r['seed']} {m}: {run.get('error') or run.get('deadline')}"
               for r in payload.get("seeds", []) for m, run in r["runs"].items()
               if run.get("error") or run.get("deadline")]  # fmt: skip
    if stopped:
        note += "\nRuns stopped or failed (judged on what they completed):\n\n"
        note += "".join(f"* {line}\n" for line in stopped)
    reused = payload.get("reused_peer_runs", [])
    if reused:
        note += (
            "\nTraining runs judged from a `--peer-runs` file, not trained again (the same "
            "run, made with the same settings; its measured wall times):\n\n"
        )
        note += "".join(f"* {r['env']} seed {r['seed']} {r['method']}: {r['file']}\n"
                        for r in reused)  # fmt: skip
    counts = seed_counts(payload.get("seeds", []))
    return head + render_summary(rows, counts) + "\n" + note + "\nFrozen settings:\n\n" + frozen
