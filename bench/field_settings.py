"""The field protocol's frozen settings (docs/protocol.md section 3): both methods' settings
per environment, the seeds, budgets and episode keys. Written before any run of the
protocol; a change after a reported seed ran is a departure the report must name. The
result file prints this table (`table`).

* **eant2_jax**: the settings of ``bench/bench_field.py``'s ``ENVS`` as they stood when the
  protocol was written (chosen on seeds 0-2 of the earlier field runs, which the protocol
  never reports; its seeds are 4000-4009 and 4000-4004), with ``max_evaluations`` = the
  budget and ``stop_when_solved`` off (both methods spend the whole budget). The library's
  bare defaults (1,000 CMA-ES iterations per structure, 20 structures) spend more than the
  whole budget in generation 0, so they would have no champion at any reporting budget.
* **TensorNEAT**: its examples (``examples/gymnax/cartpole.py``, ``arcbot.py``,
  ``examples/brax/hopper.py``, ``halfcheetah.py``): NEAT, population 1000, 20 species,
  survival threshold 0.1, compatibility threshold 1.0, ``BiasNode`` with sum aggregation,
  no initial hidden layer, 100 generations (100,000 evaluations); halfcheetah's larger
  genomes, scaled tanh and observation normalisation. Pendulum has no example: cartpole's
  settings with a continuous output (``2 tanh``, the action bounds).
* **Both**: the episodes per evaluation and the episode length (gymnax 5 episodes, as the
  cartpole example; brax 1 episode of 1,000 steps), the brax backend.
"""

from __future__ import annotations

import json
from typing import Any

__all__ = [
    "BUDGET_FRACTIONS",
    "CURVE_POINTS",
    "ENVS",
    "NORMALIZE",
    "NORM_EPISODES",
    "NORM_SEED",
    "SPARE_ROWS",
    "SEEDS",
    "TEST_EPISODES",
    "TEST_KEY",
    "TOP",
    "VALIDATION_EPISODES",
    "VALIDATION_KEY",
    "budgets",
    "env_seeds",
    "table",
]

TOP = 5  # candidates per method at each budget: its best by training fitness
VALIDATION_KEY, VALIDATION_EPISODES = 8000, 10  # jax.random.key(8000), not counted
TEST_KEY, TEST_EPISODES = 9000, 100  # jax.random.key(9000), the same for both methods
BUDGET_FRACTIONS = (0.25, 0.5, 1.0)  # of TensorNEAT's example evaluations
# The champion along a run (for the wall time to a target) at every 1/CURVE_POINTS of the
# budget: the last generation within each such share.
CURVE_POINTS = 20
SEEDS = {"gymnax": tuple(range(4000, 4010)), "brax": tuple(range(4000, 4005))}
# A trial's --normalize random (docs/protocol.md section 8): eant2_jax's inputs normalised by
# the statistics of TensorNEAT's halfcheetah example's count of random-policy episodes
# (`eant2_jax.tasks.obsnorm`), from jax.random.key(NORM_SEED), the same for every seed.
NORM_EPISODES, NORM_SEED = 1000, 0
NORMALIZE = ("none", "random")  # a trial's --normalize choices
# A trial's --spare-rows choices (docs/protocol.md section 9): ExploitConfig.spare_rows's.
SPARE_ROWS = ("idle", "restarts")

_TN = {"pop_size": 1000, "species_size": 20, "survival_threshold": 0.1,
       "compatibility_threshold": 1.0, "generations": 100, "activation": "tanh",
       "max_nodes": 50, "max_conns": 100, "obs_norm_episodes": 0}  # fmt: skip
# width 1: the default popsize on every device, section 3's setting (episodic tasks have a
# GPU default width since section 6's choice; `eant2_jax.tuning.popsize_for`).
_EANT2 = {"population": 10, "rescore": 16, "popsize": None, "width": 1, "reexploit": False,
          "min_bucket": [12, 64, 4], "pruner": "covariance"}  # fmt: skip
# brax: the batch width chosen by docs/protocol.md section 6 (`python -m bench width` on
# bench/results/field-width/, choice seeds 100-102: summed ranks frozen 8, 1,024 3, 4,096 5,
# 10,000 4), each environment's CMA-ES iterations per generation scaled by that section's
# rule so that a structure's evaluations per generation stay the frozen ones (hopper 24 x 10,
# halfcheetah 48 x 100). The frozen popsizes these replace are in the result files of the
# section 3 runs (`bench/results/field-protocol-gpu-h100.json`).
WIDTH = 1024
_BRAX_EANT2 = {**_EANT2, "min_bucket": [16, 96, 4], "reexploit": True, "width": WIDTH}

