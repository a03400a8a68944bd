"""The neuro-evolution field: eant2_jax against TensorNEAT on gymnax and brax environments,
and on the paper's servo task.

Every (environment, seed, method) is one run **in a fresh process** with no persistent
compilation cache (cold on both sides), timed from just before that process starts. A run
stops after the generation in which it has spent ``--budget`` evaluations (or the
environment's default budget), or at ``--deadline-s`` seconds from its start.

* ``eant2``: this project, ``eant2_jax.run`` on ``tasks.make("gymnax:NAME")`` or
  ``tasks.make("brax:NAME")`` with covariance pruning, ``max_evaluations`` = the budget.
  Its settings per environment are in ``ENVS`` (``--population``/``--max-iters`` override;
  ``--quick`` runs no pruner, one episode of at most ``QUICK_MAX_STEPS`` steps per evaluation
  and the smallest padding bucket that fits).
* ``tensorneat``: TensorNEAT (EMI-Group/tensorneat; its source is fetched, never vendored:
  ``--tensorneat SRC``, the folder that holds the ``tensorneat`` package), NEAT with the
  settings of its own examples (``examples/gymnax/cartpole.py``, ``examples/brax/hopper.py``:
  population 1000, 20 species, survival threshold 0.1, compatibility threshold 1.0, tanh
  bias nodes with sum aggregation, no initial hidden layer), driven generation by generation
  through ``Pipeline.step`` (what ``Pipeline.auto_run`` jits). One generation = 1000
  evaluations.

**The same evaluation on both sides.** One evaluation is one network's mean return over the
environment's ``episodes`` episodes (TensorNEAT's ``repeat_times``), at most ``max_steps``
steps each, ended when the environment says done; the environment's own reward. Each
method keeps its own input and output conventions: eant2_jax maps bounded observation
dimensions to [-1, 1] (docs/tasks-custom.md; raw on Acrobot, ``Env.normalize``),
TensorNEAT feeds raw observations; a discrete
action is the argmax of one output per action on both; a continuous one is ``tanh`` of the
outputs scaled onto the action bounds on both. brax runs the same ``--backend`` on both.
On ``servo`` (the paper's task, deterministic: ``tasks.make("servo")``) TensorNEAT's
network outputs at the 1023 start measurements go through the task's own move and cost
(``peer_methods.outputs_cost``), and the "return" is minus the task's cost.

**What is compared.** After each generation a method has a champion: for eant2_jax the best
individual after selection, for TensorNEAT the genome of the highest training fitness seen
so far (what ``Pipeline`` keeps as ``best_genome``). Training fitness is optimistic on noisy
environments (the best of many candidates on a few episodes), so after the run every
distinct champion also plays ``--test-episodes`` new episodes (keys no run drew; not counted
as evaluations or wall time): the **test return**, the number every table and curve shows.
Per environment and seed the report gives each method's test return at the budget, its
network size (weights: connections plus biases), and the evaluations and wall time (from
process start) at which eant2_jax's champion first reached TensorNEAT's final test return.

Run: ``python -m bench field --tensorneat SRC [--envs cartpole acrobot ...] [--seeds 3]``;
``--methods eant2`` alone needs no TensorNEAT.

``--protocol``: the fair field comparison of docs/protocol.md section 3 instead (frozen
settings, one champion rule and one evaluator for both methods, medians with intervals,
resumable): bench/field_protocol.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import field_protocol, harness
from bench.common import BenchInputError, Column, eant2_pruner, environment, markdown_table
from bench.field_settings import NORMALIZE, SPARE_ROWS

__all__ = ["ENVS", "METHODS", "Env", "first_reaching", "main", "summarise"]
# The runs themselves: bench/field_runner.py; the learning curves: bench/field_figure.py.

METHODS = ("eant2", "tensorneat")


@dataclasses.dataclass(frozen=True)
class Env:
    """One environment of the suite.

    Attributes:
      family, name: ``gymnax`` or ``brax``, and the environment's id there.
      n_inputs, n_outputs: observation size, and actions (discrete) or action size.
      discrete: argmax over outputs (True) or a continuous action.
      action_scale: continuous actions are ``action_scale * tanh(y)`` (the action bounds).
      episodes: episodes per evaluation, both methods.
      max_steps: steps per episode at most.
      budget: default evaluation budget per run.
      population, max_iters: eant2_jax's settings for it.
      normalize: eant2_jax's gymnax input convention (`eant2_jax.tasks.gymnax_task`):
        ``"bounds"`` maps bounded observation dimensions to [-1, 1], ``"none"`` feeds them
        raw, as TensorNEAT does. Acrobot's velocity bounds (4 pi and 9 pi rad/s) lie far
        beyond an episode's velocities, so bound-scaling shrinks the input a good policy
        turns on (the direction of swing) by 10-30x: it runs raw.
      tensorneat: options of TensorNEAT's own example for it, where they differ from its
        cartpole/hopper examples: ``max_nodes``, ``max_conns``, ``activation`` (an
        ``ACT`` name) and ``obs_norm_episodes`` (observation normalisation from that many
        random-action episodes at setup, counted in its wall time, not in evaluations).
      min_bucket: eant2_jax's `EANT2Config.min_bucket`, the smallest padding bucket
        ``(neurons, genes, sweeps)``: sized for the networks a run reaches, so that it
        compiles its engine program once (as TensorNEAT pads every genome to its
        ``max_nodes``/``max_conns`` and compiles once); None grows buckets as needed.
      rescore: eant2_jax's `ExploitConfig.rescore` on these noisy tasks: fresh draws of the
        cost that score each tuned network (16: 80 gymnax episodes, a quarter of one
        episode's spread; the library's default 4 left the champion of a generation
        testing worse than the one before it, a winner's curse; a structure's 2 x 16
        draws are 2% of its CMA-ES evaluations).
      popsize: eant2_jax's CMA-ES population per structure (`ExploitConfig.popsize`; None:
        the default of the gene bucket, 4 + 3 ln n). On brax an iteration is a 1,000-step
        episode run step after step and a step costs about the same for 170 networks as for
        1,000 (TensorNEAT's batch), so a larger population buys evaluations at no wall time.
      reexploit: eant2_jax's ``reexploit`` and ``inherit_search`` together: surviving
        parents go on tuning each generation from their own CMA-ES state (a policy on a
        long-horizon task improves over many more iterations than one short generation
        gives; without it hopper's best structure stalled for 8 generations).
    """

    family: str
    name: str
    n_inputs: int
    n_outputs: int
    discrete: bool
    action_scale: float
    episodes: int
    max_steps: int
    budget: int
    population: int
    max_iters: int
    tensorneat: tuple[tuple[str, Any], ...] = ()
    normalize: str = "bounds"
    min_bucket: tuple[int, int, int] | None = (12, 64, 4)
    rescore: int = 16
    popsize: int | None = None
    reexploit: bool = False


# eant2_jax's settings shared by the brax rows (see Env).
_BRAX_EANT2 = {"min_bucket": (16, 96, 4), "reexploit": True}
ENVS = {
    "cartpole": Env("gymnax", "CartPole-v1", 4, 2, True, 1.0, 5, 500, 20_000, 10, 100),
    # Acrobot: 50 CMA-ES iterations per generation (its small networks converge within
    # them), so that its 20,000 evaluations hold three generations of selection, not one.
    "acrobot": Env(
        "gymnax", "Acrobot-v1", 6, 3, True, 1.0, 5, 500, 20_000, 10, 50, normalize="none"
    ),
    "pendulum": Env("gymnax", "Pendulum-v1", 3, 1, False, 2.0, 5, 200, 50_000, 10, 200),
    # brax: 10 CMA-ES iterations per generation, not 100. An iteration is a 1,000-step
    # episode run one step after another whatever the batch, so a generation's wall time
    # is its iterations; shorter ones report champions (and select structures) 10x as often.
    "hopper": Env(
        "brax", "hopper", 11, 3, False, 1.0, 1, 1000, 50_000, 10, 10, **_BRAX_EANT2, popsize=24
    ),
    # TensorNEAT's examples/brax/halfcheetah.py: bigger genomes, scaled tanh, normalisation.
    "halfcheetah": Env(
        "brax",
        "halfcheetah",
        17,
        6,
        False,
        1.0,
        1,
        1000,
        50_000,
        10,
        100,
        tensorneat=(
            ("max_nodes", 50),
            ("max_conns", 200),
            ("activation", "scaled_tanh"),
            ("obs_norm_episodes", 1000),
        ),
        min_bucket=(16, 192, 4),
        popsize=48,
        reexploit=True,
    ),
    # The paper's task (kinematic, one move from each of 1023 starts; deterministic): the
    # "return" is minus the task's cost. TensorNEAT's outputs go through the task's own
    # tanh step (peer_methods.outputs_cost), as eant2_jax's identity outputs do.
    "servo": Env("servo", "servo", 10, 3, False, 1.0, 1, 1, 200_000, 20, 1000, min_bucket=None),
}
TENSORNEAT_POP = 1000
QUICK = {"seeds": 1, "budget": 300, "deadline_s": 240.0,
         "test_episodes": 3, "population": 2, "max_iters": 8, "tensorneat_pop": 100}  # fmt: skip
QUICK_MAX_STEPS = 100  # --quick's episodes are at most this long (`quick_env`)


def quick_env(env: Env) -> Env:
    """``env`` as --quick runs it (its workers get --quick), a smoke test of the bookkeeping:
    one episode per evaluation, of at most `QUICK_MAX_STEPS` steps, and eant2_jax's smallest
    padding bucket that fits (no ``min_bucket``), so that its programs compile and run small."""
    return dataclasses.replace(
        env, episodes=1, max_steps=min(env.max_steps, QUICK_MAX_STEPS), min_bucket=None
    )


# ---------------------------------------------------------------------------- the parent
def first_reaching(curve: list[dict], target: float) -> dict | None:
    """The first point of a curve whose test return is at least ``target`` (None: none)."""
    return next((p for p in curve if p.get("test_return", -math.inf) >= target), None)


def _at_budget(curve: list[dict], budget: int) -> dict | None:
    """The last point within ``budget`` evaluations (else the first point)."""
    within = [p for p in curve if p["evaluations"] <= budget]
    return within[-1] if within else (curve[0] if curve else None)


def summarise(runs: list[dict]) -> list[dict]:
    """Per environment and seed: each method's final test return and size, and where
    eant2_jax's champion first reached TensorNEAT's final test return."""
    rows = []
    keys = sorted({(r["env"], r["seed"]) for r in runs})
    for env, seed in keys:
        by = {r["method"]: r for r in runs if r["env"] == env and r["seed"] == seed}
        row: dict[str, Any] = {"env": env, "seed": seed}
        for m in METHODS:
            r = by.get(m)
            last = r["curve"][-1] if r and r["curve"] else None
            row[f"{m}_return"] = None if last is None else last.get("test_return")
            row[f"{m}_evals"] = None if last is None else last["evaluations"]
            row[f"{m}_wall_s"] = None if last is None else last["wall_s"]
            row[f"{m}_size"] = None if last is None else last["size"]
            row[f"{m}_status"] = _status(r)
        tn, ea = by.get("tensorneat"), by.get("eant2")
        target = row["tensorneat_return"]
        hit = first_reaching(ea["curve"], target) if ea and target is not None else None
        row["eant2_evals_to_tn"] = None if hit is None else hit["evaluations"]
        row["eant2_wall_to_tn_s"] = None if hit is None else hit["wall_s"]
        if tn and ea and tn["curve"]:
            same = _at_budget(ea["curve"], tn["curve"][-1]["evaluations"])
            row["eant2_return_at_tn_evals"] = None if same is None else same.get("test_return")
            tn_hit = first_reaching(tn["curve"], target)
            row["tn_wall_to_own_s"] = None if tn_hit is None else tn_hit["wall_s"]
            row["tn_evals_to_own"] = None if tn_hit is None else tn_hit["evaluations"]
        row["verdict"] = _verdict(row)
        rows.append(row)
    return rows


def _verdict(row: dict) -> str | None:
    """The issue's test of one seed: ``"win"`` when eant2_jax's champion at TensorNEAT's
    evaluations matches or beats TensorNEAT's final test return AND its champion reached
    that return no later (wall time from process start) than TensorNEAT did; else what
    failed (``"loss: return"``, ``"loss: wall"``, or both). None without both runs."""
    target, at = row.get("tensorneat_return"), row.get("eant2_return_at_tn_evals")
    if target is None or at is None:
        return None
    lost = []
    if at < target:
        lost.append("return")
    mine, theirs = row.get("eant2_wall_to_tn_s"), row.get("tn_wall_to_own_s")
    if mine is None or (theirs is not None and mine > theirs):
        lost.append("wall")
    return "win" if not lost else "loss: " + ", ".join(lost)


def _status(run: dict | None) -> str:
    if run is None:
        return "not run"
    if run.get("error"):
        return "failed"
    if not run.get("done"):
        return "killed"
    return "deadline" if run.get("deadline") else "ok"


def _spawn(method: str, env: str, seed: int, args: argparse.Namespace, budget: int,
           work: Path) -> dict:  # fmt: skip
    out = work / f"{env}-{method}-s{seed}.json"
    cmd = [sys.executable, "-m", "bench.field_runner", "worker", "--method", method, "--env", env,
           "--seed", str(seed), "--budget", str(budget), "--deadline-s", str(args.deadline_s),
           "--out", str(out), "--test-episodes", str(args.test_episodes),
           "--backend", args.backend, "--tensorneat-pop", str(args.tensorneat_pop)]  # fmt: skip
    if args.quick:
        cmd.append("--quick")
    for flag, v in (("--population", args.population), ("--max-iters", args.max_iters),
                    ("--tensorneat", args.tensorneat),
                    ("--pruner", eant2_pruner(args.quick))):  # fmt: skip
        if v is not None:
            cmd += [flag, str(v)]
    environ = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",)}
    environ["EANT2_CACHE_DIR"] = ""  # cold: no persistent compilation cache on either side
    # The checkout goes last, for `bench` alone: a checkout's eant2_jax is not importable as
    # it lies (its kernels/ is mapped in by the install), so the installed one must win.
    environ["PYTHONPATH"] = os.pathsep.join(
        filter(None, [environ.get("PYTHONPATH", ""), str(Path(__file__).resolve().parents[1])])
    )
    t0 = time.time()
    cmd += ["--t0", repr(t0)]
    err = ""
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=environ,
                              timeout=args.deadline_s + args.grace_s)  # fmt: skip
        if proc.returncode != 0:
            err = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
            err = err[0]
    except subprocess.TimeoutExpired:
        err = ""  # killed past its deadline: what it wrote is kept, marked "killed"
    total = time.time() - t0
    run = json.loads(out.read_text()) if out.is_file() else {
        "method": method, "env": env, "seed": seed, "budget": budget, "curve": []}  # fmt: skip
    run["process_s"] = total
    if err:
        run["error"] = err
    return run


def _options(p: argparse.ArgumentParser) -> None:
    # --protocol's environments (bench/field_settings.py) include some this suite lacks.
    p.add_argument("--envs", nargs="+", choices=sorted({*ENVS, *field_protocol.ENVS}),
                   default=None, help="default: all (with --quick: cartpole)")  # fmt: skip
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    # Defaults filled in by _prepare (3 seeds from 0; --protocol: the protocol's seeds).
    harness.run_options(p, seeds=None, first_seed=None, population=None,
                        helps={"population": "eant2 population override"})  # fmt: skip
    p.add_argument("--budget", type=int, default=None,
                   help="evaluations per run (default: each environment's, ENVS)")  # fmt: skip
    p.add_argument("--deadline-s", type=float, default=None,
                   help="wall seconds per run from its process start (600; --protocol: a "
                        "process's limit, 3600)")  # fmt: skip
    p.add_argument("--grace-s", type=float, default=300.0,
                   help="after its deadline a run has this long to test its champions")  # fmt: skip
    # 100: on Acrobot one champion's mean over 20 episodes still moved by +-4, the size of
    # the differences between the methods.
    p.add_argument("--test-episodes", type=int, default=100,
                   help="new episodes each champion plays after the run")  # fmt: skip
    p.add_argument("--backend", default="spring", help="brax physics backend, both methods")
    p.add_argument("--max-iters", type=int, default=None, help="eant2 CMA-ES iterations override")
    p.add_argument("--width", type=int, default=None,
                   help="--protocol trial: eant2's ExploitConfig.width (networks per engine "
                        "batch) in place of its frozen popsize")  # fmt: skip
    p.add_argument("--normalize", choices=NORMALIZE, default=None,
                   help="--protocol trial: eant2's input convention; random: observations "
                        "normalised by frozen statistics of random-policy episodes "
                        "(docs/protocol.md section 8)")  # fmt: skip
    p.add_argument("--spare-rows", choices=SPARE_ROWS, default=None,
                   help="--protocol trial: eant2's ExploitConfig.spare_rows; restarts: "
                        "each padding row searches again (protocol section 9)")  # fmt: skip
    p.add_argument("--tensorneat", default=None,
                   help="folder holding TensorNEAT's tensorneat package (its src/)")  # fmt: skip
    p.add_argument("--tensorneat-pop", type=int, default=None,
                   help=f"TensorNEAT's population ({TENSORNEAT_POP})")  # fmt: skip
    field_protocol.add_options(p)


def _prepare(args: argparse.Namespace) -> None:
    if args.protocol and not args.render:
        _check_tensorneat(args)
        args.deadline_s = args.deadline_s or 3600.0
        return field_protocol.prepare(args)
    if args.resume or args.checkpoint or args.peer_runs:
        raise BenchInputError("--checkpoint, --resume and --peer-runs belong to --protocol")
    for flag in ("width", "normalize", "spare_rows"):
        if getattr(args, flag) is not None:
            name = flag.replace("_", "-")
            raise BenchInputError(f"--{name} belongs to --protocol (a trial's option)")
    args.seeds = 3 if args.seeds is None else args.seeds
    args.first_seed = 0 if args.first_seed is None else args.first_seed
    args.deadline_s = args.deadline_s or 600.0
    args.tensorneat_pop = args.tensorneat_pop or TENSORNEAT_POP
    if args.quick:
        for k, v in QUICK.items():
            setattr(args, k, v)
    if args.envs is None:
        args.envs = ["cartpole"] if args.quick else list(ENVS)
    bad = [e for e in args.envs if e not in ENVS]
    if bad:
        raise BenchInputError(f"{', '.join(bad)}: only with --protocol (bench/field_settings.py)")
    if not args.render:  # --render measures nothing
        _check_tensorneat(args)
    for name in ("seeds", "test_episodes", "tensorneat_pop"):
        if getattr(args, name) < 1:
            raise BenchInputError(f"--{name.replace('_', '-')} must be at least 1")
    if args.first_seed < 0:
        raise BenchInputError("--first-seed must be at least 0")
    if args.budget is not None and args.budget < 1:
        raise BenchInputError("--budget must be at least 1")


def _check_tensorneat(args: argparse.Namespace) -> None:
    if "tensorneat" in args.methods:
        src = Path(args.tensorneat or "")
        if not args.tensorneat or not (src / "tensorneat" / "pipeline.py").is_file():
            raise BenchInputError(
                "--tensorneat must name the folder holding TensorNEAT's tensorneat package "
                f"(its src/), got {args.tensorneat!r}; or leave tensorneat out of --methods"
            )


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    if args.protocol:
        return field_protocol.run(args, save)
    payload: dict[str, Any] = {"environment": environment(),
                               "config": harness.settings(args), "runs": []}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="eant2-field-") as work:
        for env in args.envs:
            budget = args.budget or ENVS[env].budget
            for seed in range(args.first_seed, args.first_seed + args.seeds):
                for method in args.methods:
                    harness.log(f"field: {env} seed {seed} {method} (budget {budget})")
                    r = _spawn(method, env, seed, args, budget, Path(work))
                    payload["runs"].append(r)
                    payload["summary"] = summarise(payload["runs"])
                    save(payload)
    return payload


def _fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _pair(a: str, b: str, digits: int = 4):
    """A column value "a / b" of two row fields."""
    return lambda r: f"{_fmt(r.get(a), digits)} / {_fmt(r.get(b), digits)}"


def render(payload: dict[str, Any]) -> str:
    if payload.get("protocol"):
        return field_protocol.render(payload)
    rows = summarise(payload.get("runs", []))
    cols = [
        Column("env", "env"),
        Column("seed", "seed"),
        Column(_pair("eant2_return", "tensorneat_return"), "test return (eant2 / TN)"),
        Column(lambda r: _fmt(r.get("eant2_return_at_tn_evals")), "eant2 at TN's evals"),
        Column(_pair("eant2_evals", "tensorneat_evals"), "evals (eant2 / TN)"),
        Column(_pair("eant2_evals_to_tn", "tn_evals_to_own"), "evals to TN's return (eant2 / TN)"),
        Column(_pair("eant2_wall_to_tn_s", "tn_wall_to_own_s", 3),
               "wall s to TN's return (eant2 / TN)"),
        Column(_pair("eant2_size", "tensorneat_size"), "weights (eant2 / TN)"),
        Column(_pair("eant2_status", "tensorneat_status"), "status (eant2 / TN)"),
        Column(lambda r: _fmt(r.get("verdict")), "verdict"),
    ]  # fmt: skip
    cfg = payload.get("config", {})
    note = (
        f"Test return: mean over {cfg.get('test_episodes', '?')} new episodes of the champion "
        f"at the end of the run. Wall time from process start, cold compilation cache. brax "
        f"backend {cfg.get('backend', '?')}; TensorNEAT population {cfg.get('tensorneat_pop')}. "
        "Verdict: a win when eant2_jax's champion at TensorNEAT's evaluations matches or "
        "beats TensorNEAT's final test return and reached it no later from process start."
    )
    return markdown_table(rows, cols) + "\n" + note + "\n"


SUITE = harness.Suite(name="field", title="The field: eant2_jax and TensorNEAT",
                      description=__doc__, options=_options, run=run, render=render,
                      prepare=_prepare)  # fmt: skip


def main(argv: list[str] | None = None) -> dict[str, Any]:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "figure":
        if len(argv) < 3:
            raise BenchInputError("usage: python -m bench field figure OUT.png RESULT.json ...")
        from bench.field_figure import figure

        harness.log(f"wrote {figure(argv[1], argv[2:])}")
        return {}
    if "--protocol" in argv:  # before JAX starts: the children need the device's memory
        from bench.field_protocol import hold_no_device_memory

        hold_no_device_memory()
    return SUITE.main(argv)


if __name__ == "__main__":
    main(sys.argv[1:])
