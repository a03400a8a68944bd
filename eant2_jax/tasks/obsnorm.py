"""Frozen observation normalisation from random-policy episodes (``normalize="random"``).

The gymnax, brax and Playground adapters take ``normalize="random"``: when the task is made,
``norm_episodes`` episodes are played by a random policy with the task's own environment
(its ``environment()``: the reset and step its episodes use) and action mapping, and each
observation dimension's mean and standard deviation over every state the policy acted on
are frozen into the task as arrays (``obs_offset`` = mean, ``obs_scale`` = 1 / std, leaves
of the task pytree): the network's inputs are ``(obs - mean) / std``. TensorNEAT's brax
examples (``halfcheetah``, ``walker2d``: ``obs_normalization=True``, 1,000 sample episodes)
do the same; docs/tasks-custom.md ("Observation normalisation") says where this differs.

* **the random policy**: at every step the network outputs are drawn uniform in
  ``[-1, 1]`` and mapped by the task's ``action`` (a continuous action: uniform between its
  bounds; a discrete one: the argmax of independent uniforms, uniform over the actions).
* **keys**: ``key = jax.random.key(norm_seed)``; episode ``i`` has key
  ``k = jax.random.split(key, norm_episodes)[i]``; ``env_key, act_key = split(k)``; the
  environment gets ``env_key`` as an episode of the task gets its key (`episodic.rollout`:
  ``reset_key, step_key = split(env_key)``, step ``t`` gets ``fold_in(step_key, t)``) and
  step ``t``'s outputs are ``uniform(fold_in(act_key, t), [n_outputs], float32, -1, 1)``.
* **which observations**: each step's observation before the action (the initial one
  included, the one after the last step not), until ``max_steps`` or ``done``; an
  observation with a non-finite entry is left out (as TensorNEAT leaves out NaN rows).
* **statistics**: in float64 on the host (population standard deviation, ``ddof=0``),
  merged over blocks of episodes (`statistics`); a dimension whose spread is at most
  `SPREAD_MIN` times ``max(1, |mean|)`` is centred only (scale 1).

The statistics are a pure function of the options (the same seed gives the same arrays, to
the bit, on the same device and software), so a resumed run rebuilds them from the task
options its run directory records. Their episodes run while the task is made, so wall
times measured from process start count them.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .episodic import MAX_EPISODES, check_choice, check_int, chunked_steps

__all__ = [
    "BLOCK_FLOATS",
    "NORM_EPISODES",
    "SPREAD_MIN",
    "check_normalize",
    "frozen",
    "normalized",
    "random_observations",
    "statistics",
]

NORM_EPISODES = 1000  # TensorNEAT's halfcheetah and walker2d examples sample 1,000 episodes
# A dimension whose standard deviation is at most this times max(1, |mean|) is a constant
# (up to float32 rounding of the physics): centred, not divided by ~0.
SPREAD_MIN = 1e-6
# Observation floats recorded per device batch of episodes at most (4 bytes each): the
# episodes run in equal blocks of at most this many floats of recordings.
BLOCK_FLOATS = 2**24


def check_normalize(
    where: str, normalize: Any, norm_episodes: Any, norm_seed: Any, choices: tuple[str, ...]
) -> tuple[int, int] | None:
    """Check an adapter's normalisation options, one line naming the option at fault:
    ``normalize`` one of ``choices``; ``norm_episodes`` (1..`MAX_EPISODES`, default
    `NORM_EPISODES`) and ``norm_seed`` (0..2**31 - 1, default 0) only with ``"random"``.
    Returns ``(episodes, seed)`` for ``"random"``, else None."""
    check_choice(where, "normalize", normalize, choices)
    if normalize != "random":
        for name, value in (("norm_episodes", norm_episodes), ("norm_seed", norm_seed)):
            if value is not None:
                raise ValueError(
                    f"{where}: {name} applies only with normalize='random', "
                    f"got normalize={normalize!r}"
                )
        return None
    episodes = NORM_EPISODES if norm_episodes is None else norm_episodes
    episodes = check_int(where, "norm_episodes", episodes, high=MAX_EPISODES)
    seed = check_int(where, "norm_seed", 0 if norm_seed is None else norm_seed, low=0)
    return episodes, seed


def _random_episode(task: Any, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(observations [max_steps, n_inputs] float32, length [] int32)`` of ONE random-policy
    episode (module docstring); rows from ``length`` on are zero."""
    reset, step = task.environment()
    env_key, act_key = jax.random.split(key)
    reset_key, step_key = jax.random.split(env_key)  # as episodic.rollout splits its key
    obs, state = reset(reset_key)
    steps = task.max_steps
    seen0 = jnp.zeros((steps, task.n_inputs), jnp.float32)
    carry0 = (obs, state, seen0, jnp.bool_(True), jnp.int32(0))

    def one(carry, _):
        obs, state, seen, alive, t = carry
        live = alive & (t < steps)
        row = jnp.minimum(t, steps - 1)
        seen = seen.at[row].set(jnp.where(live, task.observation(obs), seen[row]))
        y = jax.random.uniform(
            jax.random.fold_in(act_key, t), (task.n_outputs,), jnp.float32, -1.0, 1.0
        )
        obs, state, _, done = step(jax.random.fold_in(step_key, t), state, task.action(y))
        return (obs, state, seen, live & ~done, t + live.astype(jnp.int32)), None

    def going(carry):
        return carry[3] & (carry[4] < steps)

    _, _, seen, _, t = chunked_steps(one, going, carry0, chunk=task.chunk, max_steps=steps)
    return seen, t


