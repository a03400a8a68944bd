"""A JSON result computed once per test session, whichever xdist worker asks first.

A module fixture runs once per worker that gets any of its module's tests, and pytest-xdist
(``--dist worksteal``, README's command) splits a module between its workers where the
module straddles their shares or a test is stolen: an expensive fixture (a subprocess of
several scenarios) then ran twice. `once` keeps its value in a folder that the session's
first process makes (tests/conftest.py, ``EANT2_TEST_SHARED_DIR``) and every worker
inherits: the first caller computes it under a file lock, later callers read it.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["once"]


def once(name: str, compute: Callable[[], Any]) -> Any:
    """``compute()``'s JSON value for ``name``, computed by the first caller of the session.

    A ``compute`` that raises stores nothing: the next caller computes again (and fails the
    same way, in its own test). Without the session folder (a test file run outside this
    suite's conftest) it is computed every time."""
    folder = os.environ.get("EANT2_TEST_SHARED_DIR")
    if not folder:
        return compute()
    path = Path(folder) / f"{name}.json"
    with open(path.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if path.is_file():
            return json.loads(path.read_text())
        value = compute()
        text = json.dumps(value)  # before writing: a value JSON cannot hold is an error here
        part = path.with_suffix(".part")
        part.write_text(text)
        part.replace(path)
        return json.loads(text)
