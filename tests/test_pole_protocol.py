"""The solution test's rules (EANT2Config.solution_rule) and the pole protocol's statistics
(docs/protocol.md, section 4; bench/bench_pole.py --protocol)."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import stats

import eant2_jax
from bench import bench_pole, harness, pole_tables
from bench.common import BenchInputError
from eant2_jax import EANT2Config, ExploitConfig, tasks
from eant2_jax.records import RUN_DEPENDENT

# Tiny XOR runs: the rules are about which networks the loop tests, not about the task.
CONFIG = EANT2Config(
    population=3,
    stop_when_solved=False,
    exploit=ExploitConfig(max_iters=12, chunk=4, pruner="none"),
)
GENERATIONS = 2


def _run(rule: str, test, **kw):
    events: list[dict] = []
    config = EANT2Config.from_dict(CONFIG.to_dict() | {"solution_rule": rule})
    result = eant2_jax.run(
        tasks.make("xor"),
        key=jax.random.key(11),
        config=config,
        generations=GENERATIONS,
        callback=events.append,
        solution_test=test,
        **kw,
    )
    return result, events


def _fixed(records) -> list[dict]:
    return [{k: v for k, v in r.to_json().items() if k not in RUN_DEPENDENT} for r in records]


@pytest.mark.slow
def test_champion_rule_tests_each_generation_champion_once_and_changes_nothing_else():
    """Under ``champion`` a test that never passes is called once per generation, on that
    generation's champion after selection, never during tuning; the run is the one that
    ``structure`` makes with the same test (which calls it on every improved best): the
    rule decides only where the test looks."""
    champion_calls, structure_calls = [], []

    def never(calls):
        return lambda genome: calls.append(str(genome)) and False

    champion, _ = _run("champion", never(champion_calls))
    structure, _ = _run("structure", never(structure_calls))
    assert champion.solution is None and structure.solution is None
    assert champion_calls == [r.best_genome for r in champion.generations]
    assert len(champion_calls) == GENERATIONS + 1
    assert len(structure_calls) > len(champion_calls)
    assert _fixed(champion.generations) == _fixed(structure.generations)
    assert [str(i.genome) for i in champion.population] == [
        str(i.genome) for i in structure.population
    ]


@pytest.mark.slow
def test_champion_rule_stops_at_the_first_champion_that_passes(tmp_path):
    """A champion that passes ends the run after its generation, counting all of that
    generation's evaluations; it is the solution, announced after the generation's event.
    Resumed with the test, the run tests its champion alone and stops at once."""
    calls: list[str] = []

    def second(genome):  # passes at the second call: generation 1's champion
        calls.append(str(genome))
        return len(calls) == 2

    out = tmp_path / "run"
    result, events = _run("champion", second, out=str(out))
    assert len(result.generations) == 2 and len(calls) == 2
    last = result.generations[-1]
    assert str(result.solution.genome) == last.best_genome == calls[-1]
    assert [e["event"] for e in events if e["event"] in ("generation", "solution")][-2:] == [
        "generation",
        "solution",
    ]
    assert events[-1]["evaluations"] == last.evaluations
    again: list[str] = []
    resumed = eant2_jax.resume(
        str(out), generations=GENERATIONS, solution_test=lambda g: again.append(str(g)) is None
    )
    assert again == [last.best_genome] and resumed.solution is not None
    assert len(resumed.generations) == 2


def test_solution_rule_field():
    """One value of two; old run directories read as today's rule."""
    assert EANT2Config().solution_rule == "structure"
    with pytest.raises(ValueError, match="solution_rule must be one of structure, champion"):
        EANT2Config(solution_rule="best")
    old = EANT2Config(solution_rule="champion").to_dict()
    assert EANT2Config.from_dict(old, complete=True).solution_rule == "champion"
    del old["solution_rule"]
    assert EANT2Config.from_dict(old, complete=True).solution_rule == "structure"


