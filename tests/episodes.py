"""Checks the environment adapters' tests share (gymnax, brax, Playground): a batch of
networks gets one finite cost each, and a second task built alike compiles nothing new; and,
for the adapters of environments with brax's interface, the plain Python episode loop their
returns are checked against."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from compiles import count_compiles

import eant2_jax
from eant2_jax import tasks
from eant2_jax.compiler import networks
from eant2_jax.exploration import initial_genome
from eant2_jax.reference import interpret
from eant2_jax.tasks.brax_task import calling_brax

_cost = jax.jit(lambda task, key, nets: task.cost(key, nets))


def batch_costs(spec: str, options: dict, n_in: int, n_out: int):
    """``(task, nets [2, 3], cost [2, 3])`` of six random minimal networks on
    ``tasks.make(spec, **options)``, after the checks above."""
    task = tasks.make(spec, **options)
    assert (task.n_inputs, task.n_outputs) == (n_in, n_out)
    rng = np.random.default_rng(0)
    genomes = [initial_genome(rng, n_in, n_out, weight_scale=0.5) for _ in range(6)]
    nets = jax.tree.map(lambda a: a.reshape(2, 3, *a.shape[1:]), networks(genomes, n_in))
    cost = np.asarray(_cost(task, jax.random.key(0), nets))
    assert cost.shape == (2, 3) and np.all(np.isfinite(cost))
    again = tasks.make(spec, **options)
    with count_compiles() as c:
        _cost(again, jax.random.key(1), nets)
    assert c.count == 0
    return task, nets, cost


def _strong(state):
    """``state`` with its weakly typed leaves made strongly typed (the same values and
    dtype). brax's ``reset`` gives ``reward``, ``done`` and ``info["time_out"]`` as float32
    arrays, its ``step`` as weakly typed ones (a Python number for ``reward``): the loop's
    jitted step would compile once for each kind, one program where one suffices."""

    def one(a):
        a = jnp.asarray(a)
        return jax.lax.convert_element_type(a, a.dtype) if jax.typeof(a).weak_type else a

    return jax.tree.map(one, state)


@functools.cache
def _jitted(env):
    """The environment's reset and step, jitted alone (one pair per environment object)."""
    return (
        jax.jit(lambda key: _strong(env.reset(key))),
        jax.jit(lambda state, action: _strong(env.step(state, action))),
    )


def plain_returns(task, genome: str, key, episodes: int) -> np.ndarray:
    """``[episodes, 2]`` returns and lengths of episodes of a task with brax's interface
    (brax, Playground) played one step at a time in Python: the environment's reset and
    step (jitted alone), the network by the NumPy reference, float64; the network sees every
    observation so far (its recurrent state is rebuilt from them each step)."""
    reset, step = _jitted(task.env)
    g = eant2_jax.Genome.parse(genome)
    out = []
    for k in jax.random.split(key, episodes):
        reset_key, _ = jax.random.split(k)  # as rollout splits an episode's key
        with calling_brax():
            state = reset(reset_key)
        seen, ret, t = [], 0.0, 0
        while t < task.max_steps:
            seen.append(np.asarray(state.obs, np.float64))
            y = interpret(g, np.asarray(seen)[:, None, :], hidden="tanh", output="tanh")[-1, 0]
            with calling_brax():
                state = step(state, np.clip(y, -1, 1).astype(np.float32))
            ret, t = ret + float(state.reward), t + 1
            if float(state.done) > 0:
                break
        out.append((ret, t))
    return np.asarray(out)


@functools.partial(jax.jit, static_argnames=("episodes",))
def episode_batch(task, nets, key, episodes):
    """``(returns, steps)`` ``[networks, episodes]`` (what `returns` computes, with lengths)."""
    keys = jax.random.split(key, episodes)
    return jax.vmap(jax.vmap(task.episode, in_axes=(None, 0)), in_axes=(0, None))(nets, keys)
