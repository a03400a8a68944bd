"""Tests of the EANT2 loop, its run directories and the ``eant2`` command line.

* a short XOR run through the Python API: record fields, monotone bookkeeping, solved;
* determinism: the same key and config give the same run;
* crash safety: a simulated crash inside a checkpoint write (``rundir``), a real subprocess
  killed with SIGKILL and one interrupted with SIGINT, each resumed to exactly the result of
  an uninterrupted run;
* command-line errors: exit code 2, one line, nothing in the directory changed.

The in-process runs share one configuration, so they share compiled programs (the first one
pays for compilation). The subprocess runs share a persistent compilation cache
(``EANT2_CACHE_DIR``) in a temporary directory of the session.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from compiles import force_compile_ahead, joined

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, tasks
from eant2_jax.app.cli import main
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.genomefile import GenomeFile
from eant2_jax.rundir import CHECKPOINT, GENERATIONS, PRUNING, RunDirError

RECORD_FIELDS = (
    "generation",
    "best_cost",
    "best_size",
    "mean_size",
    "best_neurons",
    "evaluations",
    "wall_s",
    "prune_attempts",
    "prune_accepted",
)
# The only fields that may differ between runs: wall times and compilation statistics.
WALL_FIELDS = eant2_jax.records.RUN_DEPENDENT
XOR_IN = np.array([[[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]]])
XOR_OUT = np.array([False, True, True, False])

# Seed 0 solves XOR in generation 1 (its first structural mutation: one hidden neuron).
SEED = 0
GENERATIONS_API = 1
# stop_when_solved off: these tests are about runs of a given number of generations.
CONFIG = EANT2Config(
    population=6, stop_when_solved=False, exploit=ExploitConfig(max_iters=300, pruner="covariance")
)

# The command-line runs: small and short (their cost is compilation and process start-up),
# without a pruner (a smaller engine program to compile; kill, Ctrl-C and resume do not
# depend on it: resume's exact pruning records, test_resume_after_crash_inside_a_commit).
CLI_RUN = ["--population", "4", "--seed", "1", "--max-iters", "200", "--pruner", "none"]
CLI_GENERATIONS = 2


def solves_xor(genome) -> bool:
    out = np.asarray(eant2_jax.evaluate(genome, XOR_IN)).ravel()
    return bool(np.all((out > 0.5) == XOR_OUT))


def _json(records) -> list[dict]:
    """Typed records (GenerationRecord, PruneAttempt) as the JSON their files hold."""
    return [r.to_json() for r in records]


def _without_wall(records: list[dict]) -> list[str]:
    """Records as canonical JSON text without the wall-clock fields (NaN-safe equality)."""
    return [
        json.dumps({k: v for k, v in r.items() if k not in WALL_FIELDS}, sort_keys=True)
        for r in records
    ]


def _state_without_wall(directory: Path) -> dict:
    state = json.loads((directory / CHECKPOINT).read_text())["state"]
    state.pop("wall_s")
    return state


def _jsonl(directory: Path, name: str) -> list[dict]:
    return [json.loads(line) for line in (directory / name).read_text().splitlines()]


def _snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (hidden ones too) with its bytes."""
    if not directory.exists():
        return {}
    return {
        str(p.relative_to(directory)): p.read_bytes()
        for p in sorted(directory.rglob("*"))
        if p.is_file()
    }


def _assert_same_run(a: Path, b: Path) -> None:
    """Two run directories hold exactly the same run (wall-clock fields aside)."""
    assert (a / "best.genome").read_bytes() == (b / "best.genome").read_bytes()
    assert _state_without_wall(a) == _state_without_wall(b)
    assert _without_wall(_jsonl(a, GENERATIONS)) == _without_wall(_jsonl(b, GENERATIONS))
    assert (a / PRUNING).read_bytes() == (b / PRUNING).read_bytes()


# ------------------------------------------------------------------------------ Python API
@pytest.fixture(scope="module")
def xor_run():
    """The reference in-process run (compiles; later runs of CONFIG reuse the programs)."""
    events = []
    t0 = time.perf_counter()
    result = eant2_jax.run(
        tasks.make("xor"),
        key=jax.random.key(SEED),
        config=CONFIG,
        generations=GENERATIONS_API,
        callback=events.append,
    )
    return result, events, time.perf_counter() - t0


@pytest.mark.slow
def test_short_xor_run(xor_run):
    result, events, _ = xor_run
    gens = _json(result.generations)
    assert [r["generation"] for r in gens] == list(range(GENERATIONS_API + 1))
    for r in gens:
        assert set(RECORD_FIELDS) <= set(r)
        assert r["population"] <= CONFIG.population
        assert r["best_size"] >= 1 and r["best_neurons"] >= 1 and r["mean_size"] >= 1
        assert 0 <= r["prune_accepted"] <= r["prune_attempts"]
    evals = [r["evaluations"] for r in gens]
    assert all(b > a for a, b in zip(evals, evals[1:], strict=False)) and evals[0] > 0
    walls = [r["wall_s"] for r in gens]
    assert all(b >= a for a, b in zip(walls, walls[1:], strict=False))
    # Selection keeps the parents, so the best cost never rises — except by the tolerance
    # within which a smaller network is preferred to a larger one (EANT2Config.size_*).
    costs = [r["best_cost"] for r in gens]
    for a, b in zip(costs, costs[1:], strict=False):
        assert b <= a + CONFIG.size_tolerance * max(abs(a), abs(b)) + CONFIG.size_atol
    # The generation events are the records; the pruning records add up.
    assert [e for e in events if e["event"] == "generation"] == [
        {"event": "generation", **r} for r in gens
    ]
    assert sum(r["prune_attempts"] for r in gens) == len(_json(result.pruning))
    assert sum(r["prune_accepted"] for r in gens) == sum(
        p["accepted"] for p in _json(result.pruning)
    )
    # The population is best first and its best is the result.
    pop = result.population
    assert pop[0].genome == result.best and str(result.best) == gens[-1]["best_genome"]
    assert pop[0].cost == gens[-1]["best_cost"]
    assert len({ind.genome.structure_key() for ind in pop}) == len(pop)
    # Generation 0 exploits the minimal network: a linear unit cannot do XOR.
    assert gens[0]["best_neurons"] == 1 and gens[0]["best_cost"] > 0.2
    assert solves_xor(result.best), f"XOR not solved after {GENERATIONS_API} generation(s)"
    assert result.best.n_neurons >= 2 and gens[-1]["best_cost"] < 1e-6


