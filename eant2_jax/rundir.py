"""Run directories: what a run writes, and how it survives a kill at any moment.

A run directory holds

* ``config.json``        the task, its options, the seed and the EANT2 configuration;
* ``generations.jsonl``  one JSON object per completed generation;
* ``pruning.jsonl``      one JSON object per pruning attempt;
* ``best.genome``        the best genome so far, in text form;
* ``checkpoint.json``    everything needed to continue after the last complete generation.

Crash safety: after a generation, its lines are appended to the ``.jsonl`` files and
flushed to disk, then ``best.genome`` and ``checkpoint.json`` are replaced atomically (write
a temporary file, fsync, rename, fsync the directory). The checkpoint records the length of
each ``.jsonl`` file at that moment; resuming truncates them back to it. So a run killed at
any instant — even with SIGKILL inside a checkpoint write — resumes from its last complete
generation with no duplicate or half-written line, and loses at most the generation in
progress.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

__all__ = ["RunDir", "RunDirError"]

CONFIG = "config.json"
GENERATIONS = "generations.jsonl"
PRUNING = "pruning.jsonl"
BEST = "best.genome"
CHECKPOINT = "checkpoint.json"
FORMAT = 1


class RunDirError(ValueError):
    """A missing, foreign or corrupt run directory."""


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (temporary file, fsync, rename, fsync dir)."""
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
    _fsync_dir(path.parent)


class RunDir:
    """A run directory on disk (see the module docstring for its files)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    @classmethod
    def create(cls, path: str | os.PathLike, config: dict) -> RunDir:
        """Make a new run directory; refuses to touch an existing non-empty one."""
        p = Path(path)
        if p.exists() and (not p.is_dir() or any(p.iterdir())):
            raise RunDirError(f"{p} already exists and is not an empty directory; not overwriting")
        p.mkdir(parents=True, exist_ok=True)
        run = cls(p)
        write_atomic(p / CONFIG, json.dumps({"format": FORMAT, **config}, indent=2) + "\n")
        for name in (GENERATIONS, PRUNING):
            (p / name).touch()
        return run

    @classmethod
    def open(cls, path: str | os.PathLike) -> RunDir:
        """Open an existing run directory for resuming; checks that it is one."""
        p = Path(path)
        if not p.is_dir():
            raise RunDirError(f"{p}: no such run directory")
        for name in (CONFIG, GENERATIONS, PRUNING):
            if not (p / name).is_file():
                raise RunDirError(f"{p} is not a run directory (missing {name})")
        run = cls(p)
        run.config()  # validates
        return run

    def config(self) -> dict:
        try:
            data = json.loads((self.path / CONFIG).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise RunDirError(f"{self.path / CONFIG} is unreadable or corrupt: {e}") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise RunDirError(f"{self.path / CONFIG}: not a run configuration of format {FORMAT}")
        return data

    def checkpoint(self) -> dict | None:
        """The last complete generation's checkpoint, or None if no generation completed."""
        p = self.path / CHECKPOINT
        if not p.exists():
            return None
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise RunDirError(f"{p} is corrupt: {e}") from None
        if not isinstance(data, dict) or "state" not in data or "offsets" not in data:
            raise RunDirError(f"{p} is corrupt: missing fields")
        return data

    def rewind(self, offsets: dict | None) -> None:
        """Truncate the ``.jsonl`` files to the lengths recorded with a checkpoint.

        Every length is checked before any file is touched, so a corrupt checkpoint leaves
        the directory as it was.
        """
        sizes = {}
        for name in (GENERATIONS, PRUNING):
            try:
                size = 0 if offsets is None else int(offsets[name])
            except (KeyError, TypeError, ValueError):
                raise RunDirError(
                    f"{self.path / CHECKPOINT} is corrupt: no valid offset of {name}"
                ) from None
            p = self.path / name
            if size < 0 or p.stat().st_size < size:
                raise RunDirError(f"{p} is shorter than its checkpoint says; the run is corrupt")
            sizes[name] = size
        for name, size in sizes.items():
            p = self.path / name
            with open(p, "r+b") as f:
                f.truncate(size)
                f.flush()
                os.fsync(f.fileno())
        # A kill inside write_atomic leaves its temporary file behind (the target itself is
        # whole, old or new): remove our own leftovers, named as write_atomic names them.
        for name in (BEST, CHECKPOINT):
            for tmp in self.path.glob(f".{name}.*.tmp"):
                tmp.unlink(missing_ok=True)

    def commit(
        self, generation_records: list[dict], pruning_records: list[dict], best: str, state: dict
    ) -> None:
        """Persist one completed generation (logs first, then the atomic checkpoint)."""
        offsets = {}
        for name, rows in ((GENERATIONS, generation_records), (PRUNING, pruning_records)):
            p = self.path / name
            with open(p, "a", encoding="utf-8") as f:
                for row in rows:
                    f.write(json.dumps(row) + "\n")
                f.flush()
                os.fsync(f.fileno())
            offsets[name] = p.stat().st_size
        write_atomic(self.path / BEST, best + "\n")
        write_atomic(
            self.path / CHECKPOINT, json.dumps({"offsets": offsets, "state": state}) + "\n"
        )

    def generations(self) -> list[dict]:
        return _read_jsonl(self.path / GENERATIONS)

    def pruning(self) -> list[dict]:
        return _read_jsonl(self.path / PRUNING)


def _read_jsonl(path: Path) -> list[dict]:
    out = []
    with open(path, encoding="utf-8") as f:
        for n, line in enumerate(f, 1):
            if line.strip():
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError as e:
                    raise RunDirError(f"{path}:{n} is corrupt: {e}") from None
    return out
