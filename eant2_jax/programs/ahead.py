"""Programs compiled ahead, in background threads, and the one way to call them.

`ahead` starts compiling a jitted function's program for arguments shaped like given ones
(a later generation's bucket, say) while the current program runs; `program` gives the
callable that runs it: the one compiled ahead (falling back by itself to jit's own path
where the arguments do not fit it after all), else the one from the program store
(`eant2_jax.programs.store`), else the function itself. Each is the program jit would
compile (same lowering), so results do not change.

The process keeps one `Registry`, ``REGISTRY`` (never rebound): the programs started, and
which programs have run. A test empties its fields (``monkeypatch.setattr(programs.REGISTRY,
"ahead", {})``) to act as a new process.
"""

from __future__ import annotations

import atexit
import dataclasses
import threading
from collections.abc import Callable

import jax
import numpy as np

from . import store

__all__ = [
    "REGISTRY",
    "Program",
    "Registry",
    "ahead",
    "ahead_enabled",
    "first_run",
    "has_run",
    "join_at_exit",
    "program",
    "started",
]

_BACKGROUND: list[threading.Thread] = []


def join_at_exit(thread: threading.Thread) -> None:
    """Have the interpreter wait for ``thread`` (a background compilation) at exit: a
    daemon thread still inside XLA's compiler when the interpreter tears down crashed the
    process (SIGSEGV) on a GPU."""
    _BACKGROUND[:] = [t for t in _BACKGROUND if t.is_alive()] + [thread]


@atexit.register
def _join_background() -> None:
    for t in list(_BACKGROUND):
        t.join()


def ahead_enabled() -> bool:
    """Whether programs are compiled ahead in background threads: on an accelerator. Not on
    a CPU, where XLA's compiler would compete with the running program for the few cores
    (and two programs at once can deadlock XLA's thread pool)."""
    return jax.default_backend() != "cpu"


def signature(args) -> tuple:
    """What jit keys its cache on: the pytree structure (static fields included) and each
    leaf's shape and dtype."""
    leaves, treedef = jax.tree.flatten(args)
    return (treedef, tuple((np.shape(a), getattr(a, "dtype", type(a))) for a in leaves))


def _key(fn, args: tuple, static: dict) -> tuple:
    return (fn, signature(args), tuple(sorted(static.items())))


class Program:
    """``fn``'s program for arguments shaped like ``args`` (and these static arguments),
    compiled in a background thread.

    Calling it with arguments of that shape runs the compiled program (waiting for it);
    where compiling failed or the arguments do not fit it (other shapes or placements than
    foreseen), it runs ``fn`` itself, as jit would. ``calls`` and ``fallbacks`` count the
    calls and those of them that ran ``fn``.
    """

    def __init__(self, fn, args: tuple, static: dict):
        self.fn, self.static = fn, static
        self.compiled = None
        self.calls = self.fallbacks = 0
        self._thread = threading.Thread(
            target=self._compile, args=(fn, args, static), name="eant2-compile-ahead",
            daemon=True,
        )  # fmt: skip
        self._thread.start()
        join_at_exit(self._thread)

    def _compile(self, fn, args, static):
        try:
            stored = store.program(fn, args, static)
            lowered = fn.lower(*args, **static) if stored is None else stored.lower(*args)
            self.compiled = lowered.compile()
        except Exception:  # noqa: BLE001 - the call then runs fn, which compiles as usual
            self.compiled = None

    def get(self):
        """The compiled program (waiting for it), or None if compiling failed."""
        self._thread.join()
        return self.compiled

    def __call__(self, *args):
        self.calls += 1
        compiled = self.get()
        if compiled is not None:
            try:
                return compiled(*args)
            except (TypeError, ValueError):  # arguments not as foreseen: jit's own path
                pass
        self.fallbacks += 1
        return self.fn(*args, **self.static)


@dataclasses.dataclass
class Registry:
    """The process's programs compiled ahead and the programs it has run.

    Attributes:
      ahead: `Program` by what jit keys its cache on (function, argument signature, static
        arguments). Like jit's own cache they live as long as the process (a run has a few
        buckets); jit's cache never holds them.
      ran: the keys of the programs `first_run` was told of.
    """

    ahead: dict[tuple, Program] = dataclasses.field(default_factory=dict)
    ran: set[tuple] = dataclasses.field(default_factory=set)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)


REGISTRY = Registry()


def ahead(fn, args: tuple, **static) -> Program:
    """``fn``'s program for arguments shaped like ``args`` (``jax.ShapeDtypeStruct``
    leaves allowed), compiled in a background thread: the one compiled or compiling
    already, else a new compilation. Call the `Program` with ``args`` alone."""
    key = _key(fn, args, static)
    with REGISTRY.lock:
        if key not in REGISTRY.ahead:
            REGISTRY.ahead[key] = Program(fn, args, static)
        return REGISTRY.ahead[key]


def started(fn, args: tuple, **static) -> Program | None:
    """The `Program` `ahead` started for such arguments, or None."""
    with REGISTRY.lock:
        return REGISTRY.ahead.get(_key(fn, args, static))


def program(fn, args: tuple, **static) -> Callable:
    """What runs ``fn(*args, **static)``: the program compiled ahead for such arguments
    (it falls back by itself), else the one from the program store, else ``fn`` itself
    with the static arguments bound. Call it with ``args`` alone."""
    early = started(fn, args, **static)
    if early is not None and early.get() is not None:
        return early
    stored = store.program(fn, args, static)
    if stored is not None:
        return stored

    def call(*a):
        return fn(*a, **static)

    return call


def has_run(fn, args: tuple, **static) -> bool:
    """Whether `first_run` was told of this program (jit's cache then holds it)."""
    return _key(fn, args, static) in REGISTRY.ran


def first_run(fn, args: tuple, **static) -> bool:
    """Whether this is the first run of ``fn``'s program for such arguments in this
    process; records it. Host-side bookkeeping (progress events) only."""
    key = _key(fn, args, static)
    with REGISTRY.lock:
        if key in REGISTRY.ran:
            return False
        REGISTRY.ran.add(key)
        return True
