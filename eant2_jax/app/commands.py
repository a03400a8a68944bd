"""The ``eant2`` commands, one function each: ``COMMANDS[name](args)`` returns the exit code.

The library never prints; these functions render its results. A mistake is a ValueError or
OSError with a one-line message (`eant2_jax.app.cli.main` prints it, exit code 2).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from . import process
from .parser import config_from, task_options

__all__ = ["COMMANDS", "free_dir"]

DEMO_GENOME = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"
# One output neuron reading both inputs, a bias and one hidden neuron: enough for XOR.
XOR_START = "N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"


def demo(args: argparse.Namespace) -> int:
    import eant2_jax

    genome = eant2_jax.Genome.parse(DEMO_GENOME)
    print(f"genome     {genome}")
    print(
        f"           {genome.n_params} parameters, {genome.n_inputs} inputs, "
        f"{genome.n_outputs} outputs, {genome.n_neurons} neurons, depth {genome.depth()}"
    )
    x = np.random.default_rng(args.seed).normal(size=(4, 2, genome.n_inputs))
    y = np.asarray(eant2_jax.evaluate(genome, x))[0]
    ref = eant2_jax.interpret(genome, x)
    first = np.round(y[:, 0].astype(float), 3).tolist()
    print(f"evaluate   stream 0 over {x.shape[0]} steps: {first}")
    print(f"reference  max |compiled - NumPy reference| = {np.max(np.abs(y - ref)):.2e}")

    import jax

    task = eant2_jax.tasks.make("xor")
    start = eant2_jax.Genome.parse(XOR_START)
    c0 = eant2_jax.cost(start, task, key=jax.random.key(0))[0]
    print(f"\nxor        start {start}  (cost {c0:.4f})")
    res = eant2_jax.optimize(start, task, key=jax.random.key(args.seed), max_iters=args.iters)
    patterns = np.array([[[0, 0], [0, 1], [1, 0], [1, 1]]], dtype=float)
    out = np.asarray(eant2_jax.evaluate(res.genome, patterns)).ravel().astype(float)
    solved = bool(np.all((out > 0.5) == np.array([False, True, True, False])))
    evals = int(res.history.evaluations[-1])
    print(f"optimize   cost {res.cost:.3g} after {evals} evaluations ({res.stop_reason})")
    print(f"           outputs on the four patterns {np.round(out, 3).tolist()}; solved: {solved}")
    print(f"tuned      {res.genome}")
    return 0 if solved else 1


def free_dir(task: str, seed: int) -> Path:
    """``runs/TASK-sSEED``, numbered if taken (a spec may be a path or module:factory: the
    directory is named by its last part)."""
    name = task.replace("\\", "/").rstrip("/").split("/")[-1].replace(".py", "")
    name = "".join(c if c.isalnum() or c in "-_." else "-" for c in name).strip("-.") or "task"
    base = Path("runs") / f"{name}-s{seed}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = Path(f"{base}-{n}")
    return path


def _finish(result, out: Path) -> int:
    last = result.generations[-1]
    print(f"best cost {last.best_cost:.6g}, size {last.best_size}: {result.best}")
    print(f"run directory: {out}")
    return 0


def _task_spec(args: argparse.Namespace) -> str:
    if args.task_file is not None:
        if args.task is not None:
            raise ValueError(f"give a task or --task-file, not both ({args.task!r})")
        path, sep, factory = args.task_file.rpartition(":")
        if not sep or not path.endswith(".py"):  # no factory, or a colon inside the path
            path, factory = args.task_file, ""
        if not path.endswith(".py"):
            raise ValueError(f"--task-file expects PATH.py[:FACTORY], got {args.task_file!r}")
        return f"{path}:{factory}" if factory else path
    if args.task is None:
        raise ValueError("name a task (xor, gymnax:CartPole-v1, module:factory) or --task-file")
    return args.task


def run(args: argparse.Namespace) -> int:
    import jax

    import eant2_jax
    from eant2_jax.progress import ProgressReporter

    spec = _task_spec(args)
    options = task_options(args.task_option, spec)
    config = config_from(args)  # every check before anything is made or created
    if config.exploit.dtype == "float64":  # before any array is made
        eant2_jax.enable_x64()
    process.user_modules()  # a spec typed on the command line may name the user's module
    task = eant2_jax.tasks.make(spec, **options)
    out = Path(args.out) if args.out else free_dir(spec, args.seed)
    # Generation 0's program starts compiling before the key exists: making the key
    # compiles two small programs of its own (docs/benchmarks.md, "Cold start").
    _start_first_program(task, args.seed, config)
    # config.json records the task's spec and options (tasks.make remembers them).
    result = eant2_jax.run(
        task,
        key=jax.random.key(args.seed),
        config=config,
        generations=args.generations,
        out=str(out),
        callback=process.interruptible(
            ProgressReporter(args.generations, header=f"eant2 run {spec}: writing {out}")
        ),
        meta={"seed": args.seed},
    )
    return _finish(result, out)


def _start_first_program(task, seed: int, config) -> None:
    """`eant2_jax.loop.compile_first_ahead` for the run of this seed (where it may)."""
    import jax

    from eant2_jax import loop

    loop.compile_first_ahead(task, jax.eval_shape(jax.random.key, seed), config)


def _named_task(spec: str | None, options, where: str):
    """The task the user named again (``--task``), built with the options the directory
    records; None when not named (the library then rebuilds only a registered task)."""
    import eant2_jax

    if spec is None:
        return None
    if not isinstance(options, dict):
        raise ValueError(f"{where}: the recorded task options are not an object")
    process.user_modules()
    return eant2_jax.tasks.make(spec, **options)


def resume(args: argparse.Namespace) -> int:
    """Continue a run directory (or finish a reproduction), with the budgets and stopping
    options it asks for (`eant2_jax.app.resumeargs`); warns in one line when the file of
    the user's task named again has changed since the run started."""
    import eant2_jax
    from eant2_jax.app.experiments import MANIFEST
    from eant2_jax.app.resumeargs import changes_of
    from eant2_jax.checkpoint import task_file_changed
    from eant2_jax.progress import ProgressReporter
    from eant2_jax.rundir import RunDir

    changes = changes_of(args)
    if (Path(args.dir) / MANIFEST).is_file():
        return _resume_reproduction(args, changes)
    with RunDir.open(args.dir, lock=False) as rundir:  # resume takes the lock itself
        meta = rundir.config()
    config = meta.get("config")
    exploit = config.get("exploit") if isinstance(config, dict) else None
    if isinstance(exploit, dict) and exploit.get("dtype") == "float64":
        eant2_jax.enable_x64()  # the run was started with float64 (--x64)
    # A task that is the user's code is rebuilt only when named again here (--task);
    # nothing a directory names is imported (docs/reliability.md, "Trust").
    task = _named_task(args.task, meta.get("task_options", {}), f"{args.dir}/config.json")
    warning = None if task is None else task_file_changed(meta, task)
    if warning is not None:
        print(f"eant2: warning: {warning}", file=sys.stderr)
    total = args.generations if args.generations is not None else meta.get("generations", 0)
    result = eant2_jax.resume(
        args.dir,
        task,
        generations=args.generations,
        changes=changes,
        callback=process.interruptible(ProgressReporter(total, header=f"eant2 resume {args.dir}")),
    )
    return _finish(result, Path(args.dir))