@pytest.mark.slow
def test_same_key_same_run(xor_run):
    first, _, _ = xor_run
    again = eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(SEED), config=CONFIG, generations=GENERATIONS_API
    )
    assert str(again.best) == str(first.best)
    assert _without_wall(_json(again.generations)) == _without_wall(_json(first.generations))
    assert json.dumps(_json(again.pruning)) == json.dumps(_json(first.pruning))
    assert [(str(i.genome), i.cost, i.origin) for i in again.population] == [
        (str(i.genome), i.cost, i.origin) for i in first.population
    ]
    other = eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(SEED + 1), config=CONFIG, generations=0
    )
    # Generation 0 is the same minimal structure, tuned from other random weights.
    assert str(other.best) != str(_json(first.generations)[0]["best_genome"])


# ------------------------------------------------------------------ crash safety (rundir)
@pytest.mark.slow
def test_resume_after_crash_inside_a_commit(xor_run, tmp_path):
    """A crash after the .jsonl append but before the checkpoint replace (and with a
    half-written temporary checkpoint left behind) resumes to exactly the reference run."""
    reference, _, _ = xor_run
    task = tasks.make("xor")
    run_dir = tmp_path / "run"
    eant2_jax.run(task, key=jax.random.key(SEED), config=CONFIG, generations=0, out=str(run_dir))
    checkpoint = json.loads((run_dir / CHECKPOINT).read_text())
    assert checkpoint["offsets"] == {
        GENERATIONS: (run_dir / GENERATIONS).stat().st_size,
        PRUNING: (run_dir / PRUNING).stat().st_size,
    }
    # What the next commit had written when it died: its log lines (one of them torn) and a
    # temporary checkpoint and best genome that never got renamed.
    with open(run_dir / GENERATIONS, "a") as f:
        f.write(json.dumps(_json(reference.generations)[1]) + "\n")
        f.write('{"generation": 2, "best_co')
    with open(run_dir / PRUNING, "a") as f:
        f.write('{"structure": 0, "iteration"')
    (run_dir / ".checkpoint.json.x1y2z3.tmp").write_text('{"offsets": {"generations.js')
    (run_dir / ".best.genome.a1b2c3.tmp").write_text("N0/1*1.0 I0*")

    resumed = eant2_jax.resume(str(run_dir), task, generations=GENERATIONS_API)

    assert str(resumed.best) == str(reference.best)
    assert _without_wall(_json(resumed.generations)) == _without_wall(_json(reference.generations))
    assert json.dumps(_json(resumed.pruning)) == json.dumps(_json(reference.pruning))
    # On disk: the torn lines are gone, each generation appears once, and the files agree
    # with the returned records.
    on_disk = _jsonl(run_dir, GENERATIONS)
    assert [r["generation"] for r in on_disk] == list(range(GENERATIONS_API + 1))
    assert _without_wall(on_disk) == _without_wall(_json(reference.generations))
    assert _jsonl(run_dir, PRUNING) == json.loads(json.dumps(_json(reference.pruning)))
    best = GenomeFile.read(run_dir / "best.genome")
    assert best.genome == reference.best and best.has_header
    assert not list(run_dir.glob(".*.tmp")), "resume leaves the dead commit's temporary files"
    state = json.loads((run_dir / CHECKPOINT).read_text())["state"]
    assert state["generation"] == GENERATIONS_API
    assert [(p["genome"], p["cost"]) for p in state["population"]] == [
        (str(i.genome), i.cost) for i in reference.population
    ]


@pytest.mark.slow
def test_resume_before_the_first_checkpoint(xor_run, tmp_path):
    """Killed inside generation 0's commit: no checkpoint yet, so the run starts over."""
    reference, _, _ = xor_run
    task = tasks.make("xor")
    run_dir = tmp_path / "run"
    eant2_jax.run(task, key=jax.random.key(SEED), config=CONFIG, generations=0, out=str(run_dir))
    (run_dir / CHECKPOINT).unlink()
    (run_dir / "best.genome").unlink()
    (run_dir / ".checkpoint.json.tmp42.tmp").write_text("")
    resumed = eant2_jax.resume(str(run_dir), task, generations=0)
    assert _without_wall(_json(resumed.generations)) == _without_wall(
        _json(reference.generations)[:1]
    )
    assert len(_jsonl(run_dir, GENERATIONS)) == 1


def test_rewind_refuses_a_log_shorter_than_its_checkpoint(tmp_path):
    from eant2_jax.rundir import RunDir

    with RunDir.create(tmp_path / "run", {"generations": 1}) as run_dir:
        run_dir.commit([{"generation": 0}], [], "N0/1*1.0 I0*1.0", {"generation": 0})
    (tmp_path / "run" / GENERATIONS).write_text("")
    with RunDir.open(tmp_path / "run") as run_dir:
        with pytest.raises(RunDirError, match="shorter than its checkpoint"):
            run_dir.read()


# ------------------------------------------------------------------------- command line
# `eant2`, with Python's Ctrl-C handler whatever this process does with SIGINT: a test suite
# started as a background job ignores SIGINT, a child inherits that, and Python then leaves
# it ignored (as it should for a user's background run), so the Ctrl-C test's signal would
# be lost. Not a `preexec_fn`: unsafe in a process with threads (JAX's).
_CLI = (
    "import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv[0] = 'eant2'; runpy.run_module('eant2_jax.app.cli', run_name='__main__')"
)


def _eant2(*args: str, cache: Path, **kw) -> subprocess.Popen:
    env = {**os.environ, "EANT2_CACHE_DIR": str(cache), "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-c", _CLI, *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kw,
    )


def _finish(proc: subprocess.Popen, timeout: float = 300) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def _wait_for_lines(path: Path, n: int, proc: subprocess.Popen, timeout: float = 300) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if path.exists() and path.read_text().count("\n") >= n:
            return
        if proc.poll() is not None:
            raise AssertionError(f"eant2 exited early ({proc.returncode}): {proc.stderr.read()}")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"no {n} line(s) in {path} after {timeout} s")


@pytest.fixture(scope="module")
def cli_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("xla-cache")


