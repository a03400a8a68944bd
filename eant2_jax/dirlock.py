"""The run directory's lock primitive: ``fcntl`` where the platform has it, else a stand-in.

A run directory is held by an exclusive, non-blocking ``flock`` on a descriptor of the
directory itself (`eant2_jax.rundir`, docs/reliability.md "Guarantees"): a second holder is
refused, even a second descriptor in the same process; the lock follows the inode across a
rename; the OS drops it when the holder dies, however it dies. ``filelock`` (a lock FILE) gives
none of the last two, and run directories need more of POSIX than the lock (directory
descriptors, ``dir_fd``, ``O_NOFOLLOW``), so the lock stays ``flock``.

Where ``fcntl`` is missing (Windows), importing the package still works; run directories are
not available there (they need POSIX directory descriptors as well as the lock), and the
stand-in's ``flock`` raises an `OSError` saying why, so nothing is ever written unlocked.

Modules import ``fcntl`` from here (``from .dirlock import fcntl``) and call it as usual.
"""

from __future__ import annotations

import errno

__all__ = ["fcntl", "HAS_FLOCK"]


class _NoFlock:
    """Stands in for the ``fcntl`` module where it is missing: ``flock`` refuses."""

    LOCK_SH, LOCK_EX, LOCK_NB, LOCK_UN = 1, 2, 4, 8  # Linux's values; never passed to an OS

    @staticmethod
    def flock(fd: int, operation: int) -> None:
        raise OSError(
            errno.ENOTSUP, "run directories need flock (POSIX), which this platform lacks"
        )


try:
    import fcntl
except ImportError:  # Windows
    fcntl = _NoFlock()
HAS_FLOCK = not isinstance(fcntl, _NoFlock)
