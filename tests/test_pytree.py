"""`eant2_jax.pytree` against its reference, ``flax.struct`` (flax is in the test extra).

Each case declares the same class twice, once with each implementation, and checks that
they flatten to the same leaves and tree structure (static values in the structure, in
field order), unflatten back, ``replace``, refuse assignment, compare and hash alike, and key
``jit``'s cache on static fields alike.
"""

from __future__ import annotations

import dataclasses
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from hypothesis import given, settings
from hypothesis import strategies as st

from eant2_jax import pytree
from eant2_jax.configspec import option


def _classes(impl):
    """The same four classes declared with ``impl`` (``pytree`` or ``flax.struct``)."""

    @impl.dataclass
    class Plain:
        a: jax.Array
        b: jax.Array

    @impl.dataclass
    class Mixed:
        w: jax.Array
        n: int = impl.field(pytree_node=False, default=3)
        name: str = impl.field(pytree_node=False, default="tanh")
        bias: jax.Array = impl.field(default_factory=lambda: jnp.zeros(2))

    @impl.dataclass(kw_only=True)
    class KwOnly:
        x: jax.Array
        size: int = impl.field(pytree_node=False, default=5)
        y: jax.Array = impl.field(default=None)

    @impl.dataclass
    class Nested:
        inner: Mixed
        scale: jax.Array
        tag: tuple = impl.field(pytree_node=False, default=("a", 1))

    return {"Plain": Plain, "Mixed": Mixed, "KwOnly": KwOnly, "Nested": Nested}


OURS, FLAX = _classes(pytree), _classes(struct)


def _instances(classes, w, n, name):
    """One instance of each class, built from the same values."""
    mixed = classes["Mixed"](w, n=n, name=name)
    return {
        "Plain": classes["Plain"](w, w * 2.0),
        "Mixed": mixed,
        "KwOnly": classes["KwOnly"](x=w, size=n, y=w + 1.0),
        "Nested": classes["Nested"](mixed, jnp.float32(0.5), tag=(name, n)),
    }


def _node_data(tree):
    """Each node's (class name, static aux data) in the flattened order, and the paths."""
    treedef = jax.tree.structure(tree)
    nodes = []

    def walk(td):
        data = td.node_data()
        if data is not None:
            nodes.append((data[0].__name__, data[1]))
        for child in td.children():
            walk(child)

    walk(treedef)
    paths = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]
    return nodes, paths, treedef.num_leaves


@settings(max_examples=15, deadline=None)
@given(
    st.integers(1, 6),
    st.integers(0, 2**31 - 1),
    st.integers(-3, 100),
    st.sampled_from(["tanh", "relu", "x"]),
)
@pytest.mark.slow
def test_flatten_unflatten_as_flax(size, seed, n, name):
    w = jnp.asarray(np.random.default_rng(seed).normal(size=size), jnp.float32)
    ours, ref = _instances(OURS, w, n, name), _instances(FLAX, w, n, name)
    for key in OURS:
        leaves, treedef = jax.tree.flatten(ours[key])
        ref_leaves, ref_treedef = jax.tree.flatten(ref[key])
        assert len(leaves) == len(ref_leaves), key
        for a, b in zip(leaves, ref_leaves, strict=True):
            np.testing.assert_array_equal(a, b)
        assert _node_data(ours[key]) == _node_data(ref[key]), key
        back = jax.tree.unflatten(treedef, leaves)
        assert type(back) is type(ours[key])
        assert jax.tree.structure(back) == treedef
        # The structure holds the static values: a different one is a different structure.
        other = jax.tree.structure(_instances(OURS, w, n + 1, name)[key])
        ref_other = jax.tree.structure(_instances(FLAX, w, n + 1, name)[key])
        assert (other == treedef) == (ref_other == ref_treedef), key


