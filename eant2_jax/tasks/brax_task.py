"""brax environments as EANT2 tasks: ``tasks.make("brax:inverted_pendulum")``.

brax (Freeman et al. 2021, https://github.com/google/brax) provides MuJoCo-style
locomotion and control environments (``ant``, ``halfcheetah``, ``hopper``,
``inverted_pendulum``, ...) as pure JAX ``reset(key)`` / ``step(state, action)``. It is an
optional extra: ``pip install "eant2-jax[brax]"``.

A network controls the environment for one episode at a time:

* **physics backend**: ``backend="generalized"`` by default, brax's own default for each
  of its environments (so returns compare with brax's published ones); ``mjx`` (MuJoCo's
  JAX port, the engine of the servo task), ``positional`` and ``spring`` can be chosen
  instead. All four run with the project's mujoco/mujoco-mjx 3.17.0; their step rates and
  compile times differ by environment and device (``spring``, one small loop, compiles
  faster than ``generalized``: bench/bench_brax.py; the field benchmark's brax runs use it,
  docs/protocol.md section 3).
* **observation -> inputs**: the observation vector as it is (float32), by default
  (``normalize="none"``). brax's trainers normalise observations with running statistics;
  this adapter does not, for the reason the gymnax adapter gives: a running normaliser
  changes the cost function while CMA-ES searches it. ``normalize="random"`` centres and
  scales each dimension by statistics of random-policy episodes played once, when the task
  is made, and frozen (`eant2_jax.tasks.obsnorm`; TensorNEAT's halfcheetah and walker2d
  examples do the same).
* **outputs -> action**: one output per actuator (output activation ``tanh``), clipped to
  ``[-1, 1]``, which brax's environments map onto the actuators' control ranges.
* **episodes and cost** (`eant2_jax.tasks.episodic`, shared with the gymnax adapter): the
  recurrent state is carried from step to step and starts at zero; an episode has at most
  ``max_steps`` steps (1000 by default, brax's ``episode_length``) and ends early when the
  environment sets its ``done`` flag (a fallen pendulum, an unhealthy hopper), the reward
  of that last step included, as brax's evaluator counts it; the cost is ``-mean return``
  over ``episodes`` episodes drawn from the cost's key.

The task is ``noisy`` (random start states): `eant2_jax.tuning.tune` scores each tuned
network once more on fresh episodes and reports that cost. One evaluation is one network's
cost (all of its ``episodes``), as the engine counts.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math
import warnings
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp

from .. import pytree
from .episodic import EpisodicTask, check_choice, check_episode_options, check_int, check_like
from .episodic import returns as returns
from .obsnorm import check_normalize, normalized

__all__ = [
    "BACKENDS",
    "MAX_FRAMES",
    "NORMALIZE",
    "PRECISIONS",
    "SOLVED_RETURNS",
    "BraxTask",
    "PipelineTask",
    "brax",
    "calling_brax",
    "check_precision",
    "returns",
]

BACKENDS = ("generalized", "mjx", "positional", "spring")
NORMALIZE = ("none", "random")  # of the brax and Playground adapters
# Precision of the float32 products in brax's physics (``jax.default_matmul_precision``):
# "highest" (the default) computes them in full float32 on every device; "default" lets a
# GPU use TF32 (a 10-bit mantissa), which is faster but makes a GPU's trajectories differ
# from a CPU's after a few steps.
PRECISIONS = ("highest", "high", "default")
# Constructor arguments of brax's PipelineEnv that an environment passes on (**kwargs), and
# their defaults (an environment sets its own n_frames when not given).
_PIPELINE_OPTIONS = {"n_frames": 1}
MAX_FRAMES = 1000  # physics steps per environment step (action repeat) at most
# The solved return of a brax environment that ports a Gymnasium one with the same reward
# (+1 per step balanced) and episode length (1000): Gymnasium's registry
# (``gymnasium.spec("InvertedPendulum-v5").reward_threshold``). Its ``solved_cost`` is
# minus this with the default constructor and ``max_steps``.
SOLVED_RETURNS = {"inverted_pendulum": 950.0}


# What brax itself warns about, none of it the user's doing (each an error under the test
# suite's warnings-as-errors): at import, that jaxopt is unmaintained; at every model load,
# that brax is no longer actively maintained (said once in the docs instead); while tracing
# a step, that it reads MJX fields through a deprecated path.
_BRAX_WARNINGS = (
    "JAXopt is no longer maintained",
    "Brax System",
    r"Accessing `\w+` directly from `\w+` is deprecated",
)


@contextlib.contextmanager
def calling_brax() -> Iterator[None]:
    """Context for calls into brax: its own warnings (above) silenced, and implicit rank
    promotion allowed (MJX's pipeline relies on it; a caller may have made it an error)."""
    with warnings.catch_warnings(), jax.numpy_rank_promotion("allow"):
        for message in _BRAX_WARNINGS:
            warnings.filterwarnings("ignore", message=message)
        yield


def _import_brax_envs():
    from . import mjx_quiet  # noqa: F401  (brax imports MJX; drop its warp lines)

    try:
        with calling_brax():
            from brax import envs
    except ImportError as e:
        raise ValueError(
            f"brax tasks need the brax package ({e}): pip install 'eant2-jax[brax]'"
        ) from None
    return envs


def _hashable(value: Any) -> Any:
    """A JSON option value as a hashable one (lists become tuples)."""
    if isinstance(value, list | tuple):
        return tuple(_hashable(v) for v in value)
    return value


@functools.cache
def _environment(name: str, backend: str, params: tuple[tuple[str, Any], ...]) -> Any:
    """The brax environment, once per process and settings: tasks alike share one object,
    so their compiled programs are shared too (the environment is a static part of them)."""
    envs = _import_brax_envs()
    with calling_brax():
        return envs.get_environment(name, backend=backend, **dict(params))


def _known_params(cls: type) -> dict[str, Any]:
    """The constructor arguments of an environment class and their defaults."""
    known = {
        p.name: p.default
        for p in inspect.signature(cls.__init__).parameters.values()
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in ("self", "backend")
    }
    return dict(sorted({**known, **_PIPELINE_OPTIONS}.items()))


def _checked_params(where: str, cls: type, params: Any) -> tuple[tuple[str, Any], ...]:
    """``params`` checked against the constructor's defaults (`check_like`: a number for a
    number, a pair for a pair...); ``n_frames`` (the action repeat) is an integer in
    1..`MAX_FRAMES`. Returns them as sorted, hashable ``(name, value)`` pairs."""
    if params is None:
        return ()
    if not isinstance(params, dict):
        raise ValueError(f"{where}: params must be an object of name: value, got {params!r:.60}")
    known = _known_params(cls)
    unknown = sorted(str(k) for k in set(params) - set(known))
    if unknown:
        raise ValueError(f"{where}: unknown params {', '.join(unknown)}; known: {', '.join(known)}")
    checked = {}
    for key, value in params.items():
        if key == "n_frames":
            checked[key] = check_int(where, "params.n_frames", value, high=MAX_FRAMES)
        else:
            checked[key] = check_like(where, f"params.{key}", value, known[key])
    return tuple(sorted((k, _hashable(v)) for k, v in checked.items()))


def check_precision(where: str, precision: str) -> None:
    """One clear line unless ``precision`` is one of `PRECISIONS`."""
    check_choice(where, "precision", precision, PRECISIONS)


@pytree.dataclass(kw_only=True)
class PipelineTask(EpisodicTask):
    """The base of the adapters for environments with brax's interface (``env.reset(key)``
    and ``env.step(state, action)`` returning a state with ``obs``, ``reward`` and ``done``:
    brax's own, and MuJoCo Playground's). A subclass gives the environment (``env``).

    Attributes:
      precision: precision of the physics' float32 products, one of `PRECISIONS` (static,
        keyword-only).
      obs_offset, obs_scale: ``[n_inputs]`` inputs are ``(obs - obs_offset) * obs_scale``
        (``normalize="random"``: `eant2_jax.tasks.obsnorm`); None: the observation as it
        is (keyword-only).
    """

    precision: str = pytree.field(pytree_node=False, default="highest")
    obs_offset: jax.Array | None = None
    obs_scale: jax.Array | None = None

    @property
    def env(self) -> Any:
        raise NotImplementedError

    def inputs(self, obs: Any) -> jax.Array:
        """Network inputs ``[n_inputs]`` of one observation: normalised where
        ``normalize="random"`` froze statistics, else the observation as it is."""
        x = self.observation(obs)
        return x if self.obs_offset is None else (x - self.obs_offset) * self.obs_scale

    def action(self, y: jax.Array) -> jax.Array:
        """The environment's action ``[n_outputs]`` (in ``[-1, 1]``) for outputs ``y``."""
        return jnp.clip(y, -1.0, 1.0)

    def environment(self):
        """``(reset, step)`` of the environment, at this task's precision."""
        env = self.env
        # "default" leaves the choice to JAX (and its caller's own context).
        exact = contextlib.nullcontext
        if self.precision != "default":
            exact = functools.partial(jax.default_matmul_precision, self.precision)

        def reset(key):
            with calling_brax(), exact():
                state = env.reset(key)
            return state.obs, state

        def step(_, state, action):  # the dynamics are deterministic: no key
            with calling_brax(), exact():
                state = env.step(state, action)
            return state.obs, state, state.reward, state.done > 0

        return reset, step


@pytree.dataclass
class BraxTask(PipelineTask):
    """A brax environment as a task (module docstring). Build with `brax`.

    Attributes:
      env_name: the brax environment name (static).
      backend: the physics pipeline (static).
      params: the environment's constructor arguments, as sorted ``(name, value)`` pairs
        (static).
      n_inputs, n_outputs: observation size and action size (static).

    and `PipelineTask`'s ``precision`` and `EpisodicTask`'s ``episodes``, ``max_steps``,
    ``chunk``, ``hidden``, ``output`` and ``noisy`` (keyword-only).
    """

    env_name: str = pytree.field(pytree_node=False)
    backend: str = pytree.field(pytree_node=False)
    params: tuple[tuple[str, Any], ...] = pytree.field(pytree_node=False)
    n_inputs: int = pytree.field(pytree_node=False)
    n_outputs: int = pytree.field(pytree_node=False)

    @property
    def env(self):
        return _environment(self.env_name, self.backend, self.params)

    @property
    def solved_cost(self) -> float | None:
        """Minus the solved return of an environment whose return defines one, with its
        default constructor and episode length (`SOLVED_RETURNS`), else None."""
        solved = SOLVED_RETURNS.get(self.env_name)
        return (
            -solved if solved is not None and not self.params and self.max_steps == 1000 else None
        )


def brax(
    name: str,
    *,
    episodes: int = 1,
    max_steps: int = 1000,
    backend: str = "generalized",
    params: dict | None = None,
    chunk: int = 50,
    hidden: str = "tanh",
    output: str = "tanh",
    precision: str = "highest",
    normalize: str = "none",
    norm_episodes: int | None = None,
    norm_seed: int | None = None,
) -> BraxTask:
    """A brax environment as a task (``tasks.make("brax:NAME", ...)``).

    Args:
      name: the brax environment name, e.g. ``inverted_pendulum``, ``hopper``,
        ``halfcheetah``.
      episodes: episodes per evaluation (the cost is minus their mean return).
      max_steps: steps per episode at most (brax's ``episode_length``; 1000 by default).
      backend: the physics pipeline: ``generalized`` (brax's default), ``mjx``,
        ``positional`` or ``spring``.
      params: arguments of the environment's constructor, e.g.
        ``{"ctrl_cost_weight": 0.01}`` for ``hopper``, or ``{"n_frames": 4}``.
      chunk: steps per block of the episode loop (its early exit is checked per block).
      hidden: activation of hidden neurons.
      output: activation of output neurons (the action is the output clipped to [-1, 1]).
      precision: precision of the physics' float32 products (``jax.default_matmul_precision``):
        ``highest`` (full float32, as on a CPU), ``high`` or ``default`` (TF32 on a GPU).
      normalize: ``"none"`` (observations as they are) or ``"random"`` (mean and standard
        deviation over random-policy episodes, frozen: `eant2_jax.tasks.obsnorm`).
      norm_episodes: random-policy episodes of ``normalize="random"`` (default 1,000).
      norm_seed: the seed of their key, ``jax.random.key(norm_seed)`` (default 0).

    Returns:
      The `BraxTask`.
    """
    where = f"brax:{name}"
    envs = _import_brax_envs()
    known = sorted(envs._envs)  # brax's registry (get_environment raises a bare KeyError)
    if name not in known:
        raise ValueError(f"unknown brax environment {name!r}; known: {', '.join(known)}")
    check_choice(where, "backend", backend, BACKENDS)
    params = _checked_params(where, envs._envs[name], params)
    check_precision(where, precision)
    episodes, max_steps, chunk = check_episode_options(
        where, episodes=episodes, max_steps=max_steps, chunk=chunk, hidden=hidden, output=output
    )
    norm = check_normalize(where, normalize, norm_episodes, norm_seed, NORMALIZE)
    try:
        env = _environment(name, backend, params)
        with calling_brax():
            obs = jax.eval_shape(env.reset, jax.random.key(0)).obs
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"{where}: cannot build the environment: {first}") from None
    if not hasattr(obs, "shape"):
        raise ValueError(f"{where}: observations are {type(obs).__name__}, not one array")
    task = BraxTask(
        env_name=name,
        backend=backend,
        params=params,
        n_inputs=math.prod(obs.shape),
        n_outputs=int(env.action_size),
        episodes=episodes,
        max_steps=max_steps,
        chunk=chunk,
        hidden=hidden,
        output=output,
        precision=precision,
    )
    return normalized(task, norm, where)
