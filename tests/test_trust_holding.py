"""The cases issue 40 found holding, kept so (docs/reliability.md): a full disk during a run
loses no committed record and resume finishes the run; a full or unwritable cache disk
costs the cache only; two runs on one cold cache, and two runs with one ``--out``; 40
processes creating one directory; two resumes of one reproduction. (A kill of ``reproduce``
then resume: tests/test_reproduce_resume.py; ``report`` on a live run:
tests/test_rundir.py::test_resume_of_a_live_run_is_refused.)"""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import pytest
from rundirs import run_main
from test_reproduce_resume import SETTINGS  # the reproduction those tests resume

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, rundir, tasks
from eant2_jax.checkpoint import validate
from eant2_jax.loop import RUN_DEPENDENT
from eant2_jax.programs import store as programstore
from eant2_jax.rundir import CONFIG, GENERATIONS, PRUNING, RunDir

RUNDIR_PY = Path(rundir.__file__)
TINY_FLAGS = ["--population", "3", "--max-iters", "30", "--pruner", "none", "--seed", "5"]


def _records(run_dir: Path) -> list[dict]:
    """A run's generation and pruning records without what describes the process."""
    rows = []
    for name in (GENERATIONS, PRUNING):
        for line in (run_dir / name).read_text().splitlines():
            rows.append({k: v for k, v in json.loads(line).items() if k not in RUN_DEPENDENT})
    return rows


# ------------------------------------------------------------------ one directory, 40 creators
CREATE = """
import importlib, os, sys, time, types
# rundir and the ground-floor modules it imports, without the package's __init__ (jax)
pkg = types.ModuleType("pkg"); pkg.__path__ = [os.path.dirname(sys.argv[1])]
sys.modules["pkg"] = pkg
rundir = importlib.import_module("pkg.rundir")
print("ready", flush=True)
while not os.path.exists(sys.argv[3]):  # all start together
    time.sleep(0.0005)
try:
    meta = {"generations": 0, "key": [0, 0], "task": "xor", "config": {}, "pid": os.getpid()}
    rundir.RunDir.create(sys.argv[2], meta).close()
    print("ok", flush=True)
except rundir.RunDirError as e:
    print("refused", e, flush=True)
"""