@pytest.fixture(scope="module")
def cli_reference(tmp_path_factory, cli_cache):
    """An uninterrupted command-line run (it fills the compilation cache)."""
    out = tmp_path_factory.mktemp("cli") / "reference"
    rc, stdout, err = _finish(
        _eant2(
            "run",
            "xor",
            "--generations",
            str(CLI_GENERATIONS),
            *CLI_RUN,
            "--out",
            str(out),
            cache=cli_cache,
        )
    )
    assert rc == 0, err
    assert stdout.splitlines()[-1] == f"run directory: {out}"
    return out


@pytest.mark.slow
def test_cli_kill_and_resume_is_exact(cli_reference, cli_cache, tmp_path, capsys, monkeypatch):
    out = tmp_path / "killed"
    proc = _eant2(
        "run",
        "xor",
        "--generations",
        str(CLI_GENERATIONS),
        *CLI_RUN,
        "--out",
        str(out),
        cache=cli_cache,
    )
    # The first line is appended before the checkpoint is written: the kill may land inside
    # that commit, in a later generation's exploitation, or in a later commit.
    _wait_for_lines(out / GENERATIONS, 1, proc)
    proc.send_signal(signal.SIGKILL)
    rc, _, _ = _finish(proc)
    assert rc == -signal.SIGKILL
    # Generation 0 of this run came from a process that found the reference's programs in
    # the persistent cache; the reference's own generation 0 compiled them.
    warm, cold = _jsonl(out, GENERATIONS)[0], _jsonl(cli_reference, GENERATIONS)[0]
    assert warm["cache_hits"] >= 1 and cold["cache_misses"] >= 1
    assert cold["compiles"] >= 1 and cold["compile_s"] > 0
    rc, _, err = _finish(_eant2("resume", str(out), cache=cli_cache))
    assert rc == 0, err
    _assert_same_run(out, cli_reference)
    assert (out / "config.json").read_bytes() == (cli_reference / "config.json").read_bytes()
    assert not list(out.glob(".*.tmp"))
    # Resuming a finished run changes nothing but reports the same result (in-process: no
    # generation is left to run, so nothing is compiled).
    before = _snapshot(out)
    rc, _, stdout = _run_main(["resume", str(out)], capsys, monkeypatch)
    assert rc == 0
    assert _snapshot(out) == before
    assert str(GenomeFile.read(out / "best.genome").genome) in stdout


@pytest.mark.slow
def test_cli_ctrl_c_exits_130_and_resumes(cli_reference, cli_cache, tmp_path):
    out = tmp_path / "interrupted"
    # Many generations and no stop at the solved level, so that the run is still going when
    # the signal arrives (a run that solved XOR ended just as the signal came, exit 0).
    proc = _eant2(
        "run",
        "xor",
        "--generations",
        "200",
        "--no-solved-stop",
        *CLI_RUN,
        "--out",
        str(out),
        cache=cli_cache,
    )
    _wait_for_lines(out / GENERATIONS, 1, proc)
    proc.send_signal(signal.SIGINT)
    rc, _, err = _finish(proc, timeout=120)
    assert rc == 130, err
    assert "interrupted" in err and f"eant2 resume {out}" in err
    assert "Traceback" not in err
    # It resumes: one more generation, and every generation the reference also ran is
    # exactly the reference's.
    done = len(_jsonl(out, GENERATIONS))  # a torn or uncheckpointed last line may be cut
    rc, _, err = _finish(_eant2("resume", str(out), "--generations", str(done), cache=cli_cache))
    assert rc == 0, err
    gens = _jsonl(out, GENERATIONS)
    assert [r["generation"] for r in gens] == list(range(done + 1))
    n = min(len(gens), CLI_GENERATIONS + 1)
    assert _without_wall(gens[:n]) == _without_wall(_jsonl(cli_reference, GENERATIONS)[:n])
    assert not list(out.glob(".*.tmp"))
    # Ctrl-C in `eant2 resume DIR` gives the same hint (it has DIR, not --out).
    proc = _eant2("resume", str(out), "--generations", "200", "--no-solved-stop", cache=cli_cache)
    _wait_for_lines(out / GENERATIONS, len(gens) + 1, proc)
    proc.send_signal(signal.SIGINT)
    rc, _, err = _finish(proc, timeout=120)
    assert rc == 130, err
    assert f"eant2 resume {out}" in err and "Traceback" not in err


def test_a_ctrl_c_swallowed_by_a_callback_still_stops_the_command(monkeypatch):
    """Python raises KeyboardInterrupt where SIGINT lands; inside a callback run from C (the
    garbage collector's) it is printed as ignored. The command remembers the signal and its
    progress callbacks raise it again, on the main thread; `main` puts the previous SIGINT
    handler back."""
    import threading

    from eant2_jax.app import cli, process

    before = signal.getsignal(signal.SIGINT)
    seen = []
    checked = process.interruptible(seen.append)
    checked({"event": "exploit"})
    assert seen == [{"event": "exploit"}]
    process.SIGINT.set()
    try:
        with pytest.raises(KeyboardInterrupt):
            checked({"event": "exploit"})
        worker = threading.Thread(target=checked, args=({"event": "generation"},))
        worker.start()
        worker.join()
        assert seen[-1] == {"event": "generation"}  # a worker thread reports, never raises
    finally:
        process.SIGINT.clear()
    # What Python would print as "Exception ignored ... Traceback": a Ctrl-C's is dropped
    # once the command has remembered it; any other goes to the hook before.
    import types

    hook = process.quiet_interrupts(seen.append)
    interrupt = types.SimpleNamespace(exc_value=KeyboardInterrupt())
    other = types.SimpleNamespace(exc_value=ValueError("x"))
    hook(interrupt)
    assert seen[-1] is interrupt  # no Ctrl-C remembered: not the command's
    process.SIGINT.set()
    try:
        hook(interrupt)
        assert seen[-1] is interrupt and len([s for s in seen if s is interrupt]) == 1
        hook(other)
        assert seen[-1] is other
    finally:
        process.SIGINT.clear()
    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # leave the JAX configuration alone
    unraisable = sys.unraisablehook
    assert cli.main(["tasks"]) == 0
    assert signal.getsignal(signal.SIGINT) is before
    assert sys.unraisablehook is unraisable


