"""The suite's compile profile (tests/compile_profile.py): what it records and prints."""

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from compile_profile import Recorder, summary
from jax import monitoring


def test_a_compile_is_recorded_for_the_running_test_and_its_program():
    rec = Recorder()
    monitoring.register_event_duration_secs_listener(rec)
    try:
        rec.test = "tests/x.py::t"

        def profiled_program(x):
            return jnp.sin(x) * 3.0

        jax.jit(profiled_program)(jnp.arange(7.0)).block_until_ready()
        rec.test = ""
        rec("/jax/some/other_event", 9.0, fun_name="ignored")
    finally:
        monitoring.unregister_event_duration_listener(rec)
    rows = [r for r in rec.records() if "profiled_program" in r["program"]]
    events = {r["event"] for r in rows}
    assert {"trace", "compile"} <= events, rows
    assert all(r["test"] == "tests/x.py::t" and r["seconds"] >= 0 for r in rows)
    assert sum(r["count"] for r in rows if r["event"] == "compile") == 1
    assert not any(r["program"] == "ignored" for r in rec.records())


def test_summary_ranks_programs_and_tests_by_seconds():
    records = [
        {"test": "a::1", "event": "compile", "program": "jit(big)", "seconds": 5.0, "count": 2},
        {"test": "a::1", "event": "trace", "program": "big", "seconds": 1.0, "count": 2},
        {"test": "b::2", "event": "compile", "program": "jit(small)", "seconds": 0.5, "count": 1},
        {"test": "", "event": "lower", "program": "jit(small)", "seconds": 0.3, "count": 1},
    ]
    text = summary(records, top=2)
    lines = text.splitlines()
    head = "compile profile (seconds in pytest's processes): trace 1.0, lower 0.3, compile 5.5"
    assert lines[0] == head
    assert lines[2].split() == ["5.0", "s", "2", "jit(big)"]
    assert lines[3].split() == ["1.0", "s", "0", "big"]  # two programs shown: top=2
    assert lines[5].split() == ["6.0", "s", "a::1"]
    assert lines[6].split() == ["0.5", "s", "b::2"]  # the lowering outside a test is not its


@pytest.mark.slow  # a pytest process of its own
def test_the_variable_writes_a_file_per_process_and_prints_the_summary(tmp_path):
    tests = tmp_path / "t"
    tests.mkdir()
    (tests / "test_one.py").write_text(
        "import jax, jax.numpy as jnp\n"
        "def test_compiles():\n"
        "    def in_the_child(x):\n"
        "        return x + 1\n"
        "    jax.jit(in_the_child)(jnp.ones(3)).block_until_ready()\n"
    )
    here = Path(__file__).parent
    out = tmp_path / "profile"
    out.mkdir()
    (out / "compiles-gw9.json").write_text("[]")  # an earlier session's: removed at the start
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "compile_profile",
         str(tests)],
        capture_output=True, text=True, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(here), "EANT2_TEST_COMPILE_PROFILE": str(out)},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (path,) = out.glob("compiles-*.json")
    rows = json.loads(path.read_text())
    mine = [r for r in rows if "in_the_child" in r["program"]]
    assert mine and all(r["test"].endswith("test_one.py::test_compiles") for r in mine)
    assert "compile profile (seconds in pytest's processes)" in proc.stdout
    assert "test_one.py::test_compiles" in proc.stdout
