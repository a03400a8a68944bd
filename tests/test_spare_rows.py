"""A batch's spare rows as restarts (issue 41 item 1; ``ExploitConfig.spare_rows``,
`eant2_jax.spare`, docs/algorithm.md "Spare rows"): checked against the plain reference, the
same rows tuned as explicit copies with every padding row idle, each structure's best search
picked and its searches' evaluations summed in NumPy."""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
from rundirs import run_main

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, Genome, pytree
from eant2_jax.genomepruning import PruneAttempt
from eant2_jax.spare import best_of, spread
from eant2_jax.tasks import xor
from eant2_jax.tasks.regression import Regression
from eant2_jax.tuning import Search, Tuned, tune

# Three XOR structures: one hidden neuron (tests/test_optimize.py's start), the same with
# other weights, and the minimal start (one output neuron reading both inputs and the bias).
GENOMES = [
    Genome.parse("N0/4*1 N1/3*0.1 I0*0.1 I1*-0.1 B*0.05 I0*0.1 I1*0.1 B*0.0"),
    Genome.parse("N0/4*1 N1/3*0.3 I0*-0.2 I1*0.2 B*0.1 I0*0.3 I1*-0.1 B*0.1"),
    Genome.parse("N0/3*1 I0*0.1 I1*0.1 B*0.0"),
]


def test_spread_gives_row_j_structure_j_mod_count_and_its_warm_start():
    start = [Search(0.3, np.eye(8)), None, Search(0.2, np.eye(4))]
    genomes, starts = spread(GENOMES, start, 8)
    assert genomes == [GENOMES[j % 3] for j in range(8)]
    assert [s is start[j % 3] for j, s in enumerate(starts)] == [True] * 8
    assert spread(GENOMES, None, 2) == (GENOMES, None)  # never fewer rows than structures


def _tuned(costs, evaluations, solution=None, pruned=()):
    rows = len(costs)
    return Tuned(
        genomes=[f"g{j}" for j in range(rows)], costs=list(costs),
        evaluations=list(evaluations), stop_reasons=[f"s{j}" for j in range(rows)],
        history=None, state=None, search_costs=[c + 1 for c in costs], solution=solution,
        pruning=[PruneAttempt(structure=j, iteration=1, pruner="covariance", gene=0,
                              kind="input", axis=0, s=None, e=0.0, e_shifted=0.0, e_refit=None,
                              e_reference=0.0, accepted=True, cond_before=1.0,
                              cond_after=1.0) for j in pruned],
        searches=[f"x{j}" for j in range(rows)], picked=["best"] * rows,
    )  # fmt: skip


def test_best_of_picks_each_structure_s_lowest_cost_and_sums_its_evaluations():
    rng = np.random.default_rng(0)
    for _ in range(20):
        count = int(rng.integers(1, 5))
        rows = count + int(rng.integers(0, 9))
        costs = rng.choice([0.5, 1.0, 2.0, np.inf, np.nan], size=rows)
        spent = rng.integers(1, 100, size=rows)
        res = best_of(_tuned(costs, spent, pruned=range(rows)), count)
        for i in range(count):
            own = np.arange(i, rows, count)
            c = np.where(np.isnan(costs[own]), np.inf, costs[own])
            j = own[np.flatnonzero(c == c.min())[0]]  # ties: the lower row
            assert res.genomes[i] == f"g{j}" and res.stop_reasons[i] == f"s{j}"
            assert res.searches[i] == f"x{j}" and res.evaluations[i] == spent[own].sum()
            assert res.search_costs[i] == costs[j] + 1 or np.isnan(costs[j])
        # Only the picked searches' pruning attempts, under their structure's index.
        assert [r.structure for r in res.pruning] == [
            i for j in range(rows) for i in range(count) if res.genomes[i] == f"g{j}"
        ]


def test_a_copy_that_passed_the_solution_test_is_its_structure_s_result():
    res = best_of(_tuned([1.0, 1.0, 1.0, 0.5, 2.0], [1] * 5, solution=4), 3)
    assert res.solution == 1 and res.genomes == ["g3", "g4", "g2"]


def test_spare_rows_round_trips_is_static_and_old_files_read_idle():
    assert ExploitConfig().spare_rows == "idle"
    config = EANT2Config(exploit=ExploitConfig(spare_rows="restarts"))
    d = json.loads(json.dumps(config.to_dict()))
    assert EANT2Config.from_dict(d, complete=True) == config
    old = {**d, "exploit": {k: v for k, v in d["exploit"].items() if k != "spare_rows"}}
    assert EANT2Config.from_dict(old, complete=True).exploit.spare_rows == "idle"
    with pytest.raises(ValueError, match="spare_rows must be one of idle, restarts"):
        ExploitConfig(spare_rows="copies")
    assert jax.tree.structure(config.exploit) != jax.tree.structure(ExploitConfig())