def _run_main(argv: list[str], capsys, monkeypatch) -> tuple[int, list[str], str]:
    """``eant2 ARGV`` in-process: (exit code, non-empty stderr lines, stdout)."""
    monkeypatch.setenv("EANT2_CACHE_DIR", "")  # leave the JAX configuration alone
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    captured = capsys.readouterr()
    return rc, [line for line in captured.err.splitlines() if line.strip()], captured.out


def _one_error(lines: list[str], *phrases: str) -> None:
    assert len(lines) == 1, lines
    assert lines[0].startswith("eant2: error: "), lines
    for phrase in phrases:
        assert phrase in lines[0], lines


@pytest.mark.parametrize(
    "argv,phrases",
    [
        (["run", "nope"], ["unknown task 'nope'", "xor"]),
        (["run", "xor", "--task-option", "hidden"], ["KEY=VALUE"]),
        (["run", "xor", "--task-option", "bogus=1"], ["bad options for task 'xor'"]),
        (["run", "xor", "--task-option", "hidden=nope"], ["nope"]),
    ],
)
def test_cli_bad_task_or_option_is_one_line(argv, phrases, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    rc, lines, _ = _run_main([*argv, "--out", str(out)], capsys, monkeypatch)
    assert rc == 2
    _one_error(lines, *phrases)
    assert not out.exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "xor", "--population", "0"],
        ["run", "xor", "--population", "x"],
        ["run", "xor", "--generations", "-1"],
        ["run", "xor", "--max-iters", "0"],
        ["run", "xor", "--pruner", "nope"],
        ["run", "xor", "--seed", "1.5"],
        ["run"],
        ["resume"],
        ["frobnicate"],
    ],
)
def test_cli_bad_arguments_exit_2(argv, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    extra = ["--out", str(out)] if argv[:1] == ["run"] and len(argv) > 1 else []
    rc, lines, _ = _run_main([*argv, *extra], capsys, monkeypatch)
    assert rc == 2
    # argparse writes its usage line(s), then one "eant2 ...: error: ..." line.
    assert lines[-1].startswith("eant2") and ": error: " in lines[-1]
    assert sum(": error: " in line for line in lines) == 1
    assert not out.exists()


def _good_run_dir(tmp_path: Path) -> Path:
    """A small but genuine run directory, as the CLI writes it (no exploitation needed)."""
    from eant2_jax.rundir import RunDir

    d = tmp_path / "run"
    rd = RunDir.create(
        d,
        {
            "task": "xor",
            "task_options": {},
            "seed": 0,
            "generations": 1,
            "key": [0, 0],
            "config": CONFIG.to_dict(),
        },
    )
    state = {
        "generation": 0,
        "population": [{"genome": "N0/2*1.0 I0*0.5 I1*0.5", "cost": 0.3, "origin": "init"}],
        "next_id": 1,
        "evaluations": 10,
        "key": [0, 0],
        "wall_s": 0.1,
    }
    rd.commit([{"generation": 0}], [], "N0/2*1.0 I0*0.5 I1*0.5", state)
    return d


def _corrupt(d: Path, name: str, text: str | None) -> None:
    if text is None:
        (d / name).unlink()
    else:
        (d / name).write_text(text)


@pytest.mark.parametrize(
    "name,text,phrase",
    [
        ("config.json", None, "missing config.json"),
        ("generations.jsonl", None, "missing generations.jsonl"),
        ("config.json", "{not json", "config.json is corrupt"),
        ("config.json", "[1, 2]", "not a run configuration"),
        # An edited config.json no longer matches its commit's checksum (a run started
        # without a task spec: tests/test_custom_task.py).
        ("config.json", '{"format": 1, "seed": 0}', "does not match the checksum"),
        (
            "config.json",
            '{"format": 1, "task": "nope", "generations": 1, "key": [0, 0], "config": {}}',
            "does not match the checksum",
        ),
        (
            "config.json",
            '{"format": 1, "task": "xor", "generations": 1, "key": [0, 0], '
            '"config": {"population": 0}}',
            "config.json does not match the checksum",
        ),
        (
            "config.json",
            '{"format": 1, "task": "xor", "generations": 1, "key": [0, 0], '
            '"config": {"colour": "red"}}',
            "config.json does not match the checksum",
        ),
        ("checkpoint.json", "", "checkpoint.json is corrupt"),
        ("checkpoint.json", '{"offsets": {"generations.js', "checkpoint.json is corrupt"),
        ("checkpoint.json", '{"state": {}}', "checkpoint.json is corrupt"),
        (
            "checkpoint.json",
            '{"offsets": {"generations.jsonl": 0, "pruning.jsonl": 0}, "state": {"x": 1}}',
            "checkpoint.json is corrupt",
        ),
        (
            "checkpoint.json",
            '{"offsets": {"generations.jsonl": 0, "pruning.jsonl": 0}, "state": {'
            '"generation": 0, "population": [{"genome": "N0/1*1.0 F9*1.0", "cost": 1.0}], '
            '"next_id": 1, "evaluations": 1, "key": [0, 0]}}',
            "checkpoint.json is corrupt",
        ),
        (
            "checkpoint.json",
            '{"offsets": {"generations.jsonl": 99999, "pruning.jsonl": 0}, "state": {'
            '"generation": 0, "population": [{"genome": "N0/1*1.0 I0*1.0", "cost": 1.0}], '
            '"next_id": 1, "evaluations": 1, "key": [0, 0]}}',
            "shorter than its checkpoint",
        ),
        (
            "checkpoint.json",
            '{"offsets": {"generations.jsonl": 0, "pruning.jsonl": 99999}, "state": {'
            '"generation": 0, "population": [{"genome": "N0/1*1.0 I0*1.0", "cost": 1.0}], '
            '"next_id": 1, "evaluations": 1, "key": [0, 0]}}',
            "shorter than its checkpoint",
        ),
        (
            "checkpoint.json",
            '{"offsets": {}, "state": {'
            '"generation": 0, "population": [{"genome": "N0/1*1.0 I0*1.0", "cost": 1.0}], '
            '"next_id": 1, "evaluations": 1, "key": [0, 0]}}',
            "checkpoint.json is corrupt",
        ),
    ],
)
def test_cli_resume_of_a_bad_run_dir(name, text, phrase, tmp_path, capsys, monkeypatch):
    d = _good_run_dir(tmp_path)
    _corrupt(d, name, text)
    before = _snapshot(d)
    rc, lines, _ = _run_main(["resume", str(d)], capsys, monkeypatch)
    assert rc == 2
    _one_error(lines, phrase)
    assert _snapshot(d) == before


def test_cli_resume_of_a_missing_dir(tmp_path, capsys, monkeypatch):
    rc, lines, _ = _run_main(["resume", str(tmp_path / "nowhere")], capsys, monkeypatch)
    assert rc == 2
    _one_error(lines, "no such run directory")
    assert not (tmp_path / "nowhere").exists()
    (tmp_path / "file").write_text("x")
    rc, lines, _ = _run_main(["resume", str(tmp_path / "file")], capsys, monkeypatch)
    assert rc == 2
    _one_error(lines, "no such run directory")
    assert (tmp_path / "file").read_text() == "x"


@pytest.mark.parametrize("kind", ["run-dir", "other-files", "a-file"])
def test_cli_run_refuses_an_existing_target(kind, tmp_path, capsys, monkeypatch):
    if kind == "run-dir":
        target = _good_run_dir(tmp_path)
    elif kind == "other-files":
        target = tmp_path / "mine"
        target.mkdir()
        (target / "notes.txt").write_text("precious")
    else:
        target = tmp_path / "a-file"
        target.write_text("precious")
    before = _snapshot(target) if target.is_dir() else target.read_bytes()
    rc, lines, _ = _run_main(["run", "xor", "--out", str(target)], capsys, monkeypatch)
    assert rc == 2
    _one_error(lines, "not overwriting")
    after = _snapshot(target) if target.is_dir() else target.read_bytes()
    assert after == before


@pytest.mark.slow
def test_cli_errors_in_a_real_process(tmp_path):
    """The installed entry point: exit code 2 and a one-line message, no traceback."""
    cmd = [sys.executable, "-m", "eant2_jax.app.cli", "resume", str(tmp_path / "nowhere")]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "EANT2_CACHE_DIR": ""}
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"eant2: error: {tmp_path / 'nowhere'}: no such run directory"
    ]
    assert proc.stdout == ""


