"""Defaults that do the library's job (issue 43 item 1): pruning wherever an
`ExploitConfig` is built, a run that stops where its task is solved, and progress numbers
that tell the truth after a resume (the population's cost mean and spread included)."""

from __future__ import annotations

import json
import math
import sys
import types

import jax
import numpy as np
import pytest

import eant2_jax
from eant2_jax import EANT2Config, ExploitConfig, strategy, tasks
from eant2_jax.progress import ProgressReporter
from eant2_jax.records import GenerationRecord
from eant2_jax.tasks.base import TaskError

# A small XOR run that solves XOR at generation 1 (seed 0; tests/test_strategy.py too).
SOLVING = EANT2Config(population=6, exploit=ExploitConfig(max_iters=100))


# ------------------------------------------------------------------------ pruning by default
def test_pruning_is_on_wherever_an_exploit_config_is_built():
    assert EANT2Config(exploit=ExploitConfig(max_iters=100)).exploit.pruner == "covariance"
    assert ExploitConfig().pruner == EANT2Config().exploit.pruner == "covariance"
    assert EANT2Config.from_dict({"exploit": {"max_iters": 5}}).exploit.pruner == "covariance"
    assert ExploitConfig(pruner="none").pruner == "none"  # plain CMA-ES when asked


def test_a_run_directory_without_a_pruner_field_reads_as_it_ran():
    """A config.json from before pruning existed (no ``pruner``) ran without pruning."""
    d = EANT2Config().to_dict()
    old = {**d, "exploit": {k: v for k, v in d["exploit"].items() if k != "pruner"}}
    assert EANT2Config.from_dict(old, complete=True).exploit.pruner == "none"
    assert EANT2Config.from_dict(d, complete=True).exploit.pruner == "covariance"


@pytest.mark.slow
def test_a_default_run_prunes():
    """The docs example's configuration (only max_iters given) prunes on XOR."""
    res = eant2_jax.run(tasks.make("xor"), key=jax.random.key(0), config=SOLVING, generations=1)
    assert sum(r.prune_accepted for r in res.generations) > 0
    assert any(a.accepted for a in res.pruning) and res.pruning[0].pruner == "covariance"


# ------------------------------------------------------------------------- stop when solved
def test_tasks_say_where_they_are_solved():
    assert tasks.make("xor").solved_cost == tasks.XOR_SOLVED == 0.04
    assert tasks.regression([[0.0]], [[1.0]]).solved_cost is None
    assert tasks.regression([[0.0]], [[1.0]], solved_cost=0.5).solved_cost == 0.5
    with pytest.raises(ValueError, match="solved_cost must be >= 0"):
        tasks.regression([[0.0]], [[1.0]], solved_cost=-1)
    assert tasks.make("dpv").solved_cost == -100_000.0
    assert tasks.make("dpv", max_steps=500).solved_cost == -500.0
    assert tasks.make("dpnv").solved_cost is None  # its solutions pass pole.solved()
    assert tasks.make("dpv", fitness="damping").solved_cost is None


def test_four_patterns_under_the_xor_level_are_all_on_the_right_side_of_one_half():
    """XOR_SOLVED's rule: a mean squared error <= 0.04 over four patterns leaves no output
    on the wrong side of 0.5 (each error <= 0.4), on random outputs drawn fresh."""
    rng = np.random.default_rng()
    y = np.array([0.0, 1.0, 1.0, 0.0])
    out = y + rng.uniform(-0.6, 0.6, size=(200_000, 4))
    low = np.mean((out - y) ** 2, axis=1) <= tasks.XOR_SOLVED
    assert low.any()
    assert np.all((out[low] > 0.5) == (y > 0.5))


