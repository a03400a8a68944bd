"""The ``eant2`` command line's arguments: argparse built once, errors in one line.

Every option that sets a configuration field is generated from the field's spec
(`eant2_jax.configspec`): its type, check and help come from there, and its value goes
through the one validated path, `config_from`. A few fields have flags of their own
(`RUN_FLAGS`); every field is reachable with ``--set NAME=VALUE`` (``eant2 config`` lists
them) and ``--config FILE.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import stat
from collections.abc import Callable
from typing import Any

from ..config import EANT2Config
from ..configspec import INT32_MAX, first_sentence, normal, spec_of
from ..jsonio import loads
from .taskoptions import read_value, task_options

__all__ = ["RUN_BASE", "REPRODUCE_BASE", "FieldFlag", "build_parser", "config_from"]
__all__ += ["RUN_FLAGS", "assignment", "field_type", "read_value", "task_options"]

# What each command's configuration starts from, before --config, flags and --set (as a
# partial EANT2Config.to_dict(); unset fields take their defaults). `eant2 run` prunes with
# the paper's method; `eant2 reproduce`'s arms choose their own pruner.
RUN_BASE: dict = {"exploit": {"pruner": "covariance"}}
REPRODUCE_BASE: dict = {"exploit": {}}
# A configuration file is a small JSON object; a larger one is not one.
MAX_CONFIG_BYTES = 1 << 20


class OneLineParser(argparse.ArgumentParser):
    """argparse with errors in one line naming the option (no usage block), and no
    abbreviated options (``--pop`` is not ``--population``)."""

    def __init__(self, *args, **kwargs):
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())}\n")


@dataclasses.dataclass(frozen=True)
class FieldFlag:
    """An option that sets one configuration field (``path``: ``exploit.max_iters``).

    Attributes:
      flags: the option strings.
      path: the field, dotted through nested configurations.
      dest: the attribute of the parsed arguments.
      shown: listed by ``--help`` (the others are older spellings of ``--set``).
      const: for a switch, the value it sets.
      metavar: the value's name in the help.
      text: how the option's text reads (default `read_value`).
    """

    flags: tuple[str, ...]
    path: str
    dest: str
    shown: bool = True
    const: Any = None
    metavar: str | None = None
    text: Callable[[str], Any] | None = None


def _bucket_text(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(p) for p in text.split(","))
    except ValueError:
        raise ValueError(f"expected NEURONS,GENES,SWEEPS, got {text!r:.40}") from None


_HIDDEN = dict(shown=False)
# The options of `eant2 run` that set a configuration field, in the order they apply (a
# later one wins: --no-prune over --pruner).
RUN_FLAGS = (
    FieldFlag(("--population",), "population", "population", metavar="N"),
    FieldFlag(("--pruner",), "exploit.pruner", "pruner", metavar="NAME"),
    FieldFlag(("--no-prune",), "exploit.pruner", "no_prune", const="none"),
    FieldFlag(("--max-iters",), "exploit.max_iters", "max_iters", metavar="N"),
    FieldFlag(("--target-cost",), "target_cost", "target_cost", metavar="COST"),
    FieldFlag(("--no-solved-stop",), "stop_when_solved", "no_solved_stop", const=False),
    FieldFlag(("--max-evaluations",), "max_evaluations", "max_evaluations", metavar="N"),
    FieldFlag(("--devices",), "devices", "devices", metavar="all|N"),
    FieldFlag(("--recurrent-start",), "init_recurrent", "recurrent_start", const=True, **_HIDDEN),
    FieldFlag(("--init-mutations",), "init_mutations", "init_mutations", metavar="K", **_HIDDEN),
    FieldFlag(("--reexploit",), "reexploit", "reexploit", const=True, **_HIDDEN),
    FieldFlag(("--inherit-search",), "inherit_search", "inherit_search", const=True, **_HIDDEN),
    FieldFlag(("--lazy-eigen",), "exploit.lazy_eigen", "lazy_eigen", metavar="F", **_HIDDEN),
    FieldFlag(("--recommend",), "exploit.recommend", "recommend", **_HIDDEN),
    FieldFlag(("--rescore",), "exploit.rescore", "rescore", metavar="K", **_HIDDEN),
    FieldFlag(("--x64",), "exploit.dtype", "x64", const="float64", **_HIDDEN),
    FieldFlag(
        ("--min-bucket",), "min_bucket", "min_bucket", metavar="N,G,S", text=_bucket_text, **_HIDDEN
    ),
)
REPRODUCE_FLAGS = (
    FieldFlag(("--population",), "population", "population", metavar="N"),
    FieldFlag(("--max-iters",), "exploit.max_iters", "max_iters", metavar="N"),
    FieldFlag(("--reexploit",), "reexploit", "reexploit", const=True),
    FieldFlag(("--inherit-search",), "inherit_search", "inherit_search", const=True),
)


def field_value(path: str, value: Any) -> Any:
    """``value`` checked by the spec of the field ``path`` names (a one-line ValueError)."""
    owner, f = EANT2Config.locate(path)
    return normal(owner.__name__, f, value)


def field_type(flag: FieldFlag) -> Callable[[str], Any]:
    """The argparse type of ``flag``: its text read and checked by its field's spec."""

    def parse(text: str) -> Any:
        try:
            return field_value(flag.path, (flag.text or read_value)(text))
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    return parse