def test_cli_asks_for_deterministic_gpu_programs_unless_told_otherwise():
    from eant2_jax.app.process import DETERMINISTIC_FLAG, deterministic_gpu

    env = {}
    assert deterministic_gpu(env) and env["XLA_FLAGS"] == DETERMINISTIC_FLAG
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=8"}
    assert deterministic_gpu(env)
    assert env["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=8",
        DETERMINISTIC_FLAG,
    ]
    # The user's own setting wins, either way; EANT2_GPU_DETERMINISTIC=0 opts out.
    env = {"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"}
    assert not deterministic_gpu(env) and env["XLA_FLAGS"] == "--xla_gpu_deterministic_ops=false"
    env = {"EANT2_GPU_DETERMINISTIC": "0"}
    assert not deterministic_gpu(env) and "XLA_FLAGS" not in env


def test_cli_process_defaults_yield_to_the_environment():
    from eant2_jax.app.process import process_defaults

    env = {}
    assert (
        process_defaults(env)
        == env
        == {
            "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
            "MUJOCO_GL": "disable",
        }
    )
    # Any allocator setting of the user's keeps JAX's allocator as they chose it.
    for var in ("XLA_PYTHON_CLIENT_PREALLOCATE", "XLA_PYTHON_CLIENT_MEM_FRACTION",
                "XLA_PYTHON_CLIENT_ALLOCATOR"):  # fmt: skip
        env = {var: "0.5", "MUJOCO_GL": "egl"}
        assert process_defaults(env) == {} and env == {var: "0.5", "MUJOCO_GL": "egl"}


