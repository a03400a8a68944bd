"""The batch as a first-class resource (issue 41 item 1): ``ExploitConfig.width``, the
networks per engine batch, sets the CMA-ES population of a batch's rows through the one rule
`eant2_jax.tuning.popsize_for` (docs/algorithm.md, "Batch width")."""

from __future__ import annotations

import copy
import json
import math
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from rundirs import run_main
from test_distributed import xla_flags  # the suite's flags, with N CPU devices

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, Genome
from eant2_jax.compiler import compile_genomes
from eant2_jax.exploitation import popsize_of
from eant2_jax.tasks import xor
from eant2_jax.tuning import optimize, popsize_for, tune

# XOR with one hidden neuron (tests/test_optimize.py's start).
START = Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0")


def plain_popsize(genes: int, rows: int, popsize: int | None, width: int | None) -> int:
    """The rule as docs/algorithm.md states it, written out (Hansen's default 4 + floor(3 ln n))."""
    default = 4 + math.floor(3 * math.log(genes))
    if popsize is not None:
        return popsize
    return default if width is None else max(default, width // rows)


def test_popsize_for_follows_the_width_rule():
    seen = set()
    for count, min_rows in [(1, 1), (3, 1), (3, 10), (5, 1), (2, 40)]:
        batch = compile_genomes([START] * count, 2, min_rows=min_rows, pad_count=True)
        rows, genes = batch.layout.slot.shape[0], batch.bucket.genes
        assert rows >= max(count, min_rows)  # padding rows count
        for popsize, width in [(None, None), (None, 16), (None, 64), (None, 4096), (7, None)]:
            config = ExploitConfig(popsize=popsize, width=width)
            got = popsize_for(config, batch)
            assert got == plain_popsize(genes, rows, popsize, width), (rows, popsize, width)
            # Rows given (`prepare`'s, before a mesh rounds them up) replace the batch's.
            given = popsize_for(config, batch, rows + 3)
            assert given == plain_popsize(genes, rows + 3, popsize, width)
            if width is not None:
                seen.add("width" if width // rows > got - 1 else "floor")
    assert seen == {"width", "floor"}  # both sides of the max were taken


def test_an_unset_width_takes_the_task_s_default_for_its_device_class(monkeypatch):
    """``width=None`` is the task's ``default_width`` for `jax.default_backend()`: an
    episodic task's is 1,024 on a GPU (docs/protocol.md section 6), none elsewhere (the
    default popsize); a task without one (XOR, the servo task) takes the default on every
    device; ``width=1`` is the default everywhere, and ``popsize`` still wins."""
    from eant2_jax import tuning
    from eant2_jax.tasks.episodic import EpisodicTask

    assert EpisodicTask.default_width == {"gpu": 1024}
    episodic = type("Wide", (), {"default_width": EpisodicTask.default_width})()
    batch = compile_genomes([START] * 3, 2, min_rows=12, pad_count=True)
    rows, genes = batch.layout.slot.shape[0], batch.bucket.genes
    got = {}
    for backend, want in [("cpu", None), ("gpu", 1024), ("tpu", None)]:
        monkeypatch.setattr(tuning.jax, "default_backend", lambda b=backend: b)
        got[backend] = popsize_for(ExploitConfig(), batch, task=episodic)
        assert got[backend] == plain_popsize(genes, rows, None, want), backend
        plain = plain_popsize(genes, rows, None, None)
        assert popsize_for(ExploitConfig(), batch, task=xor()) == plain
        assert popsize_for(ExploitConfig(width=1), batch, task=episodic) == plain
        wide = ExploitConfig(width=96)
        assert popsize_for(wide, batch, task=episodic) == plain_popsize(genes, rows, None, 96)
        assert popsize_for(ExploitConfig(popsize=5), batch, task=episodic) == 5
    assert got["gpu"] == 1024 // rows > got["cpu"] == got["tpu"]  # the width side was taken


def test_a_task_s_default_width_is_checked():
    from eant2_jax.tasks.base import TaskError, check_task

    check_task(xor())  # no default_width: the default popsize everywhere
    for bad in ({"gpu": 0}, {"gpu": True}, {"gpu": 1.5}, [1024], {1: 8}):
        task = copy.copy(xor())
        object.__setattr__(task, "__class__", type("Bad", (type(task),), {"default_width": bad}))
        with pytest.raises(TaskError, match="default_width must map backend names"):
            check_task(task)


def test_popsize_and_width_together_are_one_error():
    want = r"^ExploitConfig\.popsize = 8 and ExploitConfig\.width = 64 are both set: set one"
    with pytest.raises(ValueError, match=want):
        ExploitConfig(popsize=8, width=64)
    with pytest.raises(ValueError, match=want):
        EANT2Config.from_dict({"exploit": {"popsize": 8, "width": 64}})
    with pytest.raises(ValueError, match=r"^ExploitConfig\.width must be >= 1 \(or None\), got 0"):
        ExploitConfig(width=0)


def test_width_round_trips_is_static_and_old_files_read_none():
    assert ExploitConfig().width is None and EANT2Config().exploit.width is None
    config = EANT2Config(exploit=ExploitConfig(width=4096))
    d = json.loads(json.dumps(config.to_dict()))
    assert d["exploit"]["width"] == 4096
    assert EANT2Config.from_dict(d, complete=True) == config
    # A run directory written before the field existed ran with today's rule: None.
    old = {**d, "exploit": {k: v for k, v in d["exploit"].items() if k != "width"}}
    assert EANT2Config.from_dict(old, complete=True).exploit.width is None
    # Static: part of the program's structure, no traced leaf.
    assert jax.tree.structure(ExploitConfig(width=64)) != jax.tree.structure(ExploitConfig())
    assert len(jax.tree.leaves(ExploitConfig(width=64))) == len(jax.tree.leaves(ExploitConfig()))


def _wide_tune(key: jax.Array):
    config = ExploitConfig(width=64, max_iters=4, pruner="none")
    return tune([START] * 3, xor(), key=key, config=config)


@pytest.mark.slow
def test_a_wide_batch_evaluates_rows_times_its_popsize_and_repeats_to_the_bit():
    res = _wide_tune(jax.random.key(3))
    rows, genes = res.history.running.shape[1], int(res.state.cma.mean.shape[-1])
    popsize = popsize_of(res.state)
    assert (
        popsize
        == plain_popsize(genes, rows, None, 64)
        == 64 // rows
        > 4 + math.floor(3 * math.log(genes))
    )  # the width, not the default, set it here
    # Each running structure spends popsize evaluations per engine iteration.
    evals, running = np.asarray(res.history.evaluations), np.asarray(res.history.running)
    steps = np.diff(np.concatenate([np.zeros((1, rows), evals.dtype), evals]), axis=0)
    np.testing.assert_array_equal(steps[running], popsize)
    assert res.evaluations == [int(running[:, i].sum()) * popsize for i in range(3)]
    again = _wide_tune(jax.random.key(3))
    assert again.costs == res.costs and again.genomes == res.genomes
    np.testing.assert_array_equal(np.asarray(again.history.sigma), np.asarray(res.history.sigma))


MESH = """
import json
import jax
import eant2_jax as E
from eant2_jax import distributed, tuning
from eant2_jax.exploitation import popsize_of
assert len(jax.devices()) == 4
genomes = [E.Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0")] * 3
config = E.ExploitConfig(width=64, max_iters=4, pruner="none")
runs = [tuning.tune(genomes, E.tasks.xor(), key=jax.random.key(3), config=config, mesh=mesh)
        for mesh in (None, distributed.make_mesh(4))]
# Spare rows as restarts (6 rows: 3 copies) on 4 devices: 8 rows, the 2 added stay idle.
spare = [tuning.tune(genomes, E.tasks.xor(), key=jax.random.key(3), min_rows=5, mesh=mesh,
                     config=config.replace(spare_rows="restarts"))
         for mesh in (None, distributed.make_mesh(4))]
print(json.dumps({"rows": [r.history.running.shape[1] for r in runs + spare],
                  "popsize": [popsize_of(r.state) for r in runs],
                  "evaluations": [r.evaluations for r in runs + spare],
                  "costs": [r.costs for r in runs]}))
"""


@pytest.mark.slow  # a fresh interpreter with 4 CPU devices: about 20 s on 2 busy cores
def test_a_device_mesh_changes_placement_only_not_the_popsize():
    """Width counts the whole batch, on every device; the rows a mesh adds to split the
    batch evenly (3 rows -> 4 over 4 CPU devices) change neither the popsize nor the run,
    nor do they become restarts (`eant2_jax.spare`)."""
    env = {**os.environ, "XLA_FLAGS": xla_flags(4)}
    proc = subprocess.run([sys.executable, "-W", "error", "-c", textwrap.dedent(MESH)],
                          env=env, capture_output=True, text=True, timeout=240)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-4000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["rows"] == [3, 4, 6, 8] and out["popsize"] == [64 // 3] * 2
    assert out["evaluations"][0] == out["evaluations"][1]
    # The rows that split the batch evenly search nothing: two searches per structure, each
    # of 4 iterations of 64 // 6 candidates.
    assert out["evaluations"][2] == out["evaluations"][3] == [2 * 4 * (64 // 6)] * 3
    # Up to float reduction order across devices (tests/test_distributed.py says why).
    np.testing.assert_allclose(out["costs"][1], out["costs"][0], rtol=1e-3)


@pytest.mark.slow
def test_optimize_takes_width_as_its_one_row_s_popsize():
    res = optimize(START, xor(), key=jax.random.key(1), width=40, max_iters=2, pruner="none")
    np.testing.assert_array_equal(np.asarray(res.history.evaluations), [40, 80])


@pytest.mark.slow
def test_a_run_with_width_compiles_the_rule_s_popsize_and_repeats():
    config = EANT2Config(
        population=3, exploit=ExploitConfig(width=96, max_iters=5, pruner="none")
    )  # a width of its own: a program this process has not run, so its compile is reported
    events = []
    res = eant2_jax.run(
        xor(), key=jax.random.key(0), config=config, generations=1, callback=events.append
    )
    compiled = [e for e in events if e["event"] == "compiling"]
    assert compiled
    for e in compiled:
        rows, genes = e["structures"], e["genes"]
        assert e["popsize"] == plain_popsize(genes, rows, None, 96)
    again = eant2_jax.run(xor(), key=jax.random.key(0), config=config, generations=1)
    assert [r.to_json()["best_cost"] for r in again.generations] == [
        r.to_json()["best_cost"] for r in res.generations
    ]
    assert [r.evaluations for r in again.generations] == [r.evaluations for r in res.generations]


@pytest.mark.slow
def test_eant2_run_sets_width_from_the_command_line(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    argv = ["run", "xor", "--set", "exploit.width=64", "--population", "3", "--max-iters", "5"]
    rc, _, err = run_main([*argv, "--generations", "0", "--no-prune", "--out", out],
                          capsys, monkeypatch)  # fmt: skip
    assert rc == 0, err
    assert json.loads((out / "config.json").read_text())["config"]["exploit"]["width"] == 64
    # Generation 0 is one structure (identical minimal starts), padded to the run's 3 rows:
    # 64 // 3 = 21 candidates (the default of its 8-gene bucket is 10), 5 iterations; XOR is
    # not noisy and nothing is pruned, so every evaluation is a candidate's.
    (record,) = [json.loads(x) for x in (out / "generations.jsonl").read_text().splitlines()]
    assert record["exploited"] == 1 and record["evaluations"] == 5 * 21, record
    rc, _, err = run_main([*argv, "--set", "exploit.popsize=8", "--out", tmp_path / "both"],
                          capsys, monkeypatch)  # fmt: skip
    assert rc == 2 and len(err) == 1 and "are both set" in err[0], err
    assert not (tmp_path / "both").exists()
