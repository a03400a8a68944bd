"""Run directories you can trust (issue 16): locks, atomic creation, no links followed,
validation before truncation, checksums, cross-checks, one-line errors, number ranges.

Most cases work on a small synthetic run directory: consistent records committed through
:class:`~eant2_jax.rundir.RunDir` (no exploitation, nothing compiled), which ``eant2 resume``
accepts and finishes at once (its generations are all done). The corrupt-input table runs
``eant2`` in-process and asserts one line on stderr, exit 2 and the directory unchanged
byte for byte. Two tests start processes: a live lock holder, and kills during creation.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from eant2_jax import EANT2Config, ExploitConfig, Genome, GenomeError
from eant2_jax.app.cli import main
from eant2_jax.checkpoint import validate
from eant2_jax.pruning import PruneAttempt
from eant2_jax.records import GenerationRecord
from eant2_jax.rundir import (
    CHECKPOINT,
    CONFIG,
    GENERATIONS,
    PRUNING,
    RunDir,
    RunDirError,
    dumps,
    loads,
)

CONFIG_ = EANT2Config(population=3, exploit=ExploitConfig(max_iters=50, pruner="covariance"))
XOR_BEST = ["N0/2*1.0 I0*0.5 I1*0.5", "N0/3*1.0 I0*0.25 I1*0.5 N2/1*0.5 I0*1.0"]
RUNDIR_PY = Path(__file__).resolve().parents[1] / "eant2_jax" / "rundir.py"


def _record(g: int, attempts: int) -> dict:
    return GenerationRecord(
        generation=g, best_cost=0.3 / (g + 1), best_size=len(XOR_BEST[g].split()),
        mean_size=3.0, best_neurons=g + 1, evaluations=10 * (g + 1), wall_s=0.1 * (g + 1),
        prune_attempts=attempts, prune_accepted=0, population=1, exploited=1,
        generation_s=0.1, best_genome=XOR_BEST[g],
    ).to_json()  # fmt: skip


def _prune(g: int) -> dict:
    return PruneAttempt(
        structure=0, iteration=5, pruner="covariance", gene=1, kind="input", axis=0, s=0.5,
        e=0.3, e_shifted=float("inf"), e_refit=None, e_reference=0.3, accepted=False,
        cond_before=10.0, cond_after=float("nan"), generation=g,
    ).to_json()  # fmt: skip


def _state(g: int) -> dict:
    return {
        "generation": g,
        "population": [{"genome": XOR_BEST[g], "cost": 0.3 / (g + 1), "origin": "init"}],
        "next_id": 3,
        "evaluations": 10 * (g + 1),
        "key": [0, 0],
        "wall_s": 0.1 * (g + 1),
    }


def make_run(path: Path, generations: int = 2, total: int = 1, config=CONFIG_) -> Path:
    """A consistent run directory of xor with ``generations`` committed generations."""
    meta = {"task": "xor", "task_options": {}, "seed": 0, "generations": total, "key": [0, 0]}
    with RunDir.create(path, {**meta, "config": config.to_dict()}) as rd:
        for g in range(generations):
            rd.commit([_record(g, 1)], [_prune(g)], XOR_BEST[g], _state(g))
    return path


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every entry under ``directory`` (hidden ones too), links as their targets' names."""
    if not directory.exists():
        return {}
    out = {}
    for p in sorted(directory.rglob("*")):
        key = str(p.relative_to(directory))
        if p.is_symlink():
            out[key] = b"->" + os.readlink(p).encode()
        elif p.is_file():
            out[key] = p.read_bytes()
        else:  # a directory, or a FIFO (reading it would block)
            out[key] = b"<dir>" if p.is_dir() else b"<other>"
    return out


def run_main(argv, capsys, monkeypatch) -> tuple[int, list[str], str]:
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse
        rc = e.code
    cap = capsys.readouterr()
    return rc, [line for line in cap.err.splitlines() if line.strip()], cap.out


def assert_one_error(rc, lines, *phrases) -> None:
    assert rc == 2, lines
    errors = [line for line in lines if ": error: " in line]
    assert len(errors) == 1 and errors[0] == lines[-1], lines
    assert "Traceback" not in "\n".join(lines)
    for phrase in phrases:
        assert phrase in lines[-1], lines


