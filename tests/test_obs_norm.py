"""Frozen observation normalisation from random-policy episodes (``normalize="random"``,
`eant2_jax.tasks.obsnorm`), on gymnax's CartPole (discrete) and Pendulum (continuous):

* the recorded random-policy observations equal those of a plain Python loop over gymnax's
  own ``reset``/``step`` with the documented keys and uniform actions;
* the statistics equal NumPy's mean and standard deviation over those observations (merged
  over padded blocks of episodes or not), on fresh random keys; the task holds them;
* the same seed gives the same arrays to the bit (a resumed run rebuilds the task from the
  options its run directory records), another seed other arrays;
* the network's inputs are ``(obs - mean) / std``: the first inputs of an episode against
  NumPy, and a recurrent network's returns against a plain loop fed NumPy-normalised
  observations (the NumPy genome interpreter, float64);
* a constant observation dimension is centred only;
* bad options are one line naming the option (gymnax, brax and Playground); the brax and
  Playground tasks apply frozen statistics to their inputs (their episodes are in the slow
  lanes of their own files, so no brax or Playground episode is played here).
"""

from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import eant2_jax
from eant2_jax import checkpoint, pytree, tasks
from eant2_jax.compiler import networks
from eant2_jax.reference import interpret
from eant2_jax.tasks import obsnorm
from eant2_jax.tasks.episodic import EpisodicTask, returns

CARTPOLE = {"max_steps": 60, "chunk": 16}  # one compiled random-episode program per shape
PENDULUM = {"max_steps": 20, "chunk": 8}
EPISODES = 7  # random episodes of the statistics, in every test: the same programs


def _fresh_seed() -> int:
    return int(np.random.default_rng().integers(0, 2**31 - 1))


@functools.cache
def _jitted(env):
    """gymnax's reset and step, jitted once per environment (a new bound method each time
    would compile them again)."""
    return jax.jit(env.reset), jax.jit(env.step)


def _plain_random_episode(task, key) -> np.ndarray:
    """The observations ``[length, n]`` a random policy acts on, one step at a time in
    Python: gymnax's reset and step (jitted alone), the documented keys, the actions mapped
    in NumPy (argmax, or linearly onto the bounds)."""
    env, params = task.env, task.env_params
    reset, step = _jitted(env)
    env_key, act_key = jax.random.split(key)
    reset_key, step_key = jax.random.split(env_key)
    obs, state = reset(reset_key, params)
    rows = []
    for t in range(task.max_steps):
        rows.append(np.ravel(np.asarray(obs, np.float32)))
        y = np.asarray(jax.random.uniform(jax.random.fold_in(act_key, t), (task.n_outputs,),
                                          minval=-1.0, maxval=1.0))  # fmt: skip
        if task.discrete:
            action = np.int32(np.argmax(y))
        else:
            low, high = np.asarray(task.act_low), np.asarray(task.act_high)
            action = (low + (y + 1) / 2 * (high - low)).astype(np.float32)
        out = step(jax.random.fold_in(step_key, t), state, action, params)
        obs, state, done = out[0], out[1], bool(np.any([np.asarray(d) for d in out[3:-1]]))
        if done:
            break
    return np.asarray(rows)


