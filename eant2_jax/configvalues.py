"""What the configuration fields accept beyond `eant2_jax.configspec`'s generic checks: the
value sets, bounds, checks and converters that `eant2_jax.config` declares its fields with.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .configspec import Check, between

__all__ = [
    "DEFAULT_MAX_CONDITION",
    "DTYPES",
    "FINITE",
    "FRACTION",
    "MAX_BUCKET",
    "MAX_POPULATION",
    "NON_NEGATIVE",
    "RECOMMEND",
    "SPARE_ROWS",
    "TOLERANCE",
    "bucket_value",
    "plain_numbers",
    "weights_value",
]

RECOMMEND = ("best", "mean", "both")
SPARE_ROWS = ("idle", "restarts")  # ExploitConfig.spare_rows (`eant2_jax.spare`)
DTYPES = ("float32", "float64")
# The default bound on cond(C) by the dtype of the CMA-ES state: float32 resolves an
# eigenvalue to about 1e-7 of the largest, so a larger bound lets rounding noise through
# (sigma then explodes along an exactly flat direction); float64 honours the paper's 1e14.
DEFAULT_MAX_CONDITION = {"float32": 1e7, "float64": 1e14}
# None of target_cost and tolfun is held as -inf (no cost is below it); a config rebuilt
# from its fields (``replace``) passes -inf back in.
FINITE = Check(lambda v: v == -math.inf or math.isfinite(v), "finite")
TOLERANCE = Check(lambda v: v == -math.inf or (v >= 0 and math.isfinite(v)), ">= 0 and finite")

# A documented size limit (docs/reliability.md): far above any useful EANT2 population, far
# below the sizes that would only exhaust memory before saying anything.
MAX_POPULATION = 1_000_000
# EANT2Config.min_bucket's bound on each entry: far beyond any network a generation compiles
# (the flat parameter buffer's int32 index allows 24,576 neuron slots: compiler.MAX_BUFFER).
MAX_BUCKET = 16384
NON_NEGATIVE = Check(lambda v: v >= 0 and math.isfinite(v), ">= 0 and finite")
FRACTION = between(0, 1, open_low=True)


def weights_value(v) -> tuple[float, ...]:
    """``EANT2Config.operator_weights``: finite numbers, as a tuple of floats (a
    ValueError otherwise)."""
    if not isinstance(v, list | tuple) or not all(
        isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in v
    ):
        raise ValueError(v)
    return tuple(float(x) for x in v)


def bucket_value(v) -> tuple[int, int, int]:
    """``EANT2Config.min_bucket``: three integers in [1, `MAX_BUCKET`], as a tuple (a
    ValueError otherwise)."""
    if not (
        isinstance(v, list | tuple)
        and len(v) == 3
        and all(isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= MAX_BUCKET for x in v)
    ):
        raise ValueError(v)
    return tuple(v)


def plain_numbers(config) -> bool:
    """Whether every field of a config dataclass holds a plain value (None, a number or a
    string), not a tracer."""
    # JAX rebuilds this pytree with tracers (or other placeholders) as leaves when it
    # traces or maps over it; only a config built from plain values is normalised and
    # validated.
    values = [getattr(config, f.name) for f in dataclasses.fields(config)]
    return all(v is None or isinstance(v, int | float | str | np.number) for v in values)
