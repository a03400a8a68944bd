"""Frozen dataclass pytrees with static fields: ``dataclass`` and ``field``.

The package's containers (configurations, compiled layouts, CMA-ES state, tasks) are frozen
dataclasses registered as JAX pytrees with `jax.tree_util.register_dataclass`. A field is a
pytree node (a leaf array traced under ``jit``/``vmap``, mapped by ``jax.tree.map``) unless it
is declared ``field(pytree_node=False)``: then it is static, part of the tree's structure, so
its value is hashed and compared by ``jit``'s cache (a different value compiles anew).

This is the subset of ``flax.struct`` the package uses, with the same semantics (same
leaves, same tree structure, ``replace``, equality and hashing of a frozen dataclass), written
on JAX alone so that flax and the checkpointing stack it pulls in (orbax, tensorstore) are not
installed with the package. ``tests/test_pytree.py`` checks it against ``flax.struct``.
Like the other kernels, it imports nothing from the rest of eant2_jax; user code imports it as
``eant2_jax.pytree``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, TypeVar, dataclass_transform, overload

import jax

__all__ = ["dataclass", "field"]

_T = TypeVar("_T")
_MARK = "_eant2_pytree_dataclass"


def field(pytree_node: bool = True, *, metadata: dict | None = None, **kwargs: Any) -> Any:
    """A dataclass field; ``pytree_node=False`` makes it static (part of the tree structure).

    Args:
        pytree_node: whether the field is a pytree node (traced) or static metadata.
        metadata: more metadata for `dataclasses.field`; ``"pytree_node"`` is set from
            ``pytree_node``.
        **kwargs: `dataclasses.field`'s other arguments (``default``, ``default_factory``,
            ``repr``, ``compare``, ``kw_only``, ...).

    Returns:
        A `dataclasses.Field` marked for `dataclass`.
    """
    return dataclasses.field(metadata=(metadata or {}) | {"pytree_node": pytree_node}, **kwargs)


def _replace(self, **updates):
    """A copy of this object with the named fields replaced (`dataclasses.replace`)."""
    return dataclasses.replace(self, **updates)


@overload
def dataclass(clz: type[_T], **kwargs: Any) -> type[_T]: ...


@overload
def dataclass(**kwargs: Any) -> Callable[[type[_T]], type[_T]]: ...


@dataclass_transform(field_specifiers=(field,), frozen_default=True)
def dataclass(clz: type | None = None, **kwargs: Any) -> Any:
    """Make a class a frozen dataclass registered as a JAX pytree, with ``.replace(**kw)``.

    Fields whose metadata says ``pytree_node=False`` (see `field`; any `dataclasses.field`
    with that metadata counts) are static; the others are the tree's children, in field
    order. Used bare (``@dataclass``) or with `dataclasses.dataclass` arguments
    (``@dataclass(kw_only=True)``); ``frozen`` defaults to True. Decorating a class twice
    returns it unchanged.

    Args:
        clz: the class to transform (absent when called with arguments only).
        **kwargs: arguments of `dataclasses.dataclass`.

    Returns:
        The class (or a decorator of classes when ``clz`` is None).
    """
    if clz is None:
        return functools.partial(dataclass, **kwargs)
    if _MARK in clz.__dict__:
        return clz
    kwargs.setdefault("frozen", True)
    data_clz = dataclasses.dataclass(**kwargs)(clz)
    data_fields, meta_fields = [], []
    for f in dataclasses.fields(data_clz):
        (data_fields if f.metadata.get("pytree_node", True) else meta_fields).append(f.name)
    data_clz.replace = _replace
    jax.tree_util.register_dataclass(data_clz, data_fields, meta_fields)
    setattr(data_clz, _MARK, True)
    return data_clz