def rewrite_checkpoint(d: Path, edit) -> None:
    """A deliberate, consistent edit: change the checkpoint and recompute its state sum (so
    that the cross-checks, not the checksum, must catch it)."""
    ckpt = json.loads((d / CHECKPOINT).read_text())
    edit(ckpt)
    if "sha256" in ckpt:
        text = dumps(ckpt["state"], sort_keys=True).encode()
        ckpt["sha256"]["state"] = hashlib.sha256(text).hexdigest()
    (d / CHECKPOINT).write_text(json.dumps(ckpt) + "\n")


def rewrite_config(d: Path, edit) -> None:
    cfg = json.loads((d / CONFIG).read_text())
    edit(cfg)
    text = json.dumps(cfg)
    (d / CONFIG).write_text(text)
    if (d / CHECKPOINT).exists():
        ckpt = json.loads((d / CHECKPOINT).read_text())
        ckpt["sha256"][CONFIG] = hashlib.sha256(text.encode()).hexdigest()
        (d / CHECKPOINT).write_text(json.dumps(ckpt) + "\n")


def test_synthetic_run_is_accepted_and_resume_finishes(tmp_path, capsys, monkeypatch):
    d = make_run(tmp_path / "run")
    v = validate(str(d))
    assert v.state.generation == 1 and len(v.records) == 2 and len(v.pruning) == 2
    assert v.pruning[0].e_shifted == float("inf") and np.isnan(v.pruning[0].cond_after)
    before = snapshot(d)
    rc, lines, out = run_main(["resume", d], capsys, monkeypatch)
    assert rc == 0, lines
    assert XOR_BEST[1] in out and snapshot(d) == before


# ------------------------------------------------------------------------------ strict JSON
def test_json_is_strict_and_non_finite_numbers_round_trip(tmp_path):
    text = dumps({"a": float("inf"), "b": [float("-inf"), float("nan")], "c": 1.5})
    assert "Infinity" not in text and "NaN" not in text
    assert loads(text, "x") == {"a": "inf", "b": ["-inf", "nan"], "c": 1.5}
    with pytest.raises(RunDirError, match="x is corrupt: Infinity is not JSON"):
        loads('{"a": Infinity}', "x")
    with pytest.raises(RunDirError, match="nested deeper"):
        loads("[" * 5000 + "]" * 5000, "x")
    with pytest.raises(RunDirError, match="not UTF-8"):
        loads(b'{"a": "\xff"}', "x")
    d = make_run(tmp_path / "run")
    for name in (GENERATIONS, PRUNING, CHECKPOINT, CONFIG):
        assert b"Infinity" not in (d / name).read_bytes() and b"NaN" not in (d / name).read_bytes()


# ------------------------------------------------------------------------------ locking
def test_a_locked_directory_refuses_a_second_writer(tmp_path):
    d = make_run(tmp_path / "run")
    with RunDir.open(d):
        with pytest.raises(RunDirError, match="in use by another eant2 process"):
            RunDir.open(d)
        with RunDir.open(d, lock=False) as reader:
            assert reader.is_live()
    with RunDir.open(d) as again:  # released on close
        again.read()


@pytest.mark.slow
def test_resume_of_a_live_run_is_refused(tmp_path, capsys, monkeypatch):
    """A real process holds the run (as a live `eant2 run` does); resume and a second
    creation are refused with one line and nothing changes; once it dies, resume works."""
    d = make_run(tmp_path / "run")
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(RUNDIR_PY), str(d)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = snapshot(d)
        rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)
        assert_one_error(rc, lines, "in use by another eant2 process")
        assert snapshot(d) == before
        rc, lines, _ = run_main(["report", d, "--out", tmp_path / "rep"], capsys, monkeypatch)
        assert rc == 0 and "live run" in lines[0], lines
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
        holder.stdout.close()
    rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)  # the OS dropped the lock
    assert rc == 0, lines


HOLD = """
import importlib, os, sys, time, types
# rundir and the ground-floor module it imports, without the package's __init__ (jax)
pkg = types.ModuleType("pkg"); pkg.__path__ = [os.path.dirname(sys.argv[1])]
sys.modules["pkg"] = pkg
rundir = importlib.import_module("pkg.rundir")
rd = rundir.RunDir.open(sys.argv[2])
print("locked", flush=True)
time.sleep(600)
"""


