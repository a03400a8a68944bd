"""The ``eant2`` process: what the command sets up around a command, before and after it.

The application's choices that the library never makes: deterministic GPU programs, the
allocator and MuJoCo settings (`process_defaults`), the backend started early
(`start_backend`), and Ctrl-C remembered and turned into exit code 130 without a traceback
(`handle_sigint`, `interruptible`, `quiet_interrupts`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

import numpy as np

__all__ = ["DETERMINISTIC_FLAG", "SIGINT", "deterministic_gpu", "handle_sigint"]
__all__ += ["interruptible", "process_defaults", "quiet_interrupts", "start_backend"]
__all__ += ["quiet_stdout", "user_modules"]

DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def deterministic_gpu(environ=None) -> bool:
    """Ask XLA for deterministic GPU programs, unless EANT2_GPU_DETERMINISTIC=0 or XLA_FLAGS
    already sets the option (the application's choice; the library never touches it).

    Without it, two fresh processes on the same GPU with the same key gave different results:
    XLA's autotuner picks kernels by timing while compiling, and kernels round differently
    (docs/benchmarks.md, "Reproducibility on GPU"). CPUs ignore the option. It must be set
    before JAX starts its backend; returns whether it is in XLA_FLAGS afterwards.
    """
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if "xla_gpu_deterministic_ops" in flags:
        return DETERMINISTIC_FLAG in flags.split()
    if environ.get("EANT2_GPU_DETERMINISTIC", "1").strip() == "0":
        return False
    environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_FLAG}".strip()
    return True


# The process's settings `process_defaults` chooses when the environment names none.
ALLOCATOR_VARS = (
    "XLA_PYTHON_CLIENT_PREALLOCATE",
    "XLA_PYTHON_CLIENT_MEM_FRACTION",
    "XLA_PYTHON_CLIENT_ALLOCATOR",
)


def process_defaults(environ=None) -> dict[str, str]:
    """The command's own process settings, each only where the environment sets none (the
    application's choice; the library never touches them). Returns what it set.

    * ``XLA_PYTHON_CLIENT_PREALLOCATE=false`` (unless any ``XLA_PYTHON_CLIENT_*`` allocator
      variable is set): JAX's GPU backend otherwise reserves 75% of the GPU's memory when it
      starts, most of the backend's start time (docs/benchmarks.md, "Cold start"), while a
      run uses a few hundred MB. Memory is then taken as programs need it and kept; results
      do not change.
    * ``MUJOCO_GL=disable``: ``import mujoco`` otherwise loads an OpenGL (GLFW) library for
      rendering; the command never renders.

    Must run before JAX starts its backend and before MuJoCo is imported.
    """
    environ = os.environ if environ is None else environ
    chosen = {}
    if not any(v in environ for v in ALLOCATOR_VARS):
        chosen["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    if "MUJOCO_GL" not in environ:
        chosen["MUJOCO_GL"] = "disable"
    environ.update(chosen)
    return chosen


# Ctrl-C, remembered. Python raises KeyboardInterrupt wherever the signal lands; when that is
# inside a callback the interpreter runs from C (the garbage collector's: XLA registers one),
# the exception is printed as "ignored" and the run went on (tests/test_loop.py's Ctrl-C test
# saw it once). The command's progress callbacks raise it again (`interruptible`), and
# the print, a traceback a user need not see, is left out (`quiet_interrupts`).
SIGINT = threading.Event()


def on_sigint(signum, frame):
    SIGINT.set()
    raise KeyboardInterrupt


def interruptible(callback):
    """``callback`` (progress events, or None), first raising KeyboardInterrupt if a Ctrl-C
    has arrived since the command started (`SIGINT`); on the main thread only, where
    `eant2_jax.app.cli.main` turns it into exit 130 (worker threads of `eant2 reproduce`
    report too)."""

    def checked(event):
        if SIGINT.is_set() and threading.current_thread() is threading.main_thread():
            raise KeyboardInterrupt
        if callback is not None:
            callback(event)

    return checked


def quiet_interrupts(previous):
    """A `sys.unraisablehook` that drops a Ctrl-C's KeyboardInterrupt raised inside a
    callback run from C (Python would print it, with a traceback, as "Exception ignored"):
    the command raises it again at its next progress event (`interruptible`). Anything
    else goes to ``previous``."""

    def hook(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and SIGINT.is_set():
            return
        previous(unraisable)

    return hook


@contextlib.contextmanager
def handle_sigint() -> Iterator[None]:
    """While the command runs: a Ctrl-C is remembered (`SIGINT`) and raised as
    KeyboardInterrupt, and its "Exception ignored" print is dropped (`quiet_interrupts`);
    the previous handler and hook are put back after (main thread only)."""
    SIGINT.clear()
    previous, hook = None, sys.unraisablehook
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, on_sigint)
        sys.unraisablehook = quiet_interrupts(hook)
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            sys.unraisablehook = hook


def quiet_stdout() -> None:
    """After a broken pipe on stdout (its reader has gone, as ``head -1`` goes): point the
    stdout descriptor at the null device, so that the interpreter's last flush of what is
    still buffered cannot fail again (Python's documented convention, "Note on SIGPIPE",
    with exit code 0 chosen: the reader stopped by choice, docs/quickstart.md)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a file (captured by a test)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def user_modules() -> None:
    """Let a task the user names (``module:factory``) import modules from the working
    directory, as ``python -m`` does (appended: installed packages are never shadowed).
    Only for a spec typed on the command line, never for one read from a file."""
    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())


def start_backend():
    """Start JAX's backend in a daemon thread and return the thread: the runtime's start and
    the first transfer to the default device (on a GPU, the context and the allocator's
    pool: docs/benchmarks.md, "Cold start") then overlap the imports of the task (MuJoCo
    MJX's among them) instead of following them. Nothing is
    computed; an error is left for the main thread to meet at its first JAX call. JAX itself
    is imported here, in this thread, so that the two threads never import it at once."""
    import jax

    def start():
        try:
            jax.device_put(np.float32(0)).block_until_ready()
        except Exception:  # noqa: BLE001, S110 -- the main thread raises it, with context
            pass

    thread = threading.Thread(target=start, name="eant2-backend", daemon=True)
    thread.start()
    return thread
