"""MuJoCo Playground environments as EANT2 tasks: ``tasks.make("playground:CartpoleBalance")``.

MuJoCo Playground (Zakka et al. 2025, https://github.com/google-deepmind/mujoco_playground;
the ``playground`` package) is brax's maintained successor for MJX environments: the DM
Control Suite (``CartpoleBalance``, ``PendulumSwingup``, ``CheetahRun``, ...), locomotion
and manipulation, each a pure-JAX ``reset(key)`` / ``step(state, action)`` with brax's
interface. It is an optional extra: ``pip install "eant2-jax[playground]"``.

A network controls the environment for one episode at a time, as with the brax adapter
(`eant2_jax.tasks.brax_task`, whose episode loop this one shares):

* **physics**: MJX's JAX implementation (``impl="jax"``) by default; Playground's own default
  is MJX-Warp (``impl="warp"``), which needs NVIDIA's ``warp-lang`` and a GPU.
* **observation -> inputs**: the observation vector as it is (float32); where an
  environment's observation is a dictionary (the locomotion tasks: ``state``,
  ``privileged_state``, ...), the entry ``obs_key`` (``state`` by default). Not normalised
  by default, for the reason the gymnax adapter gives; ``normalize="random"`` freezes
  statistics of random-policy episodes into the task, as for brax
  (`eant2_jax.tasks.obsnorm`).
* **outputs -> action**: one output per actuator (``tanh``), clipped to ``[-1, 1]``,
  Playground's normalised action range.
* **episodes and cost** (`eant2_jax.tasks.episodic`): at most ``max_steps`` steps (the
  environment's ``episode_length`` by default: 1,000 for the Control Suite), ending early
  when the environment sets ``done`` (the Control Suite does only on a non-finite state);
  the cost is ``-mean return`` over ``episodes`` episodes drawn from the cost's key.

The task is ``noisy`` (random start states), as brax's and gymnax's are.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax

from .. import pytree
from .brax_task import NORMALIZE, PipelineTask, _hashable, calling_brax, check_precision
from .episodic import check_choice, check_episode_options, check_int, check_like
from .obsnorm import check_normalize, normalized

__all__ = ["IMPLS", "PlaygroundTask", "playground"]

IMPLS = ("jax", "warp")


def _registry():
    from . import mjx_quiet  # noqa: F401  (drop MJX's lines about an absent warp)

    try:
        with calling_brax():
            from mujoco_playground import registry
    except ImportError as e:
        raise ValueError(
            f"playground tasks need the playground package ({e}): "
            "pip install 'eant2-jax[playground]'"
        ) from None
    return registry


@functools.cache
def _environment(name: str, overrides: tuple[tuple[str, Any], ...]) -> Any:
    """The environment, once per process and settings (tasks alike share its programs)."""
    with calling_brax():
        return _registry().load(name, config_overrides=dict(overrides))


@pytree.dataclass
class PlaygroundTask(PipelineTask):
    """A MuJoCo Playground environment as a task (module docstring). Build with
    `playground`.

    Attributes:
      env_name: the Playground environment name (static).
      overrides: the environment's config overrides, ``impl`` included, as sorted
        ``(name, value)`` pairs (static).
      obs_key: the entry of a dictionary observation the network sees (static).
      n_inputs, n_outputs: observation size and action size (static).

    and `PipelineTask`'s ``precision`` and `EpisodicTask`'s ``episodes``, ``max_steps``,
    ``chunk``, ``hidden``, ``output`` and ``noisy`` (keyword-only).
    """

    env_name: str = pytree.field(pytree_node=False)
    overrides: tuple[tuple[str, Any], ...] = pytree.field(pytree_node=False)
    obs_key: str = pytree.field(pytree_node=False)
    n_inputs: int = pytree.field(pytree_node=False)
    n_outputs: int = pytree.field(pytree_node=False)

    @property
    def env(self):
        return _environment(self.env_name, self.overrides)

    def observation(self, obs: Any) -> jax.Array:
        """The observation vector ``[n_inputs]`` float32 (its ``obs_key`` entry where it is
        a dictionary), before normalisation."""
        return super().observation(obs[self.obs_key] if isinstance(obs, dict) else obs)


# Config fields of every Playground environment with a range: steps and repeats are
# integers >= 1, time steps positive (and the physics step no longer than the control step,
# or an environment step would advance no physics).
_COUNTS = ("episode_length", "action_repeat")
_TIMES = ("ctrl_dt", "sim_dt")


def _checked_config(where: str, defaults: Any, config: Any, prefix: str = "") -> dict:
    """``config`` checked against the environment's default config, recursively: known
    keys only, each value of its default's kind (`check_like`; an object for a nested
    config), `_COUNTS` and `_TIMES` in range; ``impl`` is its own option. Returns the
    overrides with dotted keys for nested fields (``{"vision_config.nworld": 4}``), as
    Playground applies them."""
    if config is None:
        return {}
    name = f"config{prefix}"
    if not isinstance(config, dict):
        raise ValueError(f"{where}: {name} must be an object of key: value, got {config!r:.60}")
    if not prefix and "impl" in config:
        raise ValueError(f"{where}: config.impl: set it with the impl option")
    if not prefix and config.get("vision", False) is not False:
        raise ValueError(f"{where}: config.vision: image observations are not supported")
    unknown = sorted(str(k) for k in config if k not in defaults)
    if unknown:
        raise ValueError(
            f"{where}: unknown {name} {', '.join(unknown)}; "
            f"known: {', '.join(sorted(defaults.keys()))}"
        )
    out = {}
    for key, value in config.items():
        default = defaults[key]
        if hasattr(default, "keys"):  # a nested ConfigDict: Playground takes dotted keys
            nested = _checked_config(where, default, value, f"{prefix}.{key}")
            out.update({f"{key}.{k}": v for k, v in nested.items()})
        elif not prefix and key in _COUNTS:
            out[key] = check_int(where, f"config.{key}", value)
        else:
            out[key] = check_like(where, f"{name}.{key}", value, default)
            if not prefix and key in _TIMES and out[key] <= 0:
                raise ValueError(f"{where}: config.{key} must be > 0, got {value!r}")
    if not prefix:
        ctrl = out.get("ctrl_dt", defaults.get("ctrl_dt"))
        sim = out.get("sim_dt", defaults.get("sim_dt"))
        if isinstance(ctrl, float) and isinstance(sim, float) and sim > ctrl:
            raise ValueError(f"{where}: config.sim_dt ({sim}) must be <= config.ctrl_dt ({ctrl})")
    return out


def _built(where: str, name: str, overrides: tuple[tuple[str, Any], ...]) -> tuple[Any, Any]:
    """The environment and the shape of its observation; a failure to build it is one
    ``ValueError`` naming its first line."""
    try:
        env = _environment(name, overrides)
        with calling_brax():
            obs = jax.eval_shape(env.reset, jax.random.key(0)).obs
    except (TypeError, ValueError, RuntimeError, KeyError, AttributeError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{where}: cannot build the environment: {first}") from None
    return env, obs


def _observed(where: str, obs: Any, obs_key: str) -> Any:
    """The observation the network sees: entry ``obs_key`` of a dictionary observation."""
    if isinstance(obs, dict):
        if obs_key not in obs:
            raise ValueError(
                f"{where}: observations are a dictionary without {obs_key!r}; "
                f"obs_key must be one of {', '.join(sorted(obs))}"
            )
        obs = obs[obs_key]
    return obs


def playground(
    name: str,
    *,
    episodes: int = 1,
    max_steps: int | None = None,
    impl: str = "jax",
    config: dict | None = None,
    obs_key: str = "state",
    chunk: int = 50,
    hidden: str = "tanh",
    output: str = "tanh",
    precision: str = "highest",
    normalize: str = "none",
    norm_episodes: int | None = None,
    norm_seed: int | None = None,
) -> PlaygroundTask:
    """A MuJoCo Playground environment as a task (``tasks.make("playground:NAME", ...)``).

    Args:
      name: the environment name, e.g. ``CartpoleBalance``, ``PendulumSwingup``,
        ``CheetahRun`` (``mujoco_playground.registry.ALL_ENVS``).
      episodes: episodes per evaluation (the cost is minus their mean return).
      max_steps: steps per episode at most (default: the environment's ``episode_length``).
      impl: MJX implementation: ``jax`` (default, any device) or ``warp`` (needs
        ``warp-lang`` and a GPU).
      config: overrides of the environment's config, e.g. ``{"ctrl_dt": 0.02}``.
      obs_key: the entry the network sees of a dictionary observation.
      chunk: steps per block of the episode loop (its early exit is checked per block).
      hidden: activation of hidden neurons.
      output: activation of output neurons (the action is the output clipped to [-1, 1]).
      precision: precision of the physics' float32 products (as for brax tasks).
      normalize: ``"none"`` or ``"random"`` (frozen statistics of random-policy episodes,
        as for brax tasks: `eant2_jax.tasks.obsnorm`).
      norm_episodes, norm_seed: their count (default 1,000) and the seed of their key.

    Returns:
      The `PlaygroundTask`.
    """
    where = f"playground:{name}"
    registry = _registry()
    known = list(registry.ALL_ENVS)
    if name not in known:
        raise ValueError(f"unknown playground environment {name!r}; known: {', '.join(known)}")
    check_choice(where, "impl", impl, IMPLS)
    check_precision(where, precision)
    episodes, max_steps, chunk = check_episode_options(
        where, episodes=episodes, max_steps=max_steps, chunk=chunk, hidden=hidden, output=output
    )
    norm = check_normalize(where, normalize, norm_episodes, norm_seed, NORMALIZE)
    if not isinstance(obs_key, str):
        raise ValueError(f"{where}: obs_key must be a string, got {obs_key!r:.60}")
    defaults = registry.get_default_config(name)
    config = _checked_config(where, defaults, config)  # flat, dotted keys
    overrides = tuple(sorted((k, _hashable(v)) for k, v in {**config, "impl": impl}.items()))
    env, obs = _built(where, name, overrides)
    steps = max_steps or int(config.get("episode_length", defaults.get("episode_length", 1000)))
    obs = _observed(where, obs, obs_key)
    task = PlaygroundTask(
        env_name=name,
        overrides=overrides,
        obs_key=obs_key,
        n_inputs=math.prod(obs.shape),
        n_outputs=int(env.action_size),
        episodes=episodes,
        max_steps=steps,
        chunk=chunk,
        hidden=hidden,
        output=output,
        precision=precision,
    )
    return normalized(task, norm, where)
