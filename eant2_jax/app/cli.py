"""The ``eant2`` command line. The library never prints; this module renders."""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
from pathlib import Path

import numpy as np

__all__ = ["main"]

# A genome file of 64 MiB holds millions of genes, far beyond the compiler's limits.
MAX_GENOME_BYTES = 64 * 2**20
DEMO_GENOME = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"
# One output neuron reading both inputs, a bias and one hidden neuron: enough for XOR.
XOR_START = "N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"


def _demo(args: argparse.Namespace) -> int:
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


def _task_options(pairs: list[str]) -> dict:
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise ValueError(f"--task-option expects KEY=VALUE, got {pair!r}")
        k, v = pair.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def _free_dir(task: str, seed: int) -> Path:
    # A spec may be a path or module:factory: name the directory by its last part.
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


def _user_modules() -> None:
    """Let ``eant2 run module:factory`` import modules from the working directory, as
    ``python -m`` does (appended: installed packages are never shadowed)."""
    import os

    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())


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


def _run(args: argparse.Namespace) -> int:
    import jax

    import eant2_jax
    from eant2_jax.exploitation import ExploitConfig
    from eant2_jax.loop import EANT2Config
    from eant2_jax.progress import ProgressReporter

    spec = _task_spec(args)
    options = _task_options(args.task_option)
    if args.x64:  # before any array is made
        eant2_jax.enable_x64()
    _user_modules()
    task = eant2_jax.tasks.make(spec, **options)
    exploit = {"pruner": "none" if not args.prune else args.pruner}
    if args.x64:
        exploit["dtype"] = "float64"
    if args.max_iters is not None:
        exploit["max_iters"] = args.max_iters
    for name in ("lazy_eigen", "recommend", "rescore"):  # unset: ExploitConfig's default
        if getattr(args, name) is not None:
            exploit[name] = getattr(args, name)
    config = EANT2Config(
        population=args.population,
        init_recurrent=args.recurrent_start,
        init_mutations=args.init_mutations,
        reexploit=args.reexploit,
        inherit_search=args.inherit_search,
        devices=args.devices,
        target_cost=args.target_cost,
        max_evaluations=args.max_evaluations,
        min_bucket=args.min_bucket,
        exploit=ExploitConfig(**exploit),
    )
    out = Path(args.out) if args.out else _free_dir(spec, args.seed)
    # config.json records the task's spec and options (tasks.make remembers them).
    meta = {"seed": args.seed}
    # Generation 0's program starts compiling before the key exists: making the key
    # compiles two small programs, 0.4 s on a GPU with a cold cache.
    _start_first_program(task, args.seed, config)
    result = eant2_jax.run(
        task,
        key=jax.random.key(args.seed),
        config=config,
        generations=args.generations,
        out=str(out),
        callback=_interruptible(
            ProgressReporter(args.generations, header=f"eant2 run {spec}: writing {out}")
        ),
        meta=meta,
    )
    return _finish(result, out)


def _start_first_program(task, seed: int, config) -> None:
    """`eant2_jax.loop.compile_first_ahead` for the run of this seed (where it may)."""
    import jax

    from eant2_jax import loop

    loop.compile_first_ahead(task, jax.eval_shape(jax.random.key, seed), config)


def _resume(args: argparse.Namespace) -> int:
    import eant2_jax
    from eant2_jax.app.experiments import MANIFEST
    from eant2_jax.progress import ProgressReporter
    from eant2_jax.rundir import RunDir

    if (Path(args.dir) / MANIFEST).is_file():
        return _resume_reproduction(args)
    with RunDir.open(args.dir, lock=False) as rundir:  # resume takes the lock itself
        meta = rundir.config()
    config = meta.get("config")
    exploit = config.get("exploit") if isinstance(config, dict) else None
    if isinstance(exploit, dict) and exploit.get("dtype") == "float64":
        eant2_jax.enable_x64()  # the run was started with --x64
    _user_modules()
    total = args.generations if args.generations is not None else meta.get("generations", 0)
    # The task is rebuilt from the spec config.json records.
    result = eant2_jax.resume(
        args.dir,
        generations=args.generations,
        callback=_interruptible(ProgressReporter(total, header=f"eant2 resume {args.dir}")),
    )
    return _finish(result, Path(args.dir))


