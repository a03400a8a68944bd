"""Traced engine programs kept on disk between processes, next to JAX's compilation cache.

JAX's persistent compilation cache is keyed by the *lowered* program, so every process traces
and lowers the engine program again before it can find the compiled one: on an H100 host
that was 1.4 s of a warm `eant2 run servo` start (docs/benchmarks.md, "Cold start"). This
store keeps the traced and lowered program itself (a `jax.export.Exported`), keyed by
everything that shapes it:

* the source of every module of this package and the versions of JAX, jaxlib, NumPy, Python
  and of the task libraries the process has imported (gymnax, brax, MuJoCo, ...);
* JAX's configuration (its plain values: x64, default matmul precision, PRNG, ...);
* the function, its static arguments, the arguments' pytree structure (static fields
  included) and each leaf's shape, dtype, weak type and placement.

A program whose task is defined outside this package is never stored: its code is not in
the key. The store lives in ``<compilation cache>/eant2-programs`` and is on exactly when
JAX's persistent compilation cache is (`eant2_jax.enable_compilation_cache`; the ``eant2``
command line turns it on); ``EANT2_PROGRAM_STORE=0`` turns it off alone.

A program from the store runs what tracing would have built: on the CPU the engine's states
and records are equal to the last bit either way (tests/test_programstore.py). Every stored
program is also how the process that traced it runs it, so a run computes the same with a
cold and a warm store. An unreadable or foreign file is traced again and replaced; a store
that cannot be written costs nothing but the saving. The files are Python pickles: like the
modules a process imports, the folder must be writable by its owner alone.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import os
import pickle
import sys
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from jax import export

DIRNAME = "eant2-programs"
# Libraries whose code a task of this package may trace (their versions join the key).
_TASK_LIBRARIES = ("mujoco", "mujoco-mjx", "gymnax", "brax", "playground", "flax", "chex")
_PROGRAMS: dict[str, Callable] = {}  # this process's, by key
# Custom calls whose form jax.export does not promise to keep across versions, which the
# store holds all the same: its key has the versions of JAX and jaxlib, so a program is read
# back only by the versions that wrote it. The network step's Triton kernel
# (`eant2_jax.kernels.netfused`) is one; refused, every GPU engine program was traced anew.
UNSTABLE_CUSTOM_CALLS = (export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton"),)
_LOCK = threading.Lock()


def directory() -> Path | None:
    """The store's folder, or None when it is off."""
    if os.environ.get("EANT2_PROGRAM_STORE", "1").strip() == "0":
        return None
    cache = jax.config.jax_compilation_cache_dir
    return Path(cache) / DIRNAME if cache else None


@functools.cache
def _code_digest() -> bytes:
    """This package's source and the versions of what it runs on (once per process)."""
    from .. import kernels  # a folder of its own in a source checkout (pyproject.toml)

    h = hashlib.sha256()
    # Named as in an installed package (``kernels/cmaes.py``), whichever the layout.
    files = {}
    package = sys.modules[__name__.split(".")[0]]
    for prefix, paths in (("", package.__path__), ("kernels/", kernels.__path__)):
        for root in map(Path, paths):
            for f in root.rglob("*.py"):
                name = f.relative_to(root).as_posix()
                files.setdefault(name if name.startswith(prefix) else prefix + name, f)
    for name in sorted(files):
        h.update(name.encode())
        h.update(files[name].read_bytes())
    versions = [sys.version, jax.__version__, np.__version__]
    for dist in ("jaxlib", *_TASK_LIBRARIES):
        try:
            versions.append(f"{dist}={importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{dist}=none")
    h.update(repr(versions).encode())
    return h.digest()


def _config_digest() -> bytes:
    plain = (bool, int, float, str, type(None))
    values = sorted((k, v) for k, v in jax.config.values.items() if isinstance(v, plain))
    return repr(values).encode()


def _leaf_key(x) -> tuple:
    if isinstance(x, jax.Array | jax.ShapeDtypeStruct):
        committed = x.committed if isinstance(x, jax.Array) else x.sharding is not None
        placement = repr(x.sharding) if committed else "uncommitted"
        weak = getattr(x, "weak_type", False)  # typed PRNG key arrays have none
        return ("array", x.shape, str(x.dtype), bool(weak), placement)
    if isinstance(x, np.ndarray | np.generic):
        return ("numpy", x.shape, str(x.dtype))
    if type(x) in (bool, int, float):
        return ("python", type(x).__name__)
    raise TypeError(f"unsupported leaf {type(x).__name__}")


