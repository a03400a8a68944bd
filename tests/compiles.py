"""Count XLA compilations through JAX's public monitoring events (not ``_cache_size()``).

JAX records the event ``/jax/core/compile/backend_compile_duration`` once per program that XLA
compiles (a persistent-cache hit included; an in-memory cache hit records nothing), with the
program's name as ``fun_name``: ``jit(<the function's __name__>)`` in jax 0.10. Eager
operations compile small programs of their own (``jit(add)``, ``jit(broadcast_in_dim)``, ...),
so "this function compiled once" is ``c.of(name) == 1``, while ``c.count == 0`` says nothing
compiled at all. ``tests/test_compiles.py`` checks that the event still fires and carries the
name, so a rename in a future JAX cannot make ``c.count == 0`` pass vacuously.

Usage::

    with count_compiles() as c:
        f(x)
    assert c.count == 0                  # nothing compiled at all
    assert c.of("rollout_batch") == 1    # the jitted function rollout_batch compiled once

``c`` is live inside the block too (read ``c.count`` between calls); blocks may nest.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
from collections.abc import Iterator

import jax

# Emitted once per program that XLA compiles (a cache hit emits nothing).
EVENT = "/jax/core/compile/backend_compile_duration"


@dataclasses.dataclass
class Compiles:
    """The compilations seen inside one :func:`count_compiles` block.

    Attributes:
      names: each compiled program's name (``fun_name``), in order, one per compilation.
      seconds: backend compile seconds, summed.
    """

    names: list[str] = dataclasses.field(default_factory=list)
    seconds: float = 0.0

    @property
    def count(self) -> int:
        """Programs compiled (any program, eager operations included)."""
        return len(self.names)

    def of(self, name: str) -> int:
        """Compilations of the jitted function named ``name`` (``"f"`` and ``"jit(f)"`` both
        match the program of ``jax.jit(f)``)."""
        return sum(_bare(n) == _bare(name) for n in self.names)

    def by_name(self) -> dict[str, int]:
        """Compilations per program name."""
        return dict(collections.Counter(self.names))


def _bare(name: str) -> str:
    """``jit(f)`` -> ``f``; ``f`` -> ``f``."""
    head, sep, rest = name.partition("(")
    return rest[:-1] if sep and rest.endswith(")") and head.isidentifier() else name


_active: list[Compiles] = []


def _listen(event: str, duration: float, **kwargs) -> None:
    if event == EVENT:
        for c in _active:
            c.names.append(str(kwargs.get("fun_name", "")))
            c.seconds += duration


jax.monitoring.register_event_duration_secs_listener(_listen)


@contextlib.contextmanager
def count_compiles() -> Iterator[Compiles]:
    """``with count_compiles() as c: ...``: ``c.count`` programs were compiled inside,
    ``c.of(name)`` of them by the jitted function ``name``."""
    c = Compiles()
    _active.append(c)
    try:
        yield c
    finally:
        _active.remove(c)


def nondeterministic_scatters(closed: jax.extend.core.ClosedJaxpr) -> list[str]:
    """The float scatters of a jaxpr (nested ones included) that do not promise unique
    indices: on a GPU they add in any order, and XLA's deterministic mode
    (``--xla_gpu_deterministic_ops``) turns each into a sort. Integer adds are exact in any
    order and are left out."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name.startswith("scatter"):
                dtype = eqn.outvars[0].aval.dtype
                if jax.numpy.issubdtype(dtype, jax.numpy.inexact):
                    if not eqn.params.get("unique_indices", False):
                        found.append(f"{eqn.primitive.name} -> {eqn.outvars[0].aval}")
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    # A sub-program is a Jaxpr (remat, ...) or a ClosedJaxpr (jit, cond,
                    # scan, while, custom_jvp, ...).
                    if hasattr(sub, "eqns"):
                        walk(sub)
                    elif hasattr(getattr(sub, "jaxpr", None), "eqns"):
                        walk(sub.jaxpr)

    walk(closed.jaxpr)
    return found


def force_compile_ahead(monkeypatch, *, fallback: bool = False) -> list:
    """Compile ahead on a CPU as on an accelerator (`eant2_jax.programs.ahead`), from an
    empty registry as in a fresh process. Returns the list of the programs compiled ahead
    that the engine then called: strictly (a mismatch of the arguments raises) unless
    ``fallback``, where the program's own fallback to jit stays as the library has it."""
    from eant2_jax import programs

    used = []
    program = programs.program

    def spy(*args, **kwargs):
        out = program(*args, **kwargs)
        if isinstance(out, programs.Program):
            used.append(out)
            return out if fallback else out.get()
        return out

    monkeypatch.setattr(programs, "ahead_enabled", lambda: True)
    monkeypatch.setattr(programs, "program", spy)
    monkeypatch.setattr(programs.REGISTRY, "ahead", {})
    monkeypatch.setattr(programs.REGISTRY, "ran", set())
    return used


def joined(fn, calls: list | None = None):
    """``fn`` (a function that starts compiling ahead), its compilations waited for at once
    (two programs at once on a CPU can deadlock XLA's thread pool), each asserted to have
    compiled; a thread it returns is joined first. ``calls`` collects what it returned."""
    from eant2_jax import programs

    def call(*args, **kwargs):
        out = fn(*args, **kwargs)
        if calls is not None:
            calls.append(out)
        if hasattr(out, "join"):
            out.join()
        for ahead in list(programs.REGISTRY.ahead.values()):
            assert ahead.get() is not None, "a program compiled ahead failed to compile"
        return out

    return call