def _resume_reproduction(args: argparse.Namespace, changes: dict) -> int:
    """``eant2 resume DIR`` of an ``eant2 reproduce`` directory."""
    from eant2_jax.app.experiments import MANIFEST, resume_reproduction

    if args.generations is not None or changes:
        what = "--generations" if args.generations is not None else ", ".join(changes)
        raise ValueError(
            f"{args.dir} is an eant2 reproduce directory: {what} does not apply "
            "(its runs keep the budgets they were started with)"
        )
    task = None
    if args.task is not None:
        from eant2_jax.app.manifest import read_manifest

        meta = read_manifest(args.dir)["task_meta"]
        task = _named_task(args.task, meta["task_options"], str(Path(args.dir) / MANIFEST))
    try:  # for the progress lines only; resume_reproduction checks the file
        total = json.loads((Path(args.dir) / MANIFEST).read_text())["generations"]
    except (OSError, ValueError, KeyError, TypeError):
        total = "?"
    print(f"eant2 resume: finishing the reproduction in {args.dir}", file=sys.stderr)
    path = resume_reproduction(
        args.dir, callback=process.interruptible(_reproduce_progress(total)), task=task
    )
    print(f"report: {path}")
    return 0


def _reproduce_progress(total):
    """Progress lines of a reproduction's runs on stderr."""

    def progress(event: dict) -> None:
        if event["event"] == "generation":
            line = (
                f"[{event['arm']} run {event['run']}] gen {event['generation']}/{total} "
                f"best {event['best_cost']:.4g} size {event['best_size']}"
            )
        elif event["event"] == "condition" and event["phase"] == "start":
            line = f"[condition] started on the best unpruned network ({event['size']} weights)"
        elif event["event"] == "condition":
            line = f"[condition] done in {event['wall_s']:.1f} s"
        else:
            return
        print(line, file=sys.stderr, flush=True)

    return progress