def _resume_reproduction(args: argparse.Namespace) -> int:
    """``eant2 resume DIR`` of an ``eant2 reproduce`` directory."""
    from eant2_jax.app.experiments import MANIFEST, resume_reproduction

    if args.generations is not None:
        raise ValueError(
            f"{args.dir} is an eant2 reproduce directory: --generations does not apply "
            "(its runs keep the number they were started with)"
        )
    try:  # for the progress lines only; resume_reproduction checks the file
        total = json.loads((Path(args.dir) / MANIFEST).read_text())["generations"]
    except (OSError, ValueError, KeyError, TypeError):
        total = "?"
    print(f"eant2 resume: finishing the reproduction in {args.dir}", file=sys.stderr)
    path = resume_reproduction(args.dir, callback=_interruptible(_reproduce_progress(total)))
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


def _report(args: argparse.Namespace) -> int:
    from eant2_jax.app.report import report
    from eant2_jax.rundir import RunDir

    for d in args.dirs:
        with RunDir.open(d, lock=False) as rundir:
            if rundir.is_live():
                print(
                    f"eant2: warning: {d} is being written by a live run; reporting the "
                    "generations it has committed so far",
                    file=sys.stderr,
                )
    out = Path(args.out) if args.out else Path(args.dirs[0]).parent / "report"
    path = report(
        args.dirs, out, allow_mixed=args.allow_mixed, reference=args.reference, upto=args.upto
    )
    print(f"report: {path}")
    return 0


def _show(args: argparse.Namespace) -> int:
    from eant2_jax.app.report import draw_genome, genome_stats
    from eant2_jax.genomefile import GenomeFile

    src = Path(args.genome_file)
    try:
        if src.stat().st_size > MAX_GENOME_BYTES:
            raise ValueError(
                f"{src}: {src.stat().st_size} bytes, more than a genome file may hold "
                f"({MAX_GENOME_BYTES})"
            )
        data = src.read_bytes()
    except OSError as e:
        raise ValueError(f"cannot read {src}: {e.strerror}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{src}: not UTF-8 text (byte {e.start})") from None
    spec = GenomeFile.parse(text, source=str(src))
    genome = spec.genome
    out = Path(args.out) if args.out else src.with_suffix(src.suffix + ".png")
    if out.exists() and not args.force:
        raise ValueError(f"{out} exists; not overwriting (use --out or --force)")
    print(genome)
    if spec.has_header:
        task = spec.task or "?"
        if spec.task_options:
            task += " " + json.dumps(spec.task_options)
        print(f"{'activations':>14}: hidden {spec.hidden}, output {spec.output}")
        print(f"{'task':>14}: {task} ({spec.n_inputs} inputs, {spec.n_outputs} outputs)")
    else:
        print(f"{'activations':>14}: not recorded (a file without a header)")
    for k, v in genome_stats(genome).items():
        print(f"{k:>14}: {v}")
    draw_genome(genome, out, title=src.name, n_inputs=spec.n_inputs)
    print(f"drawing: {out}")
    return 0


def _tasks(args: argparse.Namespace) -> int:
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


def _version() -> str:
    import platform

    import jax

    import eant2_jax

    return (
        f"eant2 {eant2_jax.__version__} (jax {jax.__version__}, Python {platform.python_version()})"
    )


