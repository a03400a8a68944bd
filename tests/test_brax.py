"""The brax adapter on real brax environments (the test extra installs brax: these run in CI).

* episode returns and lengths equal those of a plain Python loop over brax's own
  ``env.reset`` / ``env.step`` driven by the NumPy genome interpreter (a recurrent
  controller, so the state carried from step to step is checked too): the adapter's
  inputs, action, done-masking and return are right, not just shaped right;
* a hand-made linear controller balances ``inverted_pendulum`` for every step of every new
  episode, and a zero action falls within a few dozen steps;
* a batch of networks gets one cost each (reacher: two actuators), and a second task built
  alike compiles nothing new (cost = minus the mean return: EpisodicTask.cost, every
  adapter's, checked in test_gymnax);
* options are checked with one line; an EANT2 run of a short episode resumes from the
  command line.

The default backend, ``generalized``, compiles fastest on a CPU; ``mjx`` is checked against
the plain loop as well. Every test that compiles an episode program is in the slow lane (tens of
seconds each on a 2-core CPU); the fast lane keeps the option checks.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from episodes import batch_costs, episode_batch, plain_returns

import eant2_jax
from eant2_jax import tasks
from eant2_jax.compiler import networks

# inverted_pendulum: inputs cart position, pole angle, cart velocity, pole angular velocity;
# the one output pushes the cart. Push towards the side the pole leans to (a PD law), with a
# recurrent jumper (R0) so that the carried state matters.
BALANCE = "N0/5*1 I0*0.5 I1*5 I2*1 I3*1 R0*0.1"
NOTHING = "N0/1*1 I0*0"  # action 0 every step
SWING = "N0/2*1 I1*-3 R0*0.9"  # pushes the wrong way: falls, after a few steps
# The inverted_pendulum settings of the plain-loop test.
PENDULUM = {"max_steps": 60, "chunk": 16}


def _nets(task, *genomes):
    return networks([eant2_jax.Genome.parse(g) for g in genomes], task.n_inputs)


@pytest.mark.slow
# Several episodes a network (their keys, the batch over them) are the adapter's own code,
# the same for every backend: checked on the default backend; mjx's physics on one episode.
@pytest.mark.parametrize("backend,episodes", [("generalized", 3), ("mjx", 1)])
def test_returns_equal_a_plain_loop_over_brax_steps(backend, episodes):
    task = tasks.make("brax:inverted_pendulum", backend=backend, episodes=episodes, **PENDULUM)
    assert (task.n_inputs, task.n_outputs, task.backend) == (4, 1, backend)
    key = jax.random.key(3)
    genomes = (BALANCE, NOTHING, SWING)
    nets = _nets(task, *genomes)
    got, steps = map(np.asarray, episode_batch(task, nets, key, task.episodes))
    for i, g in enumerate(genomes):
        plain = plain_returns(task, g, key, task.episodes)
        # float32 physics in both; the network's float32 vs float64 outputs differ by ~1e-7,
        # which cannot flip a termination this far from the 0.2 rad limit: lengths exact.
        np.testing.assert_array_equal(steps[i], plain[:, 1], err_msg=g)
        np.testing.assert_allclose(got[i], plain[:, 0], rtol=1e-6, err_msg=g)
    np.testing.assert_array_equal(got[0], 60.0)  # balances every step (reward 1 a step)
    assert np.all(got[1] < 60) and np.all(got[2] < got[1]), got


@pytest.mark.slow
def test_a_batch_of_networks_gets_one_cost_each():
    """Several actuators (reacher's two; inverted_pendulum's one is the plain loop's): one
    finite cost per network of a [2, 3] batch, and a second task built alike compiles
    nothing new. That the cost is minus the mean return of the key's episodes is the rule of
    EpisodicTask.cost, every adapter's, checked exactly in test_gymnax."""
    batch_costs("brax:reacher", {"max_steps": 10, "backend": "spring"}, 11, 2)


@pytest.mark.slow
@pytest.mark.parametrize(
    "spec,options,phrase",
    [
        ("brax:nope", {}, "unknown brax environment 'nope'; known: ant,"),
        ("brax:hopper", {"backend": "warp"}, "backend must be one of generalized, mjx"),
        ("brax:hopper", {"params": {"ctrl_cost_wieght": 1}}, "unknown params ctrl_cost_wieght"),
        ("brax:hopper", {"backend": None}, "backend must be one of generalized, mjx"),
        ("brax:hopper", {"episodes": 0}, "episodes must be an integer >= 1"),
        ("brax:hopper", {"chunk": "50"}, "chunk must be an integer, got '50'"),
        ("brax:hopper", {"max_steps": 0}, "max_steps must be an integer >= 1"),
        ("brax:hopper", {"max_steps": "abc"}, "max_steps must be an integer, got 'abc'"),
        ("brax:hopper", {"max_steps": 2**31}, "max_steps must be an integer >= 1 and <="),
        ("brax:hopper", {"params": 5}, "params must be an object"),
        ("brax:hopper", {"params": {"n_frames": 0}}, "params.n_frames must be an integer >= 1"),
        ("brax:hopper", {"params": {"n_frames": 10**6}}, "params.n_frames must be an integer"),
        ("brax:hopper", {"params": {"n_frames": 2.0}}, "params.n_frames must be an integer"),
        ("brax:hopper", {"params": {"ctrl_cost_weight": "x"}}, "ctrl_cost_weight must be a fin"),
        ("brax:hopper", {"params": {"healthy_z_range": [0.5]}}, "healthy_z_range must be a list"),
        ("brax:hopper", {"params": {"healthy_z_range": 0.5}}, "healthy_z_range must be a list"),
        ("brax:hopper", {"params": {"terminate_when_unhealthy": 1}}, "must be true or false"),
        ("brax:hopper", {"precision": None}, "precision must be one of highest, high, default"),
        ("brax:hopper", {"precision": "tf32"}, "precision must be one of highest, high, default"),
        ("brax:hopper", {"hidden": "tanhh"}, "tanhh"),
        ("brax:hopper", {"bogus": 1}, "bad options"),
    ],
)
def test_bad_brax_options_are_one_line(spec, options, phrase):
    with pytest.raises(ValueError) as e:
        tasks.make(spec, **options)
    assert phrase in str(e.value) and "\n" not in str(e.value)


@pytest.mark.slow
def test_params_reach_the_environment():
    task = tasks.make("brax:hopper", backend="spring", params={"healthy_z_range": [0.5, 9.0]})
    assert task.params == (("healthy_z_range", (0.5, 9.0)),)
    assert task.env._healthy_z_range == (0.5, 9.0)


@pytest.mark.slow
def test_cli_runs_and_resumes_a_brax_task(tmp_path, capsys, monkeypatch):
    from eant2_jax.app.cli import main

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    out = tmp_path / "ip"
    argv = ["run", "brax:inverted_pendulum", "--task-option", "max_steps=40"]
    argv += ["--task-option", "backend=spring", "--generations", "0"]
    argv += ["--population", "3", "--max-iters", "5", "--no-prune", "--out", str(out)]
    assert main(argv) == 0
    meta = json.loads((out / "config.json").read_text())
    assert meta["task"] == "brax:inverted_pendulum"
    assert meta["task_options"] == {"max_steps": 40, "backend": "spring"}
    assert main(["resume", str(out), "--generations", "1"]) == 0
    lines = (out / "generations.jsonl").read_text().splitlines()
    assert [json.loads(x)["generation"] for x in lines] == [0, 1]
    assert json.loads(lines[-1])["best_cost"] >= -40  # at most 40 steps of reward 1
    capsys.readouterr()
