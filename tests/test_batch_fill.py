"""A generation's batch fill (`eant2_jax.strategy.batch_fill`, ``GenerationRecord.batch_fill``;
docs/algorithm.md "Batch width"): the share of the batch's row-iterations that searched, checked
against a plain loop and, on XOR without pruning, against each search's evaluations (a row that
runs an iteration spends its candidates' evaluations, so evaluations / candidates counts a row's
iterations without the engine's record)."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from rundirs import run_main

from eant2_jax import ExploitConfig, Genome
from eant2_jax.records import GenerationRecord
from eant2_jax.strategy import batch_fill
from eant2_jax.tasks import xor
from eant2_jax.tuning import tune


def _plain_fill(running: np.ndarray) -> float | None:
    """Row-iterations that ran over rows x the iterations up to the last in which one ran."""
    last = None
    for t in range(running.shape[0]):
        if any(bool(v) for v in running[t]):
            last = t
    if last is None:
        return None
    ran = sum(bool(v) for t in range(last + 1) for v in running[t])
    return ran / ((last + 1) * running.shape[1])


def test_batch_fill_is_the_plain_share_of_the_iterations_that_ran():
    rng = np.random.default_rng(0)
    for _ in range(40):
        ticks, rows = int(rng.integers(1, 30)), int(rng.integers(1, 12))
        stops = rng.integers(0, ticks + 1, size=rows)  # a row runs until its stop
        running = np.arange(ticks)[:, None] < stops[None, :]
        running[:, rng.random(rows) < 0.3] = False  # padding rows
        got = batch_fill(running)
        want = _plain_fill(running)
        assert got == pytest.approx(want, rel=1e-12) if want is not None else got is None
    assert batch_fill(np.zeros((0, 4), bool)) is None
    assert batch_fill(np.zeros((5, 4), bool)) is None


# Three XOR structures (tests/test_spare_rows.py's), tuned without pruning: no pruning trial
# spends an iteration, so a row's iterations are its evaluations / candidates.
GENOMES = [
    Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"),
    Genome.parse("N0/4*1 N1/3*0.3 I0*-0.2 I1*0.2 B*0.1 I0*0.3 I1*-0.1 B*0.1"),
    Genome.parse("N0/3*1 I0*0.1 I1*0.1 B*0.0"),
]


@pytest.mark.parametrize("spare_rows", ["idle", "restarts"])
def test_a_tuned_batch_s_fill_is_its_searches_iterations_over_the_batch(spare_rows):
    config = ExploitConfig(max_iters=400, sigma0=1.0, pruner="none", popsize=6,
                           spare_rows=spare_rows)  # fmt: skip
    rows = 8
    res = tune(GENOMES, xor(), min_rows=rows, config=config, key=jax.random.key(3))
    if spare_rows == "idle":
        iters = np.array(res.evaluations) // 6
    else:  # each row's own search: the same rows tuned as explicit copies
        copies = [GENOMES[j % 3] for j in range(rows)]
        ref = tune(copies, xor(), min_rows=rows, config=config.replace(spare_rows="idle"),
                   key=jax.random.key(3))  # fmt: skip
        iters = np.array(ref.evaluations) // 6
        assert [sum(iters[i::3]) * 6 for i in range(3)] == res.evaluations
    assert len(set(iters.tolist())) > 1  # searches of different lengths: a real check
    want = iters.sum() / (rows * iters.max())
    assert batch_fill(res.history.running) == pytest.approx(want, rel=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize(("spare_rows", "fill"), [("idle", 1 / 3), ("restarts", 1.0)])
def test_eant2_run_records_the_fill(spare_rows, fill, tmp_path, capsys, monkeypatch):
    # Generation 0 is one structure (identical minimal starts) in the run's 3 rows, each
    # search 5 iterations: one row of three searches, or all three with restarts.
    out = tmp_path / "run"
    argv = ["run", "xor", "--set", f"exploit.spare_rows={spare_rows}", "--population", "3",
            "--max-iters", "5", "--generations", "0", "--no-prune", "--out", out]  # fmt: skip
    rc, _, err = run_main(argv, capsys, monkeypatch)
    assert rc == 0, err
    (record,) = [json.loads(x) for x in (out / "generations.jsonl").read_text().splitlines()]
    assert record["batch_fill"] == pytest.approx(fill, rel=1e-12)


def test_a_record_written_before_the_fill_reads_none():
    record = GenerationRecord(
        generation=0, best_cost=0.5, best_size=3, mean_size=3.0, best_neurons=1,
        evaluations=10, wall_s=1.0, prune_attempts=0, prune_accepted=0, population=1,
        exploited=1, generation_s=1.0, best_genome="N0/3*1 I0*0.1 I1*0.1 B*0.0", batch_fill=0.25,
    )  # fmt: skip
    d = record.to_json()
    assert GenerationRecord.from_json(d) == record
    del d["batch_fill"]
    assert GenerationRecord.from_json(d).batch_fill is None
    with pytest.raises(ValueError, match="batch_fill"):
        GenerationRecord.from_json({**d, "batch_fill": "full"})