def test_concurrent_creations_make_one_directory(tmp_path):
    """40 synchronised pairs: exactly one creator wins each (check-then-create let both)."""
    for i in range(40):
        target = tmp_path / f"run{i}"
        barrier = threading.Barrier(2)
        results = []

        def create(target=target, barrier=barrier, results=results):
            barrier.wait()
            try:
                RunDir.create(target, {"generations": 0, "who": threading.get_ident()}).close()
                results.append("ok")
            except RunDirError:
                results.append("refused")

        threads = [threading.Thread(target=create) for _ in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(results) == ["ok", "refused"], (i, results)
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".run")) == []


KILL = """
import importlib, os, sys, time, types
# rundir and the ground-floor module it imports, without the package's __init__ (jax)
pkg = types.ModuleType("pkg"); pkg.__path__ = [os.path.dirname(sys.argv[1])]
sys.modules["pkg"] = pkg
rundir = importlib.import_module("pkg.rundir")
real = os.fsync
def slow(fd):
    time.sleep(0.04)
    real(fd)
os.fsync = slow
print("go", flush=True)
rundir.RunDir.create(sys.argv[2], {"generations": 0, "key": [0, 0], "task": "xor",
                                   "config": {}}).close()
time.sleep(600)
"""


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.1, 0.15, 0.3])
def test_kill_during_creation_leaves_nothing_half_made(delay, tmp_path):
    """SIGKILL at points through creation (every fsync slowed): the path is absent or a
    complete directory, and a new creation of it then succeeds or says it exists."""
    target = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-c", KILL, str(RUNDIR_PY), str(target)], stdout=subprocess.PIPE
    )
    assert proc.stdout.readline().strip() == b"go"
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    if target.exists():
        assert sorted(p.name for p in target.iterdir()) == [CONFIG, GENERATIONS, PRUNING]
        with RunDir.open(target) as rd:
            assert rd.read().checkpoint is None  # a stub: resume starts at generation 0
        with pytest.raises(RunDirError, match="not overwriting"):
            RunDir.create(target, {"generations": 0})
    else:
        RunDir.create(target, {"generations": 0}).close()
        assert [p.name for p in tmp_path.iterdir()] == ["run"]  # the dead one is removed


# ------------------------------------------------------------------------------ the table
def _symlink_log(d: Path, name: str) -> None:
    outside = d.parent / f"outside-{name}"
    outside.write_bytes((d / name).read_bytes() + b"precious\n" * 100)
    (d / name).unlink()
    (d / name).symlink_to(outside)


def _hardlink_log(d: Path) -> None:
    os.link(d / GENERATIONS, d.parent / "another-name")


def _fifo(d: Path) -> None:
    (d / PRUNING).unlink()
    os.mkfifo(d / PRUNING)


def _offset(value):
    def edit(d: Path):
        rewrite_checkpoint(d, lambda c: c["offsets"].__setitem__(GENERATIONS, value))

    return edit


def _line_end_offset(d: Path) -> None:  # the end of generation 0's line: drops generation 1
    first = (d / GENERATIONS).read_bytes().index(b"\n") + 1
    _offset(first)(d)


def _state_edit(field, value):
    def edit(d: Path):
        rewrite_checkpoint(d, lambda c: c["state"].__setitem__(field, value))

    return edit


def _config_edit(key, value, *, sub=None):
    def edit(d: Path):
        def change(cfg):
            target = (
                cfg if sub is None else cfg["config"] if sub == "config" else cfg["config"][sub]
            )
            if value is DELETE:
                del target[key]
            else:
                target[key] = value

        rewrite_config(d, change)

    return edit


DELETE = object()


def _append(name: str, text: bytes):
    def edit(d: Path):
        with open(d / name, "ab") as f:
            f.write(text)

    return edit


def _replace(name: str, old: bytes, new: bytes):
    def edit(d: Path):
        data = (d / name).read_bytes()
        assert old in data, (name, old)
        (d / name).write_bytes(data.replace(old, new, 1))

    return edit


def _write(name: str, data: bytes):
    def edit(d: Path):
        (d / name).write_bytes(data)

    return edit


def _two_output_best(d: Path) -> None:
    def edit(c):  # a second individual (the best one stays the record's)
        c["state"]["population"].append(
            {"genome": "N0/1*1.0 I0*1.0 N1/1*1.0 I1*1.0", "cost": 1.0, "origin": "init"}
        )

    rewrite_checkpoint(d, edit)


