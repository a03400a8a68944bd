"""The ``eant2`` command line: `main` and the installed entry point, `entry`.

The arguments are built in `eant2_jax.app.parser`, the commands are in
`eant2_jax.app.commands` (one function each), and what the process sets up around a
command (GPU determinism, allocator, backend start, Ctrl-C) in `eant2_jax.app.process`.
The library never prints; these modules render.
"""

from __future__ import annotations

import sys

from . import process
from .parser import build_parser

__all__ = ["entry", "main"]

# The commands that run the engine: they get the process's settings and an early backend.
_ENGINE_COMMANDS = ("run", "resume", "reproduce")


def main(argv: list[str] | None = None) -> int:
    """Run one ``eant2`` command; return its exit code: 0, 2 for a mistake (one line on
    stderr), 130 after Ctrl-C. Argument errors exit through argparse (code 2, one line).

    A reader that stops early (``eant2 tasks | head -1``) ends the command quietly with
    exit code 0: nothing on stderr, the rest of the output dropped (`process.quiet_stdout`).
    """
    with process.handle_sigint():
        try:
            rc = _command(argv)
            sys.stdout.flush()  # a closed pipe shows here, not at the interpreter's exit
        except BrokenPipeError:
            process.quiet_stdout()
            return 0
        return rc


def _command(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    process.deterministic_gpu()
    engine = args.command in _ENGINE_COMMANDS
    if engine:
        process.process_defaults()
    from eant2_jax.config import enable_compilation_cache

    # Compiled programs kept between runs (the application's choice; the library never
    # touches global JAX settings); EANT2_CACHE_DIR moves it, an empty value turns it off.
    enable_compilation_cache()
    from eant2_jax.distributed import initialize

    from .commands import COMMANDS

    initialize()  # joins a multi-process run when EANT2_COORDINATOR etc. are set
    backend = process.start_backend() if engine else None
    try:
        return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        # `eant2 run`/`reproduce` name their directory --out, `eant2 resume` takes DIR.
        where = getattr(args, "out", None) or getattr(args, "dir", None)
        print(
            "\neant2: interrupted; every completed generation is saved"
            + (f" (continue with: eant2 resume {where})" if where else ""),
            file=sys.stderr,
        )
        return 130
    except BrokenPipeError:
        raise  # the reader has gone: `main` ends quietly
    except (ValueError, OSError) as e:
        print(f"eant2: error: {e}", file=sys.stderr)
        return 2
    finally:
        if backend is not None:  # never exit while it is inside the runtime's start
            backend.join()


def entry() -> None:
    """The ``eant2`` command: `main`, then the exit.

    After a Ctrl-C, runs of `eant2_jax.run_many` may still be inside a compiled program in
    their worker threads; letting the interpreter tear down under them aborted the process
    ("terminate called ... FATAL: exception not rethrown", exit 134, on a GPU and on this
    CPU). Every completed generation is already on disk (each commit is atomic), so the
    process ends at once, as a kill would end it. (A worker counts while it is listed: a
    join interrupted by Ctrl-C can leave `Thread.is_alive` False for a thread still running.)
    """
    import os
    import threading

    from eant2_jax.multirun import WORKER

    rc = main()
    if rc == 130 and any(t.name.startswith(WORKER) for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    entry()
