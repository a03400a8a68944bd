"""A reproduction killed part-way is finished by `resume_reproduction` (``eant2 resume
DIR``) to exactly the result of an uninterrupted one (CPU: resumed runs are exact), and a
directory that is not a whole reproduction gets one clear error."""

from __future__ import annotations

import json

import jax
import pytest
from rundirs import run_records

from eant2_jax import tasks
from eant2_jax.app.cli import main
from eant2_jax.app.experiments import MANIFEST, reproduce, resume_reproduction
from eant2_jax.config import ExploitConfig
from eant2_jax.loop import EANT2Config
from eant2_jax.rundir import RunDirError

SETTINGS = dict(
    task_meta={"task": "xor", "task_options": {}},
    runs=2,
    generations=2,
    pruners=("covariance",),
    # A small budget: what is checked (resumed records equal to the uninterrupted ones, bit
    # for bit) does not depend on the sizes.
    config=EANT2Config(population=3, exploit=ExploitConfig(max_iters=30)),
    devices=1,
    condition=True,
    condition_iters=20,
    condition_inits=2,
    condition_dtype="float64",  # JAX's x64 mode for that experiment alone
)
RUNS = ("covariance-s0", "covariance-s1", "none-s0", "none-s1")


@pytest.mark.slow
@pytest.mark.parametrize("lockstep", [True, False])
def test_a_killed_reproduction_resumes_to_the_uninterrupted_result(
    tmp_path, capsys, lockstep, monkeypatch
):
    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # in-process: leave the JAX configuration alone
    task = tasks.make("xor")
    reproduce(task, tmp_path / "whole", lockstep=lockstep, **SETTINGS)
    # The condition experiment's float64 mode ended with it: the next reproduction's runs
    # are the float32 runs of the first (compared below).
    assert not jax.config.jax_enable_x64

    def kill(event):  # Ctrl-C in the unpruned arm (run first), after its generation 1
        if event["event"] == "generation" and event["arm"] == "none" and event["generation"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        reproduce(task, tmp_path / "cut", callback=kill, lockstep=lockstep, **SETTINGS)
    cut = tmp_path / "cut"
    assert (cut / MANIFEST).is_file() and not (cut / "report").exists()
    if lockstep:  # the arm's second run went with the first, and had not committed gen 1
        assert len((cut / "none-s1" / "generations.jsonl").read_text().splitlines()) == 1
    else:
        assert not (cut / "none-s1").exists()  # never started
    # The command line finishes it (the task is rebuilt from the manifest).
    assert main(["resume", str(cut)]) == 0
    assert "report:" in capsys.readouterr().out

    whole = tmp_path / "whole"
    for run in RUNS:
        assert run_records(cut / run) == run_records(whole / run), run
        assert (cut / run / "best.genome").read_text() == (whole / run / "best.genome").read_text()
    summary = [json.loads((d / "report" / "summary.json").read_text()) for d in (cut, whole)]
    assert summary[0] == summary[1]
    cond = [json.loads((d / "condition.json").read_text()) for d in (cut, whole)]
    assert cond[0] == cond[1]
    assert "the reproduction was resumed" in (cut / "report" / "report.md").read_text()
    # A finished reproduction resumes to itself, reading its condition result back.
    assert resume_reproduction(cut) == cut / "report" / "report.md"
    assert json.loads((cut / "report" / "summary.json").read_text()) == summary[1]


def test_what_is_not_a_reproduction_is_one_clear_error(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # in-process: leave the JAX configuration alone
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunDirError, match="not a reproduction"):
        resume_reproduction(tmp_path / "empty")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / MANIFEST).write_text(json.dumps({"version": 1, "runs": 2}))
    with pytest.raises(RunDirError, match="not a reproduce.json of version 1 with task_meta"):
        resume_reproduction(bad)
    # eant2 resume sees the manifest: --generations does not apply to a reproduction.
    assert main(["resume", str(bad), "--generations", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--generations does not apply" in err[0], err


@pytest.mark.slow
def test_ctrl_c_stops_a_reproduction_at_once(tmp_path):
    """Ctrl-C reaches the main thread while worker threads run (a plain join kept it
    waiting for every run to end), and the command exits 130 with the resume hint."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "rp"
    code = (
        "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "sys.argv[0] = 'eant2'; runpy.run_module('eant2_jax.app.cli', run_name='__main__')"
    )
    argv = ["reproduce", "--task", "xor", "--runs", "2", "--generations", "500",
            "--population", "6", "--no-condition", "--out", str(out)]  # fmt: skip
    env = {**os.environ, "EANT2_CACHE_DIR": "", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-c", code, *argv], env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    log = out / "none-s0" / "generations.jsonl"  # the unpruned arm runs first
    deadline = time.monotonic() + 240
    while not (log.is_file() and len(log.read_text().splitlines()) >= 2):
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()  # a stuck run must not hang the suite
            pytest.fail(f"no second generation within 240 s: {proc.communicate()}")
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)  # 500 generations would take far longer
    assert proc.returncode == 130, err
    assert f"eant2 resume {out}" in err
    assert "Traceback" not in err and "terminate" not in err
    assert len(log.read_text().splitlines()) < 100
