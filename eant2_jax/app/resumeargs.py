"""``eant2 resume``'s arguments: what a resume may change, and one line for the rest.

A resume may change the total of generations and the budgets and stopping options of
`eant2_jax.checkpoint.RESUMABLE` (``--max-evaluations``, ``--target-cost``, or ``--set``
for those fields); the new values are checked by the fields' specs and recorded in the run's
``config.json``. Every other option of ``eant2 run`` is refused while the arguments are
parsed, in one line naming it: a resumed run keeps its task, seed and configuration.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from ..checkpoint import RESUMABLE
from .parser import RUN_FLAGS, assignment, field_type, non_negative

__all__ = ["RUN_ONLY", "add_resume_arguments", "changes_of"]

# Options of `eant2 run` that are not configuration fields, and whether each takes a value.
RUN_ONLY = (
    ("--seed", True),
    ("--out", True),
    ("--task-option", True),
    ("--task-file", True),
    ("--config", True),
    ("--prune", False),
)
_FLAGS = [f.flags[0] for f in RUN_FLAGS if f.path in RESUMABLE]
_MAY = (
    f"a resume may change only --generations, {', '.join(_FLAGS)} (or --set "
    + ", ".join(f"{name}=..." for name in RESUMABLE)
    + ")"
)


def _refusal(option: str) -> str:
    return (
        f"{option} cannot change on resume (a run keeps its task, seed and configuration); {_MAY}"
    )


class _Fixed(argparse.Action):
    """An option of ``eant2 run`` that a resume refuses, in one line naming it."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(_refusal(option_string))


def _resumable_assignment(text: str) -> tuple[str, Any]:
    """``--set NAME=VALUE`` of a field a resume may change, checked by its spec."""
    name = text.partition("=")[0].strip()
    if name and "=" in text and name not in RESUMABLE:
        raise argparse.ArgumentTypeError(_refusal(name))
    return assignment(text)


def add_resume_arguments(resume: argparse.ArgumentParser) -> None:
    """``eant2 resume DIR``'s arguments (`changes_of` reads the changes they ask for)."""
    resume.add_argument("dir", help="the run directory (or eant2 reproduce's directory)")
    resume.add_argument(
        "--generations",
        type=non_negative,
        default=None,
        help="new total number of generations, recorded in config.json (default: as "
        "recorded; not below the generations completed)",
    )
    resume.add_argument(
        "--task",
        default=None,
        metavar="SPEC",
        help="the task, named again: needed when the directory's task is your own code "
        "(module:factory, file.py:factory), which is never imported because a directory "
        "names it; built with the recorded task options and checked against the recorded spec",
    )
    for flag in RUN_FLAGS:
        if flag.path in RESUMABLE and flag.const is not None:
            resume.add_argument(
                *flag.flags,
                dest=flag.dest,
                action="store_const",
                const=flag.const,
                default=argparse.SUPPRESS,
                help=f"set {flag.path} to {json.dumps(flag.const)}, recorded in config.json",
            )
        elif flag.path in RESUMABLE:
            resume.add_argument(
                *flag.flags,
                dest=flag.dest,
                type=field_type(flag),
                default=argparse.SUPPRESS,  # absent unless given (null is a value)
                metavar=flag.metavar,
                help=f"new {flag.path}, recorded in config.json (default: as recorded; null: none)",
            )
        else:
            nargs = 0 if flag.const is not None else None
            resume.add_argument(*flag.flags, action=_Fixed, nargs=nargs, help=argparse.SUPPRESS)
    for option, takes_value in RUN_ONLY:
        resume.add_argument(
            option, action=_Fixed, nargs=None if takes_value else 0, help=argparse.SUPPRESS
        )
    resume.add_argument(
        "--set",
        dest="assignments",
        action="append",
        type=_resumable_assignment,
        default=[],
        metavar="NAME=VALUE",
        help=f"set one of {', '.join(RESUMABLE)} (repeatable; VALUE is JSON)",
    )
    resume.set_defaults(resumable=tuple((f.dest, f.path) for f in RUN_FLAGS if f.path in RESUMABLE))


def changes_of(args: argparse.Namespace) -> dict[str, Any]:
    """The configuration fields ``eant2 resume``'s arguments change (flags, then each
    ``--set`` in order), for `eant2_jax.resume`'s ``changes``."""
    changes = {}
    for dest, path in args.resumable:
        if hasattr(args, dest):
            changes[path] = getattr(args, dest)
    for path, value in args.assignments:
        changes[path] = value
    return changes