# (id, how to corrupt, what the one line must say). The directory is a finished synthetic
# run, so an accepted case would exit 0: every row must be refused.
CORRUPT = [
    ("symlinked generations", lambda d: _symlink_log(d, GENERATIONS), "symbolic link"),
    ("symlinked pruning", lambda d: _symlink_log(d, PRUNING), "symbolic link"),
    ("hard-linked log", _hardlink_log, "hard links"),
    ("fifo log", _fifo, "not a regular file"),
    ("offset 1.5", _offset(1.5), "not an integer"),
    ("offset true", _offset(True), "not an integer"),
    ("offset string", _offset("100"), "not an integer"),
    ("offset negative", _offset(-1), "shorter than its checkpoint"),
    ("offset mid-line", lambda d: _offset((d / GENERATIONS).stat().st_size - 2)(d), "line end"),
    ("offset at an earlier line end", _line_end_offset, "does not match the checksum"),
    ("generation 99", _state_edit("generation", 99), "generation 99 but"),
    ("generation 0", _state_edit("generation", 0), "generation 0 but"),
    ("float population", _state_edit("population", 2.5), "population"),
    ("empty population", _state_edit("population", []), "population"),
    ("population of strings", _state_edit("population", ["x"]), "individual"),
    ("next_id a string", _state_edit("next_id", "3"), "next_id"),
    ("key too short", _state_edit("key", []), "key"),
    ("key out of range", _state_edit("key", [0, 2**40]), "key"),
    ("foreign key", _state_edit("key", [0, 7]), "not the run's key"),
    ("evaluations differ", _state_edit("evaluations", 12345), "evaluations"),
    ("bucket of two sizes", _state_edit("bucket", [8, 16]), "bucket"),
    ("bucket of zeros", _state_edit("bucket", [0, 16, 2]), "bucket"),
    ("two-output genome for xor", _two_output_best, "outputs"),
    ("state edited silently", _replace(CHECKPOINT, b'"next_id": 3', b'"next_id": 4'), "checksum"),
    (
        "record edited silently",
        _replace(GENERATIONS, b'"exploited": 1', b'"exploited": 2'),
        "checksum",
    ),  # fmt: skip
    (
        "pruning edited silently",
        _replace(PRUNING, b'"iteration": 5', b'"iteration": 6'),
        "checksum",
    ),  # fmt: skip
    (
        "config edited silently",
        _replace(CONFIG, b'"population": 3', b'"population": 4'),
        "checksum",
    ),  # fmt: skip
    ("config []", _config_edit("config", []), "no configuration object"),
    ("config without exploit", _config_edit("exploit", DELETE, sub="config"), "missing: exploit"),
    ("config float population", _config_edit("population", 2.5, sub="config"), "population"),
    ("config missing a field", _config_edit("similar_limit", DELETE, sub="config"), "missing"),
    ("config sigma0 1e-45", _config_edit("sigma0", 1e-45, sub="exploit"), "sigma0"),
    ("config list leaf", _config_edit("sigma0", [1], sub="exploit"), "sigma0"),
    ("config task a number", _config_edit("task", 5), "task"),
    ("config task options a list", _config_edit("task_options", []), "task_options"),
    ("config generations -1", _config_edit("generations", -1), "generations"),
    ("config format 3", _config_edit("format", 3), "not a run configuration"),
    ("config not UTF-8", _write(CONFIG, b'{"format": 2, "task": "\xff"}'), "config.json"),
    ("config deeply nested", _write(CONFIG, b"[" * 100000 + b"]" * 100000), "nested deeper"),
    ("config Infinity", _write(CONFIG, b'{"format": 2, "x": Infinity}'), "Infinity"),
    ("checkpoint not UTF-8", _write(CHECKPOINT, b"{\xff}"), "checkpoint.json is corrupt"),
    ("checkpoint a list", _write(CHECKPOINT, b"[]"), "checkpoint.json is corrupt"),
    ("checkpoint NaN", _replace(CHECKPOINT, b'"wall_s": 0.2', b'"wall_s": NaN'), "NaN"),
    (
        "checkpoint without sums",
        lambda d: rewrite_checkpoint(d, lambda c: c.pop("sha256")),
        "checksums",
    ),  # fmt: skip
    ("generations truncated", lambda d: (d / GENERATIONS).write_bytes(b""), "shorter"),
    ("checkpoint deleted", lambda d: (d / CHECKPOINT).unlink(), "refusing to start over"),
    (
        "log not UTF-8 (committed part)",
        _replace(GENERATIONS, b"exploited", b"\xffxploited"),
        "checksum",
    ),  # fmt: skip
]