def _key(fn, leaves, treedef, static: dict) -> str:
    h = hashlib.sha256(_code_digest())
    h.update(_config_digest())
    h.update(f"{fn.__module__}.{fn.__qualname__}".encode())
    h.update(repr(sorted(static.items())).encode())
    h.update(pickle.dumps(treedef))
    h.update(repr([_leaf_key(x) for x in leaves]).encode())
    return h.hexdigest()


def _in_package(task) -> bool:
    return type(task).__module__.split(".")[0] == __name__.split(".")[0]


def _wrap(fn, exported: export.Exported, out_tree) -> Callable:
    """A jitted function of the original arguments' pytree that runs ``exported``, named as
    ``fn`` (JAX's compile log and `eant2_jax.compilestats` name programs by function)."""

    def call(*args):
        return jax.tree.unflatten(out_tree, exported.call(*jax.tree.leaves(args)))

    call.__name__ = call.__qualname__ = fn.__name__
    return jax.jit(call)


def _read(path: Path):
    """``(exported, out_tree)`` from ``path``, or None: missing, partial or foreign."""
    try:
        exported, out_tree = pickle.loads(path.read_bytes())
    except Exception:  # noqa: BLE001 - traced again
        return None
    return (exported, out_tree) if isinstance(exported, export.Exported) else None


def _write(path: Path, exported: export.Exported, out_tree) -> None:
    # The VJP builder is a closure (not picklable) and never used: the engine is not
    # differentiated.
    blob = pickle.dumps((dataclasses.replace(exported, _get_vjp=None), out_tree))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        os.replace(tmp, path)  # atomic: a reader sees the old file or the new one
    except OSError:
        pass


_STORABLE: dict[Callable, int] = {}  # the functions whose programs may be stored: task's place
_FAILED: list[bool] = []


def storable(fn, *, task_at: int):
    """Let the store hold ``fn``'s programs (a jitted function whose ``task_at``-th argument
    is the task); returns ``fn``."""
    _STORABLE[fn] = task_at
    return fn


def program(fn, args: tuple, static: dict) -> Callable | None:
    """`lookup` for a function `storable` registered, or None (the store is off, cannot
    hold it, or failed before in this process: each try traces)."""
    if fn not in _STORABLE or _FAILED:
        return None
    try:
        return lookup(fn, args, static, task=args[_STORABLE[fn]])
    except Exception:  # noqa: BLE001 - e.g. an operation jax.export refuses: trace as usual
        _FAILED.append(True)
        return None


def lookup(fn, args: tuple, static: dict, *, task) -> Callable | None:
    """``functools.partial(fn, **static)`` for arguments shaped like ``args``, its traced
    program read from the store (traced and stored first when the store lacks it). None
    where the store is off or cannot hold this program (a task from outside this package,
    an argument it cannot key); the caller then uses ``fn`` as it is.

    ``fn`` is a jitted function; ``args`` may hold ``jax.ShapeDtypeStruct`` leaves (with
    the sharding of the arrays they stand for)."""
    folder = directory()
    if folder is None or not _in_package(task):
        return None
    leaves, treedef = jax.tree.flatten(args)
    try:
        key = _key(fn, leaves, treedef, static)
    except (TypeError, pickle.PicklingError, AttributeError):
        return None
    with _LOCK:
        if key in _PROGRAMS:
            return _PROGRAMS[key]
    path = folder / f"{key}.pkl"
    stored = _read(path)
    if stored is not None:
        exported, out_tree = stored
    else:
        box = {}

        def flat(*flat_args):
            out = fn(*jax.tree.unflatten(treedef, flat_args), **static)
            out_leaves, box["out_tree"] = jax.tree.flatten(out)
            return out_leaves

        exported = export.export(jax.jit(flat), disabled_checks=UNSTABLE_CUSTOM_CALLS)(*leaves)
        out_tree = box["out_tree"]
        _write(path, exported, out_tree)
    call = _wrap(fn, exported, out_tree)
    with _LOCK:
        return _PROGRAMS.setdefault(key, call)
