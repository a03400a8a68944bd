"""Commands without surprises (issue 43 item 2): a report never overwrites one or writes
into a run directory, a broken pipe ends quietly, no abbreviations, argument errors in one
line naming the option, an unwritable place named as the user named it, and an int key."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import pytest
from rundirs import run_main, run_records
from test_report import make_run

import eant2_jax
from eant2_jax import EANT2Config
from eant2_jax.checkpoint import validate
from eant2_jax.records import RUN_DEPENDENT
from eant2_jax.rundir import CHECKPOINT

TINY = ["--population", "3", "--max-iters", "20", "--no-prune"]


_main = run_main


@pytest.mark.slow
def test_report_refuses_to_overwrite_a_report_unless_forced(tmp_path, capsys, monkeypatch):
    dirs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    out = tmp_path / "rep"
    rc, stdout, err = _main(["report", *dirs, "--out", out], capsys, monkeypatch)
    assert rc == 0 and stdout == f"report: {out / 'report.md'}\n", err
    (out / "report.md").write_text("mine\n")
    rc, stdout, err = _main(["report", *dirs, "--out", out], capsys, monkeypatch)
    assert rc == 2 and stdout == "" and len(err) == 1, err
    assert "holds a report (report.md); not overwriting it" in err[0] and "--force" in err[0]
    assert (out / "report.md").read_text() == "mine\n"
    # Any of the report's files counts; an empty or foreign folder is fine.
    (out / "report.md").unlink()
    rc, _, err = _main(["report", *dirs, "--out", out], capsys, monkeypatch)
    assert rc == 2 and "(summary.json)" in err[0], err
    rc, _, err = _main(["report", *dirs, "--out", out, "--force"], capsys, monkeypatch)
    assert rc == 0 and (out / "report.md").read_text().startswith("# EANT2 report"), err
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("x")
    assert _main(["report", *dirs, "--out", other], capsys, monkeypatch)[0] == 0
    # The default folder (beside the first run) too: a second report is refused.
    monkeypatch.chdir(tmp_path)
    default = tmp_path / "report"
    assert _main(["report", *dirs], capsys, monkeypatch)[0] == 0 and default.is_dir()
    rc, _, err = _main(["report", *dirs], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1 and "not overwriting" in err[0], err


def test_report_never_writes_into_any_run_directory(tmp_path, capsys, monkeypatch):
    dirs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    bystander = Path(make_run(tmp_path / "bystander"))
    before = sorted(p.name for p in bystander.iterdir())
    for out in (bystander, bystander / "report", bystander / "a" / "b"):
        for force in ([], ["--force"]):
            rc, stdout, err = _main(["report", *dirs, "--out", out, *force], capsys, monkeypatch)
            assert rc == 2 and stdout == "" and len(err) == 1, err
            assert f"inside the run directory {bystander}" in err[0], err
    assert sorted(p.name for p in bystander.iterdir()) == before


@pytest.mark.slow
def test_a_broken_pipe_ends_quietly_with_exit_0(tmp_path):
    """``eant2 tasks | head -1``: the reader goes after one line; nothing on stderr, exit 0
    (the rest of the output is dropped)."""
    env = {**os.environ, "EANT2_CACHE_DIR": ""}
    for command in (["tasks"], ["config"]):
        with subprocess.Popen(
            [sys.executable, "-m", "eant2_jax.app.cli", *command],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            cwd=tmp_path,
        ) as proc:
            first = proc.stdout.readline()
            proc.stdout.close()  # as head -1 does
            err = proc.stderr.read()
            rc = proc.wait(timeout=120)
        assert first.strip() and err == b"" and rc == 0, (command, err, rc)


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "xor", "--gen", "1"],
        ["run", "xor", "--pop", "3"],
        ["run", "xor", "--max-eval", "3"],
        ["resume", "somewhere", "--gen", "3"],
        ["reproduce", "--gen", "1"],
        ["report", "a", "--allow"],
        ["show", "a.genome", "--forc"],
        ["demo", "--it", "3"],
        ["config", "--js"],
    ],
)
def test_no_command_takes_an_abbreviated_option(argv, capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    rc, stdout, err = _main(argv, capsys, monkeypatch)
    assert rc == 2 and stdout == "" and len(err) == 1, err
    assert err[0].startswith("eant2: error: unrecognized arguments: --"), err
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("argv", "phrase"),
    [
        ([], "the following arguments are required: COMMAND"),
        (["runn"], "invalid choice: 'runn'"),
        (["show"], "the following arguments are required: genome_file"),
        (["report"], "the following arguments are required: dirs"),
        (["run", "xor", "--seed", "x"], "argument --seed: expected an integer"),
        (["run", "xor", "--generations"], "argument --generations: expected one argument"),
        (["reproduce", "--mode", "fast"], "argument --mode: invalid choice: 'fast'"),
        (["run", "xor", "extra"], "unrecognized arguments: extra"),
        (["resume"], "the following arguments are required: dir"),
    ],
)
def test_every_kind_of_argument_error_is_one_line(argv, phrase, capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    rc, stdout, err = _main(argv, capsys, monkeypatch)
    assert rc == 2 and stdout == "" and len(err) == 1, err
    assert re.match(r"eant2( [a-z]+)?: error: ", err[0]) and phrase in err[0], err
    assert "usage:" not in err[0]


@pytest.mark.parametrize(
    ("option", "phrase"),
    [
        ("max_steps=abc", "--task-option max_steps=abc: expected an integer (the default is"),
        ("max_steps=1.5", "--task-option max_steps=1.5: expected an integer"),
        ("theta1=wide", "--task-option theta1=wide: expected a number"),
        ("hidden=3", '--task-option hidden=3: expected a string (the default is "tanh")'),
        ("steps=3", "bad options for task 'dpv': dpv() got an unexpected keyword argument"),
        ("max_steps", "--task-option expects KEY=VALUE, got 'max_steps'"),
    ],
)
def test_a_bad_task_option_is_named(option, phrase, tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    argv = ["run", "dpv", "--task-option", option, "--generations", "0", "--out", out]
    rc, stdout, err = _main(argv, capsys, monkeypatch)
    assert rc == 2 and stdout == "" and len(err) == 1 and phrase in err[0], err
    assert not out.exists()


def test_an_unwritable_place_is_named_as_the_user_named_it(tmp_path, capsys, monkeypatch):
    """No hidden temporary name (``.run.creating-...``, ``.x.png.....tmp``) in the error:
    a path under a file, and a folder that refuses new files (made so by refusing the
    temporary's creation, as a read-only folder does for a user who is not root)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    genome = tmp_path / "g.genome"
    genome.write_text("N0/2*1 I0*0.5 I1*-0.5\n")
    runs = [make_run(tmp_path / f"{p}-0", pruner=p) for p in ("covariance", "none")]
    cases = [
        (["run", "xor", *TINY, "--generations", "0", "--out", blocker / "r"], blocker / "r"),
        (["report", *runs, "--out", blocker / "rep"], blocker / "rep"),
        (["show", genome, "--out", blocker / "x.png"], blocker / "x.png"),
    ]
    for argv, named in cases:
        rc, _, err = _main(argv, capsys, monkeypatch)
        assert rc == 2 and len(err) == 1 and f"{named}:" in err[0], err
        assert ".tmp" not in err[0] and "creating" not in err[0], err

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / ".hidden.tmp"))

    ro = tmp_path / "ro"
    ro.mkdir()
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    rc, _, err = _main(["run", "xor", *TINY, "--out", ro / "r"], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1, err
    assert (
        err[0] == f"eant2: error: {ro / 'r'}: cannot create the run directory (Permission denied)"
    )
    real_open = os.open

    def no_new_files(path, flags, *args, **kwargs):
        if flags & os.O_CREAT and Path(path).parent == ro:
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", no_new_files)
    rc, _, err = _main(["show", genome, "--out", ro / "x.png"], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1, err
    assert err[0] == f"eant2: error: {ro / 'x.png'}: cannot write it (Permission denied)"


@pytest.mark.slow
def test_an_int_key_is_the_seed_s_key_and_anything_else_is_one_line(tmp_path):
    """``run(task, key=0)`` is ``run(task, key=jax.random.key(0))`` (``eant2 run --seed
    0``'s key); a bool, a negative or too large seed, or another type is one line."""
    task = eant2_jax.tasks.make("xor")
    config = EANT2Config(population=3, exploit=eant2_jax.ExploitConfig(max_iters=20))
    by_int = eant2_jax.run(task, key=0, config=config, generations=0, out=str(tmp_path / "a"))
    by_key = eant2_jax.run(task, key=jax.random.key(0), config=config, generations=0)

    def same(result):
        return [{k: v for k, v in g.to_json().items() if k not in RUN_DEPENDENT}
                for g in result.generations]  # fmt: skip

    assert same(by_int) == same(by_key)
    key = json.loads((tmp_path / "a" / "config.json").read_text())["key"]
    assert key == [int(k) for k in jax.random.key_data(jax.random.key(0))]
    for bad, phrase in [
        (True, "an int seed must be in [0, 2**32), got True"),
        (-1, "an int seed must be in [0, 2**32), got -1"),
        (2**32, "an int seed must be in [0, 2**32), got 4294967296"),
        ("0", "key must be a jax.random.key(...) or an int seed, got str"),
    ]:
        with pytest.raises(ValueError) as e:
            eant2_jax.run(task, key=bad, config=config, generations=0, out=str(tmp_path / "b"))
        assert phrase in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"keys\[1\]: an int seed"):
        eant2_jax.run_lockstep(task, [0, -3], config=config, generations=0)
    assert not (tmp_path / "b").exists()


# ----------------------------------------------------------------------------- resume
RESUME_CONFIG = EANT2Config(population=3, exploit=eant2_jax.ExploitConfig(max_iters=20))


@pytest.fixture(scope="module")
def xor_runs(tmp_path_factory):
    """A tiny XOR run of 1 generation and the same run of 2, uninterrupted."""
    d = tmp_path_factory.mktemp("xor_runs")
    task = eant2_jax.tasks.make("xor")
    for name, generations in (("one", 1), ("two", 2)):
        eant2_jax.run(task, key=jax.random.key(5), config=RESUME_CONFIG,
                      generations=generations, out=str(d / name))  # fmt: skip
    return d


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


@pytest.mark.slow
def test_resume_records_its_new_generations_and_reports_agree(
    xor_runs, tmp_path, capsys, monkeypatch
):
    """A run of 1 resumed to 2 records 2 in config.json, holds the uninterrupted run's
    records, and a report takes the two as runs of one setting (it refused "2 vs 1")."""
    d = _copy(xor_runs / "one", tmp_path / "resumed")
    rc, _, err = _main(["resume", d, "--generations", "2"], capsys, monkeypatch)
    assert rc == 0, err
    meta = json.loads((d / "config.json").read_text())
    assert meta["generations"] == 2
    assert meta["resumed"] == [{"after_generation": 1, "generations": 2}]
    assert run_records(d) == run_records(xor_runs / "two")
    v = validate(str(d))  # the checkpoint's checksum of the new config.json holds
    assert v.generations == 2 and "config_next" not in json.loads((d / CHECKPOINT).read_text())
    argv = ["report", d, xor_runs / "two", "--out", tmp_path / "rep"]
    rc, _, err = _main(argv, capsys, monkeypatch)
    assert rc == 0, err


@pytest.mark.slow
def test_resume_changes_budgets_and_stopping_options_recorded(
    xor_runs, tmp_path, capsys, monkeypatch
):
    """--target-cost and --max-evaluations (or --set) apply to the resumed run and are
    recorded; a run that meets them stops without another generation."""
    one = json.loads((xor_runs / "one" / "generations.jsonl").read_text().splitlines()[-1])
    base = validate(str(xor_runs / "one")).config
    for i, (argv, field, value) in enumerate([
        (["--target-cost", "10"], "target_cost", 10.0),
        (["--set", "target_cost=10"], "target_cost", 10.0),
        (["--max-evaluations", "1"], "max_evaluations", 1),
    ]):  # fmt: skip
        d = _copy(xor_runs / "one", tmp_path / f"r{i}")
        rc, _, err = _main(["resume", d, "--generations", "5", *argv], capsys, monkeypatch)
        assert rc == 0, err
        meta = json.loads((d / "config.json").read_text())
        assert (meta["generations"], meta["config"][field]) == (5, value)
        assert meta["resumed"] == [{"after_generation": 1, "generations": 5, field: value}]
        assert len(run_records(d)) == 2  # stopped at once: the target or budget is met
        assert validate(str(d)).config == dataclasses.replace(base, **{field: value})
    assert one["best_cost"] < 10 and one["evaluations"] > 1
    # null is the target eant2 run would resolve: the task's solved level while the stop
    # when solved is on, none without it; in Python, changes= does the same.
    rc, _, err = _main(["resume", d, "--set", "target_cost=null"], capsys, monkeypatch)
    assert rc == 0 and validate(str(d)).config.target_cost == base.target_cost, err
    argv = ["resume", d, "--target-cost", "null", "--no-solved-stop"]
    rc, _, err = _main(argv, capsys, monkeypatch)
    assert rc == 0, err
    meta = json.loads((d / "config.json").read_text())
    assert (meta["config"]["target_cost"], meta["config"]["stop_when_solved"]) == (None, False)
    assert meta["resumed"][-1] == {"after_generation": 1, "generations": 5, "target_cost": None,
                                   "stop_when_solved": False}  # fmt: skip
    d = _copy(xor_runs / "one", tmp_path / "py")
    eant2_jax.resume(str(d), changes={"target_cost": 10.0})
    assert validate(str(d)).config.target_cost == 10.0


@pytest.mark.parametrize(
    ("argv", "phrase"),
    [
        (["--population", "4"], "--population cannot change on resume"),
        (["--no-prune"], "--no-prune cannot change on resume"),
        (["--max-iters", "5"], "--max-iters cannot change on resume"),
        (["--seed", "1"], "--seed cannot change on resume"),
        (["--task-option", "a=1"], "--task-option cannot change on resume"),
        (["--config", "c.json"], "--config cannot change on resume"),
        (["--set", "exploit.sigma0=1"], "exploit.sigma0 cannot change on resume"),
        (["--set", "population=4"], "population cannot change on resume"),
        (["--max-evaluations", "0"], "argument --max-evaluations: EANT2Config.max_evaluations"),
        (["--target-cost", "inf"], "argument --target-cost: EANT2Config.target_cost"),
        (["--generations", "0"], "generations 0: the run has already completed generation 1"),
    ],
)
@pytest.mark.slow
def test_resume_refuses_every_other_change_in_one_line(
    argv, phrase, xor_runs, tmp_path, capsys, monkeypatch
):
    d = _copy(xor_runs / "one", tmp_path / "r")
    before = _files(d)
    monkeypatch.chdir(tmp_path)
    rc, stdout, err = _main(["resume", d, *argv], capsys, monkeypatch)
    assert rc == 2 and stdout == "" and len(err) == 1 and phrase in err[0], err
    assert _files(d) == before


@pytest.mark.slow
def test_resume_in_python_refuses_other_fields_by_name(xor_runs, tmp_path):
    d = _copy(xor_runs / "one", tmp_path / "r")
    before = _files(d)
    for changes, phrase in [
        ({"population": 4}, "population cannot change on resume"),
        ({"exploit": {"max_iters": 5}}, "exploit cannot change on resume"),
        ({"max_evaluations": 0}, "max_evaluations must be >= 1"),
    ]:
        with pytest.raises(ValueError, match=phrase) as e:
            eant2_jax.resume(str(d), changes=changes)
        assert "\n" not in str(e.value)
    assert _files(d) == before


@pytest.mark.parametrize("killed_after", [1, 2])
@pytest.mark.slow
def test_a_kill_inside_the_config_update_leaves_a_run_that_resumes(
    killed_after, xor_runs, tmp_path, monkeypatch
):
    """config.json and its checksum in the checkpoint are replaced in three atomic steps;
    a kill after the first or second leaves a directory that validates (old or new
    config.json) and resumes, and the next commit leaves one checksum."""
    from eant2_jax import rundir

    d = _copy(xor_runs / "one", tmp_path / "r")
    real, calls = rundir.write_atomic, []

    def killed(path, text):
        if len(calls) == killed_after:
            raise KeyboardInterrupt
        calls.append(path.name)
        real(path, text)

    monkeypatch.setattr(rundir, "write_atomic", killed)
    with pytest.raises(KeyboardInterrupt):
        eant2_jax.resume(str(d), generations=2)
    monkeypatch.setattr(rundir, "write_atomic", real)
    assert calls == [CHECKPOINT, "config.json"][:killed_after]
    assert validate(str(d)).generations == (1, 2)[killed_after - 1]
    eant2_jax.resume(str(d), generations=2)
    assert run_records(d) == run_records(xor_runs / "two")
    assert "config_next" not in json.loads((d / CHECKPOINT).read_text())
    assert validate(str(d)).generations == 2


@pytest.mark.slow
def test_resume_warns_when_the_task_file_changed(xor_runs, tmp_path, capsys, monkeypatch):
    """config.json records the SHA-256 of a user's task file; a resume naming the task
    again warns in one line when the file's content changed, and only then."""
    f = tmp_path / "mytask.py"
    f.write_text(
        "from eant2_jax import tasks\n\n\ndef make_task():\n    return tasks.make('xor')\n"
    )
    out = tmp_path / "run"
    argv = ["run", f"{f}:make_task", *TINY, "--generations", "0", "--out", out]
    rc, _, err = _main(argv, capsys, monkeypatch)
    assert rc == 0, err
    meta = json.loads((out / "config.json").read_text())
    assert meta["task_sha256"] == hashlib.sha256(f.read_bytes()).hexdigest()
    resume = ["resume", out, "--task", f"{f}:make_task"]
    rc, _, err = _main(resume, capsys, monkeypatch)
    assert rc == 0 and err == [], err
    f.write_text(f.read_text() + "# edited\n")
    rc, _, err = _main(resume, capsys, monkeypatch)
    warnings = [e for e in err if e.startswith("eant2: warning:")]
    assert rc == 0 and len(warnings) == 1, err
    assert "has changed since the run started" in warnings[0] and str(f) in warnings[0]
