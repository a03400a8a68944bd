"""Where the suite's time goes: JAX's compile time per test and per program.

``EANT2_TEST_COMPILE_PROFILE=DIR python -m pytest -n auto`` records, in every pytest process, the
seconds JAX spends tracing (``jaxpr_trace_duration``), lowering (``jaxpr_to_mlir_module_
duration``) and compiling (``backend_compile_duration``) for each test and each program
(JAX's ``jax.monitoring`` events), writes one JSON file per process into ``DIR`` and prints
the programs and the tests with the most of it at the end. Compiling is most of the suite's
time on a CPU, so this is the first measurement before cutting it. Processes the tests start
(``eant2`` commands, bench children) are not counted: their time shows in the test's own
duration (``--durations``). Nested traces are counted in each enclosing trace too.

A plugin of the suite, loaded by ``tests/conftest.py`` only where the variable is set.
A variable, not a command-line option: pytest-xdist's workers parse the command line before
they load ``tests/conftest.py``, so an option a conftest adds is unknown to them.
"""

from __future__ import annotations

import json
import os
import threading
from collections import defaultdict
from pathlib import Path

import pytest

# JAX's event names, shortened to the column they fill.
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
}


class Recorder:
    """Seconds and counts per ``(test, event, program)``, for the test that is running."""

    def __init__(self) -> None:
        self.test = ""
        self.rows: dict[tuple[str, str, str], list[float]] = defaultdict(lambda: [0.0, 0])
        self._lock = threading.Lock()

    def __call__(self, event: str, seconds: float, **kwargs) -> None:
        short = EVENTS.get(event)
        if short is None:
            return
        with self._lock:  # programs compiled ahead report from their own threads
            row = self.rows[(self.test, short, str(kwargs.get("fun_name", "?")))]
            row[0] += seconds
            row[1] += 1

    def records(self) -> list[dict]:
        with self._lock:
            return [{"test": t, "event": e, "program": p, "seconds": s, "count": n}
                    for (t, e, p), (s, n) in self.rows.items()]  # fmt: skip


def summary(records: list[dict], top: int = 15) -> str:
    """The totals per event, then the ``top`` programs (by JAX's names) and tests by seconds."""
    totals: dict[str, float] = defaultdict(float)
    programs: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    tests: dict[str, float] = defaultdict(float)
    for r in records:
        totals[r["event"]] += r["seconds"]
        tests[r["test"] or "(outside a test)"] += r["seconds"]
        programs[r["program"]][0] += r["seconds"]
        if r["event"] == "compile":
            programs[r["program"]][1] += r["count"]
    lines = ["compile profile (seconds in pytest's processes): "
             + ", ".join(f"{e} {totals[e]:.1f}" for e in EVENTS.values())]  # fmt: skip
    # JAX names a trace by its function (``f``) and the lowering and compile by the module
    # (``jit(f)``): one program shows as those two rows.
    lines.append("programs with the most (seconds of each name's events; compiles):")
    for name, (s, n) in sorted(programs.items(), key=lambda kv: -kv[1][0])[:top]:
        lines.append(f"  {s:8.1f} s {n:6d}  {name}")
    lines.append("tests with the most:")
    for name, s in sorted(tests.items(), key=lambda kv: -kv[1])[:top]:
        lines.append(f"  {s:8.1f} s  {name}")
    return "\n".join(lines)


_RECORDER: Recorder | None = None


def _folder() -> str | None:
    return os.environ.get("EANT2_TEST_COMPILE_PROFILE") or None


def pytest_configure(config):
    global _RECORDER
    folder = _folder()
    if folder is None or _RECORDER is not None:
        return
    Path(folder).mkdir(parents=True, exist_ok=True)
    if not hasattr(config, "workerinput"):  # a session's summary is of that session only
        for old in Path(folder).glob("compiles-*.json"):
            old.unlink()
    from jax import monitoring

    _RECORDER = Recorder()
    monitoring.register_event_duration_secs_listener(_RECORDER)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if _RECORDER is not None:
        _RECORDER.test = item.nodeid
    yield
    if _RECORDER is not None:
        _RECORDER.test = ""


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session):
    # Before pytest-xdist's worker reports that it finished, so that the controller's
    # summary reads every worker's file.
    folder = _folder()
    if _RECORDER is None or folder is None:
        return
    # An xdist worker's config carries ``workerinput`` (its environment may have been
    # inherited by a pytest the tests start, so the variable PYTEST_XDIST_WORKER is not it).
    name = getattr(session.config, "workerinput", {}).get("workerid", "main")
    path = Path(folder) / f"compiles-{name}.json"
    path.write_text(json.dumps(_RECORDER.records()))


def pytest_terminal_summary(terminalreporter, config):
    folder = _folder()
    if folder is None or hasattr(config, "workerinput"):
        return
    records = []
    for path in sorted(Path(folder).glob("compiles-*.json")):
        records += json.loads(path.read_text())
    terminalreporter.write_line(summary(records))
