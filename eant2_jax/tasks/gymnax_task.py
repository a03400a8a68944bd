"""gymnax environments as EANT2 tasks: ``tasks.make("gymnax:CartPole-v1")``.

gymnax (Lange 2022, https://github.com/RobertTLange/gymnax) re-implements classic control,
MinAtar, bsuite and other environments as pure JAX functions. It is an optional extra:
``pip install "eant2-jax[gymnax]"``.

A network controls the environment for one episode at a time:

* **observation -> inputs**: the observation, flattened to float32, then normalised with
  fixed numbers (``normalize="bounds"``, the default): every dimension whose observation
  space has finite bounds is mapped from ``[low, high]`` to ``[-1, 1]``; unbounded ones (the
  cart's and the pole's velocities in CartPole) are left as they are. Fixed rather than
  running statistics (evosax's and OpenAI-ES's choice): a running normaliser changes the
  cost function while CMA-ES searches it, and the task stays a pure function of its key.
  ``normalize="none"`` passes observations through; ``normalize="random"`` centres and
  scales every dimension by its mean and standard deviation over ``norm_episodes``
  random-policy episodes played when the task is made (`eant2_jax.tasks.obsnorm`), frozen
  into ``obs_offset`` and ``obs_scale``.
* **outputs -> action**: a discrete action space gets one output per action and the action
  is the ``argmax`` (output activation ``identity``); a continuous (``Box``) one gets one
  output per action dimension, clipped to ``[-1, 1]`` and mapped linearly onto
  ``[low, high]`` (output activation ``tanh``).
* **episodes and cost** (`eant2_jax.tasks.episodic`, shared with the brax adapter): the
  recurrent state is carried from step to step and starts at zero; an episode has at most
  ``max_steps`` steps (the environment's own limit by default, 500 for CartPole-v1) and
  ends when the environment says done (terminated or truncated); the cost is ``-mean
  return`` over ``episodes`` episodes drawn from the cost's key.

The task is ``noisy``: costs depend on the key, and the exploitation engine draws new
episodes at every CMA-ES iteration, so the best cost a search has seen is optimistic.
`eant2_jax.tuning.tune` therefore scores each tuned network once more on fresh
episodes and reports that cost (``Tuned.search_costs`` keeps the search's).

One evaluation is one network's cost (all of its ``episodes``), as the engine counts.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import pytree
from .episodic import EpisodicTask, check_episode_options, check_int, check_like
from .episodic import returns as returns
from .obsnorm import check_normalize, normalized

__all__ = ["NORMALIZE", "SOLVED_RETURNS", "GymnaxTask", "gymnax", "returns"]

NORMALIZE = ("bounds", "none", "random")
# The solved return of the gymnax environments that port a Gymnasium one with the same id,
# reward and episode limit: Gymnasium's registry (``gymnasium.spec(id).reward_threshold``;
# tests/test_gymnax.py checks them against it). With its default parameters and episode
# limit, such a task's ``solved_cost`` is minus this.
SOLVED_RETURNS = {
    "CartPole-v1": 475.0,
    "Acrobot-v1": -100.0,
    "MountainCar-v0": -110.0,
    "MountainCarContinuous-v0": 90.0,
}
_HUGE = 1e6  # bounds beyond this count as unbounded (gymnax writes finfo.max for "none")


def _import_gymnax():
    try:
        import gymnax as gx
    except ImportError as e:
        raise ValueError(
            f"gymnax tasks need the gymnax package ({e}): pip install 'eant2-jax[gymnax]'"
        ) from None
    return gx


@functools.cache
def _environment(name: str) -> tuple[Any, Any]:
    """``gymnax.make(name)``, once per process: one environment object per name, so that
    two tasks of one environment share their compiled programs (gymnax jits its methods
    with the environment as a static argument)."""
    gx = _import_gymnax()
    known = list(gx.registered_envs)
    if name not in known:
        raise ValueError(f"unknown gymnax environment {name!r}; known: {', '.join(known)}")
    return gx.make(name)


@pytree.dataclass
class GymnaxTask(EpisodicTask):
    """A gymnax environment as a task (module docstring). Build with `gymnax`.

    Attributes:
      env_params: the environment's parameters (a pytree of traced numbers).
      obs_offset, obs_scale: ``[n_inputs]`` inputs are ``(obs - obs_offset) * obs_scale``.
      act_low, act_high: ``[n_outputs]`` bounds of a continuous action (unused if discrete).
      env_name: the gymnax environment id (static).
      n_inputs, n_outputs: network inputs (flattened observation) and outputs (static).
      discrete: argmax over outputs (True) or a continuous action (static).
      action_shape: shape of one continuous action (static).
      solved_cost: minus the environment's solved return (`SOLVED_RETURNS`) with its
        default parameters and episode limit, else None (static).

    and `EpisodicTask`'s ``episodes``, ``max_steps``, ``chunk``, ``hidden``, ``output``
    and ``noisy`` (keyword-only).
    """

    env_params: Any
    obs_offset: jax.Array
    obs_scale: jax.Array
    act_low: jax.Array
    act_high: jax.Array
    env_name: str = pytree.field(pytree_node=False)
    n_inputs: int = pytree.field(pytree_node=False)
    n_outputs: int = pytree.field(pytree_node=False)
    discrete: bool = pytree.field(pytree_node=False)
    action_shape: tuple[int, ...] = pytree.field(pytree_node=False)
    solved_cost: float | None = pytree.field(pytree_node=False, default=None)

    @property
    def env(self):
        return _environment(self.env_name)[0]

    def inputs(self, obs: jax.Array) -> jax.Array:
        """Network inputs ``[n_inputs]`` of one observation."""
        return (self.observation(obs) - self.obs_offset) * self.obs_scale

    def action(self, y: jax.Array) -> jax.Array:
        """The environment's action for network outputs ``y`` ``[n_outputs]``."""
        if self.discrete:
            return jnp.argmax(y).astype(jnp.int32)
        a = self.act_low + (jnp.clip(y, -1.0, 1.0) + 1.0) * 0.5 * (self.act_high - self.act_low)
        return a.reshape(self.action_shape)

    def environment(self):
        """``(reset, step)`` of the gymnax environment with this task's parameters."""
        env, params = self.env, self.env_params

        def reset(key):
            return env.reset(key, params)

        def step(key, state, action):
            out = env.step(key, state, action, params)
            if len(out) == 6:  # gymnax >= 0.0.9: obs, state, reward, terminated, truncated, info
                obs, state, reward, terminated, truncated, _ = out
                return obs, state, reward, jnp.logical_or(terminated, truncated)
            obs, state, reward, done, _ = out  # older gymnax: obs, state, reward, done, info
            return obs, state, reward, done

        return reset, step


