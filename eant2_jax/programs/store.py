"""Traced engine programs kept on disk between processes, next to JAX's compilation cache.

JAX's persistent compilation cache is keyed by the *lowered* program, so every process traces
and lowers the engine program again before it can find the compiled one (docs/benchmarks.md,
"Cold start"). This store keeps the traced and lowered program itself (a
`jax.export.Exported`), keyed by everything that shapes it:

* the source of every module of this package and the versions of JAX, jaxlib, NumPy, Python
  and of the task libraries the process has imported (gymnax, brax, MuJoCo, ...);
* JAX's configuration (its plain values: x64, default matmul precision, PRNG, ...; not
  those that only say where compiled programs are cached or logged);
* the function, its static arguments, the arguments' pytree structure (static fields
  included) and each leaf's shape, dtype, weak type and placement.

A program whose task is defined outside this package is never stored: its code is not in
the key. The store lives in ``<compilation cache>/eant2-programs`` and is on exactly when
JAX's persistent compilation cache is (`eant2_jax.enable_compilation_cache`; the ``eant2``
command line turns it on); ``EANT2_PROGRAM_STORE=0`` turns it off alone.

An entry is data, never code (docs/reliability.md, "The program store"): one line of strict
JSON (the manifest: the store's format, the key, the versions of JAX and jaxlib, the size and
SHA-256 of the program's bytes, its input and output shapes and output structure) followed
by `jax.export`'s serialized bytes. Nothing is unpickled. Before the bytes are deserialized
the manifest must name this key and these versions and the hash must match; after, the
program's input shapes must be the arguments' and its outputs those of the manifest. An
entry that fails any check (damaged, another key's, another version's, not a regular file
of this user's) is never used: the program is traced again and the entry replaced. A store
folder (or the cache folder holding it) that another user owns or that others may write is
refused with one warning, as ssh refuses such an ``authorized_keys``: whoever can write
there chooses what runs. Writers write a temporary file and rename it into place, so a
reader sees an old entry or a new one; a store that cannot be written (full or read-only
disk) costs nothing but the saving.

A program from the store runs what tracing would have built: on the CPU the engine's states
and records are equal to the last bit either way (tests/test_programstore.py).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.metadata
import json
import math
import os
import stat
import sys
import tempfile
import threading
import warnings
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
def code_digest() -> bytes:
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


# JAX settings that say where and whether compiled programs are kept or logged, not what a
# program is: left out of the key, so that a moved cache folder, or another threshold of
# JAX's cache, finds the store's entries again.
_NOT_IN_KEY = (
    "jax_compilation_cache_",
    "jax_persistent_cache_",
    "jax_enable_compilation_cache",
    "jax_raise_persistent_cache_errors",
    "jax_log_compiles",
    "jax_explain_cache_misses",
    "jax_logging_level",
    "jax_debug_log_modules",
)


def _config_digest() -> bytes:
    plain = (bool, int, float, str, type(None))
    values = sorted(
        (k, v)
        for k, v in jax.config.values.items()
        if isinstance(v, plain) and not k.startswith(_NOT_IN_KEY)
    )
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


def _tree_key(treedef) -> list:
    """The pytree structure as plain data: each node's type (module and name) and aux data,
    in order (what jit's cache key holds of it)."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return ["*"]
    node, aux = treedef.node_data()
    return [
        f"{node.__module__}.{node.__qualname__}",
        repr(aux),
        *map(_tree_key, treedef.children()),
    ]


def _key(fn, leaves, treedef, static: dict) -> str:
    h = hashlib.sha256(code_digest())
    h.update(_config_digest())
    h.update(f"{fn.__module__}.{fn.__qualname__}".encode())
    h.update(repr(sorted(static.items())).encode())
    h.update(repr(_tree_key(treedef)).encode())
    h.update(repr([_leaf_key(x) for x in leaves]).encode())
    return h.hexdigest()


def _in_package(task) -> bool:
    return type(task).__module__.split(".")[0] == __name__.split(".")[0]


# ------------------------------------------------------------------------ trusted folders
class UntrustedFolderWarning(UserWarning):
    """A store or cache folder another user owns or may write was refused (no store then)."""


_WARNED: set[str] = set()


def _own(st: os.stat_result) -> bool:
    """Owned by this user and writable by nobody else (as ssh asks of ``authorized_keys``)."""
    getuid = getattr(os, "getuid", None)  # no such rule on Windows
    return getuid is None or (st.st_uid == getuid() and not st.st_mode & 0o022)


def _holds_safely(st: os.stat_result) -> bool:
    """A folder's parent: this user's or root's, and writable by others only where the
    sticky bit keeps them from renaming what they do not own (``/tmp``)."""
    getuid = getattr(os, "getuid", None)
    if getuid is None:
        return True
    return st.st_uid in (getuid(), 0) and (not st.st_mode & 0o022 or st.st_mode & stat.S_ISVTX)


def trusted_folder(path: str | os.PathLike, what: str = "program store") -> bool:
    """Whether ``path`` may hold programs this process runs: a folder this user owns that no
    other user may write (where it exists), in a parent that no other user can rename it
    in. Else one warning per folder and process (`UntrustedFolderWarning`), and False: the
    caller goes without."""
    path = Path(path)
    for folder, safe in ((path.parent, _holds_safely), (path, _own)):
        try:
            st = folder.stat()
        except FileNotFoundError:
            continue
        except OSError:
            return False
        if not stat.S_ISDIR(st.st_mode):  # not a folder: nothing can be stored there
            return False
        if not safe(st):
            if str(folder) not in _WARNED:
                _WARNED.add(str(folder))
                warnings.warn(
                    f"{what} refused: {folder} is not a folder that only its owner, this "
                    "user, can write (docs/reliability.md, the program store)",
                    UntrustedFolderWarning,
                    stacklevel=3,
                )
            return False
    return True


# ---------------------------------------------------------------------------------- entries
FORMAT = "eant2-program/2"
SUFFIX = ".program"
MAX_BYTES = 1 << 30  # an entry larger than this is not one of ours
_SERIALIZABLE: set[type] = set()


def _versions() -> dict:
    return {"jax": jax.__version__, "jaxlib": importlib.metadata.version("jaxlib")}


def _aval(shape, dtype) -> list:
    return [list(map(int, shape)), str(dtype)]


def serializable(*types: type) -> None:
    """Let `jax.export` write and read pytree nodes of these types (dataclass pytrees of
    this package whose static fields are plain values) by name: the output structure of
    a stored program is data in its bytes, rebuilt only from types registered here."""
    for cls in types:
        if cls in _SERIALIZABLE:
            continue
        export.register_pytree_node_serialization(
            cls,
            serialized_name=f"{cls.__module__}.{cls.__qualname__}",
            serialize_auxdata=lambda aux: json.dumps(_plain(aux)).encode(),
            deserialize_auxdata=lambda blob: _unplain(json.loads(bytes(blob))),
        )
        _SERIALIZABLE.add(cls)


def _plain(aux):
    """Aux data as JSON (tuples tagged); TypeError for anything but plain values."""
    if isinstance(aux, tuple | list):
        return {"tuple" if isinstance(aux, tuple) else "list": [_plain(a) for a in aux]}
    if aux is None or type(aux) in (bool, int, str) or (type(aux) is float and math.isfinite(aux)):
        return aux
    raise TypeError(f"aux data {type(aux).__name__} is not plain")


def _unplain(data):
    if isinstance(data, dict):
        ((kind, items),) = data.items()
        items = [_unplain(a) for a in items]
        return tuple(items) if kind == "tuple" else items
    return data


def _strict_json(text: bytes):
    def refuse(name):
        raise ValueError(f"not strict JSON: {name}")

    return json.loads(text.decode("utf-8"), parse_constant=refuse)


def _in_avals(leaves) -> list:
    """The input shapes and dtypes a program of these arguments has (as `jax.export`
    abstracts them: Python numbers by JAX's dtype rules)."""
    return [_aval(a.shape, a.dtype) for a in jax.eval_shape(lambda *a: a, *leaves)]


def read_entry(path: Path, key: str, leaves) -> export.Exported | None:
    """The program of the entry at ``path`` if every check passes (module docstring), else
    None: missing, damaged, foreign, of other versions, not this user's regular file."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:  # non-blocking: a FIFO planted as an entry must not hang the run
        fd = os.open(path, flags)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not (stat.S_ISREG(st.st_mode) and _own(st)):  # a folder, FIFO, device...
            return None
        with os.fdopen(os.dup(fd), "rb") as f:
            data = f.read(MAX_BYTES + 1)
    except OSError:
        return None
    finally:
        os.close(fd)
    head, sep, payload = data.partition(b"\n")
    try:
        manifest = _strict_json(head)
        expected = {"format": FORMAT, "key": key, **_versions()}
        if not (
            sep
            and isinstance(manifest, dict)
            and all(manifest.get(k) == v for k, v in expected.items())
            and manifest.get("bytes") == len(payload)
            and manifest.get("sha256") == hashlib.sha256(payload).hexdigest()
            and manifest.get("in_avals") == _in_avals(leaves)
        ):
            return None
        exported = export.deserialize(bytearray(payload))
        exported.mlir_module()  # deserialize parses lazily: damaged StableHLO fails here
        # Calling it lowers the module into the caller's: bytes that parse but do not lower
        # (a forged entry whose entry function lost its name) fail here, not in the run.
        jax.jit(exported.call).lower(*leaves)
    except Exception:  # noqa: BLE001 - traced again and replaced
        return None
    if not (
        [_aval(a.shape, a.dtype) for a in exported.in_avals] == manifest["in_avals"]
        and [_aval(a.shape, a.dtype) for a in exported.out_avals] == manifest.get("out_avals")
        and str(exported.out_tree) == manifest.get("out_tree")
        and jax.default_backend() in exported.platforms
    ):
        return None
    return exported


def _write(folder: Path, path: Path, key: str, exported: export.Exported) -> None:
    """Write the entry (manifest line and bytes) atomically; nothing where it cannot."""
    try:
        payload = bytes(exported.serialize())
        manifest = {
            "format": FORMAT,
            "key": key,
            **_versions(),
            "bytes": len(payload),
            "sha256": hashlib.sha256(payload).hexdigest(),
            "in_avals": [_aval(a.shape, a.dtype) for a in exported.in_avals],
            "out_avals": [_aval(a.shape, a.dtype) for a in exported.out_avals],
            "out_tree": str(exported.out_tree),
        }
        head = json.dumps(manifest, sort_keys=True, allow_nan=False).encode()
    except Exception:  # noqa: BLE001 - e.g. a node type not `serializable`: not stored
        return
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        if not trusted_folder(folder):
            return
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(head + b"\n" + payload)
        os.replace(tmp, path)  # atomic: a reader sees the old entry or the new one
        tmp = None
    except OSError:  # full or read-only disk: no saving
        pass
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _wrap(fn, exported: export.Exported) -> Callable:
    """A jitted function of the original arguments' pytree that runs ``exported``, named as
    ``fn`` (JAX's compile log and `eant2_jax.programs.stats` name programs by function)."""

    def call(*args):
        return exported.call(*jax.tree.leaves(args))

    call.__name__ = call.__qualname__ = fn.__name__
    return jax.jit(call)


_STORABLE: dict[Callable, int] = {}  # the functions whose programs may be stored: task's place
_FAILED: list[bool] = []


def storable(fn, *, task_at: int, types: tuple[type, ...] = ()):
    """Let the store hold ``fn``'s programs: a jitted function whose ``task_at``-th argument
    is the task, and whose outputs are pytrees of these `serializable` types (and tuples,
    lists, dicts, None). Returns ``fn``."""
    serializable(*types)
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
    program read from the store (traced and stored first when the store lacks it, or its
    entry fails a check). None where the store is off, refused (`trusted_folder`) or cannot
    hold this program (a task from outside this package, an argument it cannot key); the
    caller then uses ``fn`` as it is.

    ``fn`` is a jitted function; ``args`` may hold ``jax.ShapeDtypeStruct`` leaves (with
    the sharding of the arrays they stand for)."""
    folder = directory()
    if folder is None or not _in_package(task):
        return None
    if not (trusted_folder(folder.parent, "compilation cache") and trusted_folder(folder)):
        return None
    leaves, treedef = jax.tree.flatten(args)
    try:
        key = _key(fn, leaves, treedef, static)
    except (TypeError, AttributeError):
        return None
    with _LOCK:
        if key in _PROGRAMS:
            return _PROGRAMS[key]
    path = folder / f"{key}{SUFFIX}"
    exported = read_entry(path, key, leaves)
    if exported is None:

        def flat(*flat_args):
            return fn(*jax.tree.unflatten(treedef, flat_args), **static)

        exported = export.export(jax.jit(flat), disabled_checks=UNSTABLE_CUSTOM_CALLS)(*leaves)
        _write(folder, path, key, exported)
    call = _wrap(fn, exported)
    with _LOCK:
        return _PROGRAMS.setdefault(key, call)
