"""The one way the applications write files: whole, in place, never through a link.

Every file the ``eant2`` commands write (reports, figures, drawings, summaries) goes through
this module. A file is written to a fresh temporary name in the destination's own folder
(created with ``O_CREAT | O_EXCL | O_NOFOLLOW``, mode ``0o644`` less the umask), flushed to
disk, and renamed over the destination: a kill at any moment leaves either the old file or
the whole new one, never a partial one (at worst a stray ``.<name>.<random>.tmp`` beside it).

The destination must be absent or a regular file. A symbolic link there (a dangling one
included) or anything that is not a regular file (a FIFO, a device, a folder) is refused with
one `OutputError` naming the path, and nothing is written: a link planted at an output by a
received bundle is never followed, its target never touched. The rename replaces a name, not
what a name points to, so a link planted between the check and the rename is replaced, not
followed. Folders made by `make_folder` are refused the same way when a link sits at their
name. See docs/reliability.md, "Outputs".
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

__all__ = ["OutputError", "exists", "make_folder", "save_figure", "write_bytes", "write_text"]
__all__ += ["write_with"]

_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
_FLAGS |= getattr(os, "O_CLOEXEC", 0)
# Filesystems that cannot make a hard link (used for a write that must not replace a file).
_NO_LINK = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EXDEV, errno.EMLINK}


class OutputError(OSError):
    """An output that cannot be written safely: a link or a non-regular file at its name."""


def _check_destination(path: Path) -> bool:
    """Raise `OutputError` unless ``path`` is absent or a regular file; return whether it
    exists. Never follows a link at ``path`` (its parent folders are the caller's)."""
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):  # absent (its folder too)
        return False
    if stat.S_ISLNK(st.st_mode):
        raise OutputError(f"{path}: is a symbolic link; refusing to write through it")
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: exists and is not a regular file; refusing to write it")
    return True


def exists(path: str | os.PathLike) -> bool:
    """Whether a regular file is at ``path`` (to be replaced, or kept); `OutputError` for a
    link or anything else there, which no write of this module goes through."""
    return _check_destination(Path(path))


def make_folder(path: str | os.PathLike, *, exist_ok: bool = True) -> Path:
    """Create the folder ``path`` (and its parents) unless it is there; return it.

    Raises:
      OutputError: a symbolic link (a dangling one included) or a non-folder is at ``path``,
        or the folder exists and ``exist_ok`` is false.
    """
    path = Path(path)
    try:
        os.mkdir(path, 0o777)  # the umask applies, as for any folder
        return path
    except FileNotFoundError as e:
        if path.parent == path or os.path.lexists(path.parent):  # a folder that refuses it
            raise OutputError(f"{path}: cannot create the folder ({e.strerror})") from None
        make_folder(path.parent)
        return make_folder(path, exist_ok=exist_ok)
    except FileExistsError:
        pass
    except OSError as e:
        raise OutputError(f"{path}: cannot create the folder ({e.strerror})") from None
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode):
        raise OutputError(f"{path}: is a symbolic link; refusing to write into it")
    if not stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{path}: exists and is not a folder")
    if not exist_ok:
        raise OutputError(f"{path}: already exists")
    return path


def _open_temp(folder: Path, name: str) -> tuple[int, Path]:
    """A fresh file in ``folder`` that nothing else names: (descriptor, path)."""
    while True:
        tmp = folder / f".{name}.{secrets.token_hex(6)}.tmp"
        try:
            return os.open(tmp, _FLAGS, 0o644), tmp
        except FileExistsError:
            continue  # a name drawn twice: draw another


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: some filesystems refuse it)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _link_into_place(tmp: Path, path: Path) -> None:
    """Give ``tmp``'s file the name ``path`` only if nothing has that name (no overwrite)."""
    try:
        os.link(tmp, path, follow_symlinks=False)
    except FileExistsError:
        raise OutputError(f"{path}: already exists; refusing to overwrite it") from None
    except OSError as e:
        if e.errno not in _NO_LINK:
            raise
        if _check_destination(path):  # no hard links here: check, then rename
            raise OutputError(f"{path}: already exists; refusing to overwrite it") from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def write_with(
    path: str | os.PathLike, write: Callable[[IO[bytes]], Any], *, overwrite: bool = True
) -> Path:
    """Write ``path`` whole and atomically by calling ``write(f)`` on a fresh binary file.

    Args:
      path: the destination; absent or a regular file (see the module's docstring).
      write: called once with the open temporary file; it writes the contents.
      overwrite: when false, refuse an existing file at ``path`` (checked atomically).

    Returns:
      ``path`` as a `Path`.

    Raises:
      OutputError: a link or a non-regular file at ``path``, or an existing file when
        ``overwrite`` is false. Nothing is written then.
    """
    path = Path(path)
    if _check_destination(path) and not overwrite:
        raise OutputError(f"{path}: already exists; refusing to overwrite it")
    folder = path.parent
    try:
        fd, tmp = _open_temp(folder, path.name)
    except OSError as e:  # named as the caller named it, not by the temporary name
        raise OutputError(f"{path}: cannot write it ({e.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        if overwrite:
            _check_destination(path)  # again, just before the rename
            os.replace(tmp, path)
        else:
            _link_into_place(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_folder(folder)
    return path


def write_bytes(path: str | os.PathLike, data: bytes, *, overwrite: bool = True) -> Path:
    """Write ``data`` to ``path`` whole and atomically, never through a link (`write_with`)."""
    return write_with(path, lambda f: f.write(data), overwrite=overwrite)


def write_text(path: str | os.PathLike, text: str, *, overwrite: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``path`` whole and atomically, never through a link."""
    return write_bytes(path, text.encode("utf-8"), overwrite=overwrite)


def save_figure(fig: Any, path: str | os.PathLike, *, overwrite: bool = True, **kwargs) -> Path:
    """Save a matplotlib figure to ``path`` whole and atomically, never through a link.

    Args:
      fig: a ``matplotlib.figure.Figure``.
      path: the destination; its suffix names the format unless ``format=`` is given.
      overwrite: when false, refuse an existing file at ``path``.
      **kwargs: passed to ``fig.savefig`` (``dpi``, ``bbox_inches``...).
    """
    path = Path(path)
    kwargs.setdefault("format", path.suffix[1:].lower() or "png")
    return write_with(path, lambda f: fig.savefig(f, **kwargs), overwrite=overwrite)