@jax.jit
def _episodes(task: Any, keys: jax.Array) -> tuple[jax.Array, jax.Array]:
    return jax.vmap(_random_episode, in_axes=(None, 0))(task, keys)


def random_observations(task: Any, keys: jax.Array) -> tuple[np.ndarray, np.ndarray]:
    """The observations of random-policy episodes, one per key (module docstring).

    Args:
      task: an episodic task with ``environment()``, ``observation``, ``action``,
        ``n_inputs``, ``n_outputs``, ``max_steps`` and ``chunk``.
      keys: ``[episodes]`` episode keys.

    Returns:
      ``(observations [episodes, max_steps, n_inputs] float32, lengths [episodes] int32)``:
      row ``t`` of episode ``i`` is the observation its step ``t`` acted on, for ``t <
      lengths[i]`` (zero after).
    """
    seen, lengths = _episodes(task, keys)
    return np.asarray(seen), np.asarray(lengths)


def _merge(a: tuple, b: tuple) -> tuple:
    """Count, mean and sum of squared deviations of two sets of rows merged (Chan et al.)."""
    (na, ma, sa), (nb, mb, sb) = a, b
    n = na + nb
    if nb == 0:
        return a
    delta = mb - ma
    return n, ma + delta * (nb / n), sa + sb + delta**2 * (na * nb / n)


def statistics(
    task: Any, *, episodes: int, key: jax.Array, block: int | None = None
) -> tuple[np.ndarray, np.ndarray, int]:
    """Mean and standard deviation ``[n_inputs]`` (float64) of the finite observations of
    ``episodes`` random-policy episodes (keys ``jax.random.split(key, episodes)``), and
    their count.

    Args:
      task: as for `random_observations`.
      episodes: episodes to play.
      key: their key.
      block: episodes per device batch (default: as many as `BLOCK_FLOATS` allows); blocks
        are equal, the last one padded with repeated keys whose episodes are dropped.

    Raises:
      ValueError: no finite observation at all.
    """
    keys = jax.random.split(key, episodes)
    if block is None:
        block = max(1, BLOCK_FLOATS // (task.max_steps * task.n_inputs))
    n_blocks = math.ceil(episodes / block)
    size = math.ceil(episodes / n_blocks)  # equal blocks: one compiled program
    pad = n_blocks * size - episodes
    keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], pad, axis=0)]) if pad else keys
    acc = (0, np.zeros(task.n_inputs), np.zeros(task.n_inputs))
    for b in range(n_blocks):
        seen, lengths = random_observations(task, keys[b * size : (b + 1) * size])
        real = min(size, episodes - b * size)
        live = np.arange(task.max_steps)[None, :] < lengths[:real, None]
        rows = seen[:real][live].astype(np.float64)
        rows = rows[np.all(np.isfinite(rows), axis=1)]
        if len(rows):
            mean = rows.mean(axis=0)
            acc = _merge(acc, (len(rows), mean, ((rows - mean) ** 2).sum(axis=0)))
    count, mean, squares = acc
    if count == 0:
        raise ValueError("the random-policy episodes saw no finite observation")
    return mean, np.sqrt(squares / count), count


def frozen(task: Any, *, episodes: int, seed: int, where: str) -> tuple[jax.Array, jax.Array]:
    """``(obs_offset, obs_scale)`` ``[n_inputs]`` float32 of ``normalize="random"``: the mean,
    and 1 / std (1 where the spread is at most `SPREAD_MIN` times ``max(1, |mean|)``), of
    `statistics` over ``episodes`` episodes from ``jax.random.key(seed)``."""
    try:
        mean, std, _ = statistics(task, episodes=episodes, key=jax.random.key(seed))
    except ValueError as e:
        raise ValueError(f"{where}: normalize='random': {e}") from None
    flat = std <= SPREAD_MIN * np.maximum(1.0, np.abs(mean))
    scale = np.where(flat, 1.0, 1.0 / np.where(flat, 1.0, std))
    return jnp.asarray(mean, jnp.float32), jnp.asarray(scale, jnp.float32)


def normalized(task: Any, norm: tuple[int, int] | None, where: str) -> Any:
    """``task`` with the statistics of ``normalize="random"`` frozen into its ``obs_offset``
    and ``obs_scale``, where ``norm`` (the checked ``(norm_episodes, norm_seed)`` of
    `check_normalize`) is not None; else ``task``."""
    if norm is None:
        return task
    offset, scale = frozen(task, episodes=norm[0], seed=norm[1], where=where)
    return task.replace(obs_offset=offset, obs_scale=scale)
