"""The ``eant2`` command line: options generated from the configuration's field specs, one
validated path (flags, ``--set``, ``--config``), one-line errors before anything is
created, outputs never written through a link, and no code run because a directory names
it (issue 39 item 4, issue 40)."""

from __future__ import annotations

import json
import os

import pytest
from rundirs import retask, run_main

from eant2_jax import EANT2Config, ExploitConfig
from eant2_jax.app.parser import build_parser, config_from
from eant2_jax.rundir import RunDir

TINY = ["--population", "3", "--max-iters", "20", "--generations", "0", "--no-prune"]


_main = run_main


@pytest.mark.parametrize(
    ("argv", "phrase"),
    [
        (["run", "xor", "--max-iters", "2147483648"], "argument --max-iters: ExploitConfig."),
        (["run", "xor", "--set", "exploit.patience=2147483648"], "patience must be at most"),
        (["run", "xor", "--population", "0"], "argument --population: EANT2Config.population"),
        (["run", "xor", "--max-iters", "x"], "ExploitConfig.max_iters must be an integer"),
        (["run", "xor", "--pop", "3"], "unrecognized arguments: --pop 3"),  # no abbreviations
        (["run", "xor", "--set", "exploit.sigma=1"], "did you mean 'exploit.sigma0'"),
        (["run", "xor", "--set", "sigma0"], "expected NAME=VALUE"),
        (["run", "xor", "--pruner", "lottery"], "pruner must be one of covariance"),
        (["run", "xor", "--min-bucket", "8,40"], "min_bucket must be None or three integers"),
        (["run", "xor", "--generations", "-1"], "argument --generations: must be in [0, "),
    ],
)
def test_option_errors_are_one_line_and_create_nothing(argv, phrase, tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    rc, stdout, err = _main([*argv, "--out", out], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1 and phrase in err[0], err
    assert "usage:" not in err[0] and stdout == ""
    assert not out.exists()


def test_cross_field_and_file_errors_are_one_line_before_the_run_directory(
    tmp_path, capsys, monkeypatch
):
    out = tmp_path / "run"
    bad = tmp_path / "bad.json"
    for text, phrase in [
        ('{"exploit": {"sigma0": 1e-45}}', "outside the range of a float32 state"),
        ('{"populaton": 3}', "unknown EANT2Config option(s): populaton"),
        ('{"exploit": {"max_iters": 2.5}}', "max_iters must be int"),
        ("[1, 2]", "not a JSON object of configuration fields"),
        ('{"exploit": NaN}', "is corrupt"),
    ]:
        bad.write_text(text)
        rc, _, err = _main(["run", "xor", "--config", bad, "--out", out], capsys, monkeypatch)
        assert rc == 2 and len(err) == 1 and err[0].startswith("eant2: error: "), err
        assert phrase in err[0], err
    rc, _, err = _main(["run", "xor", "--config", tmp_path, "--out", out], capsys, monkeypatch)
    assert rc == 2 and "not a regular file" in err[0]
    assert not out.exists()


def test_flags_set_and_config_files_reach_the_same_fields(tmp_path):
    parse = build_parser().parse_args
    by_flags = config_from(parse(["run", "xor", "--max-iters", "40", "--population", "7"]))
    by_set = config_from(
        parse(["run", "xor", "--set", "exploit.max_iters=40", "--set", "population=7"])
    )
    want = EANT2Config(population=7, exploit=ExploitConfig(max_iters=40, pruner="covariance"))
    assert by_flags == by_set == want
    assert config_from(parse(["run", "xor"])) == EANT2Config()  # eant2 run's defaults
    # The older spellings are the same path: --x64 is exploit.dtype, --no-prune the pruner.
    old = parse(["run", "xor", "--x64", "--no-prune", "--min-bucket", "8,40,4", "--rescore", "2"])
    config = config_from(old)
    assert (config.exploit.dtype, config.exploit.max_condition) == ("float64", 1e14)
    assert (config.exploit.pruner, config.min_bucket, config.exploit.rescore) == (
        "none", (8, 40, 4), 2
    )  # fmt: skip
    # A file, then flags, then each --set in order; a run directory's config.json works.
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"format": 2, "config": {"population": 5, "exploit": {"sigma0": 0.2}}}))
    args = parse(["run", "xor", "--config", str(f), "--population", "6", "--set", "population=9"])
    config = config_from(args)
    assert (config.population, config.exploit.sigma0, config.exploit.pruner) == (
        9, 0.2, "covariance"
    )  # fmt: skip
    args = parse(["run", "xor", "--set", "min_bucket=[8, 40, 4]", "--set", "devices=all"])
    assert (config_from(args).min_bucket, config_from(args).devices) == ((8, 40, 4), "all")
    # eant2 reproduce's base leaves the pruner to its arms.
    rep = config_from(parse(["reproduce", "--max-iters", "30", "--set", "exploit.chunk=10"]))
    assert rep == EANT2Config(exploit=ExploitConfig(max_iters=30, chunk=10))


