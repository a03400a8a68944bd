"""The one harness every benchmark suite runs under: arguments, output files, printing.

A suite declares a :class:`Suite`: its name, its own options, how to measure (``run``) and
how to show a payload (``render``). The harness does the rest, the same way for every suite:

* the run options several suites share (``--task``, ``--population``, ``--generations``,
  ``--seed``, ``--seeds``, ``--first-seed``): one definition each, in one group, added by
  :func:`run_options` with the suite's defaults;
* common options: ``--quick`` (smoke-test sizes), ``--out`` (default
  ``bench/results/<name>-<device tag>.json``), ``--force``, ``--render JSON`` (redo the
  markdown of a result file without measuring), and ``--repeats`` / ``--warmup`` where the
  suite declares defaults for them;
* the no-overwrite rule: a run refuses to start when its JSON or markdown file already
  exists (committed results are kept as measured) unless ``--force`` is given;
* output: the payload as JSON and its markdown (a header naming the device, then the suite's
  tables) side by side, rewritten whenever the suite saves a partial payload (a run cut off
  by a time limit keeps what it measured) and at the end; the markdown is printed.

Usage, in a suite module::

    SUITE = harness.Suite(name="forward", title="Forward throughput", description=__doc__,
                          options=_options, run=run, render=render, repeats=7, min_repeats=5)

    main = SUITE.main  # python -m bench forward [options]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from bench.common import BenchInputError, Column, default_out, markdown_table

__all__ = [
    "HARNESS_OPTIONS",
    "RUN_OPTIONS",
    "Output",
    "Suite",
    "execute",
    "header",
    "log",
    "main",
    "parse_args",
    "run_options",
    "sections",
    "settings",
]

# The harness's own options: not part of a suite's settings (see :func:`settings`).
HARNESS_OPTIONS = ("out", "force", "render")

# The run options several suites share: (type, help). One definition each; a suite picks the
# ones it has and their defaults with :func:`run_options`.
RUN_OPTIONS: dict[str, tuple[type, str]] = {
    "task": (str, "the task, as `eant2 run TASK` names it"),
    "population": (int, "EANT2Config.population (structures per generation)"),
    "generations": (int, "generations to run"),
    "seed": (int, "seed of the PRNG key (jax.random.key(seed))"),
    "seeds": (int, "how many seeds: first-seed, first-seed + 1, ..."),
    "first_seed": (int, "the first of the seeds"),
}

Payload = dict[str, Any]
Save = Callable[[Payload], object]


@dataclasses.dataclass(frozen=True)
class Suite:
    """What a benchmark suite declares; everything else is the harness's.

    Attributes:
      name: ``python -m bench NAME``; the default output is ``bench/results/NAME-<tag>.json``.
      title: first words of the markdown header, e.g. ``"Forward throughput"``.
      description: the ``--help`` text (the module docstring).
      options: ``options(parser)`` adds the suite's own arguments.
      run: ``run(args, save) -> payload``: measures and returns the JSON payload; may call
        ``save(payload)`` with the payload so far after each case.
      render: ``render(payload) -> str``: the markdown tables of a payload (also of a
        partial one), without the header.
      prepare: ``prepare(args)``, optional: applies ``--quick`` sizes and derived defaults
        to the parsed arguments and checks them (raises :class:`BenchInputError`).
      repeats: default of ``--repeats`` (timed calls per case); None: no such option.
      min_repeats: the smallest ``--repeats`` accepted.
      warmup: default of ``--warmup`` (untimed calls before the timed ones); None: no option.
    """

    name: str
    title: str
    description: str
    options: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace, Save], Payload]
    render: Callable[[Payload], str]
    prepare: Callable[[argparse.Namespace], None] | None = None
    repeats: int | None = None
    min_repeats: int = 1
    warmup: int | None = None

    def main(self, argv: Sequence[str] | None = None) -> Payload:
        """The suite's command line, ``python -m bench NAME [options]``; the payload."""
        return main(self, argv)