def assignment(text: str) -> tuple[str, Any]:
    """``--set NAME=VALUE``: the field's dotted name and its checked value."""
    name, sep, raw = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r:.60}")
    try:
        return name.strip(), field_value(name.strip(), read_value(raw))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _default_of(path: str, base: dict) -> Any:
    config = EANT2Config.from_dict(base)
    for row in config.describe():
        if row[0] == path:
            return row[2]
    raise KeyError(path)


def add_config_options(parser: argparse.ArgumentParser, flags, base: dict) -> None:
    """The options that set configuration fields: ``flags`` (help and checks from the
    fields' specs), ``--set`` and ``--config``."""
    import json

    for flag in flags:
        _, f = EANT2Config.locate(flag.path)
        help_ = argparse.SUPPRESS
        if flag.shown and flag.const is None:
            help_ = (
                f"{first_sentence(spec_of(f))} (default {json.dumps(_default_of(flag.path, base))})"
            )
        elif flag.shown:
            help_ = f"set {flag.path} to {json.dumps(flag.const)}"
        kwargs = dict(dest=flag.dest, default=None, help=help_)
        if flag.const is not None:
            parser.add_argument(*flag.flags, action="store_const", const=flag.const, **kwargs)
        else:
            parser.add_argument(*flag.flags, type=field_type(flag), metavar=flag.metavar, **kwargs)
    parser.set_defaults(field_flags=tuple((f.dest, f.path) for f in flags), config_base=base)
    parser.add_argument(
        "--set",
        dest="assignments",
        action="append",
        type=assignment,
        default=[],
        metavar="NAME=VALUE",
        help="set any configuration field, e.g. exploit.sigma0=0.3 (repeatable; VALUE is JSON "
        "or a string; `eant2 config` lists the fields and their defaults)",
    )
    parser.add_argument(
        "--config",
        dest="config_file",
        default=None,
        metavar="FILE.json",
        help="configuration fields from a JSON object (as `eant2 config --json` prints; a run "
        "directory's config.json works too); flags and --set override it",
    )


def read_config_file(path: str) -> dict:
    """A JSON object of configuration fields, read as data: a regular file of at most
    `MAX_CONFIG_BYTES`, strict JSON (one-line ValueError otherwise)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except (OSError, ValueError) as e:
        raise ValueError(f"--config {path}: cannot read it ({getattr(e, 'strerror', e)})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise ValueError(f"--config {path}: not a regular file")
        data = os.read(fd, MAX_CONFIG_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > MAX_CONFIG_BYTES:
        raise ValueError(f"--config {path}: more than {MAX_CONFIG_BYTES} bytes")
    d = loads(data, f"--config {path}")
    if isinstance(d, dict) and "format" in d and isinstance(d.get("config"), dict):
        d = d["config"]  # a run directory's config.json
    if not isinstance(d, dict):
        raise ValueError(f"--config {path}: not a JSON object of configuration fields")
    return d


def _merge(into: dict, d: dict) -> None:
    for k, v in d.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v


def _assign(into: dict, path: str, value: Any) -> None:
    *outer, name = path.split(".")
    for part in outer:
        into = into.setdefault(part, {})
    into[name] = list(value) if isinstance(value, tuple) else value


def config_from(args: argparse.Namespace) -> EANT2Config:
    """The command's configuration: its base, then ``--config``'s fields, then the field
    flags, then each ``--set`` in order (a later one wins); checked once, by the specs."""
    import copy

    data = copy.deepcopy(args.config_base)
    if args.config_file is not None:
        _merge(data, read_config_file(args.config_file))
    for dest, path in args.field_flags:
        value = getattr(args, dest)
        if value is not None:
            _assign(data, path, value)
    for path, value in args.assignments:
        _assign(data, path, value)
    if not isinstance(data.get("exploit"), dict):
        raise ValueError("the configuration's 'exploit' must be an object")
    return EANT2Config.from_dict(data)


def positive(text: str) -> int:
    value = non_negative(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def non_negative(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r:.40}") from None
    if not 0 <= value <= INT32_MAX:
        raise argparse.ArgumentTypeError(f"must be in [0, {INT32_MAX}], got {text:.40}")
    return value


def seed(text: str) -> int:
    """A run seed: JAX's 32-bit keys wrap seeds modulo 2**32, so only [0, 2**32) are
    distinct runs (2**32 would silently repeat seed 0)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r:.40}") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**32), got {text:.40}")
    return value


def version() -> str:
    import platform

    import jax

    import eant2_jax

    return (
        f"eant2 {eant2_jax.__version__} (jax {jax.__version__}, Python {platform.python_version()})"
    )


