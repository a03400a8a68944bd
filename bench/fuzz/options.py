"""gymnax, brax and MuJoCo Playground task options: random options (of the right names,
with values of random types and ranges, plus unknown names) given to
`eant2_jax.tasks.make`, as ``--task-option`` and a run directory's ``task_options`` give
them. Accepted means the task made holds what was asked (episodes, max_steps, chunk, the
environment parameters or config overrides); anything wrong must be one line naming the
option, when the task is made.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from bench.fuzz.common import Tally, classify
from eant2_jax import tasks

TARGETS = (  # spec, weight; brax and Playground make slower (an environment per setting)
    ("gymnax:CartPole-v1", 4), ("gymnax:Pendulum-v1", 2), ("gymnax:Acrobot-v1", 2),
    ("gymnax:DeepSea-bsuite", 1), ("brax:inverted_pendulum", 2), ("brax:hopper", 1),
    ("playground:CartpoleBalance", 1),
)  # fmt: skip
VALUES = [None, True, False, 0, -1, 1, 2, 3, 7, 50, 2**31 - 1, 2**31, 2**63, 10**30, 0.5, 2.0,
          -0.0, 1e308, math.inf, math.nan, "", "x", "abc", "50", "tanh", "none", "bounds",
          "generalized", "spring", "jax", "warp", "highest", "default", "state", [], [1],
          [1, 2], [1, 2, 3], [0.5, math.inf], {}, {"a": 1}, [[[]]]]  # fmt: skip
VALID = {  # values an option takes (half the draws), so that accepted cases are checked too
    "episodes": [1, 2, 3], "max_steps": [1, 7, 50], "chunk": [1, 7, 50],
    "hidden": ["tanh", "sigmoid"], "output": ["tanh", "identity"],
    "normalize": ["bounds", "none"], "backend": ["generalized", "spring"],
    "precision": ["highest", "default"], "impl": ["jax"], "obs_key": ["state"],
    "params": [1, 2, 0.5, 3.0, 20, [0.5, 2.0], [-1.0, 0.0, 1.0], True, False],
}  # fmt: skip
COMMON = ("episodes", "max_steps", "chunk", "hidden", "output")
OWN = {
    "gymnax": ("normalize", "params"),
    "brax": ("backend", "params", "precision"),
    "playground": ("impl", "config", "obs_key", "precision"),
}
PARAMS = {  # names an environment knows (and one it does not)
    "gymnax:CartPole-v1": ("max_steps_in_episode", "gravity", "length", "bogus"),
    "gymnax:Pendulum-v1": ("max_steps_in_episode", "max_torque", "dt", "bogus"),
    "gymnax:Acrobot-v1": ("max_steps_in_episode", "available_torque", "dt", "bogus"),
    "gymnax:DeepSea-bsuite": ("max_steps_in_episode", "deterministic", "bogus"),
    "brax:inverted_pendulum": ("n_frames", "bogus"),
    "brax:hopper": ("n_frames", "ctrl_cost_weight", "healthy_z_range",
                    "terminate_when_unhealthy", "bogus"),
    "playground:CartpoleBalance": ("episode_length", "action_repeat", "ctrl_dt", "sim_dt",
                                   "vision", "vision_config", "impl", "bogus"),
}  # fmt: skip


def _value(rng, name: str):
    pool = VALID.get(name, VALUES) if rng.integers(2) else VALUES
    return pool[rng.integers(len(pool))]


def draw(rng) -> tuple[str, dict]:
    """A spec and random options for it."""
    weights = np.array([w for _, w in TARGETS], float)
    spec = TARGETS[rng.choice(len(TARGETS), p=weights / weights.sum())][0]
    family = spec.split(":")[0]
    names = (*COMMON, *OWN[family], "bogus")
    options = {}
    for _ in range(rng.integers(1, 4)):
        name = names[rng.integers(len(names))]
        if name in ("params", "config"):
            keys = PARAMS[spec]
            value = {keys[rng.integers(len(keys))]: _value(rng, "params")}
            if rng.integers(4) == 0:  # the object itself of another type
                value = VALUES[rng.integers(len(VALUES))]
        else:
            value = _value(rng, name)
        options[name] = value
    return spec, options


def _same(a, b) -> bool:
    """Equal as numbers (NaN never is), arrays and tuples item by item."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b or (isinstance(a, np.bool_) and bool(a) is b)
    try:
        return bool(np.array_equal(np.asarray(a, float), np.asarray(b, float)))
    except (TypeError, ValueError):
        return a == b


def check(spec: str, options: dict) -> str | tuple[str, str]:
    task = tasks.make(spec, **options)
    for name in ("episodes", "max_steps", "chunk", "hidden", "output"):
        if name in options and options[name] is not None and getattr(task, name) != options[name]:
            return "silent_wrong", f"{name} is {getattr(task, name)!r}"
    asked = options.get("params") or options.get("config") or {}
    if spec.startswith("gymnax:"):
        got = vars(task.env_params)
        for k, v in asked.items():
            limit = "max_steps" in options and k == "max_steps_in_episode"
            if not limit and not _same(got[k], v):
                return "silent_wrong", f"params.{k} is {got[k]!r}"
    elif spec.startswith("brax:"):
        got = dict(task.params)
        if any(not _same(got.get(k), v) for k, v in asked.items()):
            return "silent_wrong", f"params are {task.params}"
    else:
        got = dict(task.overrides)
        for k, v in asked.items():
            if not isinstance(v, dict) and not _same(got.get(k), v):
                return "silent_wrong", f"config.{k} is {got.get(k)!r}"
    return "accepted"


def run(rng: np.random.Generator, n: int, tmp: Path) -> Tally:
    """``n`` random option sets."""
    tally = Tally("task options")
    for _ in range(n):
        spec, options = draw(rng)
        verdict, detail = classify(lambda: check(spec, options))  # noqa: B023
        tally.add(spec.split(":")[0], verdict, detail, case=f"{spec} {options!r:.200}")
    return tally
