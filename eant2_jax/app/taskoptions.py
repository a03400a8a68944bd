"""``--task-option KEY=VALUE``: a task's options from the command line, each checked
against the type of its default so that a wrong value names its option (``--task-option
max_steps=abc: expected an integer``) instead of failing inside the task's factory."""

from __future__ import annotations

import inspect
import json
from typing import Any

from ..jsonio import loads

__all__ = ["read_value", "task_options"]


def read_value(text: str) -> Any:
    """An option's value: strict JSON if it is JSON (``0.3``, ``null``, ``[8, 40, 4]``),
    else the text itself (``covariance``)."""
    try:
        return loads(text, "the value")
    except ValueError:
        return text


def _defaults(spec: str | None) -> dict[str, Any]:
    """The options a registered task's factory takes, with their defaults ({} for a task
    that is not registered: a user's factory is not imported to look)."""
    from eant2_jax import tasks

    if spec is None or spec not in tasks.names():
        return {}
    return tasks.options(spec)


def _expected(default: Any, value: Any) -> str | None:
    """What ``value`` should have been, given the option's default; None if it fits."""
    if isinstance(default, bool):
        return None if isinstance(value, bool) else "true or false"
    if isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
        return None if ok else "an integer"
    if isinstance(default, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        return None if ok else "a number"
    if isinstance(default, str):
        return None if isinstance(value, str) else "a string"
    return None  # None, required or another type: the factory decides


def task_options(pairs: list[str], spec: str | None = None) -> dict:
    """``--task-option KEY=VALUE`` pairs as a dict (VALUE: JSON, else the text), each
    value of a registered task ``spec`` checked against its default's type.

    Raises:
      ValueError: one line naming the option: not KEY=VALUE, or a value of the wrong type.
    """
    defaults = _defaults(spec)
    out = {}
    for pair in pairs:
        if "=" not in pair:
            raise ValueError(f"--task-option expects KEY=VALUE, got {pair!r}")
        k, v = pair.split("=", 1)
        out[k] = read_value(v)
        default = defaults.get(k, inspect.Parameter.empty)
        want = None if default is inspect.Parameter.empty else _expected(default, out[k])
        if want is not None:
            raise ValueError(
                f"--task-option {k}={v!s:.40}: expected {want} (the default is "
                f"{json.dumps(default)})"
            )
    return out