def _reproduce(args: argparse.Namespace) -> int:
    import eant2_jax
    from eant2_jax.app.experiments import reproduce
    from eant2_jax.exploitation import ExploitConfig
    from eant2_jax.loop import EANT2Config

    options = {"mode": args.mode} if args.task == "servo" else {}
    options.update(_task_options(args.task_option))
    task = eant2_jax.tasks.make(args.task, **options)
    if args.seed + args.runs > 2**32:
        raise ValueError(f"--seed {args.seed} + --runs {args.runs} goes past 2**32")
    pruners = [p.strip() for p in args.pruners.split(",") if p.strip()]
    from eant2_jax.app.experiments import arm_config

    for arm in pruners:  # one clear line before anything runs
        arm_config(EANT2Config(), arm)
    exploit = {} if args.max_iters is None else {"max_iters": args.max_iters}
    config = EANT2Config(
        population=args.population,
        reexploit=args.reexploit,
        inherit_search=args.inherit_search,
        exploit=ExploitConfig(**exploit),
    )
    out = Path(args.out) if args.out else _free_dir(f"reproduce-{args.task}", args.seed)
    args.out = str(out)  # for the interruption hint (eant2 resume OUT)
    total = args.generations

    progress = _reproduce_progress(total)

    print(f"eant2 reproduce: writing {out}", file=sys.stderr)
    path = reproduce(
        task,
        out,
        task_meta={"task": args.task, "task_options": options},
        runs=args.runs,
        generations=args.generations,
        pruners=pruners,
        config=config,
        seed=args.seed,
        workers_per_device=args.workers,
        lockstep=args.lockstep,
        condition=not args.no_condition,
        condition_iters=args.condition_iters,
        condition_inits=args.condition_inits,
        condition_dtype=args.condition_dtype,
        callback=_interruptible(progress),
    )
    print(f"report: {path}")
    return 0


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _non_negative(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _factor(text: str) -> float:
    value = float(text)
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be >= 0 and finite, got {text}")
    return value


def _seed(text: str) -> int:
    """A run seed: JAX's 32-bit keys wrap seeds modulo 2**32, so only [0, 2**32) are
    distinct runs (2**32 would silently repeat seed 0)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r:.40}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**32), got {text:.40}")
    return value


def _devices(text: str) -> int | str:
    if text == "all":
        return text
    try:
        return _positive(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'all' or a count >= 1, got {text!r}") from None


def _bucket(text: str) -> tuple[int, int, int]:
    """``N,G,S``: three integers >= 1 (EANT2Config.min_bucket checks their range)."""
    parts = text.split(",")
    try:
        values = tuple(int(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or min(values) < 1:
        raise argparse.ArgumentTypeError(
            f"expected three integers >= 1 as NEURONS,GENES,SWEEPS, got {text!r:.40}"
        )
    return values


def _parser() -> argparse.ArgumentParser:
    from eant2_jax.config import RECOMMEND
    from eant2_jax.kernels.pruning import PRUNERS

    p = argparse.ArgumentParser(prog="eant2", description="EANT2 neuro-evolution in JAX.")
    p.add_argument("--version", action="version", version=_version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser(
        "demo", help="evaluate a small recurrent genome, then tune a network on XOR with CMA-ES"
    )
    demo.add_argument("--seed", type=int, default=0, help="seed of inputs and CMA-ES")
    demo.add_argument("--iters", type=_positive, default=600, help="CMA-ES iteration budget")
    demo.set_defaults(func=_demo)

    run = sub.add_parser("run", help="run EANT2 on a task, writing a run directory")
    run.add_argument(
        "task",
        nargs="?",
        default=None,
        help="task: a name (xor, servo, dpv, dpnv), gymnax:ENV (e.g. gymnax:CartPole-v1), "
        "brax:ENV (e.g. brax:hopper), module:factory or file.py:factory (docs/tasks-custom.md)",
    )
    run.add_argument(
        "--task-file",
        default=None,
        metavar="PATH.py[:FACTORY]",
        help="a Python file defining the task's factory (default name: make_task)",
    )
    run.add_argument(
        "--prune",
        dest="prune",
        action="store_true",
        default=True,
        help="prune connections during exploitation (default)",
    )
    run.add_argument("--no-prune", dest="prune", action="store_false", help="do not prune")
    run.add_argument(
        "--pruner",
        choices=[x for x in PRUNERS if x != "none"],
        default="covariance",
        help="pruning method (default: covariance)",
    )
    run.add_argument(
        "--generations",
        type=_non_negative,
        default=15,
        help="generations after the initial one (default 15)",
    )
    run.add_argument("--population", type=_positive, default=20, help="population size")
    run.add_argument(
        "--recurrent-start",
        action="store_true",
        help="recurrent-ready minimal start: each output neuron also reads its own previous "
        "output through a weight-0 recurrent jumper (same function; for tasks that need memory)",
    )
    run.add_argument(
        "--init-mutations",
        type=_non_negative,
        default=0,
        metavar="K",
        help="a diverse generation 0: K structural mutations of each minimal start (default 0)",
    )
    run.add_argument(
        "--reexploit",
        action="store_true",
        help="tune the surviving parents again every generation, with the offspring",
    )
    run.add_argument(
        "--inherit-search",
        action="store_true",
        help="children start CMA-ES from their parent's covariance (identity on new genes); "
        "re-exploited parents continue from their own step size and covariance",
    )
    run.add_argument(
        "--seed", type=_seed, default=0, help="seed of the run's PRNG key, in [0, 2**32)"
    )
    run.add_argument(
        "--max-iters",
        type=_positive,
        default=None,
        help="CMA-ES iteration budget per structure and generation",
    )
    run.add_argument(
        "--lazy-eigen",
        type=_factor,
        default=None,
        metavar="F",
        help="decompose C only every F / (n (c1 + cmu)) iterations, rounded down to a "
        "power of two (default 0.5, pycma's factor; 0: every iteration)",
    )
    run.add_argument(
        "--recommend",
        choices=RECOMMEND,
        default=None,
        help="on a noisy task, the tuned network: the search's best candidate, its "
        "distribution mean, or (default) whichever scores lower on fresh episodes",
    )
    run.add_argument(
        "--rescore",
        type=_positive,
        default=None,
        metavar="K",
        help="on a noisy task, fresh draws of the cost that score each tuned network (default 4)",
    )
    run.add_argument(
        "--devices",
        type=_devices,
        default=None,
        help="split exploitation over devices: 'all' or a count (default: JAX's default device)",
    )
    run.add_argument(
        "--x64",
        action="store_true",
        help="keep the CMA-ES state in float64 (JAX's x64 mode; networks stay float32)",
    )
    run.add_argument(
        "--target-cost",
        type=float,
        default=None,
        help="stop once the best cost is at or below this",
    )
    run.add_argument(
        "--max-evaluations",
        type=int,
        default=None,
        metavar="N",
        help="stop after the generation in which the run's evaluations reach N",
    )
    run.add_argument(
        "--min-bucket",
        type=_bucket,
        default=None,
        metavar="N,G,S",
        help="the smallest padding bucket (neurons, genes, sweeps) a generation compiles into: "
        "fewer programs to compile when networks grow (default: the smallest that fits)",
    )
    run.add_argument(
        "--task-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="option of the task (repeatable); VALUE is JSON or a string",
    )
    run.add_argument(
        "--out",
        default=None,
        help="run directory to create (default: runs/TASK-sSEED, numbered if taken)",
    )
    run.set_defaults(func=_run)

    rep = sub.add_parser(
        "reproduce", help="the paper's experiments (with/without pruning) + report"
    )
    rep.add_argument("--runs", type=_positive, default=10, help="runs per arm (default 10)")
    rep.add_argument("--generations", type=_non_negative, default=15, help="default 15")
    rep.add_argument(
        "--mode",
        choices=["kinematic", "dynamic"],
        default="kinematic",
        help="servo physics mode (default kinematic)",
    )
    rep.add_argument(
        "--pruners",
        default="covariance",
        help="comma-separated pruning arms, e.g. covariance,covariance-literal,obs,obd,"
        "magnitude,snr (NAME-literal: the paper's rule as written); an arm without pruning "
        "is always added",
    )
    rep.add_argument("--population", type=_positive, default=20, help="population size")
    rep.add_argument(
        "--max-iters",
        type=_positive,
        default=None,
        help="CMA-ES iteration budget per structure and generation",
    )
    rep.add_argument(
        "--reexploit", action="store_true", help="every arm tunes surviving parents again"
    )
    rep.add_argument(
        "--inherit-search",
        action="store_true",
        help="every arm's children start from their parent's covariance (see eant2 run)",
    )
    rep.add_argument("--task", default="servo", help="task (default: servo, the paper's)")
    rep.add_argument("--seed", type=_seed, default=0, help="first seed, in [0, 2**32)")
    rep.add_argument(
        "--workers",
        type=_positive,
        default=1,
        help="concurrent runs (with --no-lockstep) or lock-step groups per device (default 1)",
    )
    rep.add_argument(
        "--lockstep",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="tune each generation of an arm's runs in one batch (default; fewer "
        "compilations); --no-lockstep runs each alone",
    )
    rep.add_argument(
        "--condition-iters",
        type=_positive,
        default=10_000,
        help="CMA-ES budget of each run of the condition experiment (default 10000)",
    )
    rep.add_argument(
        "--condition-inits",
        type=_positive,
        default=5,
        help="random initialisations of each network in the condition experiment (default 5)",
    )
    rep.add_argument(
        "--condition-dtype",
        choices=["float64", "float32"],
        default="float64",
        help="CMA-ES state in the condition experiment (default float64: x64 mode for it alone)",
    )
    rep.add_argument(
        "--task-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="option of the task (repeatable), e.g. n_starts=64",
    )
    rep.add_argument(
        "--no-condition", action="store_true", help="skip the condition experiment (paper V.A)"
    )
    rep.add_argument("--out", default=None, help="new output directory")
    rep.set_defaults(func=_reproduce)

    report = sub.add_parser("report", help="report.md and figures from run directories")
    report.add_argument("dirs", nargs="+", help="run directories")
    report.add_argument("--out", default=None, help="output folder (default: DIR/../report)")
    report.add_argument(
        "--allow-mixed",
        action="store_true",
        help="report runs of different tasks or configurations together (refused otherwise)",
    )
    report.add_argument(
        "--reference",
        default=None,
        metavar="ARM",
        help="the arm p-values are computed against (default: none, the arm without pruning)",
    )
    report.add_argument(
        "--upto",
        type=_non_negative,
        default=None,
        metavar="GEN",
        help="read every run only up to this generation (arms at equal generations when "
        "some runs stopped early)",
    )
    report.set_defaults(func=_report)

    show = sub.add_parser("show", help="print a genome file's statistics and draw it")
    show.add_argument("genome_file", help="a file holding a genome in text form")
    show.add_argument("--out", default=None, help="PNG to write (default: GENOME_FILE.png)")
    show.add_argument("--force", action="store_true", help="replace an existing PNG")
    show.set_defaults(func=_show)

    tasks = sub.add_parser("tasks", help="list the registered tasks and their options")
    tasks.set_defaults(func=_tasks)

    resume = sub.add_parser(
        "resume",
        help="continue a run directory from its last generation, or finish an eant2 "
        "reproduce directory",
    )
    resume.add_argument("dir", help="the run directory (or eant2 reproduce's directory)")
    resume.add_argument(
        "--generations",
        type=_non_negative,
        default=None,
        help="new total number of generations (default: as first asked)",
    )
    resume.set_defaults(func=_resume)
    return p


DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def _deterministic_gpu(environ=None) -> bool:
    """Ask XLA for deterministic GPU programs, unless EANT2_GPU_DETERMINISTIC=0 or XLA_FLAGS
    already sets the option (the application's choice; the library never touches it).

    Without it, two fresh processes on the same GPU with the same key gave different results:
    XLA's autotuner picks kernels by timing while compiling, and kernels round differently
    (docs/benchmarks.md, "Reproducibility on GPU"). CPUs ignore the option. It must be set
    before JAX starts its backend; returns whether it is in XLA_FLAGS afterwards.
    """
    import os

    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if "xla_gpu_deterministic_ops" in flags:
        return DETERMINISTIC_FLAG in flags.split()
    if environ.get("EANT2_GPU_DETERMINISTIC", "1").strip() == "0":
        return False
    environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()
    return True


# The process's settings `_process_defaults` chooses when the environment names none.
_ALLOCATOR_VARS = (
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "XLA_PYTHON_CLIENT_MEM_FRACTION",
    "XLA_PYTHON_CLIENT_ALLOCATOR",
)


def _process_defaults(environ=None) -> dict[str, str]:
    """The command's own process settings, each only where the environment sets none (the
    application's choice; the library never touches them). Returns what it set.

    * ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` (unless any ``XLA_PYTHON_CLIENT_*`` allocator
      variable is set): JAX's GPU backend otherwise reserves 75% of the GPU's memory when it
      starts. On an H100 host that reservation was most of the backend's start: 1.5-2.9 s
      against 0.4 s without it (docs/benchmarks.md, "Cold start"), and a run uses a few
      hundred MB. Memory is then taken as programs need it and kept; results do not change.
    * ``MUJOCO_GL=disable``: ``import mujoco`` otherwise loads an OpenGL (GLFW) library for
      rendering, 0.4 s on that host; the command never renders.

    Must run before JAX starts its backend and before MuJoCo is imported.
    """
    import os

    environ = os.environ if environ is None else environ
    chosen = {}
    if not any(v in environ for v in _ALLOCATOR_VARS):
        chosen["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    if "MUJOCO_GL" not in environ:
        chosen["MUJOCO_GL"] = "disable"
    environ.update(chosen)
    return chosen


# Ctrl-C, remembered. Python raises KeyboardInterrupt wherever the signal lands; when that is
# inside a callback the interpreter runs from C (the garbage collector's: XLA registers one),
# the exception is printed as "ignored" and the run went on (tests/test_loop.py's Ctrl-C test
# saw it once). The command's progress callbacks raise it again (`_interruptible`), and
# the print, a traceback a user need not see, is left out (`_quiet_interrupts`).
_SIGINT = threading.Event()


def _on_sigint(signum, frame):
    _SIGINT.set()
    raise KeyboardInterrupt


def _interruptible(callback):
    """``callback`` (progress events, or None), first raising KeyboardInterrupt if a Ctrl-C
    has arrived since the command started (`_SIGINT`); on the main thread only, where
    `main` turns it into exit 130 (worker threads of `eant2 reproduce` report too)."""

    def checked(event):
        if _SIGINT.is_set() and threading.current_thread() is threading.main_thread():
            raise KeyboardInterrupt
        if callback is not None:
            callback(event)

    return checked


def _quiet_interrupts(previous):
    """A `sys.unraisablehook` that drops a Ctrl-C's KeyboardInterrupt raised inside a
    callback run from C (Python would print it, with a traceback, as "Exception ignored"):
    the command raises it again at its next progress event (`_interruptible`). Anything
    else goes to ``previous``."""

    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and _SIGINT.is_set():
            return
        previous(unraisable)

    return hook


def main(argv: list[str] | None = None) -> int:
    _SIGINT.clear()
    previous, hook = None, sys.unraisablehook
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, _on_sigint)
        sys.unraisablehook = _quiet_interrupts(hook)
    try:
        return _main(argv)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            sys.unraisablehook = hook


def _main(argv: list[str] | None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    _deterministic_gpu()
    if args.func in (_run, _resume, _reproduce):
        _process_defaults()
    from eant2_jax.config import enable_compilation_cache

    # Compiled programs kept between runs (the application's choice; the library never
    # touches global JAX settings); EANT2_CACHE_DIR moves it, an empty value turns it off.
    enable_compilation_cache()
    from eant2_jax.distributed import initialize

    initialize()  # joins a multi-process run when EANT2_COORDINATOR etc. are set
    backend = _start_backend() if args.func in (_run, _resume, _reproduce) else None
    try:
        return args.func(args)
    except KeyboardInterrupt:
        # `eant2 run`/`reproduce` name their directory --out, `eant2 resume` takes DIR.
        where = getattr(args, "out", None) or getattr(args, "dir", None)
        print(
            "\neant2: interrupted; every completed generation is saved"
            + (f" (continue with: eant2 resume {where})" if where else ""),
            file=sys.stderr,
        )
        return 130
    except (ValueError, OSError) as e:
        print(f"eant2: error: {e}", file=sys.stderr)
        return 2
    finally:
        if backend is not None:  # never exit while it is inside the runtime's start
            backend.join()


def _start_backend():
    """Start JAX's backend in a daemon thread and return the thread: the runtime's start and
    the first transfer to the default device (on a GPU, the context and the allocator's
    pool: about 1 s on an H100 host, docs/benchmarks.md, "Cold start") then overlap the
    imports of the task (MuJoCo MJX: 2-3 s there) instead of following them. Nothing is
    computed; an error is left for the main thread to meet at its first JAX call. JAX itself
    is imported here, in this thread, so that the two threads never import it at once."""
    import threading

    import jax

    def start():
        try:
            jax.device_put(np.float32(0)).block_until_ready()
        except Exception:  # noqa: BLE001, S110 -- the main thread raises it, with context
            pass

    thread = threading.Thread(target=start, name="eant2-backend", daemon=True)
    thread.start()
    return thread


def entry() -> None:
    """The ``eant2`` command: `main`, then the exit.

    After a Ctrl-C, runs of `eant2_jax.run_many` may still be inside a compiled program in
    their worker threads; letting the interpreter tear down under them aborted the process
    ("terminate called ... FATAL: exception not rethrown", exit 134, on a GPU and on this
    CPU). Every completed generation is already on disk (each commit is atomic), so the
    process ends at once, as a kill would end it. (A worker counts while it is listed: a
    join interrupted by Ctrl-C can leave `Thread.is_alive` False for a thread still running.)
    """
    import os
    import threading

    from eant2_jax.multirun import WORKER

    rc = main()
    if rc == 130 and any(t.name.startswith(WORKER) for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    entry()
