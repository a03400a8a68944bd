"""Episodes of a network in a reinforcement-learning environment: what the environment
adapters (`eant2_jax.tasks.gymnax_task`, `eant2_jax.tasks.brax_task`) share.

An adapter says how to reset and step its environment and how observations become inputs
and outputs become actions; `rollout` runs one episode of one network, and `EpisodicTask`
(the base of the adapters' task classes) holds the episode settings, plays episodes with
them (``play``) and turns episodes into the cost the engine minimises:

* **recurrent state**: the network's neuron outputs are carried from step to step
  (`eant2_jax.kernels.network.step`), so recurrent jumpers see the previous step; they
  start at zero in every episode.
* **episode**: at most ``max_steps`` steps; steps after the episode ends (the environment's
  done flag) are masked out, so every episode of a batch runs the same program. The reward
  of the step that ends an episode counts (as brax's evaluator and gymnax count it).
  Episodes run in blocks of ``chunk`` steps inside a ``lax.while_loop`` that stops once
  every episode of the batch has ended. A non-finite return (absurd weights) ends the
  episode and scores ``-inf``.
* **cost**: ``-mean return`` over ``episodes`` episodes; their start states and the
  environment's noise come from the cost's key, the same draws for every network of the call
  (common random numbers). Such a task is ``noisy``: `eant2_jax.tuning.tune` scores each
  tuned network once more on fresh episodes before reporting it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ..kernels import network as kn
from .base import map_networks

__all__ = ["EpisodicTask", "returns", "rollout"]

# reset(key) -> (obs, state); step(key, state, action) -> (obs, state, reward, done).
Reset = Callable[[jax.Array], tuple[Any, Any]]
Step = Callable[[jax.Array, Any, jax.Array], tuple[Any, Any, jax.Array, jax.Array]]


def rollout(
    net: kn.Network,
    key: jax.Array,
    *,
    reset: Reset,
    step: Step,
    inputs: Callable[[Any], jax.Array],
    action: Callable[[jax.Array], jax.Array],
    max_steps: int,
    chunk: int,
    hidden: str,
    output: str,
) -> tuple[jax.Array, jax.Array]:
    """Return (sum of rewards) and length (steps) of ONE episode of ONE network.

    Args:
      net: the network.
      key: the episode's key (its start state, and the environment's noise at each step).
      reset: ``reset(key) -> (obs, state)``.
      step: ``step(key, state, action) -> (obs, state, reward, done)``.
      inputs: ``inputs(obs) -> [n_in]`` network inputs of an observation.
      action: ``action(y) -> action`` of the network's outputs ``y`` ``[n_out]``.
      max_steps: steps at most (static).
      chunk: steps per block between the batch's early-exit checks (static).
      hidden: activation name of hidden neurons.
      output: activation name of output neurons.

    Returns:
      ``(return [], steps [] int32)``.
    """
    reset_key, step_key = jax.random.split(key)
    obs, state = reset(reset_key)
    h0 = jnp.zeros(net.bias.shape, jnp.float32)
    carry0 = (obs, state, h0, jnp.float32(0.0), jnp.bool_(True), jnp.int32(0))

    def one(carry, _):
        obs, state, h, ret, alive, t = carry
        y, h = kn.step(net, inputs(obs), h, hidden=hidden, output=output)
        obs, state, reward, done = step(jax.random.fold_in(step_key, t), state, action(y))
        live = alive & (t < max_steps)
        ret = ret + jnp.where(live, jnp.asarray(reward, jnp.float32), 0.0)
        alive = live & ~done & jnp.isfinite(ret)
        return (obs, state, h, ret, alive, t + live.astype(jnp.int32)), None

    def block(carry):
        return jax.lax.scan(one, carry, None, length=min(chunk, max_steps))[0]

    def going(carry):
        return carry[4] & (carry[5] < max_steps)

    _, _, _, ret, _, t = jax.lax.while_loop(going, block, carry0)
    return ret, t


@struct.dataclass(kw_only=True)
class EpisodicTask:
    """A task made of episodes: the base of the environment adapters' task classes, which
    add their environment's fields and define ``inputs``, ``action`` and ``episode``
    (usually through `play`). Its fields are keyword-only.

    Attributes:
      max_steps: steps per episode at most (static).
      output: activation of output neurons (static).
      episodes: episodes per evaluation (static).
      chunk: steps per block between the batch's early-exit checks (static).
      hidden: activation of hidden neurons (static).
      noisy: costs depend on the key (static; see `eant2_jax.tuning.tune`).
    """

    max_steps: int = struct.field(pytree_node=False)
    output: str = struct.field(pytree_node=False)
    episodes: int = struct.field(pytree_node=False, default=1)
    chunk: int = struct.field(pytree_node=False, default=50)
    hidden: str = struct.field(pytree_node=False, default="tanh")
    noisy: bool = struct.field(pytree_node=False, default=True)

    def inputs(self, obs: Any) -> jax.Array:
        """Network inputs ``[n_inputs]`` of one observation."""
        raise NotImplementedError

    def action(self, y: jax.Array) -> Any:
        """The environment's action for network outputs ``y`` ``[n_outputs]``."""
        raise NotImplementedError

    def episode(self, net: kn.Network, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Return (sum of rewards) and length of ONE episode of ONE network."""
        raise NotImplementedError

    def play(
        self, net: kn.Network, key: jax.Array, reset: Reset, step: Step
    ) -> tuple[jax.Array, jax.Array]:
        """`rollout` of ONE network with this task's inputs, action and settings."""
        return rollout(
            net,
            key,
            reset=reset,
            step=step,
            inputs=self.inputs,
            action=self.action,
            max_steps=self.max_steps,
            chunk=self.chunk,
            hidden=self.hidden,
            output=self.output,
        )

    def cost(self, key: jax.Array, nets: kn.Network) -> jax.Array:
        """``-mean return`` ``[*batch]`` over ``episodes`` episodes drawn from ``key``."""
        keys = jax.random.split(key, self.episodes)

        def one(net):
            ret, _ = jax.vmap(self.episode, in_axes=(None, 0))(net, keys)
            ret = jnp.where(jnp.isfinite(ret), ret, -jnp.inf)
            return -jnp.mean(ret)

        return map_networks(one, nets)


@functools.partial(jax.jit, static_argnames=("episodes",))
def _returns(task: EpisodicTask, nets: kn.Network, key: jax.Array, episodes: int):
    keys = jax.random.split(key, episodes)
    return map_networks(lambda net: jax.vmap(task.episode, in_axes=(None, 0))(net, keys)[0], nets)


def returns(task: EpisodicTask, nets: kn.Network, *, key: jax.Array, episodes: int) -> np.ndarray:
    """Returns ``[*batch, episodes]`` of networks on ``episodes`` new episodes (host side;
    for checking a result on episodes it never saw: not counted as evaluations)."""
    return np.asarray(_returns(task, nets, key, int(episodes)))