# ------------------------------------------------------------------------ the statistics
@pytest.mark.parametrize("n", [1, 7, 20, 53])
def test_wilson_interval_matches_scipy(n):
    """Against scipy's Wilson score interval (binomtest's proportion_ci) at every count."""
    for k in range(n + 1):
        ci = stats.binomtest(k, n).proportion_ci(0.95, method="wilson")
        low, high = pole_tables.wilson_interval(k, n)
        np.testing.assert_allclose([low, high], [ci.low, ci.high], rtol=1e-9, atol=1e-12)


def test_wilson_interval_known_values_and_bad_counts():
    z2 = pole_tables.Z95**2
    assert pole_tables.wilson_interval(0, 10) == (0.0, pytest.approx(z2 / (10 + z2)))
    low, high = pole_tables.wilson_interval(19, 20)
    assert (round(low, 4), round(high, 4)) == (0.7639, 0.9911)
    with pytest.raises(ValueError, match="0 <= solved <= runs"):
        pole_tables.wilson_interval(3, 2)


@pytest.mark.slow
def test_protocol_row_counts_unsolved_runs_as_never():
    runs = [
        {"seed": 0, "solved": True, "evaluations": 400, "generations": 0, "tests": 1},
        {"seed": 1, "solved": True, "evaluations": 1000, "generations": 1, "tests": 2},
        {"seed": 2, "solved": False, "evaluations": 41_000, "generations": 5, "tests": 6},
    ]
    row = pole_tables.protocol_row("dpnv-rr-champion", runs, budget=40_000)
    assert (row["task"], row["start"], row["solution_rule"]) == (
        "dpnv",
        "recurrent-ready",
        "champion",
    )
    assert row["solved"] == 2 and row["solved_in_generation_0"] == 1
    assert row["median_evals"] == np.median([400, 1000, np.inf]) == 1000
    assert row["median_low"] <= 1000 <= row["median_high"]
    assert row["mean_evals_solved"] == 700 and row["mean_evals_failures_as_budget"] == 41_400 / 3
    assert row["tests_per_run"] == 3
    lost = pole_tables.protocol_row("dpv-structure", runs[2:], budget=40_000)
    assert lost["median_text"] == "never [never, never]"


def test_protocol_options():
    args = harness.parse_args(bench_pole.SUITE, ["--protocol"])
    assert (args.first_seed, args.seeds) == (5000, 20)
    assert args.variants == list(pole_tables.PROTOCOL) and args.variants[0].startswith("dpnv")
    assert args.out.endswith(".json") and "pole-protocol-" in args.out
    plain = harness.parse_args(bench_pole.SUITE, [])
    assert (plain.first_seed, plain.seeds, plain.solution_rule) == (0, 20, "structure")
    with pytest.raises(BenchInputError, match="--variants needs --protocol"):
        harness.parse_args(bench_pole.SUITE, ["--variants", "dpv-champion"])


@pytest.mark.slow
def test_protocol_bench_quick_and_merged(tmp_path):
    """Quick runs of two variants in two files, merged into one table; its markdown redone
    from the JSON."""
    a, b, out = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "p.json"
    for variant, path in (("dpv-champion", a), ("dpv-structure", b)):
        bench_pole.main(["--protocol", "--quick", "--variants", variant, "--out", str(path)])
    payload = bench_pole.main(["--merge", str(a), str(b), "--out", str(out)])
    assert [r["variant"] for r in payload["rows"]] == ["dpv-champion", "dpv-structure"]
    assert payload["config"]["eant2"]["dpv-champion"]["solution_rule"] == "champion"
    assert payload["config"]["eant2"]["dpv-structure"]["solution_rule"] == "structure"
    md = out.with_suffix(".md").read_text()
    assert "solved [Wilson 95%]" in md and "dpv-champion" in md
    again = bench_pole.main(["--render", str(out), "--force"])
    assert again == payload