@pytest.mark.slow
def test_forty_processes_creating_one_directory(tmp_path):
    """40 processes create one run directory at the same instant: exactly one wins, the 39
    others are refused in one line each, and the directory is the winner's, whole."""
    target, go = tmp_path / "run", tmp_path / "go"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", CREATE, str(RUNDIR_PY), str(target), str(go)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(40)
    ]
    try:
        for p in procs:
            assert p.stdout.readline() == "ready\n"
        go.touch()
        outs = [p.communicate(timeout=120)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert all(p.returncode == 0 for p in procs), outs
    won = [(p.pid, o) for p, o in zip(procs, outs, strict=True) if o == "ok\n"]
    refused = [o for o in outs if o.startswith("refused ")]
    assert len(won) == 1 and len(refused) == 39, outs
    assert all(o.count("\n") == 1 and str(target) in o for o in refused), refused
    assert sorted(p.name for p in target.iterdir()) == [CONFIG, GENERATIONS, PRUNING]
    assert json.loads((target / CONFIG).read_text())["pid"] == won[0][0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["go", "run"]  # no half-made one
    RunDir.open(target).close()


# ---------------------------------------------------------------------------- a full disk
class _FullDisk:
    """``os.write`` that, once armed, writes half of its first buffer into a file of
    ``folder`` and then fails with ENOSPC (as a disk that filled up mid-record)."""

    def __init__(self, folder: Path):
        self.folder, self.armed, self.half_written, self.refused = str(folder), False, False, 0
        self.real = os.write

    def __call__(self, fd, data):
        if self.armed and os.readlink(f"/proc/self/fd/{fd}").startswith(self.folder):
            if not self.half_written:
                self.half_written = True
                return self.real(fd, bytes(data)[: max(1, len(data) // 2)])
            self.refused += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.real(fd, data)


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")
def test_a_full_disk_mid_run_loses_nothing_and_resume_finishes(tmp_path, capsys, monkeypatch):
    """The disk fills while generation 1 is being committed (half a record written):
    ``eant2 run`` ends with one line, generation 0 stays committed and checks, and
    ``eant2 resume`` finishes with exactly the records of an uninterrupted run."""
    argv = ["run", "xor", "--generations", "2", *TINY_FLAGS]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    rc, _, err = run_main([*argv, "--out", whole], capsys, monkeypatch)
    assert rc == 0, err
    full, commit, commits = _FullDisk(cut), RunDir.commit, []

    def commit_then_fill(self, *args, **kwargs):
        full.armed = len(commits) == 1  # generation 0 is committed: the disk fills
        commits.append(1)
        return commit(self, *args, **kwargs)

    monkeypatch.setattr(os, "write", full)
    monkeypatch.setattr(RunDir, "commit", commit_then_fill)
    rc, _, err = run_main([*argv, "--out", cut], capsys, monkeypatch)
    monkeypatch.setattr(os, "write", full.real)
    monkeypatch.setattr(RunDir, "commit", commit)
    assert full.half_written and full.refused >= 1
    assert rc == 2 and "No space left on device" in err[-1] and "Traceback" not in "".join(err)
    assert validate(str(cut)).state.generation == 0  # the committed generation, checked
    rc, _, err = run_main(["resume", cut], capsys, monkeypatch)
    assert rc == 0, err
    assert _records(cut) == _records(whole)
    assert (cut / "best.genome").read_text() == (whole / "best.genome").read_text()


# ------------------------------------------------------------------------- full cache disk
# The sizes and settings of TINY_FLAGS: the programs of the command runs above.
TINY = EANT2Config(population=3, exploit=ExploitConfig(max_iters=30, pruner="none"))


def _run_records(**kwargs) -> tuple[str, list[str]]:
    res = eant2_jax.run(tasks.make("xor"), key=jax.random.key(3), config=TINY, **kwargs)
    rows = [r.to_json() for r in [*res.generations, *res.pruning]]
    return str(res.best), [
        json.dumps({k: v for k, v in r.items() if k not in RUN_DEPENDENT}, sort_keys=True)
        for r in rows
    ]


@pytest.mark.slow
def test_a_full_cache_disk_costs_the_saving_only(tmp_path, monkeypatch):
    """Every write of the program store ends in ENOSPC (its temporary files are /dev/full):
    the run computes what it computes with the store off, and leaves no entry or temporary
    file behind."""
    folder = tmp_path / "programs"
    monkeypatch.setattr(programstore, "_PROGRAMS", {})
    monkeypatch.setattr(programstore, "directory", lambda: None)
    off = _run_records(generations=0)
    mkstemp, filled = tempfile.mkstemp, []

    def onto_dev_full(*args, **kwargs):
        fd, name = mkstemp(*args, **kwargs)
        if Path(name).parent == folder:
            full = os.open("/dev/full", os.O_WRONLY)
            os.dup2(full, fd)
            os.close(full)
            filled.append(name)
        return fd, name

    monkeypatch.setattr(tempfile, "mkstemp", onto_dev_full)
    monkeypatch.setattr(programstore, "_PROGRAMS", {})
    monkeypatch.setattr(programstore, "directory", lambda: folder)
    assert _run_records(generations=0) == off
    assert filled, "the store wrote nothing: the test proves nothing"
    assert list(folder.iterdir()) == []


@pytest.mark.slow
def test_an_unwritable_cache_folder_costs_the_cache_only(tmp_path, capsys, monkeypatch):
    """``EANT2_CACHE_DIR`` under a regular file (nothing can be made or written there, as on
    a read-only disk): ``eant2 run`` exits 0 with the records of a run without the cache,
    and the file is untouched."""
    argv = ["run", "xor", "--generations", "1", *TINY_FLAGS]
    rc, _, err = run_main([*argv, "--out", tmp_path / "off"], capsys, monkeypatch)
    assert rc == 0, err
    blocker = tmp_path / "file"
    blocker.write_text("not a folder\n")
    monkeypatch.setenv("EANT2_CACHE_DIR", str(blocker / "xla"))
    monkeypatch.setattr(programstore, "_PROGRAMS", {})
    from eant2_jax.app.cli import main

    assert main([str(a) for a in [*argv, "--out", tmp_path / "ro"]]) == 0
    assert _records(tmp_path / "ro") == _records(tmp_path / "off")
    assert blocker.read_text() == "not a folder\n"


# ------------------------------------------------------- real full and read-only cache disks
MOUNTS = """
set -e
mount -t tmpfs -o size=96k,mode=0700 tmpfs "$FULL"
for ro in "$RO_COLD" "$RO_WARM"; do mount --bind "$ro" "$ro"; mount -o remount,bind,ro "$ro"; done
if touch "$RO_WARM/x" 2>/dev/null; then exit 3; fi
for pair in "full=$FULL" "ro_cold=$RO_COLD" "ro_warm=$RO_WARM"; do
  name=${pair%%=*}
  (EANT2_CACHE_DIR=${pair#*=} "$PY" -m eant2_jax.app.cli $ARGV --out "$OUT/$name" \\
     >"$OUT/$name.log" 2>&1; echo $? >"$OUT/$name.rc") &
done
wait
du -sb "$FULL" | cut -f1 >"$OUT/full.used"
"""


def _namespaces() -> bool:
    """Whether this process may mount in a mount namespace of its own (root, or a kernel
    that lets users make one)."""
    try:
        with tempfile.TemporaryDirectory() as d:
            cmd = ["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=4k tmpfs {d}"]
            return subprocess.run(cmd, capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


@pytest.mark.slow
@pytest.mark.skipif(not _namespaces(), reason="needs mounts in a mount namespace (root)")
def test_a_full_or_read_only_cache_disk_leaves_the_run_as_it_was(tmp_path, three_runs):
    """Real disks, mounted in a namespace of the test's own: a 96 KiB tmpfs that the
    cache fills, an empty folder mounted read-only, and a warm cache mounted read-only.
    ``eant2 run`` exits 0 on each with the records of the runs that warmed the cache (the
    same command: `three_runs`, its cache copied here, and its run that ran alone)."""
    argv = ["run", "xor", "--generations", "1", *TINY_FLAGS]
    runs, results = three_runs
    assert results[1][0] == 0, results[1][2][-3000:]
    first, warm = runs / "alone", tmp_path / "warm"
    shutil.copytree(runs / "cache", warm)
    held = sum(p.stat().st_size for p in warm.rglob("*") if p.is_file())
    assert held > 2 * 96 * 1024, f"the cache holds {held} bytes: a 96 KiB disk would not fill"
    dirs = {"FULL": tmp_path / "full", "RO_COLD": tmp_path / "ro_cold", "RO_WARM": warm}
    out = tmp_path / "out"
    for d in (*dirs.values(), out):
        d.mkdir(exist_ok=True)
    env = {**os.environ, **{k: str(v) for k, v in dirs.items()}, "OUT": str(out),
           "PY": sys.executable, "ARGV": " ".join(argv)}  # fmt: skip
    proc = subprocess.run(["unshare", "-m", "sh", "-c", MOUNTS], env=env, capture_output=True,
                          text=True, timeout=590)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert int((out / "full.used").read_text()) > 48 * 1024  # it did fill
    for name in ("full", "ro_cold", "ro_warm"):
        log = (out / f"{name}.log").read_text()
        assert (out / f"{name}.rc").read_text().strip() == "0", (name, log[-3000:])
        assert "Traceback" not in log, (name, log[-3000:])
        assert _records(out / name) == _records(first), name


# -------------------------------------------------------- concurrent processes, real commands
def _eant2(args, env) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "eant2_jax.app.cli", *map(str, args)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(procs) -> list[tuple[int, str, str]]:
    try:
        outs = [p.communicate(timeout=590) for p in procs]
        return [(p.returncode, *o) for p, o in zip(procs, outs, strict=True)]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()


@pytest.fixture(scope="module")
def three_runs(tmp_path_factory):
    """Three ``eant2 run`` processes at once on one empty cache folder (``cache``), two of
    them with one ``--out`` (``shared``), the third alone (``alone``): the folder and the
    processes' ``(exit code, stdout, stderr)``. Once for the module: the runs leave a warm
    cache, which `test_a_full_or_read_only_cache_disk_leaves_the_run_as_it_was` mounts."""
    tmp_path = tmp_path_factory.mktemp("three")
    env = {**os.environ, "EANT2_CACHE_DIR": str(tmp_path / "cache")}
    argv = ["run", "xor", "--generations", "1", *TINY_FLAGS]
    shared, alone = tmp_path / "shared", tmp_path / "alone"
    procs = [_eant2([*argv, "--out", out], env) for out in (shared, alone, shared)]
    return tmp_path, _finish(procs)


@pytest.mark.slow
def test_two_runs_on_one_cold_cache_and_two_runs_with_one_out(three_runs):
    """Three ``eant2 run`` processes at once on one empty cache folder, two of them with one
    ``--out``: one of those two is refused in one line and the directory is the other's,
    whole; the runs that ran have the same records (same seed), and the cache holds
    entries both of XLA and of the program store."""
    tmp_path, results = three_runs
    cache, shared, alone = tmp_path / "cache", tmp_path / "shared", tmp_path / "alone"
    (rc_a, _, err_a), (rc_b, _, err_b), (rc_c, _, err_c) = results
    assert rc_b == 0, err_b[-3000:]
    assert sorted([rc_a, rc_c]) == [0, 2], (err_a[-3000:], err_c[-3000:])
    loser = (err_a if rc_a == 2 else err_c).strip().splitlines()
    assert "Traceback" not in "\n".join(loser) and str(shared) in loser[-1], loser
    assert "not overwriting" in loser[-1] or "in use by another eant2 process" in loser[-1]
    assert validate(str(shared)).state.generation == 1
    assert _records(shared) == _records(alone)
    assert any(p.parent == cache for p in cache.iterdir() if p.is_file())
    assert list((cache / programstore.DIRNAME).glob("*.program"))


# A small reproduction with every part of one (two arms of two runs in lock-step, the
# condition experiment, the report): what the two resumes race for is its run directories
# and files, whatever sizes its programs have, however many generations they run past the
# cut and whichever pruner its second arm has (smaller, fewer and cheaper to compile: the
# magnitude pruner's programs compile faster than the covariance pruner's).
REPRODUCTION = {**SETTINGS, "generations": 1, "condition_inits": 1, "pruners": ("magnitude",)}


@pytest.mark.slow
def test_two_resumes_of_one_reproduction(tmp_path, monkeypatch):
    """A reproduction cut in its first arm, then two ``eant2 resume`` of it at once: each
    finishes it or is refused in one line (a run directory in use), no record is written
    twice, every run checks, and a last resume finds it finished (changes no run). That
    the records are those of an uninterrupted reproduction: tests/test_reproduce_resume.py."""
    from eant2_jax.app.cli import main
    from eant2_jax.app.experiments import reproduce

    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # in-process: leave the JAX configuration alone

    zeros = []

    def cut_short(event):  # after generation 0 of the first arm's two runs (in lock-step,
        # both committed: the resume goes on in lock-step, one program): generation 1 is left
        if event["event"] == "generation" and event["arm"] == "none" and event["generation"] == 0:
            zeros.append(event["run"])
            if len(zeros) == REPRODUCTION["runs"]:
                raise KeyboardInterrupt

    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        reproduce(tasks.make("xor"), cut, callback=cut_short, **REPRODUCTION)
    env = {**os.environ, "EANT2_CACHE_DIR": ""}
    procs = [_eant2(["resume", cut], env) for _ in range(2)]
    results = _finish(procs)
    assert 0 in [rc for rc, _, _ in results], [e[-3000:] for _, _, e in results]
    for rc, _, err in results:
        assert rc in (0, 2) and "Traceback" not in err, err[-3000:]
        if rc == 2:
            assert "in use by another eant2 process" in err.strip().splitlines()[-1], err
    runs = sorted(p for p in cut.iterdir() if (p / CONFIG).is_file())
    assert [p.name for p in runs] == ["magnitude-s0", "magnitude-s1", "none-s0", "none-s1"]
    logs = {}
    for run in runs:  # generations 0 and 1 once each (a linear unit never solves XOR: no
        # run stops after generation 0), all committed
        lines = (run / GENERATIONS).read_text().splitlines()
        gens = [json.loads(x)["generation"] for x in lines]
        assert gens == [0, 1], (run.name, gens)
        assert validate(str(run)).state.generation == gens[-1], run.name
        logs[run.name] = (run / GENERATIONS).read_bytes()
    assert main(["resume", str(cut)]) == 0  # finished: nothing more to run
    assert {run.name: (run / GENERATIONS).read_bytes() for run in runs} == logs
    assert (cut / "report" / "report.md").is_file()