@pytest.mark.slow
def test_cli_sets_process_defaults_before_mujoco_and_the_backend(
    cli_reference, cli_cache, tmp_path
):
    """In a fresh `eant2 run` process, MuJoCo is imported with MUJOCO_GL=disable (no OpenGL
    library loaded) and JAX's backend starts without preallocating. (Any task starts the
    backend: the command-line reference's XOR run, whose programs the cache holds.)"""
    probe = (
        "import os, sys\n"
        "from eant2_jax.app import cli\n"
        "rc = cli.main(sys.argv[1:])\n"
        "import mujoco.rendering.classic.gl_context as g\n"
        "print(os.environ['XLA_PYTHON_CLIENT_PREALLOCATE'], os.environ['MUJOCO_GL'],\n"
        "      'GLContext' in vars(g), 'glfw' in sys.modules, rc)\n"
    )
    unset = ("MUJOCO_GL", "XLA_PYTHON_CLIENT_PREALLOCATE")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    env["EANT2_CACHE_DIR"] = str(cli_cache)
    proc = subprocess.run(
        [sys.executable, "-c", probe, "run", "xor", *CLI_RUN, "--generations", "0",
         "--out", str(tmp_path / "r")],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[-5:] == ["false", "disable", "False", "False", "0"], proc.stdout


@pytest.mark.slow
def test_cli_x64_run_records_float64_and_resumes(tmp_path, capsys, monkeypatch):
    """``eant2 run --x64`` keeps the CMA-ES state in float64; resume turns x64 on again.
    In this process: x64 is turned off between the two commands, as a new process has it.
    (No pruner: a smaller float64 program to compile; the state's dtype does not depend on
    it.)"""
    out = tmp_path / "x64"
    argv = ["run", "xor", "--generations", "0", "--population", "3", "--max-iters", "40",
            "--pruner", "none", "--x64", "--out", str(out)]  # fmt: skip
    rc, err, _ = _run_main(argv, capsys, monkeypatch)
    assert rc == 0, err
    assert jax.config.jax_enable_x64
    config = json.loads((out / "config.json").read_text())
    assert config["config"]["exploit"]["dtype"] == "float64"
    jax.config.update("jax_enable_x64", False)
    rc, err, _ = _run_main(["resume", str(out), "--generations", "1"], capsys, monkeypatch)
    assert rc == 0, err
    assert jax.config.jax_enable_x64
    assert len(_jsonl(out, GENERATIONS)) == 2


def test_bucket_grows_with_headroom_and_is_kept_while_it_fits():
    from eant2_jax.compiler import Bucket
    from eant2_jax.programs.guesses import grow_bucket

    small = Genome.parse("N0/2*1 I0*1 I1*1")  # 1 neuron, 3 genes, depth 1
    first = grow_bucket([small], None)
    assert first == Bucket(neurons=4, genes=8, sweeps=2)  # room for a hidden neuron
    hidden = Genome.parse("N0/2*1 N1/2*1 I0*1 I1*1 I1*1")  # depth 2: fits the same bucket
    assert grow_bucket([hidden], first) is first
    assert grow_bucket([small], first) is first  # never shrinks
    deep = Genome.parse("N0/1*1 N1/1*1 N2/1*1 I0*1")  # depth 3: a new, larger bucket
    grown = grow_bucket([deep, small], first)
    assert grown.sweeps == 4 and grown.neurons >= 4 and grown.genes >= 8
    # A floor (EANT2Config.min_bucket): every bucket is at least it, rounded to the series.
    floored = grow_bucket([small], None, (5, 40, 3))
    assert floored == Bucket(neurons=6, genes=48, sweeps=3)
    assert grow_bucket([hidden, small], floored, (5, 40, 3)) is floored
    assert grow_bucket([deep], floored, (5, 40, 3)) is floored  # depth 3: 3 sweeps do
    deeper = Genome.parse("N0/1*1 N1/1*1 N2/1*1 N3/1*1 I0*1")  # depth 4: 5 sweeps, then 6
    assert grow_bucket([deeper], floored, (5, 40, 3)) == Bucket(neurons=6, genes=48, sweeps=6)


@pytest.mark.slow
def test_min_bucket_compiles_once_and_is_a_checked_option(tmp_path):
    """A run with a bucket floor large enough for its networks compiles its engine program
    in generation 0 only (the default grows into new buckets, each compiled), repeats with
    the same key, and writes the floor into its run directory; bad floors are one clear
    error, and configurations written before the option read as no floor."""
    from eant2_jax.app.parser import build_parser

    config = EANT2Config(
        population=4,
        min_bucket=(8, 40, 4),
        stop_when_solved=False,
        exploit=ExploitConfig(max_iters=60, pruner="none"),
    )
    runs = [
        eant2_jax.run(
            tasks.make("xor"),
            key=jax.random.key(5),
            config=config,
            generations=4,
            out=str(tmp_path / f"r{i}"),
        )  # fmt: skip
        for i in range(2)
    ]
    assert _without_wall(_json(runs[0].generations)) == _without_wall(_json(runs[1].generations))
    gens = runs[0].generations
    assert max(g.best_size for g in gens) > 3  # networks grew (hidden neurons) within it
    assert all(g.compile_s == 0 for g in gens[1:])  # nothing compiled after generation 0
    state = json.loads((tmp_path / "r0" / "checkpoint.json").read_text())["state"]
    assert state["bucket"] == [8, 48, 4]
    written = json.loads((tmp_path / "r0" / "config.json").read_text())["config"]
    assert written["min_bucket"] == [8, 40, 4]
    assert EANT2Config.from_dict(written, complete=True) == config
    old = CONFIG.to_dict()
    del old["min_bucket"]
    assert EANT2Config.from_dict(old, complete=True) == CONFIG
    for bad in ((8, 40), (8, 0, 4), (8, 40, 4.0), (8, 40, True), "8,40,4", (8, 40, 10**6)):
        with pytest.raises(ValueError, match="min_bucket must be None or three integers"):
            EANT2Config(min_bucket=bad)
    parse = build_parser().parse_args
    assert parse(["run", "xor", "--min-bucket", "8,40,4"]).min_bucket == (8, 40, 4)
    assert parse(["run", "xor"]).min_bucket is None


# --------------------------------------------------------------------- the solution test
@pytest.mark.slow
def test_solution_test_stops_the_run_at_the_first_pass(xor_run, tmp_path):
    """The loop tests the best network of each structure it tunes whenever it has changed
    and stops at the first that passes: generation 0 (a linear unit) never passes XOR, so
    it is exactly the reference's; the run ends in the generation that finds a solution,
    with no more evaluations than the reference spent there."""
    reference, _, _ = xor_run
    tested, events = [], []

    def test(genome):
        tested.append(str(genome))
        return solves_xor(genome)

    run_dir = tmp_path / "run"
    result = eant2_jax.run(
        tasks.make("xor"),
        key=jax.random.key(SEED),
        config=CONFIG,
        generations=GENERATIONS_API + 5,
        callback=events.append,
        solution_test=test,
        out=str(run_dir),
    )
    ref = _json(reference.generations)
    gens = _json(result.generations)
    assert result.solution is not None and solves_xor(result.solution.genome)
    assert len(gens) == GENERATIONS_API + 1  # the reference solves XOR in its last generation
    assert _without_wall(gens[:1]) == _without_wall(ref[:1])
    assert gens[-1]["evaluations"] <= ref[-1]["evaluations"]
    assert result.solution.origin != "init"
    # No network is tested twice (unchanged bests are skipped).
    assert len(set(tested)) == len(tested) and str(result.solution.genome) == tested[-1]
    # The solution event follows the last generation's event.
    assert [e["event"] for e in events if e["event"] in ("generation", "solution")][-2:] == [
        "generation",
        "solution",
    ]
    assert events[-1] == {
        "event": "solution",
        "generation": GENERATIONS_API,
        "evaluations": gens[-1]["evaluations"],
        **result.solution.to_json(),
    }
    # Resumed with the same test, the run stops at once: its solution survived selection.
    again = eant2_jax.resume(str(run_dir), generations=GENERATIONS_API + 5, solution_test=test)
    assert again.solution is not None and solves_xor(again.solution.genome)
    assert len(_jsonl(run_dir, GENERATIONS)) == GENERATIONS_API + 1


@pytest.mark.slow
def test_max_evaluations_stops_after_the_generation_that_reaches_it(xor_run, tmp_path):
    """An evaluation budget ends the run after the generation in which it is reached: the
    generations up to there are exactly the reference's, and a resume asked for more
    generations does nothing more."""
    reference, _, _ = xor_run
    ref = _json(reference.generations)
    budget = ref[1]["evaluations"] - 1  # reached within generation 1, not before
    run_dir = tmp_path / "run"
    result = eant2_jax.run(
        tasks.make("xor"),
        key=jax.random.key(SEED),
        config=dataclasses.replace(CONFIG, max_evaluations=budget),
        generations=GENERATIONS_API + 3,
        out=str(run_dir),
    )
    gens = _json(result.generations)
    assert _without_wall(gens) == _without_wall(ref[:2])
    assert gens[0]["evaluations"] < budget <= gens[-1]["evaluations"]
    again = eant2_jax.resume(str(run_dir), generations=GENERATIONS_API + 5)
    assert len(again.generations) == 2 and len(_jsonl(run_dir, GENERATIONS)) == 2
    with pytest.raises(ValueError, match="max_evaluations"):
        EANT2Config(max_evaluations=0)
    loaded = EANT2Config.from_dict(CONFIG.to_dict() | {"max_evaluations": 7})
    assert loaded.max_evaluations == 7


@pytest.mark.slow
def test_solution_test_halts_every_structure_and_counts_only_evaluations():
    """Through `tune`: the test halts the whole batch after the chunk in which a network
    passes; the evaluations are those spent until then (the test's work is not counted)."""
    from eant2_jax.tuning import tune

    genomes = [Genome.parse("N0/2*1 I0*0.1 I1*-0.1"), Genome.parse("N0/3*1 B*0 I0*0.1 I1*0")]
    config = ExploitConfig(max_iters=40, chunk=5, patience=1000, popsize=6, pruner="none")
    full = tune(genomes, tasks.make("xor"), key=jax.random.key(3), config=config)
    assert full.solution is None and full.evaluations == [240, 240]
    calls = []

    def test(genome):
        calls.append(genome)
        return len(calls) == 3  # passes on the third network tested

    res = tune(genomes, tasks.make("xor"), key=jax.random.key(3), config=config, solution_test=test)
    # Both structures improve in the first chunk: tests 1 and 2, then 3 after chunk 2; the
    # structure whose network passed is the solution.
    assert res.solution is not None and res.genomes[res.solution] == calls[2]
    assert res.stop_reasons == ["halted", "halted"]
    assert res.evaluations == [10 * 6, 10 * 6]


def test_recurrent_start_option():
    config = EANT2Config(init_recurrent=True)
    assert EANT2Config.from_dict(config.to_dict(), complete=True) == config
    # A configuration written before the option existed reads as the plain start.
    old = CONFIG.to_dict()
    del old["init_recurrent"]
    assert EANT2Config.from_dict(old, complete=True) == CONFIG
    with pytest.raises(ValueError, match="init_recurrent must be bool"):
        EANT2Config(init_recurrent=1)
    from eant2_jax.strategy import initialise

    genomes, _ = initialise(jax.random.key(0), tasks.make("xor"), config)
    assert [str(g).split()[-1] for g in genomes] == ["R0*0.0"]
    from eant2_jax.app.parser import build_parser

    args = build_parser().parse_args(["run", "xor", "--recurrent-start"])
    assert args.recurrent_start and not build_parser().parse_args(["run", "xor"]).recurrent_start


def test_diverse_start_option():
    """``init_mutations``: generation 0 holds distinct structures, each a minimal start with
    K structural mutations that compute its function (new genes join at weight 0), new neuron
    ids unique across the population; 0 keeps the paper's start, and the same key gives the
    same genomes."""
    from eant2_jax.app.parser import build_parser
    from eant2_jax.reference import interpret
    from eant2_jax.strategy import initialise

    task = tasks.make("servo", mode="kinematic", n_starts=4)
    plain, next_plain = initialise(jax.random.key(3), task, EANT2Config(population=8))
    assert len(plain) == 1 and next_plain == task.n_outputs
    config = EANT2Config(population=8, init_mutations=3)
    genomes, next_id = initialise(jax.random.key(3), task, config)
    again, _ = initialise(jax.random.key(3), task, config)
    assert [str(g) for g in genomes] == [str(g) for g in again]
    assert len({g.structure_key() for g in genomes}) == len(genomes) == 8
    assert any(g.n_neurons > task.n_outputs for g in genomes)  # some grew hidden neurons
    hidden = [i for g in genomes for i in g.neuron_ids if i >= task.n_outputs]
    assert len(hidden) == len(set(hidden)) and next_id == task.n_outputs + len(hidden)
    assert all(i < next_id for i in hidden)
    # Every start computes a minimal network's function: what joined did so at weight 0, so
    # the outputs equal those of the output neurons with their direct inputs only.
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 5, task.n_inputs)).astype(np.float32)
    for g in genomes:
        parent = g.parent
        minimal = []
        for i, gene in enumerate(g.genes):
            if parent[i] == -1:
                kept = [
                    c for j, c in enumerate(g.genes) if parent[j] == i and c.kind == GeneKind.INPUT
                ]
                minimal += [dataclasses.replace(gene, arity=len(kept)), *kept]
        np.testing.assert_allclose(interpret(g, x), interpret(Genome(minimal), x), rtol=1e-6)
    old = CONFIG.to_dict()
    del old["init_mutations"]
    assert EANT2Config.from_dict(old, complete=True) == CONFIG
    with pytest.raises(ValueError, match="init_mutations must be in"):
        EANT2Config(init_mutations=-1)
    assert build_parser().parse_args(["run", "xor", "--init-mutations", "2"]).init_mutations == 2