def write_report(args: argparse.Namespace) -> int:
    from eant2_jax.app.report import default_folder, report
    from eant2_jax.rundir import RunDir

    for d in args.dirs:
        with RunDir.open(d, lock=False) as rundir:
            if rundir.is_live():
                print(
                    f"eant2: warning: {d} is being written by a live run; reporting the "
                    "generations it has committed so far",
                    file=sys.stderr,
                )
    out = Path(args.out) if args.out else default_folder(args.dirs)
    path = report(
        args.dirs,
        out,
        allow_mixed=args.allow_mixed,
        reference=args.reference,
        upto=args.upto,
        overwrite=args.force,
    )
    print(f"report: {path}")
    return 0


def show(args: argparse.Namespace) -> int:
    """Print a genome file's header and statistics and draw it. The file is read within
    bounds (`eant2_jax.genomefile.read_text`); the statistics are printed whatever the
    drawing: an existing PNG is kept (and said so) unless ``--force`` replaces it, and a
    link or non-file at its name is refused before anything is printed. The PNG is written
    whole and never through a link (`eant2_jax.app.outputs`)."""
    from eant2_jax.app import outputs
    from eant2_jax.app.netdraw import draw_network
    from eant2_jax.app.report import genome_stats
    from eant2_jax.genomefile import GenomeFile, read_text

    src = Path(args.genome_file)
    spec = GenomeFile.parse(read_text(src), source=str(src))
    genome = spec.genome
    out = Path(args.out) if args.out else src.with_suffix(src.suffix + ".png")
    keep = outputs.exists(out) and not args.force  # a link or non-file: OutputError
    print(genome)
    if spec.has_header:
        # The header's strings are the file's: shown as JSON escapes them (a task name
        # holding a newline or a terminal escape sequence shows as \n, \u001b).
        task = json.dumps(spec.task)[1:-1] if spec.task else "?"
        if spec.task_options:
            task += " " + json.dumps(spec.task_options)
        print(f"{'activations':>14}: hidden {spec.hidden}, output {spec.output}")
        print(f"{'task':>14}: {task} ({spec.n_inputs} inputs, {spec.n_outputs} outputs)")
    else:
        print(f"{'activations':>14}: not recorded (a file without a header)")
    for k, v in genome_stats(genome).items():
        print(f"{k:>14}: {v}")
    if keep:
        print(f"drawing: {out} (exists: kept; --force replaces it, --out names another)")
        return 0
    draw_network(genome, out, title=src.name, n_inputs=spec.n_inputs, overwrite=args.force)
    print(f"drawing: {out}")
    return 0