def log(msg: str) -> None:
    """Progress to stderr (stdout carries the tables)."""
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------ arguments
def parse_args(suite: Suite, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The suite's parsed arguments: the harness's common options plus the suite's own."""
    p = argparse.ArgumentParser(
        prog=f"python -m bench {suite.name}",
        description=suite.description,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    common = p.add_argument_group("common to every suite")
    common.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    common.add_argument(
        "--out",
        default=None,
        help=f"JSON path; the markdown goes next to it (default bench/results/{suite.name}-"
        "<device tag>.json, e.g. -cpu, -gpu-h100)",
    )
    common.add_argument(
        "--force", action="store_true", help="replace existing result files (refused otherwise)"
    )
    common.add_argument(
        "--render",
        default=None,
        metavar="JSON",
        help="measure nothing: rewrite the markdown of this result file (needs --force if the "
        "markdown exists) and print it",
    )
    if suite.repeats is not None:
        common.add_argument(
            "--repeats",
            type=int,
            default=suite.repeats,
            help=f"timed calls per case (>= {suite.min_repeats}; default {suite.repeats})",
        )
    if suite.warmup is not None:
        common.add_argument(
            "--warmup", type=int, default=suite.warmup, help="untimed calls before the timed ones"
        )
    suite.options(p)
    args = p.parse_args(argv)
    if suite.repeats is not None and args.repeats < suite.min_repeats:
        raise BenchInputError(f"--repeats must be at least {suite.min_repeats}")
    if suite.prepare is not None:
        suite.prepare(args)
    return args


def run_options(
    parser: argparse.ArgumentParser, *, helps: dict[str, str] | None = None, **defaults: Any
) -> None:
    """Add the run options a suite shares with the others, in one group of its ``--help``.

    Args:
      parser: the suite's parser (the ``options`` of its :class:`Suite`).
      helps: a suite's own help text for some of them (e.g. what its ``--task`` times).
      **defaults: the options the suite has, each with its default (None: unset, the suite
        decides), by name: ``task``, ``population``, ``generations``, ``seed``, ``seeds``,
        ``first_seed`` (``--first-seed``). Options not named are not added.

    Raises:
      ValueError: a name that is not one of :data:`RUN_OPTIONS`.
    """
    unknown = sorted(set(defaults) - set(RUN_OPTIONS))
    if unknown:
        raise ValueError(f"not a shared run option: {', '.join(unknown)}")
    helps = helps or {}
    group = parser.add_argument_group("run options (shared by the suites)")
    for name, (kind, text) in RUN_OPTIONS.items():
        if name in defaults:
            default = defaults[name]
            suffix = "" if default is None else f" (default {default})"
            group.add_argument(
                "--" + name.replace("_", "-"),
                type=kind,
                default=default,
                help=helps.get(name, text) + suffix,
            )


def settings(args: argparse.Namespace, *exclude: str) -> dict[str, Any]:
    """The suite's settings for a payload's ``config``: the parsed arguments without the
    harness's own options (where files go is not a setting) and without ``exclude``."""
    return {k: v for k, v in vars(args).items() if k not in HARNESS_OPTIONS + exclude}


# --------------------------------------------------------------------------------- output
def header(title: str, payload: Payload) -> str:
    """``"<title> on **<device>** (<platform>), jax <version>, <date>."`` of a payload whose
    environment is at its top level or under ``"environment"``."""
    env = payload.get("environment", payload)
    count = env.get("device_count") or 1
    device = env.get("device_kind", "?") if count == 1 else f"{count} x {env['device_kind']}"
    return (
        f"{title} on **{device}** ({env.get('platform')}), jax {env.get('jax_version')}, "
        f"{env.get('date_utc')}."
    )


def sections(payload: Payload, parts: Sequence[tuple[str, str, Sequence[Column]]]) -> str:
    """Markdown for a payload of several parts: for each ``(key, heading, columns)`` whose
    rows ``payload[key]`` are present, a ``###`` heading and the table."""
    out = []
    for key, heading, columns in parts:
        if payload.get(key):
            out.append(f"### {heading}\n\n" + markdown_table(payload[key], columns))
    return "\n".join(out)


class Output:
    """The JSON and markdown files of one run, written only where allowed.

    Args:
      suite: the suite (its ``title`` and ``render`` make the markdown).
      path: the JSON path; the markdown is the same path with ``.md``.
      force: replace existing files. Without it, existing files are refused here, before
        anything is measured.

    Raises:
      BenchInputError: a file exists and ``force`` is false.
    """

    def __init__(self, suite: Suite, path: str | Path, *, force: bool):
        self.suite = suite
        self.json = Path(path)
        self.md = self.json.with_suffix(".md")
        if not force:
            for p in (self.json, self.md):
                if p.exists():
                    raise BenchInputError(
                        f"{p} exists; pass --force to replace it, or --out to write elsewhere"
                    )

    def markdown(self, payload: Payload) -> str:
        return header(self.suite.title, payload) + "\n\n" + self.suite.render(payload)

    def save(self, payload: Payload) -> str:
        """Write the payload (JSON) and its markdown; return the markdown."""
        md = self.markdown(payload)
        self.json.parent.mkdir(parents=True, exist_ok=True)
        self.json.write_text(json.dumps(payload, indent=2) + "\n")
        self.md.write_text(md)
        return md


# ------------------------------------------------------------------------------- running
def execute(suite: Suite, args: argparse.Namespace) -> Payload:
    """Run a suite on parsed arguments: measure, write, print; return the payload."""
    if args.render:
        return _render(suite, args)
    out = Output(suite, args.out or default_out(suite.name), force=args.force)
    payload = suite.run(args, out.save)
    print(out.save(payload))
    log(f"wrote {out.json} and {out.md}")
    return payload


def _render(suite: Suite, args: argparse.Namespace) -> Payload:
    try:
        payload = json.loads(Path(args.render).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise BenchInputError(f"cannot read {args.render}: {e}") from e
    out = Output(suite, args.render, force=True)
    if out.md.exists() and not args.force:
        raise BenchInputError(f"{out.md} exists; pass --force to rewrite it")
    md = out.markdown(payload)
    out.md.write_text(md)
    print(md)
    return payload


def main(suite: Suite, argv: Sequence[str] | None = None) -> Payload:
    """A suite's command line: ``python -m bench NAME [options]``."""
    return execute(suite, parse_args(suite, argv))
