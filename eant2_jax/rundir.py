"""Run directories: what a run writes, how it survives a kill, and why it can be trusted.

A run directory holds

* ``config.json``        the task, its options, the seed and the EANT2 configuration;
* ``generations.jsonl``  one JSON object per completed generation;
* ``pruning.jsonl``      one JSON object per pruning attempt;
* ``best.genome``        the best genome so far, in text form (a copy of the checkpoint's);
* ``checkpoint.json``    everything needed to continue after the last complete generation.

Crash safety: a generation's lines are appended to the logs and fsynced, then
``best.genome`` and ``checkpoint.json`` are replaced atomically (`jsonio.write_atomic`).
The checkpoint records each log's length; resuming truncates the logs back to it, so a run
killed at any instant resumes from its last complete generation with no duplicate or torn
line.

Trust (docs/reliability.md, "Guarantees"): one writer (an exclusive ``flock`` on the
directory for the writer's life; a second ``resume`` of a live run is refused); atomic
creation (built under a hidden name, locked, renamed into place, so the path is absent or a
complete directory); no links followed (every file opened with ``O_NOFOLLOW`` relative to
the directory, regular, the logs with one link); validate, then truncate (offsets at line
ends, records numbering the checkpoint's generation + 1, and in format 2 SHA-256 sums of
``config.json``, the committed log prefixes and the state, all checked before anything is
truncated); strict JSON (`eant2_jax.jsonio`; format 2 refuses ``Infinity``/``NaN``).

Directories of format 1 (before checksums) are still read and resumed; their files may
hold bare ``Infinity``/``NaN`` and their checkpoint has no checksums.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import os
import shutil
import stat
from pathlib import Path
from typing import Any

from . import jsonio
from .dircreate import Unlockable, Vanished, locked_temp_dir, remove_dead_creations
from .dirlock import fcntl
from .jsonio import as_float, dumps, fsync_dir, typed_fields, write_atomic
from .jsonio import short as _short

__all__ = ["Committed", "RunDir", "RunDirError", "as_float", "dumps", "loads", "typed_fields"]

CONFIG = "config.json"
GENERATIONS = "generations.jsonl"
PRUNING = "pruning.jsonl"
BEST = "best.genome"
CHECKPOINT = "checkpoint.json"
LOGS = (GENERATIONS, PRUNING)
FORMAT = 2  # 2: checksums in the checkpoint, strict JSON; 1 is still read (see above)
FORMATS = (1, 2)
# What the checkpoint's "sha256" holds: the config file, the committed log prefixes, the state.
SUMS = (CONFIG, GENERATIONS, PRUNING, "state")


class RunDirError(ValueError):
    """A missing, foreign, corrupt or busy run directory (the message is one line)."""


# ----------------------------------------------------------------------------- strict JSON
def loads(data: bytes | str, where: str, *, strict: bool = True) -> Any:
    """Parse JSON from a run directory (`jsonio.loads`); any problem is a one-line
    `RunDirError` that names ``where``. ``strict`` refuses ``Infinity`` and ``NaN``."""
    return jsonio.loads(data, where, strict=strict, error=RunDirError)


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _state_sum(state: dict) -> str:
    return _sha(dumps(state, sort_keys=True).encode())


@dataclasses.dataclass(frozen=True)
class Committed:
    """What a run directory has committed, read and checked by `RunDir.read`.

    Attributes:
      config: ``config.json``'s object.
      checkpoint: ``checkpoint.json``'s object, or None before the first commit.
      offsets: committed length of each log (0 without a checkpoint).
      generations, pruning: the records in the committed log prefixes.
      best: ``best.genome``'s text (stripped), or None if absent.
      strict: whether the directory is of the strict format (2).
    """

    config: dict
    checkpoint: dict | None
    offsets: dict[str, int]
    generations: list[dict]
    pruning: list[dict]
    best: str | None
    strict: bool


class RunDir:
    """A run directory on disk (see the module docstring for its files and guarantees).

    Use `create` or `open`, and `close` (or ``with``) when done: the
    object holds the directory open, and locked when it was opened to write.
    """

    def __init__(self, path: str | os.PathLike, fd: int):
        self.path = Path(path)
        self._fd = fd
        self._sums: dict[str, Any] = {}  # running SHA-256 of each log's committed prefix
        self._config_sum: str | None = None

    # ------------------------------------------------------------------ opening and locking
    @classmethod
    def create(cls, path: str | os.PathLike, config: dict, *, _attempts: int = 0) -> RunDir:
        """Make a new run directory, locked; refuses to touch an existing non-empty one.

        The directory is built under a hidden temporary name beside ``path`` and renamed
        into place, so ``path`` is never half-made. A temporary directory left by a process
        killed while creating is removed by the next ``create`` of the same path.
        """
        p = Path(path)
        if p.is_symlink() or (p.exists() and (not p.is_dir() or any(p.iterdir()))):
            raise RunDirError(f"{p} already exists and is not an empty directory; not overwriting")
        text = dumps({"format": FORMAT, **config}, indent=2) + "\n"
        try:  # an unwritable place is named as the user named it, not by a hidden name
            p.parent.mkdir(parents=True, exist_ok=True)
            remove_dead_creations(p)
            tmp, fd = locked_temp_dir(p)
        except Vanished:
            return cls._create_again(path, config, _attempts)
        except Unlockable:
            raise RunDirError(f"{p}: could not lock its new directory") from None
        except OSError as e:
            why = e.strerror
            if e.errno in (errno.EEXIST, errno.ENOTDIR):  # p.parent.mkdir met a file
                why = "a part of its path is not a folder"
            raise RunDirError(f"{p}: cannot create the run directory ({why})") from None
        try:
            run = cls(tmp, fd)
            run._write_new(CONFIG, text.encode())
            for name in LOGS:
                run._write_new(name, b"")
            os.fsync(fd)
            try:
                os.rename(tmp, p)  # replaces an empty directory; fails on anything else
            except OSError as e:
                if e.errno in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR):
                    raise RunDirError(
                        f"{p} already exists and is not an empty directory; not overwriting"
                    ) from None
                raise
        except FileNotFoundError:
            # Removed by another creator's clean-up after the lock was checked: start again.
            os.close(fd)
            shutil.rmtree(tmp, ignore_errors=True)
            return cls._create_again(path, config, _attempts)
        except BaseException:
            if "run" in locals():
                run.close()
            else:
                os.close(fd)
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        fsync_dir(p.parent)
        run.path = p
        run._config_sum = _sha(text.encode())
        run._sums = {name: hashlib.sha256() for name in LOGS}
        return run

    @classmethod
    def _create_again(cls, path, config: dict, attempts: int) -> RunDir:
        """`create` once more, after its new directory vanished (at most 20 times)."""
        if attempts >= 20:
            raise RunDirError(f"{path}: could not create it (its new directory kept vanishing)")
        return cls.create(path, config, _attempts=attempts + 1)

    @classmethod
    def open(cls, path: str | os.PathLike, *, lock: bool = True) -> RunDir:
        """Open an existing run directory; checks that it is one.

        Args:
          path: the directory.
          lock: take the exclusive lock (to write: resume); refused while another process
            holds it. Without it the directory is only read (report).
        """
        p = Path(path)
        if not p.is_dir():
            raise RunDirError(f"{p}: no such run directory")
        try:
            fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY)
        except OSError as e:
            raise RunDirError(f"{p}: cannot open the run directory: {e.strerror}") from None
        run = cls(p, fd)
        try:
            if lock:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    raise RunDirError(
                        f"{p} is in use by another eant2 process (a live run); not touching it"
                    ) from None
            for name in (CONFIG, *LOGS):
                if run._lstat(name) is None:
                    raise RunDirError(f"{p} is not a run directory (missing {name})")
            for name in (CONFIG, *LOGS, BEST, CHECKPOINT):
                run._lstat(name, check=True)
        except BaseException:
            run.close()
            raise
        return run

    def is_live(self) -> bool:
        """Whether another process holds the directory's lock (a run is writing it)."""
        fd = os.open(self.path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        finally:
            os.close(fd)  # closing drops a lock taken here
        return False

    def close(self) -> None:
        """Release the lock and the directory."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> RunDir:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass

    # ------------------------------------------------------------------ raw file access
    def _lstat(self, name: str, *, check: bool = False) -> os.stat_result | None:
        try:
            st = os.stat(name, dir_fd=self._fd, follow_symlinks=False)
        except FileNotFoundError:
            return None
        if check and not stat.S_ISREG(st.st_mode):
            what = "a symbolic link" if stat.S_ISLNK(st.st_mode) else "not a regular file"
            raise RunDirError(f"{self.path / name} is {what}; refusing the run directory")
        if check and name in LOGS and st.st_nlink != 1:
            raise RunDirError(
                f"{self.path / name} has {st.st_nlink} hard links; refusing the run directory"
            )
        return st

    def _open(self, name: str, flags: int) -> int:
        """A descriptor of a regular file of the directory, never through a link."""
        try:
            fd = os.open(name, flags | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=self._fd)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise RunDirError(
                    f"{self.path / name} is a symbolic link; refusing the run directory"
                ) from None
            raise RunDirError(f"{self.path / name}: {e.strerror}") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or (name in LOGS and st.st_nlink != 1):
            os.close(fd)
            self._lstat(name, check=True)
            raise RunDirError(f"{self.path / name} changed while opening it")
        return fd

    def _read(self, name: str) -> bytes | None:
        if self._lstat(name, check=True) is None:
            return None
        fd = self._open(name, os.O_RDONLY)
        with os.fdopen(fd, "rb") as f:
            return f.read()

    def _write_new(self, name: str, data: bytes) -> None:
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
        fd = os.open(name, flags, 0o666, dir_fd=self._fd)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())

    # ------------------------------------------------------------------ reading
    def config(self) -> dict:
        """``config.json`` (an object of a known format), or a `RunDirError`."""
        where = str(self.path / CONFIG)
        data = self._read(CONFIG)
        if data is None:
            raise RunDirError(f"{self.path} is not a run directory (missing {CONFIG})")
        head = loads(data, where, strict=False)
        if not isinstance(head, dict) or head.get("format") not in FORMATS:
            raise RunDirError(f"{where}: not a run configuration of format {FORMAT}")
        if head["format"] >= 2:
            head = loads(data, where, strict=True)
        return head

    def read(self) -> Committed:
        """Everything committed, checked: offsets, checksums and the record count.

        Reads nothing beyond the checkpoint's offsets, so it also reads a live run
        consistently. Raises `RunDirError` (one line) on any inconsistency.
        """
        config_bytes = self._read(CONFIG)
        config = self.config()
        strict = config["format"] >= 2
        where = str(self.path / CHECKPOINT)
        raw = self._read(CHECKPOINT)
        ckpt = None
        if raw is not None:
            ckpt = loads(raw, where, strict=strict)
            if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state"), dict):
                raise RunDirError(f"{where} is corrupt: no state object")
            if not isinstance(ckpt.get("offsets"), dict):
                raise RunDirError(f"{where} is corrupt: no offsets object")
        logs = {name: self._read(name) or b"" for name in LOGS}
        # Without a checkpoint the run was killed inside generation 0's commit (its lines
        # may be appended, the checkpoint not yet written): more than that one record means
        # the checkpoint was lost, and starting over would drop committed generations.
        lines = logs[GENERATIONS].count(b"\n")
        if ckpt is None and lines > 1:
            raise RunDirError(
                f"{where} is missing but {GENERATIONS} holds {lines} records; "
                "refusing to start over"
            )
        offsets = dict.fromkeys(LOGS, 0) if ckpt is None else self._offsets(ckpt, logs, where)
        if ckpt is not None and (strict or "sha256" in ckpt):
            self._check_sums(ckpt, config_bytes, logs, offsets, where)
        records = {name: self._records(name, logs[name][: offsets[name]], strict) for name in LOGS}
        gens = records[GENERATIONS]
        for i, row in enumerate(gens):
            if row.get("generation") != i or isinstance(row.get("generation"), bool):
                raise RunDirError(
                    f"{self.path / GENERATIONS}:{i + 1} is corrupt: generation "
                    f"{_short(row.get('generation'))} where {i} belongs"
                )
        if ckpt is not None:
            g = ckpt["state"].get("generation")
            if isinstance(g, bool) or not isinstance(g, int) or g != len(gens) - 1:
                raise RunDirError(
                    f"{where} is corrupt: generation {_short(g)} but {GENERATIONS} commits "
                    f"{len(gens)} record(s)"
                )
        best = self._read(BEST)
        if best is not None:
            try:
                best = best.decode("utf-8").strip()
            except UnicodeDecodeError:
                best = ""  # derived; rewritten from the checkpoint by rewind
        self._config_sum = _sha(config_bytes)
        self._sums = {name: hashlib.sha256(logs[name][: offsets[name]]) for name in LOGS}
        return Committed(config, ckpt, offsets, gens, records[PRUNING], best, strict)

    def _offsets(self, ckpt: dict, logs: dict[str, bytes], where: str) -> dict[str, int]:
        """The checkpoint's offset of each log, checked: an integer at a line end within it."""
        offsets = {}
        for name in LOGS:
            off = ckpt["offsets"].get(name)
            if isinstance(off, bool) or not isinstance(off, int):
                raise RunDirError(
                    f"{where} is corrupt: the offset of {name} is {_short(off)}, not an integer"
                )
            if off < 0 or off > len(logs[name]):
                raise RunDirError(
                    f"{self.path / name} is shorter than its checkpoint says "
                    f"({len(logs[name])} < {off} bytes); the run is corrupt"
                )
            if off > 0 and logs[name][off - 1 : off] != b"\n":
                raise RunDirError(
                    f"{where} is corrupt: the offset {off} of {name} is not at a line end"
                )
            offsets[name] = off
        return offsets

    def _check_sums(self, ckpt: dict, config_bytes, logs, offsets, where: str) -> None:
        """The checkpoint's SHA-256 sums against the config, the log prefixes and its state."""
        sums = ckpt.get("sha256")
        if not isinstance(sums, dict) or sorted(sums) != sorted(SUMS):
            raise RunDirError(f"{where} is corrupt: no checksums of {', '.join(SUMS)}")
        actual = {
            CONFIG: _sha(config_bytes),
            **{name: _sha(logs[name][: offsets[name]]) for name in LOGS},
            "state": _state_sum(ckpt["state"]),
        }
        # A config.json replaced by a resume: the checkpoint names the new file's sum
        # while the replacement is under way (`replace_config`).
        if sums[CONFIG] != actual[CONFIG] and ckpt.get("config_next") == actual[CONFIG]:
            actual[CONFIG] = sums[CONFIG]
        for name in SUMS:
            if sums[name] != actual[name]:
                what = "the checkpoint's state" if name == "state" else name
                raise RunDirError(
                    f"{self.path}: {what} does not match the checksum of its last "
                    "commit (edited or damaged); refusing the run directory"
                )

    def _records(self, name: str, committed: bytes, strict: bool) -> list[dict]:
        """A log's committed lines as JSON objects."""
        rows = []
        for n, line in enumerate(committed.split(b"\n")[:-1], 1):
            row = loads(line, f"{self.path / name}:{n}", strict=strict)
            if not isinstance(row, dict):
                raise RunDirError(f"{self.path / name}:{n} is corrupt: not a JSON object")
            rows.append(row)
        return rows

    # ------------------------------------------------------------------ writing
    def rewind(self, offsets: dict[str, int], best: str | None = None) -> None:
        """Truncate the logs to the offsets `read` checked, restore ``best.genome`` from
        the checkpoint (``best``) if it differs, and remove a dead commit's temporary files.

        Call only after `read` and every other check passed: this is the first write.
        """
        for name in LOGS:
            fd = self._open(name, os.O_WRONLY)
            try:
                if os.fstat(fd).st_size != offsets[name]:
                    os.ftruncate(fd, offsets[name])
                    os.fsync(fd)
            finally:
                os.close(fd)
        # A kill inside write_atomic leaves its temporary file behind (the target itself is
        # whole, old or new): remove our own leftovers, named as write_atomic names them.
        for name in (BEST, CHECKPOINT, CONFIG):
            for tmp in self.path.glob(f".{name}.*.tmp"):
                tmp.unlink(missing_ok=True)
        # best.genome is a copy of the checkpoint's best: a kill between its rename and the
        # checkpoint's leaves the next generation's there.
        if best is not None:
            current = self._read(BEST)
            if current != (best + "\n").encode():
                write_atomic(self.path / BEST, best + "\n")

    def replace_config(self, config: dict, checkpoint: dict | None) -> None:
        """Replace ``config.json`` with ``config`` (its ``format`` included), after `read`
        and `rewind`, keeping the checkpoint's checksum of it true at every instant.

        With a checkpoint of checksums (``checkpoint``, as `read` returned it), three
        atomic replacements: the checkpoint naming the new file's sum as ``config_next``
        (`read` accepts either sum while it is there), config.json, then the checkpoint
        with the new sum alone. A kill between any two leaves a directory that `read`
        accepts, with the old or the new config.json; nothing committed is lost.
        """
        text = dumps(config, indent=2) + "\n"
        new = _sha(text.encode())
        sums = None if checkpoint is None else checkpoint.get("sha256")
        if isinstance(sums, dict):
            base = {k: v for k, v in checkpoint.items() if k != "config_next"}
            write_atomic(self.path / CHECKPOINT, dumps({**base, "config_next": new}) + "\n")
            write_atomic(self.path / CONFIG, text)
            done = {**base, "sha256": {**sums, CONFIG: new}}
            write_atomic(self.path / CHECKPOINT, dumps(done) + "\n")
        else:  # before the first commit, or a format without checksums
            write_atomic(self.path / CONFIG, text)
        self._config_sum = new

    def commit(
        self, generation_records: list[dict], pruning_records: list[dict], best: str, state: dict
    ) -> None:
        """Persist one completed generation (logs first, then the atomic checkpoint)."""
        offsets = {}
        for name, rows in ((GENERATIONS, generation_records), (PRUNING, pruning_records)):
            data = "".join(dumps(row) + "\n" for row in rows).encode()
            fd = self._open(name, os.O_WRONLY | os.O_APPEND)
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view) :]
                os.fsync(fd)
                offsets[name] = os.fstat(fd).st_size
            finally:
                os.close(fd)
            self._sums[name].update(data)
        sums = {
            CONFIG: self._config_sum,
            **{name: self._sums[name].copy().hexdigest() for name in LOGS},
            "state": _state_sum(state),
        }
        write_atomic(self.path / BEST, best + "\n")
        write_atomic(
            self.path / CHECKPOINT,
            dumps({"format": FORMAT, "offsets": offsets, "state": state, "sha256": sums}) + "\n",
        )