def test_environment_solved_returns_are_gymnasiums():
    """The tables of solved returns are Gymnasium's registry, with its episode limits."""
    gymnasium = pytest.importorskip("gymnasium")
    from eant2_jax.tasks import brax_task, gymnax_task

    for name, solved in gymnax_task.SOLVED_RETURNS.items():
        assert gymnasium.spec(name).reward_threshold == solved, name
    spec = gymnasium.spec("InvertedPendulum-v5")
    assert (spec.reward_threshold, spec.max_episode_steps) == (950.0, 1000)
    assert brax_task.SOLVED_RETURNS == {"inverted_pendulum": spec.reward_threshold}
    level = brax_task.BraxTask.solved_cost.fget
    pendulum = types.SimpleNamespace(env_name="inverted_pendulum", params=(), max_steps=1000)
    assert level(pendulum) == -950.0
    assert level(types.SimpleNamespace(**{**vars(pendulum), "max_steps": 500})) is None
    assert level(types.SimpleNamespace(**{**vars(pendulum), "env_name": "hopper"})) is None


@pytest.mark.slow
def test_a_gymnax_task_with_its_default_limit_has_its_solved_cost():
    pytest.importorskip("gymnax")
    assert tasks.make("gymnax:CartPole-v1").solved_cost == -475.0
    assert tasks.make("gymnax:CartPole-v1", max_steps=200).solved_cost is None
    assert tasks.make("gymnax:Pendulum-v1").solved_cost is None


def test_a_task_with_a_bad_solved_cost_is_one_line():
    task = tasks.make("xor").replace(solved_cost=math.nan)
    with pytest.raises(TaskError, match="solved_cost must be a finite number or None"):
        tasks.check_task(task)


def test_the_target_resolves_once_to_the_tasks_level_unless_told_otherwise():
    xor = tasks.make("xor")
    assert strategy.resolved(EANT2Config(), xor).target_cost == 0.04
    assert strategy.resolved(strategy.resolved(EANT2Config(), xor), xor).target_cost == 0.04
    assert strategy.resolved(EANT2Config(target_cost=0.1), xor).target_cost == 0.1
    assert strategy.resolved(EANT2Config(stop_when_solved=False), xor).target_cost is None
    assert strategy.resolved(EANT2Config(), tasks.make("dpnv")).target_cost is None
    # A run with a solution test is solved by the test, not by its cost's level.
    assert strategy.resolved(EANT2Config(), xor, tested=True).target_cost is None
    assert strategy.resolved(EANT2Config(target_cost=0.1), xor, tested=True).target_cost == 0.1
    # A run directory from before the option ran every generation: it reads that way.
    d = EANT2Config().to_dict()
    old = {k: v for k, v in d.items() if k != "stop_when_solved"}
    assert EANT2Config.from_dict(old, complete=True).stop_when_solved is False


def _cli(argv, capsys, monkeypatch):
    from eant2_jax.app.cli import main

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    monkeypatch.setattr(sys, "path", list(sys.path))
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.err


def _records(out):
    lines = (out / "generations.jsonl").read_text().splitlines()
    return [GenerationRecord.from_json(json.loads(x)) for x in lines]


@pytest.mark.slow
def test_eant2_run_xor_stops_at_the_solved_generation(tmp_path, capsys, monkeypatch):
    """README's first command stops where XOR is solved, and records the target it used."""
    out = tmp_path / "xor"
    small = ["--population", "6", "--max-iters", "100", "--seed", "0"]
    rc, err = _cli(["run", "xor", "--generations", "30", *small, "--out", out], capsys, monkeypatch)
    assert rc == 0
    recs = _records(out)
    assert len(recs) == 2 and recs[-1].best_cost <= 0.04 < recs[0].best_cost, err
    config = json.loads((out / "config.json").read_text())["config"]
    assert config["target_cost"] == 0.04 and config["stop_when_solved"] is True
    # Turned off (a flag, or the config value), it runs every generation.
    off = tmp_path / "off"
    argv = ["run", "xor", "--generations", "2", *small, "--no-solved-stop", "--out", off]
    assert _cli(argv, capsys, monkeypatch)[0] == 0
    assert len(_records(off)) == 3
    assert json.loads((off / "config.json").read_text())["config"]["target_cost"] is None


