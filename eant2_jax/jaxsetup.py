"""Process-wide JAX settings a user turns on once, first: 64-bit mode and the persistent
compilation cache. The library itself never changes global JAX settings (the ``eant2``
command line calls `enable_compilation_cache`)."""

from __future__ import annotations

import math
import os
from pathlib import Path

__all__ = ["enable_compilation_cache", "enable_x64"]


def enable_x64() -> None:
    """Turn on JAX's 64-bit mode, which ``ExploitConfig(dtype="float64")`` needs. Call it
    before any array is made: arrays made earlier keep their 32-bit types."""
    import jax

    jax.config.update("jax_enable_x64", True)


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_secs: float = 0.0
) -> Path | None:
    """Keep compiled XLA programs on disk between processes (JAX's persistent compilation
    cache, with XLA's GPU autotuning results): a second run of the same programs loads
    them instead of compiling (on a GPU, a servo run's first generation went from 22.9 s
    to 12.4 s: docs/benchmarks.md). With it, the engine's traced programs are kept too
    (`eant2_jax.programs.store`, in the folder's ``eant2-programs``), so that a later process
    neither traces nor compiles them. The ``eant2`` command line calls it; the library
    itself never changes global JAX settings, so Python users call it once, first.

    Args:
      path: the cache folder; default ``$EANT2_CACHE_DIR``, else
        ``~/.cache/eant2_jax/xla``. An empty ``EANT2_CACHE_DIR`` (or ``path=""``) turns the
        cache off.
      min_compile_secs: keep only programs that took at least this long to compile (0:
        every program, so that a warm start compiles nothing).

    Returns:
      The folder used, or None when the cache is off.
    """
    import jax

    from .programs import store as programs_store

    if path is None:
        path = os.environ.get("EANT2_CACHE_DIR", str(Path.home() / ".cache" / "eant2_jax" / "xla"))
    if not str(path):
        return None
    path = Path(path).expanduser()
    if not (min_compile_secs >= 0 and math.isfinite(min_compile_secs)):
        raise ValueError(f"min_compile_secs must be >= 0 and finite, got {min_compile_secs!r}")
    if not programs_store.trusted_folder(path, "compilation cache"):  # as ssh: others' or shared
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_secs))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