ENVS: dict[str, dict[str, Any]] = {
    "cartpole": {
        "family": "gymnax", "name": "CartPole-v1", "episodes": 5, "max_steps": 500,
        "discrete": True, "example": "examples/gymnax/cartpole.py",
        "eant2": {**_EANT2, "max_iters": 100, "normalize": "bounds"},
        "tensorneat": {**_TN, "output": "argmax"},
    },
    "acrobot": {
        "family": "gymnax", "name": "Acrobot-v1", "episodes": 5, "max_steps": 500,
        "discrete": True, "example": "examples/gymnax/arcbot.py",
        "eant2": {**_EANT2, "max_iters": 50, "normalize": "none"},
        "tensorneat": {**_TN, "output": "argmax"},
    },
    "pendulum": {
        "family": "gymnax", "name": "Pendulum-v1", "episodes": 5, "max_steps": 200,
        "discrete": False, "example": "none (cartpole's settings, output 2 tanh)",
        "eant2": {**_EANT2, "max_iters": 200, "normalize": "bounds"},
        "tensorneat": {**_TN, "output": "2 tanh"},
    },
    "hopper": {
        "family": "brax", "name": "hopper", "episodes": 1, "max_steps": 1000,
        "discrete": False, "example": "examples/brax/hopper.py", "backend": "spring",
        "eant2": {**_BRAX_EANT2, "max_iters": 3},
        "tensorneat": {**_TN, "output": "tanh"},
    },
    "halfcheetah": {
        "family": "brax", "name": "halfcheetah", "episodes": 1, "max_steps": 1000,
        "discrete": False, "example": "examples/brax/halfcheetah.py", "backend": "spring",
        "eant2": {**_BRAX_EANT2, "max_iters": 57, "min_bucket": [16, 192, 4]},
        "tensorneat": {**_TN, "output": "tanh", "max_conns": 200,
                       "activation": "scaled_tanh", "obs_norm_episodes": 1000},
    },
    # Never run by the project before section 6's check that the width rule carries over:
    # eant2_jax takes halfcheetah's settings (its networks' sizes, 17 inputs and 6 outputs,
    # are halfcheetah's 18 and 6; hopper's are 11 and 3), TensorNEAT its own example.
    "walker2d": {
        "family": "brax", "name": "walker2d", "episodes": 1, "max_steps": 1000,
        "discrete": False, "example": "examples/brax/walker2d.py", "backend": "spring",
        "seeds": [4000, 4001, 4002],
        "eant2": {**_BRAX_EANT2, "max_iters": 57, "min_bucket": [16, 192, 4]},
        "tensorneat": {**_TN, "output": "tanh", "max_conns": 200, "obs_norm_episodes": 1000},
    },
}  # fmt: skip


def env_seeds(name: str) -> list[int]:
    """The protocol's seeds of one environment: its own ``seeds`` where it names them (an
    environment added to check a rule, fewer seeds), else its family's (`SEEDS`)."""
    env = ENVS[name]
    return list(env.get("seeds") or SEEDS[env["family"]])


def budgets(env: dict[str, Any]) -> list[int]:
    """The reporting budgets (evaluations) of an environment: `BUDGET_FRACTIONS` of its
    TensorNEAT example's ``pop_size * generations``."""
    tn = env["tensorneat"]
    total = tn["pop_size"] * tn["generations"]
    return [round(f * total) for f in BUDGET_FRACTIONS]


def table(names: list[str] | None = None) -> dict[str, Any]:
    """The frozen settings as the result file records them (a JSON copy)."""
    envs = {k: v for k, v in ENVS.items() if names is None or k in names}
    return json.loads(
        json.dumps(
            {
                "envs": envs,
                "seeds": SEEDS,
                "top": TOP,
                "validation": {"key": VALIDATION_KEY, "episodes": VALIDATION_EPISODES},
                "test": {"key": TEST_KEY, "episodes": TEST_EPISODES},
                "budget_fractions": BUDGET_FRACTIONS,
                "curve_points": CURVE_POINTS,
                "budgets": {k: budgets(v) for k, v in envs.items()},
            }
        )
    )
