"""Compatibility name of `eant2_jax.programs.stats` until every caller imports it from there."""

from .programs.stats import CompileStats as CompileStats
from .programs.stats import snapshot as snapshot
