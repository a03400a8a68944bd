"""Count XLA compilations through JAX's public monitoring events (not ``_cache_size()``)."""

from __future__ import annotations

import contextlib
import dataclasses

import jax

# Emitted once per program that XLA compiles (a cache hit emits nothing).
EVENT = "/jax/core/compile/backend_compile_duration"


@dataclasses.dataclass
class Compiles:
    count: int = 0


_active: list[Compiles] = []


def _listen(event: str, duration: float, **kwargs) -> None:
    del duration, kwargs
    if event == EVENT:
        for c in _active:
            c.count += 1


jax.monitoring.register_event_duration_secs_listener(_listen)


@contextlib.contextmanager
def count_compiles():
    """``with count_compiles() as c: ...``; ``c.count`` programs were compiled inside."""
    c = Compiles()
    _active.append(c)
    try:
        yield c
    finally:
        _active.remove(c)