@pytest.mark.slow
def test_a_failed_solution_test_keeps_a_run_going_past_the_solved_level(tmp_path):
    """dpv's seeds 5003 and 5014 (docs/pole.md): a training cost at the task's solved level
    whose network fails the solution test does not end the run; the test decides."""
    config = EANT2Config(population=6, exploit=ExploitConfig(max_iters=100))
    tested: list[float] = []
    result = eant2_jax.run(
        tasks.make("xor"),
        key=jax.random.key(0),
        config=config,
        generations=2,
        out=str(tmp_path / "run"),
        solution_test=lambda g: tested.append(1.0) is not None,  # never passes
    )
    recs = _records(tmp_path / "run")
    assert len(recs) == 3 and result.solution is None
    assert recs[1].best_cost <= 0.04  # the level the run alone stops at (the CLI test above)
    assert tested  # the test ran
    config_json = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    assert config_json["target_cost"] is None and config_json["stop_when_solved"] is True


# -------------------------------------------------------------------------- progress numbers
TINY = EANT2Config(population=3, stop_when_solved=False, exploit=ExploitConfig(max_iters=20))
RATE = 1000.0  # evaluations per second of the simulated clock


class _Clock:
    """A clock that advances by the evaluations each generation spent at ``RATE``."""

    def __init__(self, evaluations: int = 0):
        self.t, self.evaluations = 0.0, evaluations

    def __call__(self) -> float:
        return self.t

    def feed(self, reporter):
        def callback(event):
            if event.get("event") == "generation":
                self.t += (event["evaluations"] - self.evaluations) / RATE
                self.evaluations = event["evaluations"]
            reporter(event)

        return callback


def _rates(text: str) -> list[float]:
    lines = [x for x in text.splitlines() if " evals, " in x]
    return [float(x.split(" evals, ")[1].split("/s")[0].replace(",", "")) for x in lines]


@pytest.mark.slow
def test_the_progress_rate_after_a_resume_is_this_process_s(tmp_path):
    """Uninterrupted and resumed, the rate is the evaluations of the process over its time:
    both show the simulated clock's rate (the whole run's count over a resumed process's
    time showed about twice it)."""
    import io

    task, key = tasks.make("xor"), jax.random.key(3)
    clock, stream = _Clock(), io.StringIO()
    whole = ProgressReporter(3, stream=stream, live=False, clock=clock)
    eant2_jax.run(task, key=key, config=TINY, generations=3, callback=clock.feed(whole))
    first = eant2_jax.run(task, key=key, config=TINY, generations=1, out=str(tmp_path / "r"))
    clock2, stream2 = _Clock(first.generations[-1].evaluations), io.StringIO()
    resumed = ProgressReporter(3, stream=stream2, live=False, clock=clock2)
    eant2_jax.resume(str(tmp_path / "r"), generations=3, callback=clock2.feed(resumed))
    uninterrupted, after = _rates(stream.getvalue())[-1], _rates(stream2.getvalue())[-1]
    assert len(_rates(stream2.getvalue())) == 2
    assert after == pytest.approx(uninterrupted, rel=0.1)
    assert after == pytest.approx(RATE, rel=0.01)


@pytest.mark.slow
def test_each_generation_carries_the_populations_cost_mean_and_spread():
    import io

    stream = io.StringIO()
    res = eant2_jax.run(
        tasks.make("xor"), key=jax.random.key(1), config=TINY, generations=1,
        callback=ProgressReporter(1, stream=stream, live=False),
    )  # fmt: skip
    last = res.generations[-1]
    costs = np.array([ind.cost for ind in res.population])
    assert last.mean_cost == pytest.approx(np.mean(costs), rel=1e-12)
    assert last.cost_std == pytest.approx(np.std(costs), rel=1e-12, abs=1e-15)
    assert last.generation_evaluations == last.evaluations - res.generations[0].evaluations
    assert f"| mean {last.mean_cost:.4g} ± {last.cost_std:.2g} |" in stream.getvalue()
    # A record written before these fields existed reads them as None.
    old = {k: v for k, v in last.to_json().items() if k not in ("mean_cost", "cost_std")}
    assert GenerationRecord.from_json(old).mean_cost is None
