"""What every fuzz target shares: the classes a case ends in, the marker file, payloads.

Classes (`CLASSES`):

* ``error``: a clean one-line error (a ValueError subclass whose message has no newline);
* ``accepted``: accepted, and what was read equals what the input says (or, for a store
  entry, the program's result equals the traced one's);
* ``traceback``: any other exception, a crash or a hang (a bug);
* ``silent_wrong``: accepted with a result other than the input's (a bug);
* ``lost``: a file outside the input changed, or committed bytes changed (a bug);
* ``executed``: code named by the data ran: the marker file that every hostile payload
  would create exists after the case (a bug, the worst).
"""

from __future__ import annotations

import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

CLASSES = ("error", "accepted", "traceback", "silent_wrong", "lost", "executed")
BUGS = CLASSES[2:]


class Marker:
    """A file that hostile payloads create; its existence after a case means code named by
    the data ran. ``clear()`` before each case."""

    def __init__(self, folder: Path):
        self.path = Path(folder) / "EXECUTED-MARKER"

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)

    def fired(self) -> bool:
        return self.path.exists()


def hostile_tasks(marker: Marker, folder: Path) -> list[tuple[str, dict]]:
    """Task specs and options that create the marker if anything imports or calls them:
    a shell command, a file opened for writing, Python files shipped in ``folder`` (by
    absolute and relative path, and as a module found on ``sys.path`` from the working
    directory). Writes the shipped files."""
    m = str(marker.path)
    code = f"open({m!r}, 'w').close()\n\ndef make_task(**options):\n    return None\n"
    (folder / "task.py").write_text(code)
    (folder / "evil_task_module.py").write_text(code)
    return [
        ("os:system", {"command": f"touch {m}"}),
        ("subprocess:getoutput", {"cmd": f"touch {m}"}),
        ("builtins:open", {"file": m, "mode": "w"}),
        ("pathlib:Path.touch", {}),
        (f"{folder}/task.py:make_task", {}),
        (f"{folder}/task.py", {}),
        ("task.py:make_task", {}),
        ("task.py", {}),
        ("evil_task_module:make_task", {}),
    ]


def one_line(e: BaseException) -> tuple[str, str]:
    """``error`` for a ValueError of one non-empty line, else ``traceback``."""
    msg = str(e)
    if isinstance(e, ValueError) and msg and "\n" not in msg:
        return "error", msg[:200]
    return "traceback", f"{type(e).__name__}: {msg[:200]}"


def classify(case: Callable[[], Any], marker: Marker | None = None) -> tuple[str, str]:
    """Run one case: its own verdict (``accepted``/``silent_wrong``/``lost``, or a pair of
    verdict and detail), ``error`` or ``traceback`` for what it raises, and ``executed``
    whenever the marker exists."""
    if marker is not None:
        marker.clear()
    try:
        got = case()
        verdict, detail = (got, "") if isinstance(got, str) else got
    except ValueError as e:
        verdict, detail = one_line(e)
    except (Exception, RecursionError, MemoryError):  # noqa: BLE001 - a bug, recorded
        verdict, detail = "traceback", traceback.format_exc(limit=4)[-400:]
    if marker is not None and marker.fired():
        marker.clear()
        verdict, detail = "executed", f"the marker was created ({detail})"
    return verdict, detail


class Tally:
    """Counts of classes by case kind, and the bug cases (at most ``keep``)."""

    def __init__(self, target: str, keep: int = 50):
        self.target, self.keep = target, keep
        self.counts: dict[str, dict[str, int]] = {}
        self.bugs: list[dict[str, Any]] = []
        self.n_bugs = 0

    def add(self, kind: str, verdict: str, detail: str = "", case: Any = None) -> None:
        self.counts.setdefault(kind, dict.fromkeys(CLASSES, 0))[verdict] += 1
        if verdict in BUGS:
            self.n_bugs += 1
            if len(self.bugs) < self.keep:
                self.bugs.append(
                    {
                        "target": self.target,
                        "kind": kind,
                        "class": verdict,
                        "case": case,
                        "detail": detail,
                    }  # fmt: skip
                )

    def rows(self) -> list[dict[str, Any]]:
        """One row per kind and one for the target (all kinds)."""
        rows = [{"what": f"{self.target} ({k})", **v} for k, v in sorted(self.counts.items())]
        total = {c: sum(v[c] for v in self.counts.values()) for c in CLASSES}
        return [*rows, {"what": f"{self.target} (all)", **total}]


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def json_paths(obj, prefix=()):
    """Every path into a JSON value (the root's ``()`` first), for mutating one field."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from json_paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from json_paths(v, (*prefix, i))


def set_path(obj, path, value):
    """``obj`` with the value at ``path`` replaced (in place; the root path returns
    ``value``)."""
    if not path:
        return value
    target = obj
    for p in path[:-1]:
        target = target[p]
    target[path[-1]] = value
    return obj
