"""Strict JSON and typed fields: the ground floor every file the library writes stands on.

Run directories (`eant2_jax.rundir`), records, configurations and pruning records are all
written and read through these few functions, so one rule holds everywhere:

* written strictly: ``allow_nan=False``; a non-finite float is written as the string
  ``"inf"``, ``"-inf"`` or ``"nan"``, which `as_float` reads back;
* read strictly: bare ``Infinity``/``NaN`` refused (unless ``strict=False``, for files of
  older formats), text that is not UTF-8 or nests deeper than `MAX_DEPTH` refused with a
  one-line error, before the parser could hit Python's recursion limit;
* typed fields: a dataclass is rebuilt from a JSON object field by field, each checked
  against its annotation (`typed_fields`);
* replaced atomically: `write_atomic` writes a temporary file, fsyncs it and renames it
  into place, so a reader sees the old file or the new one, never half of one.

This module imports nothing from the package.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["MAX_DEPTH", "as_float", "dumps", "fsync_dir", "loads", "short", "typed_fields"]
__all__ += ["write_atomic"]

# Nesting deeper than this in a file we wrote is corruption (ours is at most 4 deep);
# refusing it early keeps Python's recursion limit out of the error path.
MAX_DEPTH = 32

_NONFINITE = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}


def _encode(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return "nan" if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {k: _encode(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_encode(v) for v in obj]
    return obj


def dumps(obj: Any, **kwargs) -> str:
    """Strict JSON: non-finite floats become the strings ``"inf"``, ``"-inf"``, ``"nan"``."""
    return json.dumps(_encode(obj), allow_nan=False, **kwargs)


def short(value: Any) -> str:
    """``repr(value)``, cut to 40 characters (for one-line error messages)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def as_float(value: Any, what: str) -> float:
    """A float field as `dumps` wrote it (a number, or "inf", "-inf", "nan")."""
    if isinstance(value, str) and value in _NONFINITE:
        return _NONFINITE[value]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number, got {short(value)}")
    return float(value)


def typed_fields(cls, d: Any, what: str, defaults: dict | None = None) -> dict:
    """The fields of dataclass ``cls`` from a JSON object, each checked against its
    annotation (``int``, ``float``, ``str``, ``bool``, optionally ``| None``); a ValueError
    names ``what`` and the field. Floats go through `as_float`."""
    if not isinstance(d, dict):
        raise ValueError(f"{what} is not a JSON object")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ValueError(f"{what} has unknown field(s) {', '.join(map(repr, unknown))}")
    out = {}
    for name, f in fields.items():
        if name not in d:
            if defaults is not None and name in defaults:
                out[name] = defaults[name]
                continue
            if f.default is not dataclasses.MISSING:
                continue
            raise ValueError(f"{what} has no field {name!r}")
        v = d[name]
        kind, *rest = str(f.type).replace(" ", "").split("|")
        if v is None and "None" in rest:
            out[name] = None
        elif kind == "float":
            out[name] = as_float(v, f"{what}: {name}")
        elif kind == "int" and isinstance(v, int) and not isinstance(v, bool):
            out[name] = v
        elif kind == "str" and isinstance(v, str):
            out[name] = v
        elif kind == "bool" and isinstance(v, bool):
            out[name] = v
        else:
            raise ValueError(f"{what}: {name} must be {str(f.type)}, got {short(v)}")
    return out


def _depth_ok(text: str) -> bool:
    """Whether the JSON text nests at most MAX_DEPTH deep (brackets inside strings count,
    which only makes the test stricter than needed for text we did not write)."""
    depth = deepest = 0
    for ch in text:
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
            if deepest > MAX_DEPTH:
                return False
        elif ch in "]}":
            depth -= 1
    return True


def loads(
    data: bytes | str, where: str, *, strict: bool = True, error: type[Exception] = ValueError
) -> Any:
    """Parse JSON read from a file; any problem is a one-line ``error`` that names ``where``.

    Args:
      data: the file's bytes (must be UTF-8) or text.
      where: what to call the source in the message (a path, ``path:line``).
      strict: refuse ``Infinity`` and ``NaN`` (files of older formats may hold them).
      error: the exception class to raise (a `ValueError` subclass such as
        `eant2_jax.rundir.RunDirError`).
    """
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise error(f"{where} is corrupt: not UTF-8 (byte {e.start})") from None
    if not _depth_ok(data):
        raise error(f"{where} is corrupt: JSON nested deeper than {MAX_DEPTH}")

    def constant(name):
        raise ValueError(f"{name} is not JSON (non-finite numbers are written as strings)")

    try:
        return json.loads(data, parse_constant=constant if strict else None)
    except (ValueError, RecursionError) as e:
        raise error(f"{where} is corrupt: {str(e).splitlines()[0]}") from None


def read_upto(fd: int, limit: int) -> bytes:
    """At most ``limit + 1`` bytes of an open file, counted as they are read (what ``stat``
    says is not trusted: ``/proc`` files claim size 0, a file may grow while read), so a
    caller refuses a file over ``limit`` bytes by the length of what it got."""
    chunks, size = [], 0
    while size <= limit:
        chunk = os.read(fd, min(1 << 20, limit + 1 - size))
        if not chunk:
            break
        chunks.append(chunk)
        size += len(chunk)
    return b"".join(chunks)


def fsync_dir(path: Path) -> None:
    """Flush a directory's entries (a rename or creation in it) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (temporary file, fsync, rename, fsync dir).

    The rename replaces a link at ``path`` itself, never what it points to."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    # mkstemp makes the file 0600; give it the mode an ordinary open() would (umask).
    umask = os.umask(0)
    os.umask(umask)
    os.fchmod(fd, 0o666 & ~umask)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
