"""`eant2_jax.dirlock`: the run directory's lock is ``flock`` where ``fcntl`` exists (a second
holder refused, in this process or another; released when the holder is killed), and where
it is missing the module imports and its stand-in refuses to lock."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from eant2_jax import dirlock

PACKAGE = Path(__file__).resolve().parents[1] / "eant2_jax"
# dirlock alone, as part of a bare package (no __init__, so no jax), in a fresh interpreter.
BARE = f"""
import importlib, sys, types
pkg = types.ModuleType("pkg"); pkg.__path__ = [{str(PACKAGE)!r}]
sys.modules["pkg"] = pkg
"""


def _python(code: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", BARE + textwrap.dedent(code)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def _lock(path: Path) -> int:
    """A descriptor of the directory holding its exclusive lock; BlockingIOError if held."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        dirlock.fcntl.flock(fd, dirlock.fcntl.LOCK_EX | dirlock.fcntl.LOCK_NB)
    except BaseException:
        os.close(fd)
        raise
    return fd


def test_flock_where_fcntl_exists(tmp_path):
    import fcntl

    assert dirlock.fcntl is fcntl and dirlock.HAS_FLOCK
    fd = _lock(tmp_path)
    with pytest.raises(BlockingIOError):  # a second descriptor of this process
        _lock(tmp_path)
    os.close(fd)
    os.close(_lock(tmp_path))  # released on close


def test_a_second_process_is_refused_until_the_holder_is_killed(tmp_path):
    holder = _python(
        """
        import os, time
        dirlock = importlib.import_module("pkg.dirlock")
        fd = os.open(sys.argv[1], os.O_RDONLY | os.O_DIRECTORY)
        dirlock.fcntl.flock(fd, dirlock.fcntl.LOCK_EX | dirlock.fcntl.LOCK_NB)
        print("locked", flush=True)
        time.sleep(600)
        """.replace("sys.argv[1]", repr(str(tmp_path)))
    )
    try:
        assert holder.stdout.readline().strip() == "locked", holder.stderr.read()
        with pytest.raises(BlockingIOError):
            _lock(tmp_path)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
        holder.stdout.close()
        holder.stderr.close()
    os.close(_lock(tmp_path))  # the OS dropped the killed holder's lock


def test_without_fcntl_it_imports_and_refuses_to_lock(tmp_path):
    """As on Windows: ``fcntl`` cannot be imported; the stand-in refuses with one line."""
    proc = _python(
        f"""
        import errno, os
        sys.modules["fcntl"] = None  # import fcntl now raises ImportError
        dirlock = importlib.import_module("pkg.dirlock")
        assert not dirlock.HAS_FLOCK
        fd = os.open({str(tmp_path)!r}, os.O_RDONLY | os.O_DIRECTORY)
        try:
            dirlock.fcntl.flock(fd, dirlock.fcntl.LOCK_EX | dirlock.fcntl.LOCK_NB)
        except OSError as e:
            assert e.errno == errno.ENOTSUP, e
            print(e.strerror)
        """
    )
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.strip() == "run directories need flock (POSIX), which this platform lacks"