def test_compile_statistics_count_this_process_compilations():
    """`programs.stats`: a new program counts once with its seconds, a second call of it (the
    in-memory cache) counts nothing; records written before the fields existed load as 0."""
    import jax.numpy as jnp

    from eant2_jax.programs import stats as compilestats
    from eant2_jax.records import GenerationRecord

    f = jax.jit(lambda x: jnp.cos(x) * 3.0 - 0.25)  # a program no other test compiles
    x = jnp.asarray(np.arange(7.0, dtype=np.float32))  # made before: arange compiles too
    before = compilestats.snapshot()
    f(x).block_until_ready()
    first = compilestats.snapshot() - before
    assert first.programs == 1 and first.seconds > 0
    again = compilestats.snapshot()
    f(x).block_until_ready()
    assert compilestats.snapshot() - again == compilestats.CompileStats()
    old = {k: v for k, v in _record_json().items() if k not in ("compiles", "compile_s")}
    del old["cache_hits"], old["cache_misses"]
    record = GenerationRecord.from_json(old)
    stats = (record.compiles, record.compile_s, record.cache_hits, record.cache_misses)
    assert stats == (0, 0, 0, 0)


def _record_json() -> dict:
    return {
        "generation": 0, "best_cost": 0.5, "best_size": 3, "mean_size": 3.0, "best_neurons": 1,
        "evaluations": 10, "wall_s": 0.1, "prune_attempts": 0, "prune_accepted": 0,
        "population": 1, "exploited": 1, "generation_s": 0.1, "best_genome": "N0/1*1 I0*1",
        "compiles": 2, "compile_s": 1.5, "cache_hits": 1, "cache_misses": 1,
    }  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("task", ["xor", "servo"])
