"""Tasks: what a network is scored on, and the registry that names them.

``make(spec, **options)`` builds a task from a spec, which is one of

* a registered name (``xor``, ``servo``, ``dpv``, ``dpnv``; `names`);
* ``NAMESPACE:NAME`` for a registered family of tasks (``gymnax:CartPole-v1``, ``brax:hopper``,
  ``playground:CartpoleBalance``; `namespaces`);
* ``module.path:factory``, a factory in an importable module;
* ``path/to/file.py:factory`` (or ``path/to/file.py``, factory ``make_task``), a factory in
  a Python file.

``register(name, factory)`` and ``register_namespace(prefix, factory)`` add to the registry.
A task built by `make` remembers its spec and options (`spec_of`), so a run
directory records how to rebuild it: `eant2_jax.resume` rebuilds a registered task by
itself (`is_registered`), and checks a user's task, which the caller names again, against
the recorded spec (nothing a data file names is imported: docs/reliability.md, "Trust").
The protocol a task must follow is `Task` (``docs/tasks-custom.md``);
`check_task` checks it with one clear line per mistake.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
import weakref
from collections.abc import Callable
from pathlib import Path

from .base import ReportingTask as ReportingTask
from .base import Task as Task
from .base import TaskError as TaskError
from .base import check_task as check_task
from .base import map_networks as map_networks
from .base import solved_cost as solved_cost
from .regression import XOR_SOLVED as XOR_SOLVED
from .regression import Regression as Regression
from .regression import regression as regression
from .regression import xor as xor

_REGISTRY: dict[str, Callable[..., Task]] = {}
_NAMESPACES: dict[str, Callable[..., Task]] = {}
DEFAULT_FACTORY = "make_task"  # the factory of a file spec without ":factory"


def register(name: str, factory: Callable[..., Task], *, overwrite: bool = False) -> None:
    """Register a task factory under ``name`` (ValueError if taken, unless ``overwrite``)."""
    if ":" in name:
        raise ValueError(f"task name {name!r} must not contain ':' (specs use it)")
    if not overwrite and name in _REGISTRY:
        raise ValueError(f"task {name!r} is already registered")
    _REGISTRY[name] = factory


def register_namespace(
    prefix: str, factory: Callable[..., Task], *, overwrite: bool = False
) -> None:
    """Register a family of tasks: ``make("PREFIX:NAME", **o)`` calls ``factory(NAME, **o)``."""
    if not prefix.isidentifier():
        raise ValueError(f"namespace {prefix!r} must be an identifier")
    if not overwrite and prefix in _NAMESPACES:
        raise ValueError(f"namespace {prefix!r} is already registered")
    _NAMESPACES[prefix] = factory


def names() -> list[str]:
    """The registered task names, sorted."""
    return sorted(_REGISTRY)


def namespaces() -> list[str]:
    """The registered task families (``make("PREFIX:NAME")``), sorted."""
    return sorted(_NAMESPACES)


def is_registered(spec: object) -> bool:
    """Whether ``spec`` names a registered task or a task of a registered family
    (``PREFIX:NAME``): one that `make` builds without importing or running code the spec
    names. ``module:factory`` and ``file.py[:factory]`` specs are user code: a spec read
    from a data file (a run directory, a reproduction's manifest) is rebuilt by itself only
    when this holds (docs/reliability.md, "Trust")."""
    if not isinstance(spec, str) or not spec:
        return False
    if spec in _REGISTRY:
        return True
    head, sep, name = spec.partition(":")
    return bool(sep and name and head in _NAMESPACES)


# How each task made by make() was built: id(task) -> (weak reference, spec, options). A
# side table, not a field, so that a task stays the user's own pytree.
_SPECS: dict[int, tuple[weakref.ref, str, dict]] = {}


def spec_of(task: Task) -> dict | None:
    """``{"task": spec, "task_options": options}`` of a task built by `make`, else
    None. The spec is canonical (a file spec holds the file's absolute path), so
    ``make(d["task"], **d["task_options"])`` rebuilds the task from anywhere."""
    entry = _SPECS.get(id(task))
    if entry is None or entry[0]() is not task:
        return None
    return {"task": entry[1], "task_options": dict(entry[2])}


def _remember(task: Task, spec: str, options: dict) -> None:
    key = id(task)
    try:
        ref = weakref.ref(task, lambda _: _SPECS.pop(key, None))
    except TypeError:  # a type without weak references: nothing to remember
        return
    _SPECS[key] = (ref, spec, dict(options))


def _load_file(path: Path):
    """Import a Python file as a module (once per file and modification time)."""
    stamp = f"{path}:{path.stat().st_mtime_ns}"
    name = f"eant2_user_task_{path.stem}_{hashlib.sha1(stamp.encode()).hexdigest()[:10]}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ValueError(f"cannot import {path} as Python")
    module = importlib.util.module_from_spec(spec)
    # Registered before it runs: dataclasses (eant2_jax.pytree) look their module up by name.
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def _resolve(spec: str) -> tuple[Callable[..., Task], str]:
    """The factory a spec names, and the spec in canonical form."""
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"a task spec is a non-empty string, got {spec!r}")
    if spec in _REGISTRY:
        return _REGISTRY[spec], spec
    head, sep, name = spec.partition(":")
    if sep and head in _NAMESPACES:
        if not name:
            raise ValueError(f"task {spec!r}: name the task after '{head}:'")
        family = _NAMESPACES[head]

        def make_in_family(**options):
            return family(name, **options)

        make_in_family.__signature__ = _options_signature(family)
        return make_in_family, spec
    if sep:
        source, attr = spec.rsplit(":", 1)
    elif spec.endswith(".py"):
        source, attr = spec, DEFAULT_FACTORY
    else:
        families = "".join(f"{p}:NAME, " for p in namespaces())
        raise ValueError(
            f"unknown task {spec!r}; known tasks: {', '.join(names())}; "
            f"or {families}module:factory, file.py[:factory]"
        )
    if not attr.isidentifier():
        raise ValueError(f"task {spec!r}: {attr!r} is not a factory name")
    if source.endswith(".py"):
        path = Path(source).expanduser().resolve()
        if not path.is_file():
            raise ValueError(f"task {spec!r}: no such file {path}")
        module = _load_file(path)
        canonical = f"{path}:{attr}"
    else:
        try:
            module = importlib.import_module(source)
        except ModuleNotFoundError as e:
            raise ValueError(
                f"task {spec!r}: cannot import module {source!r} ({e}); is it on PYTHONPATH?"
            ) from None
        canonical = f"{source}:{attr}"
    factory = getattr(module, attr, None)
    if factory is None:
        raise ValueError(f"task {spec!r}: {source} defines no {attr!r}")
    if not callable(factory):
        raise ValueError(f"task {spec!r}: {attr!r} is a {type(factory).__name__}, not a factory")
    return factory, canonical


def _options_signature(family: Callable[..., Task]) -> inspect.Signature | None:
    """The keyword options of a family's factory ``factory(name, **options)``."""
    try:
        params = list(inspect.signature(family).parameters.values())[1:]
    except (TypeError, ValueError):
        return None
    return inspect.Signature(params)


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


def make(spec: str, **options) -> Task:
    """Build a task from its spec (module docstring) and options.

    Raises:
      ValueError: unknown name (the message lists the known ones), a module or file that
        cannot be found, a bad option, or a factory that returns something that is not a
        task (`TaskError`, naming what is missing).
    """
    factory, canonical = _resolve(spec)
    try:
        inspect.signature(factory).bind(**options)
    except TypeError as e:
        raise ValueError(f"bad options for task {spec!r}: {e}") from None
    except ValueError:  # no signature (a builtin): let the call decide
        pass
    try:
        task = factory(**options)
    except TypeError as e:
        raise ValueError(f"bad options for task {spec!r}: {e}") from None
    check_task(task, what=f"task {spec!r}")
    _remember(task, canonical, options)
    return task


register("xor", xor)


def _lazy(module: str, attr: str) -> Callable[..., Task]:
    """A factory that imports its module on first use (MJX, gymnax, brax and Playground are
    slow to import); ``resolve()`` returns the real factory (for its signature and docstring)."""

    def resolve() -> Callable[..., Task]:
        return getattr(importlib.import_module(f"{__name__}.{module}"), attr)

    def make_task(*args, **options) -> Task:
        return resolve()(*args, **options)

    make_task.__name__ = attr
    make_task.resolve = resolve
    return make_task


register("servo", _lazy("servo", "servo"))
register("dpv", _lazy("pole", "dpv"))
register("dpnv", _lazy("pole", "dpnv"))
register_namespace("gymnax", _lazy("gymnax_task", "gymnax"))
register_namespace("brax", _lazy("brax_task", "brax"))
register_namespace("playground", _lazy("playground_task", "playground"))