def _rows(seen: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    live = np.arange(seen.shape[1])[None, :] < lengths[:, None]
    return seen[live].astype(np.float64)


@pytest.mark.slow
@pytest.mark.parametrize("name,options", [("CartPole-v1", CARTPOLE), ("Pendulum-v1", PENDULUM)])
def test_statistics_equal_numpy_over_the_recorded_random_observations(name, options):
    seed = _fresh_seed()
    key, episodes = jax.random.key(seed), EPISODES
    plain = tasks.make(f"gymnax:{name}", **options)
    seen, lengths = obsnorm.random_observations(plain, jax.random.split(key, episodes))
    assert seen.shape == (episodes, options["max_steps"], plain.n_inputs)
    for i, k in enumerate(jax.random.split(key, episodes)[:3]):
        loop = _plain_random_episode(plain, k)
        assert lengths[i] == len(loop), (seed, i)
        # float32 both; an action mapped in NumPy and in XLA (fused multiply-adds) can differ
        # by an ulp, which Pendulum's dynamics carry on: 1e-5 over 20 steps.
        np.testing.assert_allclose(seen[i, : lengths[i]], loop, rtol=1e-5, atol=1e-5)
        assert not np.any(seen[i, lengths[i] :])
    if name == "CartPole-v1":  # random pushes end some episodes before max_steps
        assert np.all(lengths >= 1) and np.any(lengths < options["max_steps"]), lengths
    rows = _rows(seen, lengths)
    want_mean, want_std = rows.mean(axis=0), rows.std(axis=0)
    for block in (None, 3):  # one block; three of 3 episodes, the last padded by 2
        mean, std, count = obsnorm.statistics(plain, episodes=episodes, key=key, block=block)
        assert count == len(rows) == lengths.sum()
        np.testing.assert_allclose(mean, want_mean, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(std, want_std, rtol=1e-12)
    task = tasks.make(f"gymnax:{name}", normalize="random", norm_episodes=episodes,
                      norm_seed=seed, **options)  # fmt: skip
    # float32 of the float64 statistics: within a float32 rounding.
    np.testing.assert_allclose(task.obs_offset, want_mean, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(task.obs_scale, 1 / want_std, rtol=1e-6)
    assert task.obs_offset.dtype == task.obs_scale.dtype == jnp.float32


@pytest.mark.slow
def test_the_same_seed_gives_the_same_bits_and_a_resume_rebuilds_them(tmp_path):
    seed = _fresh_seed()
    options = {"normalize": "random", "norm_episodes": EPISODES, "norm_seed": seed, **CARTPOLE}
    task = tasks.make("gymnax:CartPole-v1", **options)
    again = tasks.make("gymnax:CartPole-v1", **options)
    other = tasks.make("gymnax:CartPole-v1", **{**options, "norm_seed": (seed + 1) % 2**31})
    for name in ("obs_offset", "obs_scale"):
        a, b, c = (np.asarray(getattr(t, name)) for t in (task, again, other))
        assert a.tobytes() == b.tobytes()
        assert a.tobytes() != c.tobytes()
    # What a run directory's config.json records, read back as a resume reads it.
    meta = json.loads(json.dumps(checkpoint.run_meta(task, {"seed": 0})))
    assert meta["task_options"] == options
    rebuilt = checkpoint.task_for(tmp_path, meta, None)
    for name in ("obs_offset", "obs_scale"):
        bits = np.asarray(getattr(task, name)).tobytes()
        assert np.asarray(getattr(rebuilt, name)).tobytes() == bits


@pytest.mark.slow
def test_the_network_sees_obs_minus_mean_over_std():
    seed = _fresh_seed()
    task = tasks.make("gymnax:Pendulum-v1", normalize="random", norm_episodes=EPISODES,
                      norm_seed=seed, **PENDULUM)  # fmt: skip
    mean, std, _ = obsnorm.statistics(task, episodes=EPISODES, key=jax.random.key(seed))
    key = jax.random.key(seed + 1)
    reset_key, _ = jax.random.split(key)  # as an episode splits its key
    obs, _ = task.env.reset(reset_key, task.env_params)
    first = np.asarray(task.inputs(obs))
    np.testing.assert_allclose(first, (np.asarray(obs, np.float64) - mean) / std, rtol=1e-5,
                               atol=1e-6)  # fmt: skip
    # A recurrent network's returns: the adapter's episodes against a plain loop that feeds
    # the NumPy interpreter (obs - mean) / std.
    genome = "N0/4*1 I0*0.8 I1*-0.6 I2*0.4 R0*0.3"
    g = eant2_jax.Genome.parse(genome)
    got = returns(task, networks([g], task.n_inputs), key=key, episodes=2)[0]
    _, step = _jitted(task.env)
    for i, k in enumerate(jax.random.split(key, 2)):
        reset_key, step_key = jax.random.split(k)
        obs, state = task.env.reset(reset_key, task.env_params)
        seen, ret = [], 0.0
        for t in range(task.max_steps):
            seen.append((np.asarray(obs, np.float64) - mean) / std)
            y = interpret(g, np.asarray(seen)[:, None, :], hidden="tanh", output="tanh")[-1, 0]
            action = (2.0 * np.clip(y, -1, 1)).astype(np.float32)  # bounds [-2, 2]
            out = step(jax.random.fold_in(step_key, t), state, action, task.env_params)
            obs, state, ret = out[0], out[1], ret + float(out[2])
        # float32 network and normalisation against float64: ~1e-6 relative per step.
        np.testing.assert_allclose(got[i], ret, rtol=1e-4)


@pytree.dataclass
class Flat(EpisodicTask):
    """A toy environment whose observation is (a random walk, the constant 5, zero)."""

    n_inputs: int = pytree.field(pytree_node=False, default=3)
    n_outputs: int = pytree.field(pytree_node=False, default=1)

    def environment(self):
        def reset(key):
            x = jax.random.normal(key, ())
            return jnp.stack([x, jnp.float32(5.0), jnp.float32(0.0)]), x

        def step(_, x, action):
            x = x + action[0]
            obs = jnp.stack([x, jnp.float32(5.0), jnp.float32(0.0)])
            return obs, x, jnp.float32(0.0), jnp.bool_(False)

        return reset, step

    def observation(self, obs):
        return obs.astype(jnp.float32)

    def action(self, y):
        return y


@pytest.mark.slow
def test_a_constant_dimension_is_centred_only():
    task = Flat(max_steps=12, output="tanh", chunk=5)
    offset, scale = obsnorm.frozen(task, episodes=4, seed=_fresh_seed(), where="flat")
    np.testing.assert_array_equal(np.asarray(offset)[1:], [5.0, 0.0])
    np.testing.assert_array_equal(np.asarray(scale)[1:], [1.0, 1.0])
    assert 0 < float(scale[0]) < 10  # the random walk's spread is of order 1


@pytest.mark.slow
@pytest.mark.parametrize(
    "spec,options,phrase",
    [
        (
            "gymnax:CartPole-v1",
            {"normalize": "runing"},
            "normalize must be one of bounds, none, random",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_episodes": 0},
            "norm_episodes must be an integer >= 1 and <= 65536, got 0",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_episodes": 2.0},
            "norm_episodes must be an integer, got 2.0",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_episodes": "9"},
            "norm_episodes must be an integer, got '9'",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_seed": -1},
            "norm_seed must be an integer >= 0",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_seed": 2**31},
            "norm_seed must be an integer >= 0 and <= 2147483647",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "random", "norm_seed": True},
            "norm_seed must be an integer, got True",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"norm_seed": 3},
            "norm_seed applies only with normalize='random', got normalize='bounds'",
        ),  # fmt: skip
        (
            "gymnax:CartPole-v1",
            {"normalize": "none", "norm_episodes": 3},
            "norm_episodes applies only with normalize='random'",
        ),  # fmt: skip
        (
            "brax:hopper",
            {"normalize": "bounds"},
            "brax:hopper: normalize must be one of none, random, got 'bounds'",
        ),  # fmt: skip
        (
            "brax:hopper",
            {"normalize": "random", "norm_episodes": -2},
            "brax:hopper: norm_episodes must be an integer >= 1",
        ),  # fmt: skip
        (
            "brax:hopper",
            {"norm_seed": 1},
            "brax:hopper: norm_seed applies only with normalize='random'",
        ),  # fmt: skip
        (
            "playground:CartpoleBalance",
            {"normalize": None},
            "normalize must be one of none, random, got None",
        ),  # fmt: skip
        (
            "playground:CartpoleBalance",
            {"normalize": "random", "norm_seed": "0"},
            "norm_seed must be an integer, got '0'",
        ),  # fmt: skip
    ],
)
def test_bad_normalisation_options_are_one_line(spec, options, phrase):
    with pytest.raises(ValueError) as e:
        tasks.make(spec, **options)
    assert phrase in str(e.value) and "\n" not in str(e.value), str(e.value)


@pytest.mark.slow
@pytest.mark.parametrize(
    "spec,options", [("brax:hopper", {"backend": "spring"}), ("playground:CartpoleBalance", {})]
)
def test_brax_and_playground_inputs_use_frozen_statistics(spec, options):
    task = tasks.make(spec, **options)  # no episode played: the option's default is "none"
    assert task.obs_offset is None and task.obs_scale is None
    n = task.n_inputs
    rng = np.random.default_rng()
    x = rng.normal(size=n).astype(np.float32)
    np.testing.assert_array_equal(task.inputs(jnp.asarray(x)), x)  # as it is
    mean, std = rng.normal(size=n), rng.uniform(0.1, 3.0, size=n)
    frozen = task.replace(obs_offset=jnp.asarray(mean, jnp.float32),
                          obs_scale=jnp.asarray(1 / std, jnp.float32))  # fmt: skip
    np.testing.assert_allclose(frozen.inputs(jnp.asarray(x)), (x - mean) / std, rtol=1e-5,
                               atol=1e-6)  # fmt: skip
    # The statistics are leaves: another set of them is the same program.
    leaves = jax.tree.leaves(frozen)
    assert any(leaf is frozen.obs_offset for leaf in leaves)


@pytest.mark.slow
def test_a_resumed_run_goes_on_as_an_uninterrupted_one(tmp_path, capsys, monkeypatch):
    """From the command line: a run stopped after generation 0 and resumed (its task rebuilt
    from config.json, the random episodes played again) records what a run of two
    generations records, field for field (timings aside)."""
    from eant2_jax.app.cli import main
    from eant2_jax.records import RUN_DEPENDENT

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    argv = ["run", "gymnax:Pendulum-v1", "--population", "2", "--max-iters", "4", "--no-prune"]
    for option in ("normalize=random", f"norm_episodes={EPISODES}", "norm_seed=11",
                   *(f"{k}={v}" for k, v in PENDULUM.items())):  # fmt: skip
        argv += ["--task-option", option]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    assert main([*argv, "--generations", "1", "--out", str(whole)]) == 0
    assert main([*argv, "--generations", "0", "--out", str(parts)]) == 0
    meta = json.loads((parts / "config.json").read_text())
    assert meta["task_options"]["norm_seed"] == 11
    assert main(["resume", str(parts), "--generations", "1"]) == 0

    def records(out):
        rows = [json.loads(x) for x in (out / "generations.jsonl").read_text().splitlines()]
        return [{k: v for k, v in r.items() if k not in RUN_DEPENDENT} for r in rows]

    assert len(records(whole)) == 2 and records(parts) == records(whole)
    capsys.readouterr()