def test_first_program_compiled_ahead_from_shapes_is_used_and_changes_nothing(monkeypatch, task):
    """On an accelerator generation 0's engine program starts compiling from shapes alone,
    before any key or engine state exists (`programs.guesses.compile_first_ahead`). Forced on here:
    generation 0 runs that very program (called without jit's fallback, so arguments placed
    otherwise than foreseen would raise), and the run is exactly that of the usual path, on
    two tasks (XOR and servo)."""
    from eant2_jax import programs
    from eant2_jax.programs import guesses

    # XOR: the reference run's configuration (its programs are compiled already), pruning
    # records compared too. Servo: a small one without a pruner (what is compiled ahead is
    # generation 0's engine program; the pruner's programs come after it, XOR covers them).
    exploit = ExploitConfig(max_iters=4, pruner="none")
    config = CONFIG if task == "xor" else EANT2Config(population=4, stop_when_solved=False,
                                                      exploit=exploit)  # fmt: skip
    options = {"n_starts": 4} if task == "servo" else {}

    def run():
        return eant2_jax.run(tasks.make(task, **options), key=jax.random.key(3), config=config,
                             generations=0)  # fmt: skip

    plain = run()
    used = force_compile_ahead(monkeypatch)  # no fallback to jit: a mismatch raises
    monkeypatch.setattr(guesses, "compile_first_ahead", joined(guesses.compile_first_ahead))
    ahead = run()
    assert len(used) == 1 and len(programs.REGISTRY.ahead) == 1
    assert ahead.best == plain.best
    assert _without_wall(_json(ahead.generations)) == _without_wall(_json(plain.generations))
    assert _without_wall(_json(ahead.pruning)) == _without_wall(_json(plain.pruning))
    # Where generation 0's structure depends on the run's draws, nothing is guessed.
    monkeypatch.setattr(programs.REGISTRY, "ahead", {})
    diverse = dataclasses.replace(config, init_mutations=2)
    assert not guesses.compile_first_ahead(tasks.make(task, **options), jax.random.key(3), diverse)
    assert not programs.REGISTRY.ahead


@pytest.mark.slow
def test_cli_starts_the_first_program_before_the_key_exists(xor_run, monkeypatch, tmp_path):
    """`eant2 run` starts generation 0's program from the seed's key shape before it makes
    the key; the run then uses that program (strictly: no fallback to jit). The reference
    run's settings (`CONFIG`, the command line's defaults otherwise): its programs are
    compiled already."""
    from eant2_jax import loop, programs
    from eant2_jax.app import cli
    from eant2_jax.programs import guesses

    calls = []
    first = joined(guesses.compile_first_ahead)

    def spy(task, key, config, runs=1):
        calls.append(isinstance(key, jax.ShapeDtypeStruct))
        return first(task, key, config, runs)

    used = force_compile_ahead(monkeypatch)
    monkeypatch.setattr(loop, "compile_first_ahead", spy)  # the CLI's name of it
    monkeypatch.setattr(guesses, "compile_first_ahead", spy)  # the driver's
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    argv = ["run", "xor", "--population", str(CONFIG.population), "--generations", "0",
            "--max-iters", str(CONFIG.exploit.max_iters),
            "--out", str(tmp_path / "run")]  # fmt: skip
    assert cli.main(argv) == 0
    assert calls == [True, False]  # the CLI's, from the key's shape; then run's own
    assert len(used) == 1 and len(programs.REGISTRY.ahead) == 1


@pytest.mark.slow
def test_next_bucket_compiled_ahead_is_used_and_changes_nothing(xor_run, monkeypatch):
    """On an accelerator the loop guesses the next bucket and compiles its engine program in
    a background thread (`programs.guesses.compile_next_bucket`). Forced on here, with the threads
    joined at once (two programs at once on a CPU can deadlock XLA's thread pool): a run
    whose buckets were guessed uses the programs compiled ahead, and gives exactly the run
    of the usual path. Whether and when a run grows into a new bucket depends on its float
    results, which can differ between CPU models (XLA compiles for the host's instruction
    set; on a 2-core Intel Xeon, key 0 stays in one bucket for three generations): the
    reference run's configuration and key one generation further first, then other keys,
    until a run has used a guessed bucket's program; every run tried must equal its usual
    path."""
    from eant2_jax import programs
    from eant2_jax.programs import guesses

    def run(seed, generations):
        return eant2_jax.run(tasks.make("xor"), key=jax.random.key(seed), config=CONFIG,
                             generations=generations)  # fmt: skip

    def joined_guess(guessed):
        guess = guesses.compile_next_bucket

        def call(*args):
            before = list(programs.REGISTRY.ahead.values())
            thread = guess(*args)
            if thread is not None:
                thread.join()
                for ahead in list(programs.REGISTRY.ahead.values()):
                    ahead.get()
                    if not any(ahead is b for b in before):
                        guessed.append(ahead)
            return thread

        return call

    reference = _json(xor_run[0].generations)
    for seed, generations in ((SEED, GENERATIONS_API + 1), (1, 4), (2, 4), (3, 4), (4, 4)):
        plain = run(seed, generations)
        if seed == SEED:
            assert _without_wall(_json(plain.generations)[: len(reference)]) == _without_wall(
                reference
            )
        guessed = []  # the programs the next-bucket guesses compiled
        with monkeypatch.context() as patch:
            used = force_compile_ahead(patch, fallback=True)
            patch.setattr(guesses, "compile_next_bucket", joined_guess(guessed))
            patch.setattr(guesses, "compile_first_ahead", joined(guesses.compile_first_ahead))
            ahead = run(seed, generations)
        assert ahead.best == plain.best
        assert _without_wall(_json(ahead.generations)) == _without_wall(_json(plain.generations))
        assert _without_wall(_json(ahead.pruning)) == _without_wall(_json(plain.pruning))
        # Generation 0's program compiled ahead is used too: count the guessed ones only.
        if any(any(u is g for g in guessed) for u in used):
            break
    else:
        pytest.fail("no run grew into a guessed bucket: no guessed bucket's program ran")
