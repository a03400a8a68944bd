"""A new directory made atomically: built under a hidden name, locked, renamed into place.

`eant2_jax.rundir.RunDir.create` builds a run directory this way, so the path is either
absent or a complete directory; the hidden directory of a process killed while creating is
removed by the next creation of the same path (`remove_dead_creations`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

from .dirlock import fcntl

__all__ = ["CREATING", "Vanished", "locked_temp_dir", "remove_dead_creations"]

CREATING = ".creating-"


class Vanished(Exception):
    """A creation's new directory was removed under it (see `remove_dead_creations`)."""


class Unlockable(Exception):
    """A creation's new directory stayed locked by another process."""


def locked_temp_dir(p: Path) -> tuple[Path, int]:
    """A fresh hidden directory beside ``p``, mode ``0o777`` less the umask, opened and
    locked exclusively: (its path, the descriptor holding the lock).

    Raises:
      OSError: the folder of ``p`` refuses it (the caller names ``p``, not the hidden name).
      Vanished: another creator's clean-up removed it first (start again).
      Unlockable: another process kept it locked.
    """
    tmp = Path(tempfile.mkdtemp(dir=p.parent, prefix=f".{p.name}{CREATING}"))
    fd = -1
    try:
        try:
            fd = _open_locked(tmp)
        except FileNotFoundError:  # removed by another creator's clean-up
            raise Vanished from None
        if not _same_inode(tmp, fd):  # removed and made again
            raise Vanished
    except BaseException:
        if fd >= 0:
            os.close(fd)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp, fd


def _open_locked(tmp: Path) -> int:
    """``tmp`` with the creation's mode, opened and locked exclusively."""
    fd = -1
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)
        fd = os.open(tmp, os.O_RDONLY | os.O_DIRECTORY)
        # The lock is on the directory's inode: it stays held across the rename. Nobody
        # else writes a fresh hidden directory, but another creator's clean-up may hold
        # a shared lock on it for a moment to see whether it is alive: wait that out.
        for attempt in range(200):
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if attempt == 199:
                    raise Unlockable from None
                time.sleep(0.005)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        raise
    return fd


def _same_inode(path: Path, fd: int) -> bool:
    try:
        return os.stat(path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
    except OSError:
        return False


def remove_dead_creations(p: Path) -> None:
    """Remove temporary directories of creations of ``p`` whose process died (unlocked)."""
    for tmp in p.parent.glob(f".{p.name}{CREATING}*"):
        if tmp.is_symlink() or not tmp.is_dir():
            continue
        try:
            fd = os.open(tmp, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # a live creation
            # Removed while locked: a creation that has just made it waits for the lock, then
            # finds it gone and starts again (see RunDir.create).
            shutil.rmtree(tmp, ignore_errors=True)
        finally:
            os.close(fd)
