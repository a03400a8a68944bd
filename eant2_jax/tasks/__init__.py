"""Tasks: what a network is scored on, and the registry that names them.

``make(name, **options)`` builds a registered task; ``register(name, factory)`` adds one.
"""

from __future__ import annotations

from collections.abc import Callable

from .base import ReportingTask as ReportingTask
from .base import Task as Task
from .base import map_networks as map_networks
from .regression import Regression as Regression
from .regression import regression as regression
from .regression import xor as xor

_REGISTRY: dict[str, Callable[..., Task]] = {}


def register(name: str, factory: Callable[..., Task], *, overwrite: bool = False) -> None:
    """Register a task factory under ``name`` (ValueError if taken, unless ``overwrite``)."""
    if not overwrite and name in _REGISTRY:
        raise ValueError(f"task {name!r} is already registered")
    _REGISTRY[name] = factory


def names() -> list[str]:
    """The registered task names, sorted."""
    return sorted(_REGISTRY)


def factory(name: str) -> Callable[..., Task]:
    """The factory registered as ``name`` (a lazily imported one is imported now)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(names())}")
    f = _REGISTRY[name]
    return getattr(f, "resolve", lambda: f)()


def options(name: str) -> dict[str, object]:
    """The options of task ``name``: its factory's keyword arguments and their defaults
    (``inspect.Parameter.empty`` for a required one)."""
    import inspect

    params = inspect.signature(factory(name)).parameters.values()
    return {
        p.name: p.default for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
    }


def make(name: str, **options) -> Task:
    """Build the registered task ``name`` with its options.

    Raises:
      ValueError: unknown name (the message lists the known ones) or a bad option.
    """
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(names())}") from None
    try:
        return factory(**options)
    except TypeError as e:
        raise ValueError(f"bad options for task {name!r}: {e}") from None


register("xor", xor)


def _lazy(module: str, attr: str) -> Callable[..., Task]:
    """A factory that imports its module on first use (MJX is slow to import); ``resolve()``
    returns the real factory (for its signature and docstring)."""
    import importlib

    def resolve() -> Callable[..., Task]:
        return getattr(importlib.import_module(f"{__name__}.{module}"), attr)

    def make_task(**options) -> Task:
        return resolve()(**options)

    make_task.__name__ = attr
    make_task.resolve = resolve
    return make_task


register("servo", _lazy("servo", "servo"))
register("dpv", _lazy("pole", "dpv"))
register("dpnv", _lazy("pole", "dpnv"))
