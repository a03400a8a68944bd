"""The gymnax adapter on real gymnax environments (the test extra installs gymnax: these run in CI).

* a hand-made linear controller balances CartPole-v1 for the full 500 steps on every new
  episode, and a constant action falls within a few dozen steps (the adapter's inputs,
  action mapping, done-masking and return are right, not just shaped right);
* cost = -mean return of the same episodes (the cost of every adapter); a batch of networks
  gets one cost each, discrete and continuous action spaces alike, and
  a second task built alike compiles nothing new;
* options are checked with one line; an EANT2 run of a short CartPole resumes from the
  command line.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from episodes import batch_costs

import eant2_jax
from eant2_jax import tasks
from eant2_jax.compiler import networks
from eant2_jax.tasks.gymnax_task import returns

# Output 1 (push right) = theta + theta_dot (normalised): the textbook linear controller.
BALANCE = "N0/1*1 I0*0 N1/2*1 I2*1 I3*1"
ALWAYS_LEFT = "N0/1*1 I0*0 N1/1*0 I0*0"


def _nets(task, *genomes):
    return networks([eant2_jax.Genome.parse(g) for g in genomes], task.n_inputs)


@pytest.mark.slow
def test_cartpole_controllers_get_the_returns_they_should():
    task = tasks.make("gymnax:CartPole-v1", episodes=8)
    assert (task.n_inputs, task.n_outputs, task.max_steps, task.discrete) == (4, 2, 500, True)
    key = jax.random.key(7)
    r = returns(task, _nets(task, BALANCE, ALWAYS_LEFT), key=key, episodes=8)
    assert r.shape == (2, 8)
    np.testing.assert_array_equal(r[0], 500.0)
    assert np.all((r[1] >= 5) & (r[1] <= 30)), r[1]  # falls over quickly
    # cost = -mean return over the task's episodes, drawn from the key: the very episodes
    # above. EpisodicTask.cost is the cost of every adapter (gymnax, brax, Playground), so
    # this checks it for all three; their own episodes are checked in their files.
    cost = eant2_jax.cost([BALANCE, ALWAYS_LEFT], task, key=key)
    np.testing.assert_allclose(cost, -r.mean(axis=1), rtol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name,options,n_in,n_out",
    [
        ("CartPole-v1", {"max_steps": 20, "episodes": 2}, 4, 2),
        ("Pendulum-v1", {"max_steps": 20}, 3, 1),
    ],
)
def test_a_batch_of_networks_gets_one_cost_each(name, options, n_in, n_out):
    task, _, _ = batch_costs(f"gymnax:{name}", options, n_in, n_out)
    if name == "Pendulum-v1":  # bounded observations normalised, the action mapped
        np.testing.assert_allclose(task.obs_scale, [1.0, 1.0, 1 / 8])
        np.testing.assert_allclose([task.act_low[0], task.act_high[0]], [-2.0, 2.0])


@pytest.mark.slow
@pytest.mark.parametrize(
    "spec,options,phrase",
    [
        ("gymnax:Nope-v0", {}, "unknown gymnax environment 'Nope-v0'"),
        ("gymnax:CartPole-v1", {"normalize": "running"}, "normalize must be one of"),
        ("gymnax:CartPole-v1", {"params": {"gravty": 1}}, "unknown params gravty"),
        ("gymnax:CartPole-v1", {"episodes": 0}, "episodes must be an integer >= 1"),
        ("gymnax:CartPole-v1", {"episodes": 2.5}, "episodes must be an integer, got 2.5"),
        ("gymnax:CartPole-v1", {"episodes": 10**6}, "episodes must be an integer >= 1 and <="),
        ("gymnax:CartPole-v1", {"chunk": True}, "chunk must be an integer, got True"),
        ("gymnax:CartPole-v1", {"max_steps": "abc"}, "max_steps must be an integer, got 'abc'"),
        ("gymnax:CartPole-v1", {"max_steps": 0}, "max_steps must be an integer >= 1"),
        ("gymnax:CartPole-v1", {"max_steps": 2**31}, "max_steps must be an integer >= 1 and <="),
        ("gymnax:CartPole-v1", {"normalize": None}, "normalize must be one of bounds, none"),
        ("gymnax:CartPole-v1", {"hidden": 3}, "hidden must be an activation name, got 3"),
        ("gymnax:CartPole-v1", {"output": "tanhh"}, "output: unknown activation 'tanhh'"),
        ("gymnax:CartPole-v1", {"params": [1]}, "params must be an object"),
        ("gymnax:CartPole-v1", {"params": {"gravity": "x"}}, "params.gravity must be a finite"),
        ("gymnax:CartPole-v1", {"params": {"gravity": 1e999}}, "params.gravity must be a finite"),
        ("gymnax:CartPole-v1", {"params": {"gravity": [9.8]}}, "params.gravity must be a finite"),
        ("gymnax:CartPole-v1", {"params": {"max_steps_in_episode": -5}}, "max_steps_in_episode"),
        ("gymnax:CartPole-v1", {"params": {"max_steps_in_episode": 2.5}}, "max_steps_in_episode"),
        ("gymnax:Acrobot-v1", {"params": {"available_torque": [1, 2]}}, "list of shape [3]"),
        ("gymnax:Acrobot-v1", {"params": {"available_torque": [1, 2, "x"]}}, "torque[2] must"),
        ("gymnax:DeepSea-bsuite", {"params": {"deterministic": 1}}, "must be true or false"),
        ("gymnax:CartPole-v1", {"bogus": 1}, "bad options"),
    ],
)
def test_bad_gymnax_options_are_one_line(spec, options, phrase):
    with pytest.raises(ValueError) as e:
        tasks.make(spec, **options)
    assert phrase in str(e.value) and "\n" not in str(e.value)


def test_params_reach_the_environment_with_their_kinds():
    task = tasks.make(
        "gymnax:Acrobot-v1", max_steps=40, params={"available_torque": [-2, 0, 2], "dt": 1}
    )
    np.testing.assert_array_equal(task.env_params.available_torque, [-2.0, 0.0, 2.0])
    assert task.env_params.available_torque.dtype == np.float32  # the default's dtype
    assert task.env_params.dt == 1.0 and isinstance(task.env_params.dt, float)
    assert (task.max_steps, task.env_params.max_steps_in_episode) == (40, 40)
    task = tasks.make("gymnax:CartPole-v1", params={"max_steps_in_episode": 30})
    assert (task.max_steps, task.env_params.max_steps_in_episode) == (30, 30)


@pytest.mark.slow
def test_cli_runs_and_resumes_a_gymnax_task(tmp_path, capsys, monkeypatch):
    from eant2_jax.app.cli import main

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    out = tmp_path / "cp"
    argv = ["run", "gymnax:CartPole-v1", "--task-option", "max_steps=50", "--generations", "0"]
    argv += ["--population", "3", "--max-iters", "10", "--no-prune", "--out", str(out)]
    assert main(argv) == 0
    meta = json.loads((out / "config.json").read_text())
    assert (meta["task"], meta["task_options"]) == ("gymnax:CartPole-v1", {"max_steps": 50})
    assert main(["resume", str(out), "--generations", "1"]) == 0
    lines = (out / "generations.jsonl").read_text().splitlines()
    assert [json.loads(x)["generation"] for x in lines] == [0, 1]
    assert json.loads(lines[-1])["best_cost"] >= -50  # at most 50 steps of reward 1
    capsys.readouterr()