def test_lockstep_refuses_restarts_that_would_mix_its_runs():
    config = EANT2Config(population=2, exploit=ExploitConfig(spare_rows="restarts"))
    keys = [jax.random.key(0), jax.random.key(1)]
    with pytest.raises(ValueError, match="spare_rows='restarts'"):
        eant2_jax.run_lockstep(xor(), keys, config=config, generations=0)


@pytest.mark.slow
def test_restarts_are_the_explicit_copies_each_structure_s_best_kept():
    """Against the reference: the 8 rows tuned as explicit copies (row j holds structure
    j % 3, its warm start too) with nothing spare, then each structure's lowest cost picked
    in NumPy. The covariance pruner runs, so pruning attempts are mapped too. The
    structures' own rows are the searches they get with idle padding, to the bit."""
    key, min_rows = jax.random.key(7), 8
    start = [Search(0.3, np.eye(GENOMES[0].n_params)), None, None]
    config = ExploitConfig(max_iters=30, sigma0=1.0)
    res = tune(GENOMES, xor(), key=key, min_rows=min_rows, start=start,
               config=config.replace(spare_rows="restarts"))  # fmt: skip
    copies, starts = [GENOMES[j % 3] for j in range(8)], [start[j % 3] for j in range(8)]
    ref = tune(copies, xor(), key=key, min_rows=min_rows, start=starts, config=config)
    idle = tune(GENOMES, xor(), key=key, min_rows=min_rows, start=start, config=config)
    assert idle.costs == ref.costs[:3] and idle.evaluations == ref.evaluations[:3]
    assert len({ref.costs[j] for j in range(8)}) > 3  # the copies searched differently
    for i in range(3):
        own = list(range(i, 8, 3))
        j = own[int(np.argmin([ref.costs[r] for r in own]))]
        assert res.genomes[i] == ref.genomes[j] and res.costs[i] == ref.costs[j]
        assert res.costs[i] <= idle.costs[i]
        assert res.evaluations[i] == sum(ref.evaluations[r] for r in own)
        assert res.stop_reasons[i] == ref.stop_reasons[j]
        got = [(a.iteration, a.gene, a.accepted) for a in res.pruning if a.structure == i]
        assert got == [(a.iteration, a.gene, a.accepted) for a in ref.pruning if a.structure == j]
    assert res.pruning  # the mapping above was exercised


@pytest.mark.slow
def test_eant2_run_with_restarts_spends_every_row_s_evaluations(tmp_path, capsys, monkeypatch):
    out = tmp_path / "run"
    argv = ["run", "xor", "--set", "exploit.spare_rows=restarts", "--population", "3",
            "--max-iters", "5", "--generations", "0", "--no-prune", "--out", out]  # fmt: skip
    rc, _, err = run_main(argv, capsys, monkeypatch)
    assert rc == 0, err
    saved = json.loads((out / "config.json").read_text())["config"]["exploit"]
    assert saved["spare_rows"] == "restarts"
    # Generation 0 is one structure (identical minimal starts) in the run's 3 rows: three
    # searches of 5 iterations of the 8-gene bucket's default 10 candidates.
    (record,) = [json.loads(x) for x in (out / "generations.jsonl").read_text().splitlines()]
    assert record["exploited"] == 1 and record["evaluations"] == 3 * 5 * 10, record


@pytree.dataclass
class NoisyXor(Regression):
    """XOR's cost plus a uniform draw of the key (times 0.05): noisy, so `tune` scores each
    search's result again on fresh draws, and restarts are picked on those."""

    noisy: bool = pytree.field(pytree_node=False, default=True)

    def cost(self, key, nets):
        plain = super().cost(key, nets)
        return plain + 0.05 * jax.random.uniform(key, plain.shape)


def noisy_xor() -> NoisyXor:
    plain = xor()
    return NoisyXor(**{f.name: getattr(plain, f.name) for f in dataclasses.fields(plain)})


@pytest.mark.slow
def test_on_a_noisy_task_restarts_are_picked_on_their_fresh_draws():
    """As against the explicit copies above, on a noisy task: the pick follows the costs on
    fresh episodes (`tune` step 7), and the evaluations include every search's rescoring."""
    key, config = jax.random.key(4), ExploitConfig(max_iters=20, sigma0=1.0, pruner="none")
    genomes = GENOMES[:2]
    res = tune(genomes, noisy_xor(), key=key, min_rows=6,
               config=config.replace(spare_rows="restarts"))  # fmt: skip
    ref = tune([genomes[j % 2] for j in range(6)], noisy_xor(), key=key, min_rows=6,
               config=config)  # fmt: skip
    assert ref.costs != ref.search_costs  # rescored
    for i in range(2):
        own = [i, i + 2, i + 4]
        j = own[int(np.argmin([ref.costs[r] for r in own]))]
        assert (res.costs[i], res.search_costs[i], res.picked[i]) == (
            ref.costs[j], ref.search_costs[j], ref.picked[j])  # fmt: skip
        assert res.genomes[i] == ref.genomes[j]
        assert res.evaluations[i] == sum(ref.evaluations[r] for r in own)
        assert res.evaluations[i] > sum(int(ref.history.evaluations[-1, r]) for r in own)