@pytest.mark.parametrize("corrupt,phrase", [c[1:] for c in CORRUPT], ids=[c[0] for c in CORRUPT])
def test_corrupt_run_directory_is_one_line_exit_2_unchanged(
    corrupt, phrase, tmp_path, capsys, monkeypatch
):
    d = make_run(tmp_path / "run")
    corrupt(d)
    before, around = snapshot(d), snapshot(tmp_path)
    rc, lines, out = run_main(["resume", d], capsys, monkeypatch)
    assert_one_error(rc, lines, phrase)
    assert out == ""
    assert snapshot(d) == before and snapshot(tmp_path) == around


def test_symlinked_log_outside_file_is_untouched(tmp_path, capsys, monkeypatch):
    """The issue's attack: a symlinked log pointing outside; resume used to truncate it."""
    d = make_run(tmp_path / "run")
    _append(GENERATIONS, b'{"torn": ')(d)  # uncommitted tail: resume would truncate
    _symlink_log(d, GENERATIONS)
    outside = tmp_path / f"outside-{GENERATIONS}"
    size = outside.stat().st_size
    rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)
    assert_one_error(rc, lines, "symbolic link")
    assert outside.stat().st_size == size


def test_uncommitted_tail_is_truncated_and_committed_records_kept(tmp_path, capsys, monkeypatch):
    d = make_run(tmp_path / "run")
    committed = {n: (d / n).read_bytes() for n in (GENERATIONS, PRUNING)}
    _append(GENERATIONS, b'{"generation": 2, "best_co')(d)
    _append(PRUNING, b"garbage\xff\n")(d)
    (d / "best.genome").write_text("N0/1*1 I0*1\n")  # a kill between the two renames
    rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)
    assert rc == 0, lines
    assert {n: (d / n).read_bytes() for n in (GENERATIONS, PRUNING)} == committed
    # Restored from the checkpoint, with the header of what is needed to run it.
    assert (d / "best.genome").read_text().splitlines()[-1] == XOR_BEST[1]


def test_legacy_format_1_directory_still_resumes(tmp_path, capsys, monkeypatch):
    """A directory as the previous code wrote it (format 1: no checksums, bare Infinity)."""
    d = make_run(tmp_path / "run")
    cfg = json.loads((d / CONFIG).read_text())
    cfg["format"] = 1
    (d / CONFIG).write_text(json.dumps(cfg, indent=2) + "\n")
    ckpt = json.loads((d / CHECKPOINT).read_text())
    (d / CHECKPOINT).write_text(json.dumps({"offsets": ckpt["offsets"], "state": ckpt["state"]}))
    text = (d / PRUNING).read_bytes()
    (d / PRUNING).write_bytes(text.replace(b'"inf"', b"Infinity").replace(b'"nan"', b"NaN"))
    ckpt["offsets"][PRUNING] = len((d / PRUNING).read_bytes())
    (d / CHECKPOINT).write_text(json.dumps({"offsets": ckpt["offsets"], "state": ckpt["state"]}))
    rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)
    assert rc == 0, lines
    # A config edit in a legacy directory is still caught by the cross-checks.
    rewrite = json.loads((d / CHECKPOINT).read_text())
    rewrite["state"]["generation"] = 5
    (d / CHECKPOINT).write_text(
        json.dumps({"offsets": rewrite["offsets"], "state": rewrite["state"]})
    )
    rc, lines, _ = run_main(["resume", d], capsys, monkeypatch)
    assert_one_error(rc, lines, "generation 5 but")


