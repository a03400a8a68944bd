"""Nothing a run directory names runs as code (issue 40; docs/reliability.md, "Trust"):
`eant2_jax.resume` rebuilds only registered tasks by itself; a user's task is used only
when the caller names it again, and then it must be the recorded one."""

from __future__ import annotations

import json

import jax
import pytest
from rundirs import retask

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, tasks
from eant2_jax.checkpoint import validate
from eant2_jax.rundir import CONFIG, RunDir, RunDirError

TINY = EANT2Config(population=3, exploit=ExploitConfig(max_iters=20, pruner="none"))
TASK_FILE = """\
import pathlib
pathlib.Path({marker!r}).write_text("imported")
from eant2_jax import tasks

def make_task():
    return tasks.make("xor")
"""


@pytest.mark.slow
def test_resume_runs_no_module_a_directory_names(tmp_path):
    """``os:system`` with a command, in a complete directory with recomputed checksums and in
    a stub: resume refuses in one line and the command never ran."""
    marker = tmp_path / "pwned"
    options = {"command": f"touch {marker}"}
    out = tmp_path / "run"
    eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(0), config=TINY, generations=0, out=str(out)
    )
    retask(out, "os:system", options)
    validate(str(out))  # the directory itself is consistent
    with pytest.raises(RunDirError, match=r"'os:system' is user code.*--task SPEC") as e:
        eant2_jax.resume(str(out), generations=1)
    assert "\n" not in str(e.value)
    stub = tmp_path / "stub"
    meta = {"task": "os:system", "task_options": options, "generations": 1, "key": [0, 0]}
    RunDir.create(stub, {**meta, "config": TINY.to_dict()}).close()
    with pytest.raises(RunDirError, match="is user code"):
        eant2_jax.resume(str(stub))
    assert not marker.exists()


@pytest.mark.slow
def test_resume_imports_no_task_file_shipped_in_the_directory(tmp_path, monkeypatch):
    """A directory naming ``task.py:make_task`` beside its own files, resumed from inside
    it (``cd DIR; eant2 resume .``): nothing imported, the marker its module body would
    write is absent."""
    out = tmp_path / "run"
    eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(0), config=TINY, generations=0, out=str(out)
    )
    marker = tmp_path / "imported"
    (out / "task.py").write_text(TASK_FILE.format(marker=str(marker)))
    retask(out, "task.py:make_task", {})
    monkeypatch.chdir(out)
    with pytest.raises(RunDirError, match="'task.py:make_task' is user code"):
        eant2_jax.resume(".", generations=1)
    assert not marker.exists()


@pytest.mark.slow
def test_a_user_task_named_again_resumes_and_must_be_the_recorded_one(tmp_path):
    """The user's file task, passed again: resume goes on; another task is refused in one
    line before anything changes."""
    user = tmp_path / "user"
    user.mkdir()
    marker = tmp_path / "imported"
    (user / "mytask.py").write_text(TASK_FILE.format(marker=str(marker)))
    spec = f"{user / 'mytask.py'}:make_task"
    out = tmp_path / "run"
    eant2_jax.run(tasks.make(spec), key=jax.random.key(0), config=TINY, generations=0, out=str(out))
    assert json.loads((out / CONFIG).read_text())["task"] == spec
    marker.unlink()
    with pytest.raises(RunDirError, match="is user code"):
        eant2_jax.resume(str(out), generations=1)
    assert not marker.exists()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(RunDirError, match=r"the task given, 'xor', is not the run's") as e:
        eant2_jax.resume(str(out), tasks.make("xor"), generations=1)
    assert "\n" not in str(e.value)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    res = eant2_jax.resume(str(out), tasks.make(spec), generations=1)
    assert [r.generation for r in res.generations] == [0, 1]


@pytest.mark.slow
def test_a_registered_task_is_rebuilt_by_itself(tmp_path):
    out = tmp_path / "run"
    eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(0), config=TINY, generations=0, out=str(out)
    )
    res = eant2_jax.resume(str(out), generations=1)
    assert [r.generation for r in res.generations] == [0, 1]
