"""The MuJoCo Playground adapter on a real Playground environment (the test extra installs
``playground``: these run in CI):

* episode returns and lengths equal those of a plain Python loop over Playground's own
  ``env.reset`` / ``env.step`` driven by the NumPy genome interpreter (a recurrent
  controller, so the carried state is checked too), and a second task built alike
  compiles nothing (the cost over a batch, EpisodicTask.cost, is every adapter's:
  test_gymnax checks it);
* options are checked with one line; an EANT2 run resumes from the command line.

The tests that compile an episode program (a minute or more each on a 2-core CPU) are in the
slow lane; the fast lane keeps the option checks.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
from compiles import count_compiles
from episodes import episode_batch, plain_returns

import eant2_jax
from eant2_jax import tasks
from eant2_jax.compiler import networks

# CartpoleBalance: inputs cart position, cos and sin of the pole angle, cart and pole
# velocities; the one output pushes the cart.
PUSH = "N0/5*1 I0*0.5 I2*4 I3*0.5 I4*1 R0*0.1"
NOTHING = "N0/1*1 I0*0"


# One episode a network: several episodes (their keys, the batch over them) are the code
# Playground's adapter shares with brax's (PipelineTask), checked in test_brax's plain loop.
OPTIONS = {"max_steps": 40, "chunk": 16, "episodes": 1}


@pytest.mark.slow
def test_returns_equal_a_plain_loop_over_playground_steps():
    """The adapter's episodes (returns and lengths) are those of the plain loop; a second
    task built alike compiles nothing new (it shares the environment, so the program). The
    cost over a batch of networks (EpisodicTask.cost, shared by every adapter) is checked in
    test_gymnax; a Playground batch's costs in an engine run by the command-line test below."""
    task = tasks.make("playground:CartpoleBalance", **OPTIONS)
    assert (task.n_inputs, task.n_outputs, task.overrides) == (5, 1, (("impl", "jax"),))
    key = jax.random.key(5)
    genomes = (PUSH, NOTHING)
    nets = networks([eant2_jax.Genome.parse(g) for g in genomes], task.n_inputs)
    got, steps = map(np.asarray, episode_batch(task, nets, key, task.episodes))
    for i, g in enumerate(genomes):
        plain = plain_returns(task, g, key, task.episodes)
        np.testing.assert_array_equal(steps[i], plain[:, 1], err_msg=g)
        # float32 physics in both; the network's float32 vs float64 outputs differ by ~1e-7.
        np.testing.assert_allclose(got[i], plain[:, 0], rtol=1e-4, err_msg=g)
    assert np.all(steps == 40)  # the Control Suite never ends an episode early
    assert not np.allclose(got[0], got[1])
    assert np.all((got >= 0) & (got <= 40))  # a reward in [0, 1] per step
    again = tasks.make("playground:CartpoleBalance", **OPTIONS)
    with count_compiles() as c:
        episode_batch(again, nets, jax.random.key(1), again.episodes)
    assert c.count == 0


@pytest.mark.slow
@pytest.mark.parametrize(
    "options,phrase",
    [
        ({"impl": "c"}, "impl must be one of jax, warp"),
        ({"config": {"ctrl_dtt": 0.02}}, "unknown config ctrl_dtt"),
        ({"impl": None}, "impl must be one of jax, warp"),
        ({"episodes": 0}, "episodes must be an integer >= 1"),
        ({"max_steps": 0}, "max_steps must be an integer >= 1"),
        ({"max_steps": "abc"}, "max_steps must be an integer, got 'abc'"),
        ({"chunk": 1.5}, "chunk must be an integer, got 1.5"),
        ({"obs_key": 3}, "obs_key must be a string"),
        ({"config": []}, "config must be an object"),
        ({"config": {"episode_length": -5}}, "config.episode_length must be an integer >= 1"),
        ({"config": {"episode_length": "x"}}, "config.episode_length must be an integer"),
        ({"config": {"action_repeat": 0}}, "config.action_repeat must be an integer >= 1"),
        ({"config": {"ctrl_dt": -0.01}}, "config.ctrl_dt must be > 0"),
        ({"config": {"ctrl_dt": "fast"}}, "config.ctrl_dt must be a finite number"),
        ({"config": {"sim_dt": 0.5}}, "config.sim_dt (0.5) must be <= config.ctrl_dt"),
        ({"config": {"impl": "warp"}}, "config.impl: set it with the impl option"),
        ({"config": {"vision": True}}, "config.vision: image observations are not supported"),
        ({"config": {"vision_config": 3}}, "config.vision_config must be an object"),
        ({"config": {"vision_config": {"cam_res": [3]}}}, "vision_config.cam_res must be a list"),
        ({"config": {"vision_config": {"nope": 3}}}, "unknown config.vision_config nope"),
        ({"precision": "tf32"}, "precision must be one of highest, high, default"),
        ({"hidden": "tanhh"}, "tanhh"),
    ],
)
def test_bad_playground_options_are_one_line(options, phrase):
    with pytest.raises(ValueError) as e:
        tasks.make("playground:CartpoleBalance", **options)
    assert phrase in str(e.value) and "\n" not in str(e.value)


@pytest.mark.slow
def test_an_unknown_environment_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown playground environment 'Nope'; known: "):
        tasks.make("playground:Nope")


@pytest.mark.slow
def test_config_reaches_the_environment():
    task = tasks.make("playground:CartpoleBalance", config={"episode_length": 300})
    assert task.max_steps == 300 and ("episode_length", 300) in task.overrides
    assert task.env._config.episode_length == 300
    # a nested config's fields, as Playground's dotted keys
    task = tasks.make("playground:CartpoleBalance", config={"vision_config": {"nworld": 3}})
    assert ("vision_config.nworld", 3) in task.overrides
    assert task.env._config.vision_config.nworld == 3


@pytest.mark.slow
def test_cli_runs_and_resumes_a_playground_task(tmp_path, capsys, monkeypatch):
    from eant2_jax.app.cli import main

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    out = tmp_path / "ps"
    # PendulumSwingup: the Playground task whose programs compile fastest (~30% less than
    # CartpoleBalance's on a 2-core CPU); the command line treats every Playground task alike.
    argv = ["run", "playground:PendulumSwingup", "--task-option", "max_steps=30"]
    argv += ["--generations", "0", "--population", "3", "--max-iters", "5", "--no-prune"]
    # Generation 0 compiles into the bucket generation 1 needs (neurons, genes, sweeps), so
    # that the resume reuses the run's program: with the physics in it, each compilation
    # takes many seconds on a 2-core CPU. (A resume that compiles a new bucket is the same path
    # on any task: docs/quickstart.md's XOR resume, checked by test_docs_outputs.)
    argv += ["--set", "min_bucket=[4,12,3]"]
    assert main([*argv, "--out", str(out)]) == 0
    meta = json.loads((out / "config.json").read_text())
    assert meta["task"] == "playground:PendulumSwingup"
    assert meta["task_options"] == {"max_steps": 30}
    assert main(["resume", str(out), "--generations", "1"]) == 0
    lines = (out / "generations.jsonl").read_text().splitlines()
    assert [json.loads(x)["generation"] for x in lines] == [0, 1]
    assert -30 <= json.loads(lines[-1])["best_cost"] <= 0  # at most 30 steps of reward <= 1
    capsys.readouterr()