def test_report_of_malformed_records_is_one_line(tmp_path, capsys, monkeypatch):
    d = make_run(tmp_path / "run")
    rewrite_config(d, lambda c: None)
    data = (d / GENERATIONS).read_bytes().replace(b'"best_size": 3', b'"best_size": "3"', 1)
    (d / GENERATIONS).write_bytes(data)
    ckpt = json.loads((d / CHECKPOINT).read_text())
    ckpt["sha256"][GENERATIONS] = hashlib.sha256(data).hexdigest()
    ckpt["offsets"][GENERATIONS] = len(data)
    (d / CHECKPOINT).write_text(json.dumps(ckpt))
    out = tmp_path / "report"
    rc, lines, _ = run_main(["report", d, "--out", out], capsys, monkeypatch)
    assert_one_error(rc, lines, "generations.jsonl", "best_size")
    assert not out.exists()


# ------------------------------------------------------------------------ flags and genomes
@pytest.mark.parametrize(
    "argv,phrase",
    [
        (["run", "xor", "--seed", str(2**64)], "--seed"),
        (["run", "xor", "--seed", "-1"], "--seed"),
        (["run", "xor", "--seed", "1" * 5000], "--seed"),
        (["run", "xor", "--devices", "99"], "device"),
        (["run", "xor", "--target-cost", "nan"], "target_cost"),
        (["run", "xor", "--max-evaluations", "0"], "max_evaluations"),
        (["run", "xor", "--min-bucket", "8,40"], "--min-bucket"),
        (["run", "xor", "--min-bucket", "8,40,99999"], "min_bucket"),
        (["run", "xor", "--population", "99999999999999999999999"], "population"),
    ],
)
def test_bad_flags_create_nothing(argv, phrase, tmp_path, capsys, monkeypatch):
    rc, lines, _ = run_main([*argv, "--out", tmp_path / "out"], capsys, monkeypatch)
    if rc != 2:
        pytest.fail(f"exit {rc}: {lines}")
    assert_one_error(rc, lines, phrase)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "data,phrase",
    [
        (b"N0/1*1 I\xd9\xa3*1", "unknown token"),  # an Arabic-Indic digit
        (b"N0/1*1 I" + b"9" * 5000 + b"*1", "larger than"),
        (b"N0/1*1 I0*1\xff", "not UTF-8"),
        (b"", "empty genome"),
        (b"N0/1*1 I0*nan", "non-finite"),
        (b"N0/1*1 I0*1e999", "non-finite"),
    ],
)
def test_bad_genome_files_are_one_line(data, phrase, tmp_path, capsys, monkeypatch):
    src = tmp_path / "g.genome"
    src.write_bytes(data)
    rc, lines, _ = run_main(["show", src], capsys, monkeypatch)
    assert_one_error(rc, lines, str(src), phrase)
    assert [p.name for p in tmp_path.iterdir()] == ["g.genome"]


def test_show_is_fast_on_a_wide_genome(tmp_path, capsys, monkeypatch):
    src = tmp_path / "wide.genome"
    src.write_text("N0/1*1 I20000*1\n")
    t0 = time.perf_counter()
    rc, lines, out = run_main(["show", src], capsys, monkeypatch)
    assert rc == 0, lines
    assert time.perf_counter() - t0 < 20, "over 5 minutes before issue 16"
    assert "inputs_read: 20001" in out


def test_genome_numbers_are_ascii_and_bounded():
    with pytest.raises(GenomeError, match="unknown token"):
        Genome.parse("N0/1*1 I\u0663*1")
    with pytest.raises(GenomeError, match="larger than 2147483647"):
        Genome.parse("N2147483648/1*1 I0*1")
    assert Genome.parse("N2147483647/1*1 I0*1").neuron_ids == (2147483647,)


@pytest.mark.slow
def test_compiling_beyond_the_int32_slot_table_is_a_clear_error():
    from eant2_jax.compiler import compile_genomes

    n = 24_577  # padded to 32,768 neuron slots: 2 * 32768**2 entries overflow int32
    genes = f"N0/{n - 1}*1 " + " ".join(f"N{i}/1*1 B*1" for i in range(1, n))
    with pytest.raises(ValueError, match="int32 slot table"):
        compile_genomes([Genome.parse(genes)], n_inputs=1)


@pytest.mark.parametrize("sigma0", [1e-45, 1e-39, 1e39, float("nan")])
def test_sigma0_is_checked_in_the_state_dtype(sigma0):
    with pytest.raises(ValueError, match="sigma0"):
        ExploitConfig(sigma0=sigma0)


def test_sigma0_in_float64_range_is_fine_for_a_float64_state():
    assert ExploitConfig(sigma0=1e-45, dtype="float64").sigma0 == 1e-45
