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
import math
import types
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import pytree
from ..kernels import network as kn
from .base import map_networks

__all__ = [
    "INT32_MAX",
    "MAX_EPISODES",
    "EpisodicTask",
    "check_choice",
    "check_episode_options",
    "check_int",
    "check_like",
    "chunked_steps",
    "returns",
    "rollout",
]

INT32_MAX = 2**31 - 1  # step counters and lengths are int32 on the device
# Episodes per evaluation at most: each is a vmapped lane of every network's evaluation.
MAX_EPISODES = 65_536


# ------------------------------------------------------------------------------ options
# The adapters check every option by type and range when the task is made (before a run
# directory exists), each with one line naming it: an option read from the command line or
# a run directory may be a string, a float, a list or a JSON object of anything.


def _short(value: Any) -> str:
    """A value for an error message: its repr, on one line, at most 60 characters."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_int(where: str, name: str, value: Any, *, low: int = 1, high: int = INT32_MAX) -> int:
    """``value`` as an int in ``[low, high]``, else one line naming option ``name``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{where}: {name} must be an integer, got {_short(value)}")
    if not low <= value <= high:
        raise ValueError(
            f"{where}: {name} must be an integer >= {low} and <= {high}, got {_short(value)}"
        )
    return int(value)


def check_choice(where: str, name: str, value: Any, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices``, else one line naming option ``name``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(
            f"{where}: {name} must be one of {', '.join(choices)}, got {_short(value)}"
        )
    return value


def _real(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def check_like(where: str, name: str, value: Any, default: Any) -> Any:
    """``value`` checked against the kind of ``default`` (the setting it replaces): a bool
    for a bool, an int (within int32) for an int, a finite number for a float, a string for
    a string, and for a sequence or array one of the same length (shape) whose items
    follow these rules (an infinite bound is allowed where the default has one). Values of
    other kinds (an enumeration, None) are left to the environment. Returns the value, a
    list becoming a tuple."""
    if isinstance(default, bool | np.bool_):
        if not isinstance(value, bool | np.bool_):
            raise ValueError(f"{where}: {name} must be true or false, got {_short(value)}")
    elif isinstance(default, int | np.integer):
        return check_int(where, name, value, low=-INT32_MAX - 1)
    elif isinstance(default, float | np.floating):
        if not _real(value) or not math.isfinite(value):
            raise ValueError(f"{where}: {name} must be a finite number, got {_short(value)}")
        return float(value)
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise ValueError(f"{where}: {name} must be a string, got {_short(value)}")
    elif isinstance(default, list | tuple) or hasattr(default, "shape"):
        want, flat = np.shape(default), np.ravel(np.asarray(default))
        if want == ():  # a 0-d array: a number of its dtype
            return check_like(where, name, value, flat[0].item())
        try:
            got = np.asarray(value, dtype=object) if isinstance(value, list | tuple) else None
        except ValueError:  # ragged beyond numpy's object arrays
            got = None
        if got is None or got.shape != want:
            raise ValueError(
                f"{where}: {name} must be a list of shape {list(want)}, got {_short(value)}"
            )
        for i, (v, d) in enumerate(zip(np.ravel(got), flat, strict=True)):
            d = d.item()
            if _real(d) and _real(v) and math.isinf(v) and math.isinf(d):
                continue  # an unbounded end, as the default has
            check_like(where, f"{name}[{i}]", v, d)
        return tuple(value) if isinstance(value, list) else value
    return value


def check_episode_options(
    where: str, *, episodes: Any, max_steps: Any, chunk: Any, hidden: Any, output: Any
) -> tuple[int, int | None, int]:
    """Check the options every adapter shares (one line naming the option): ``episodes``
    in 1..`MAX_EPISODES`, ``max_steps`` (None: the environment's) and ``chunk`` in
    1..`INT32_MAX`, activation names. Returns ``(episodes, max_steps, chunk)`` as ints."""
    episodes = check_int(where, "episodes", episodes, high=MAX_EPISODES)
    if max_steps is not None:
        max_steps = check_int(where, "max_steps", max_steps)
    chunk = check_int(where, "chunk", chunk)
    for name, value in (("hidden", hidden), ("output", output)):
        if value is None and name == "output":
            continue
        if not isinstance(value, str):
            raise ValueError(f"{where}: {name} must be an activation name, got {_short(value)}")
        try:
            kn.activation(value)
        except ValueError as e:
            raise ValueError(f"{where}: {name}: {e}") from None
    return episodes, max_steps, chunk


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

    def going(carry):
        return carry[4] & (carry[5] < max_steps)

    _, _, _, ret, _, t = chunked_steps(one, going, carry0, chunk=chunk, max_steps=max_steps)
    return ret, t


def chunked_steps(one: Callable, going: Callable, carry0: Any, *, chunk: int, max_steps: int):
    """An episode's steps in blocks: ``chunk`` steps of ``one(carry, None) -> (carry, None)``
    (a `jax.lax.scan`) while ``going(carry)``; the batch's episodes that ended ride along in
    the block, and a batch stops once none goes on. Returns the last carry."""

    def block(carry):
        return jax.lax.scan(one, carry, None, length=min(chunk, max_steps))[0]

    return jax.lax.while_loop(going, block, carry0)


@pytree.dataclass(kw_only=True)
class EpisodicTask:
    """A task made of episodes: the base of the environment adapters' task classes, which
    add their environment's fields and define ``environment``, ``observation``, ``inputs``
    and ``action`` (or ``episode`` itself). Its fields are keyword-only.

    Attributes:
      max_steps: steps per episode at most (static).
      output: activation of output neurons (static).
      episodes: episodes per evaluation (static).
      chunk: steps per block between the batch's early-exit checks (static).
      hidden: activation of hidden neurons (static).
      noisy: costs depend on the key (static; see `eant2_jax.tuning.tune`).
    """

    max_steps: int = pytree.field(pytree_node=False)
    output: str = pytree.field(pytree_node=False)
    episodes: int = pytree.field(pytree_node=False, default=1)
    chunk: int = pytree.field(pytree_node=False, default=50)
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    noisy: bool = pytree.field(pytree_node=False, default=True)
    # The batch width where the config sets none, by `jax.default_backend()`
    # (`eant2_jax.tuning.popsize_for`): a GPU's as docs/protocol.md section 6 chose it on brax.
    default_width: ClassVar[Mapping[str, int]] = types.MappingProxyType({"gpu": 1024})

    def environment(self) -> tuple[Reset, Step]:
        """``(reset, step)`` of the environment, as `rollout` takes them."""
        raise NotImplementedError

    def observation(self, obs: Any) -> jax.Array:
        """The observation vector ``[n_inputs]`` float32, before any normalisation (an
        array observation flattened; an adapter with another kind overrides it)."""
        return jnp.ravel(obs).astype(jnp.float32)

    def inputs(self, obs: Any) -> jax.Array:
        """Network inputs ``[n_inputs]`` of one observation."""
        raise NotImplementedError

    def action(self, y: jax.Array) -> Any:
        """The environment's action for network outputs ``y`` ``[n_outputs]``."""
        raise NotImplementedError

    def episode(self, net: kn.Network, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Return (sum of rewards) and length of ONE episode of ONE network (`play` in
        the task's `environment`)."""
        return self.play(net, key, *self.environment())

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