def _bounds(space: Any, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """The finite ``(low, high)`` of a space, broadcast to ``shape`` and flattened."""
    if hasattr(space, "low") and hasattr(space, "high"):
        low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
    elif hasattr(space, "n"):  # a discrete observation: 0 .. n-1
        low, high = np.zeros(()), np.asarray(space.n - 1, np.float64)
    else:
        return None
    low = np.broadcast_to(low, shape).ravel()
    high = np.broadcast_to(high, shape).ravel()
    return low, high


def _from_bounds(bounds: tuple[np.ndarray, np.ndarray] | None, n: int):
    """``(offset, scale)`` ``[n]`` that map finite bounds onto [-1, 1] (``normalize="bounds"``);
    an unbounded dimension (or no bounds at all) is left as it is."""
    if bounds is None:
        return np.zeros(n), np.ones(n)
    low, high = bounds
    finite = (np.abs(low) < _HUGE) & (np.abs(high) < _HUGE) & (high > low)
    offset = np.where(finite, (high + low) / 2, 0.0)
    return offset, np.where(finite, 2 / np.where(finite, high - low, 1.0), 1.0)


def _with_params(where: str, env_params: Any, params: Any) -> Any:
    """The environment's parameters with ``params`` replacing fields, each checked against
    the kind of the field's default (`check_like`: a number for a number, an array of the
    same shape for an array); ``max_steps_in_episode`` is a whole number of steps >= 1."""
    if params is None:
        return env_params
    if not isinstance(params, dict):
        raise ValueError(f"{where}: params must be an object of field: value, got {params!r:.60}")
    known = vars(env_params)
    unknown = sorted(str(k) for k in set(params) - set(known))
    if unknown:
        raise ValueError(
            f"{where}: unknown params {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
    fields = {}
    for key, value in params.items():
        default = known[key]
        if key == "max_steps_in_episode":
            if isinstance(value, float) and value.is_integer() and isinstance(default, float):
                value = int(value)  # a float limit (the bandits') given as one
            value = check_int(where, "params.max_steps_in_episode", value)
            fields[key] = type(default)(value)
        elif hasattr(default, "shape") and np.ndim(default):
            checked = check_like(where, f"params.{key}", value, default)
            fields[key] = jnp.asarray(checked, default.dtype)
        else:
            fields[key] = check_like(where, f"params.{key}", value, default)
    return env_params.replace(**fields)


def _episode_limit(where: str, env_params: Any, limit: Any, max_steps: int | None) -> tuple:
    """``(env_params, max_steps)``: the environment's episode limit by default; a given
    ``max_steps`` also becomes the environment's limit where it is smaller."""
    if max_steps is None:
        if limit is None:
            raise ValueError(f"{where} has no episode limit: pass max_steps")
        max_steps = int(limit)
    elif limit is not None:
        env_params = env_params.replace(max_steps_in_episode=min(int(limit), max_steps))
    return env_params, max_steps


def _actions(space: Any) -> tuple:
    """``(discrete, n_outputs, action_shape, low, high)`` of an action space: a discrete one
    has one output per action (and zero bounds), a box one per action coordinate."""
    discrete = hasattr(space, "n") and not hasattr(space, "low")
    if discrete:
        n_outputs, action_shape = int(space.n), ()
        low = high = np.zeros(n_outputs)
    else:
        action_shape = tuple(int(s) for s in space.shape)
        n_outputs = max(1, math.prod(action_shape))
        low, high = _bounds(space, action_shape)
    return discrete, n_outputs, action_shape, low, high


def gymnax(
    name: str,
    *,
    episodes: int = 1,
    max_steps: int | None = None,
    normalize: str = "bounds",
    norm_episodes: int | None = None,
    norm_seed: int | None = None,
    params: dict | None = None,
    chunk: int = 50,
    hidden: str = "tanh",
    output: str | None = None,
) -> GymnaxTask:
    """A gymnax environment as a task (``tasks.make("gymnax:NAME", ...)``).

    Args:
      name: the gymnax environment id, e.g. ``CartPole-v1``, ``Pendulum-v1``.
      episodes: episodes per evaluation (the cost is minus their mean return).
      max_steps: steps per episode at most (default: the environment's
        ``max_steps_in_episode``; a smaller value also becomes the environment's limit).
      normalize: ``"bounds"`` (finite observation bounds mapped to [-1, 1]), ``"none"``, or
        ``"random"`` (mean and standard deviation over random-policy episodes, frozen:
        `eant2_jax.tasks.obsnorm`).
      norm_episodes: random-policy episodes of ``normalize="random"`` (default 1,000).
      norm_seed: the seed of their key, ``jax.random.key(norm_seed)`` (default 0).
      params: values replacing fields of the environment's default parameters.
      chunk: steps per block of the episode loop (its early exit is checked per block).
      hidden: activation of hidden neurons.
      output: activation of output neurons (default: ``identity`` for a discrete action
        space, ``tanh`` for a continuous one).

    Returns:
      The `GymnaxTask`.
    """
    where = f"gymnax:{name}"
    env, env_params = _environment(name)
    episodes, max_steps, chunk = check_episode_options(
        where, episodes=episodes, max_steps=max_steps, chunk=chunk, hidden=hidden, output=output
    )
    norm = check_normalize(where, normalize, norm_episodes, norm_seed, NORMALIZE)
    env_params = _with_params(where, env_params, params)
    limit = getattr(env_params, "max_steps_in_episode", None)
    solved = SOLVED_RETURNS.get(name) if not params and max_steps in (None, limit) else None
    env_params, max_steps = _episode_limit(where, env_params, limit, max_steps)
    obs_shape = jax.eval_shape(env.reset, jax.random.key(0), env_params)[0].shape
    n_inputs = math.prod(obs_shape)
    offset, scale = np.zeros(n_inputs), np.ones(n_inputs)
    if normalize == "bounds":
        offset, scale = _from_bounds(
            _bounds(env.observation_space(env_params), obs_shape), n_inputs
        )
    discrete, n_outputs, action_shape, low, high = _actions(env.action_space(env_params))
    output = output or ("identity" if discrete else "tanh")
    task = GymnaxTask(
        env_params=env_params,
        obs_offset=jnp.asarray(offset, jnp.float32),
        obs_scale=jnp.asarray(scale, jnp.float32),
        act_low=jnp.asarray(low, jnp.float32),
        act_high=jnp.asarray(high, jnp.float32),
        env_name=name,
        n_inputs=n_inputs,
        n_outputs=n_outputs,
        discrete=discrete,
        action_shape=action_shape,
        solved_cost=None if solved is None else -solved,
        episodes=episodes,
        max_steps=max_steps,
        chunk=chunk,
        hidden=hidden,
        output=output,
    )
    return normalized(task, norm, where)