def build_parser() -> argparse.ArgumentParser:
    """The ``eant2`` parser; ``args.command`` names the command (`commands.COMMANDS`)."""
    p = OneLineParser(prog="eant2", description="EANT2 neuro-evolution in JAX.")
    p.add_argument("--version", action="version", version=version())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser(
        "demo", help="evaluate a small recurrent genome, then tune a network on XOR with CMA-ES"
    )
    demo.add_argument("--seed", type=seed, default=0, help="seed of inputs and CMA-ES")
    demo.add_argument("--iters", type=positive, default=600, help="CMA-ES iteration budget")
    _run_parser(sub.add_parser("run", help="run EANT2 on a task, writing a run directory"))
    _reproduce_parser(
        sub.add_parser("reproduce", help="the paper's experiments (with/without pruning) + report")
    )
    _report_parser(sub.add_parser("report", help="report.md and figures from run directories"))
    show = sub.add_parser("show", help="print a genome file's statistics and draw it")
    show.add_argument("genome_file", help="a file holding a genome in text form")
    show.add_argument("--out", default=None, help="PNG to write (default: GENOME_FILE.png)")
    show.add_argument("--force", action="store_true", help="replace an existing PNG")
    from .render import add_arguments as render_arguments  # eant2 render (its module)

    render_arguments(sub.add_parser("render", help="animate a network on its task (GIF/MP4)"))
    from .export_cmd import add_parser as export_parser  # eant2 export (its module)

    export_parser(sub)
    sub.add_parser("tasks", help="list the registered tasks and their options")
    config = sub.add_parser(
        "config", help="list the configuration fields --set takes, with defaults and help"
    )
    config.add_argument(
        "--json", action="store_true", help="print eant2 run's default configuration as JSON"
    )
    from .resumeargs import add_resume_arguments  # it builds on this module's options

    add_resume_arguments(
        sub.add_parser(
            "resume",
            help="continue a run directory from its last generation, or finish an eant2 "
            "reproduce directory",
        )
    )
    return p


def _task_arguments(run: argparse.ArgumentParser) -> None:
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
        "--task-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="option of the task (repeatable); VALUE is JSON or a string",
    )


def _run_parser(run: argparse.ArgumentParser) -> None:
    run.epilog = (
        "Older spellings of --set, still accepted: --recurrent-start, --init-mutations K, "
        "--reexploit, --inherit-search, --lazy-eigen F, --recommend R, --rescore K, --x64, "
        "--min-bucket N,G,S."
    )
    _task_arguments(run)
    run.add_argument(
        "--generations",
        type=non_negative,
        default=15,
        help="generations after the initial one (default 15)",
    )
    run.add_argument(
        "--seed", type=seed, default=0, help="seed of the run's PRNG key, in [0, 2**32)"
    )
    run.add_argument("--prune", action="store_true", help=argparse.SUPPRESS)  # the default
    add_config_options(run, RUN_FLAGS, RUN_BASE)
    run.add_argument(
        "--out",
        default=None,
        help="run directory to create (default: runs/TASK-sSEED, numbered if taken)",
    )


def _reproduce_parser(rep: argparse.ArgumentParser) -> None:
    rep.add_argument("--runs", type=positive, default=10, help="runs per arm (default 10)")
    rep.add_argument("--generations", type=non_negative, default=15, help="default 15")
    rep.add_argument(
        "--mode",
        choices=["kinematic", "dynamic"],
        default="kinematic",
        help="servo physics mode (default kinematic)",
    )
    rep.add_argument(
        "--arms",
        "--pruners",
        dest="pruners",
        default="covariance",
        metavar="ARM[:RUNS],...",
        help="comma-separated arms, each with its run count if not --runs: the protocol's "
        "none, literal, default, no-refit, mean-reference, trigger-only, window-250, random, "
        "magnitude, obs, obd, snr (docs/protocol.md), or a pruner's name, or NAME-literal "
        "(the paper's rule as written); e.g. none:20,literal:20,default:20,no-refit:10. An "
        "arm without pruning (none) is always added. --pruners: the older spelling",
    )
    add_config_options(rep, REPRODUCE_FLAGS, REPRODUCE_BASE)
    rep.add_argument("--task", default="servo", help="task (default: servo, the paper's)")
    rep.add_argument("--seed", type=seed, default=0, help="first seed, in [0, 2**32)")
    rep.add_argument(
        "--workers",
        type=positive,
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
        type=positive,
        default=10_000,
        help="CMA-ES budget of each run of the condition experiment (default 10000)",
    )
    rep.add_argument(
        "--condition-inits",
        type=positive,
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


def _report_parser(report: argparse.ArgumentParser) -> None:
    report.add_argument("dirs", nargs="+", help="run directories")
    report.add_argument(
        "--out",
        default=None,
        help="output folder, never inside a run directory (default: DIR/../report)",
    )
    report.add_argument(
        "--force", action="store_true", help="replace a report already in the output folder"
    )
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
        type=non_negative,
        default=None,
        metavar="GEN",
        help="read every run only up to this generation (arms at equal generations when "
        "some runs stopped early)",
    )
