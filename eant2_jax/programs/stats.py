"""Process-wide XLA compilation statistics, from JAX's public monitoring events.

A run records, per generation, how many programs XLA compiled, the seconds JAX spent tracing,
lowering and compiling, and the persistent compilation cache's hits and misses
(`eant2_jax.enable_compilation_cache`), so that a user can tell a slow generation that
compiled from one that ran (`eant2_jax.loop.GenerationRecord`).

The counts are those of the whole process: in a process that runs several EANT2 runs at once
(`eant2_jax.run_many`), a generation's record counts every run's compilations in its time.

::

    before = stats.snapshot()
    ...  # anything that may compile
    spent = stats.snapshot() - before
"""

from __future__ import annotations

import dataclasses
import threading

import jax

__all__ = ["CompileStats", "snapshot"]

# Emitted once per program XLA compiles (a persistent-cache load included; an in-memory
# cache hit emits nothing), and for its tracing and lowering.
_DURATIONS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}
_PROGRAM = "/jax/core/compile/backend_compile_duration"
_HIT = "/jax/compilation_cache/cache_hits"
_MISS = "/jax/compilation_cache/cache_misses"


@dataclasses.dataclass(frozen=True)
class CompileStats:
    """Compilation counts (of the process so far, or a difference of two snapshots).

    Attributes:
      programs: programs XLA compiled or loaded from the persistent cache.
      trace_s, lower_s, compile_s: seconds spent tracing, lowering and compiling (or
        loading) them.
      cache_hits, cache_misses: persistent-cache lookups that found a program and that did
        not (both 0 while the cache is off).
    """

    programs: int = 0
    trace_s: float = 0.0
    lower_s: float = 0.0
    compile_s: float = 0.0
    cache_hits: int = 0
    cache_misses: int = 0

    @property
    def seconds(self) -> float:
        """Tracing, lowering and compiling together."""
        return self.trace_s + self.lower_s + self.compile_s

    def __sub__(self, other: CompileStats) -> CompileStats:
        return CompileStats(
            **{
                f.name: getattr(self, f.name) - getattr(other, f.name)
                for f in dataclasses.fields(self)
            }
        )


_lock = threading.Lock()
_totals = {f.name: f.default for f in dataclasses.fields(CompileStats)}
_listening = False


def _on_duration(name: str, seconds: float, **kwargs) -> None:
    del kwargs
    field = _DURATIONS.get(name)
    if field is not None:
        with _lock:
            _totals[field] += seconds
            _totals["programs"] += name == _PROGRAM


def _on_event(name: str, **kwargs) -> None:
    del kwargs
    if name in (_HIT, _MISS):
        with _lock:
            _totals["cache_hits" if name == _HIT else "cache_misses"] += 1


def snapshot() -> CompileStats:
    """The process's totals since the first call (which starts listening; JAX offers no
    way to stop a listener, and one that counts is cheap)."""
    global _listening
    with _lock:
        if not _listening:
            jax.monitoring.register_event_duration_secs_listener(_on_duration)
            jax.monitoring.register_event_listener(_on_event)
            _listening = True
        return CompileStats(**_totals)