def test_config_lists_every_field_from_the_specs(capsys, monkeypatch):
    rc, out, _ = _main(["config"], capsys, monkeypatch)
    assert rc == 0
    for name, kind, _, help_ in EANT2Config().describe():
        assert f"\n{name} = " in "\n" + out and kind in out and help_ in out, name
    assert '\nexploit.pruner = "covariance"  (str)\n' in out
    rc, out, _ = _main(["config", "--json"], capsys, monkeypatch)
    assert EANT2Config.from_dict(json.loads(out), complete=True) == EANT2Config()


def test_resume_of_a_directory_naming_os_system_runs_nothing(tmp_path, capsys, monkeypatch):
    """``eant2 resume DIR`` of a directory whose task is ``os:system`` with a command: exit
    code 2, one line asking for --task, the command never ran (a stub directory and a
    complete one with recomputed checksums alike); a task named that is not the recorded
    one is refused too (here by the options recorded with the command)."""
    marker = tmp_path / "pwned"
    options = {"command": f"touch {marker}"}
    stub = tmp_path / "stub"
    meta = {"task": "os:system", "task_options": options, "generations": 1, "key": [0, 0]}
    RunDir.create(stub, {**meta, "config": EANT2Config().to_dict()}).close()
    run = tmp_path / "run"
    rc, _, err = _main(["run", "xor", *TINY, "--out", run], capsys, monkeypatch)
    assert rc == 0, err
    retask(run, "os:system", options)
    for d in (stub, run):
        rc, stdout, err = _main(["resume", d], capsys, monkeypatch)
        assert rc == 2 and len(err) == 1 and "'os:system' is user code" in err[0], err
        assert "--task SPEC" in err[0] and stdout == ""
        # Another task named: built with the recorded options (xor takes no "command").
        rc, _, err = _main(["resume", d, "--task", "xor"], capsys, monkeypatch)
        assert rc == 2 and len(err) == 1 and "bad options for task 'xor'" in err[0], err
    assert not marker.exists()


def test_show_writes_its_png_whole_and_never_through_a_link(tmp_path, capsys, monkeypatch):
    src = tmp_path / "best.genome"
    src.write_text("N0/2*1 I0*0.5 I1*-0.5\n")
    png = tmp_path / "best.genome.png"
    target = tmp_path / "victim"
    png.symlink_to(target)  # dangling
    for force in ([], ["--force"]):
        rc, _, err = _main(["show", src, *force], capsys, monkeypatch)
        assert rc == 2 and len(err) == 1, err
        assert not target.exists()
    png.unlink()
    rc, out, err = _main(["show", src], capsys, monkeypatch)
    assert rc == 0 and png.read_bytes()[:4] == b"\x89PNG" and f"drawing: {png}" in out
    # A second show prints the statistics again and keeps the PNG (issue 43); --force
    # replaces it.
    png.write_bytes(b"mine")
    rc, again, err = _main(["show", src], capsys, monkeypatch)
    assert rc == 0 and err == [] and png.read_bytes() == b"mine"
    assert again.splitlines()[:-1] == out.splitlines()[:-1]
    assert again.splitlines()[-1] == f"drawing: {png} (exists: kept; --force replaces it, " \
        "--out names another)"  # fmt: skip
    assert _main(["show", src, "--force"], capsys, monkeypatch)[0] == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    fifo = tmp_path / "fifo.genome"
    os.mkfifo(fifo)
    rc, _, err = _main(["show", fifo, "--out", tmp_path / "f.png"], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1 and "not a regular file" in err[0], err


def test_resume_of_a_reproduction_builds_the_named_task_with_the_manifest_options(
    tmp_path, capsys, monkeypatch
):
    """``eant2 resume REP --task SPEC`` of a reproduction: the task is built from the spec
    named with the options reproduce.json records, before anything runs (here those of
    ``os:system``, which xor does not take: one line, nothing created)."""
    from eant2_jax.app.experiments import MANIFEST

    marker = tmp_path / "pwned"
    rep = tmp_path / "rep"
    rep.mkdir()
    manifest = {
        "version": 1,
        "task_meta": {"task": "os:system", "task_options": {"command": f"touch {marker}"}},
        "runs": 1, "generations": 1, "pruners": ["covariance"],
        "config": EANT2Config(population=3).to_dict(), "seed": 0, "devices": 1,
        "workers_per_device": 1, "lockstep": True, "condition": False,
        "condition_iters": 10, "condition_inits": 1, "condition_dtype": "float64",
    }  # fmt: skip
    (rep / MANIFEST).write_text(json.dumps(manifest))
    rc, _, err = _main(["resume", rep, "--task", "xor"], capsys, monkeypatch)
    assert rc == 2 and len(err) == 1 and "bad options for task 'xor'" in err[0], err
    assert sorted(p.name for p in rep.iterdir()) == [MANIFEST] and not marker.exists()
