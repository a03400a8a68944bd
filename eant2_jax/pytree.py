"""Frozen dataclass pytrees for tasks and containers: ``dataclass`` and ``field``.

Declare a custom task (or any container passed into a compiled program) with
``@pytree.dataclass``; sizes, names and other values that shape the program are static fields,
``pytree.field(pytree_node=False)``. The semantics are ``flax.struct``'s, written on
`jax.tree_util.register_dataclass` (the implementation lives with the kernels, which import
nothing from the rest of the package: `eant2_jax.kernels.pytree`).
"""

from .kernels.pytree import dataclass as dataclass
from .kernels.pytree import field as field

__all__ = ["dataclass", "field"]