def test_replace_and_frozen():
    for classes in (OURS, FLAX):
        m = classes["Mixed"](jnp.ones(3))
        r = m.replace(n=7, w=jnp.zeros(3))
        assert (r.n, r.name, m.n) == (7, "tanh", 3)
        np.testing.assert_array_equal(r.w, np.zeros(3))
        with pytest.raises(dataclasses.FrozenInstanceError):
            m.n = 4
        with pytest.raises(TypeError):
            m.replace(missing=1)
    with pytest.raises(TypeError):
        OURS["KwOnly"](jnp.ones(2))  # kw_only: no positional arguments, as flax


def test_eq_and_hash_as_flax():
    """Equality and hashing of a frozen dataclass, on hashable (Python) leaves."""
    for a, b in [(1, 1), (1, 2), (0.5, 0.5)]:
        for n_a, n_b in [(3, 3), (3, 4)]:
            got = OURS["Mixed"](a, n=n_a, bias=0) == OURS["Mixed"](b, n=n_b, bias=0)
            want = FLAX["Mixed"](a, n=n_a, bias=0) == FLAX["Mixed"](b, n=n_b, bias=0)
            assert got == want
            if got:
                assert hash(OURS["Mixed"](a, n=n_a, bias=0)) == hash(
                    OURS["Mixed"](b, n=n_b, bias=0)
                )
    assert OURS["Plain"](1, 2) != FLAX["Plain"](1, 2)  # different classes, as two dataclasses


@pytest.mark.parametrize("classes", [OURS, FLAX], ids=["pytree", "flax"])
def test_static_fields_key_the_jit_cache(classes):
    """A new static value compiles anew; a new leaf value of the same shape does not."""
    traces = []

    @jax.jit
    def f(m):
        traces.append(m.n)
        return m.w * m.n + m.bias.sum()

    Mixed = classes["Mixed"]
    f(Mixed(jnp.ones(2), n=2))
    f(Mixed(jnp.ones(2) * 3.0, n=2))
    np.testing.assert_allclose(f(Mixed(jnp.ones(2), n=5)), [5.0, 5.0])
    f(Mixed(jnp.ones(2) - 1.0, n=5))
    assert traces == [2, 5]


@pytest.mark.slow
def test_vmap_and_tree_map():
    ours, ref = (
        _instances(OURS, jnp.arange(3.0), 2, "tanh"),
        _instances(FLAX, jnp.arange(3.0), 2, "tanh"),
    )
    for key in OURS:
        doubled = jax.tree.map(lambda x: x * 2, ours[key])
        assert type(doubled) is type(ours[key])
        for a, b in zip(
            jax.tree.leaves(doubled),
            jax.tree.leaves(jax.tree.map(lambda x: x * 2, ref[key])),
            strict=True,
        ):
            np.testing.assert_array_equal(a, b)
    batch = OURS["Mixed"](jnp.arange(6.0).reshape(3, 2), n=4, bias=jnp.ones((3, 2)))
    out = jax.vmap(lambda m: m.w * m.n + m.bias)(batch)
    np.testing.assert_array_equal(out, np.arange(6.0).reshape(3, 2) * 4 + 1)


def test_plain_dataclass_fields_and_configspec_options():
    """Static-ness is read from the field's metadata, so `configspec.option` and a plain
    `dataclasses.field` work as under flax."""

    def declare(impl):
        @impl.dataclass
        class Config:
            rate: float = option(0.1, static=False)
            size: int = option(4, static=True)
            plain: int = dataclasses.field(default=2)

        return Config

    for impl in (pytree, struct):
        cfg = declare(impl)()
        assert jax.tree.leaves(cfg) == [0.1, 2]
        assert jax.tree.structure(cfg).node_data()[1] == (4,)


def test_decorating_twice_and_pickle():
    Mixed = OURS["Mixed"]
    assert pytree.dataclass(Mixed) is Mixed
    # Not needed by the package, but a module-level class pickles as any dataclass.
    assert pickle.loads(pickle.dumps(_Module(1, 2))) == _Module(1, 2)


@pytree.dataclass
class _Module:
    a: int
    b: int = pytree.field(pytree_node=False)