def list_tasks(args: argparse.Namespace) -> int:
    import inspect

    from eant2_jax import tasks
    from eant2_jax.kernels import activations

    for name in tasks.names():
        doc = (inspect.getdoc(tasks.factory(name)) or "").split("\n\n")[0].replace("\n", " ")
        print(f"{name}: {doc}" if doc else name)
        opts = [
            f"{k}={'(required)' if v is inspect.Parameter.empty else json.dumps(v)}"
            for k, v in tasks.options(name).items()
        ]
        print("    options: " + (", ".join(opts) if opts else "none"))
    print(
        "\nEnvironment families, NAMESPACE:NAME (optional extras, their options in "
        f"docs/tasks-custom.md): {', '.join(tasks.namespaces())}."
    )
    print("Set an option with --task-option KEY=VALUE (VALUE is JSON or a string).")
    print(f"Activations (hidden=, output=): {', '.join(activations.names())}.")
    return 0


def list_config(args: argparse.Namespace) -> int:
    """The configuration fields ``--set NAME=VALUE`` takes, from their specs, with ``eant2
    run``'s defaults (or that configuration as JSON, a template for ``--config``)."""
    from eant2_jax.app.parser import RUN_BASE
    from eant2_jax.config import EANT2Config
    from eant2_jax.jsonio import dumps

    base = EANT2Config.from_dict(RUN_BASE)
    if args.json:
        print(dumps(base.to_dict(), indent=2))
        return 0
    for name, kind, default, text in base.describe():
        print(f"{name} = {dumps(default)}  ({kind})")
        print(f"    {text}")
    print(
        "\nSet one with --set NAME=VALUE (VALUE is JSON or a string), or many with "
        "--config FILE.json."
    )
    return 0


def run_reproduction(args: argparse.Namespace) -> int:
    import eant2_jax
    from eant2_jax.app.arms import parse_arms
    from eant2_jax.app.experiments import reproduce

    options = {"mode": args.mode} if args.task == "servo" else {}
    options.update(task_options(args.task_option, args.task))
    config = config_from(args)
    arms = parse_arms(args.pruners, args.runs)  # one clear line before anything runs
    most = max(n for _, n in arms)
    if args.seed + most > 2**32:
        raise ValueError(f"--seed {args.seed} + {most} runs goes past 2**32")
    pruners = [a for a, _ in arms if a != "none"]  # reproduce adds it
    arm_runs = {a: n for a, n in arms if n != args.runs}
    task = eant2_jax.tasks.make(args.task, **options)
    out = Path(args.out) if args.out else free_dir(f"reproduce-{args.task}", args.seed)
    args.out = str(out)  # for the interruption hint (eant2 resume OUT)
    print(f"eant2 reproduce: writing {out}", file=sys.stderr)
    path = reproduce(
        task,
        out,
        task_meta={"task": args.task, "task_options": options},
        runs=args.runs,
        generations=args.generations,
        pruners=pruners,
        arm_runs=arm_runs,
        config=config,
        seed=args.seed,
        workers_per_device=args.workers,
        lockstep=args.lockstep,
        condition=not args.no_condition,
        condition_iters=args.condition_iters,
        condition_inits=args.condition_inits,
        condition_dtype=args.condition_dtype,
        callback=process.interruptible(_reproduce_progress(args.generations)),
    )
    print(f"report: {path}")
    return 0


def render(args: argparse.Namespace) -> int:
    from eant2_jax.app.render import command

    return command(args)


def export(args: argparse.Namespace) -> int:
    from eant2_jax.app.export_cmd import export as command

    return command(args)


# The commands by name (`eant2_jax.app.parser.build_parser`'s ``args.command``).
COMMANDS = {
    "demo": demo,
    "run": run,
    "reproduce": run_reproduction,
    "report": write_report,
    "show": show,
    "render": render,
    "export": export,
    "tasks": list_tasks,
    "config": list_config,
    "resume": resume,
}
