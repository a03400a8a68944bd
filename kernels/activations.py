"""Activation functions: each a JAX function for the kernels with its NumPy reference beside it.

An activation is known by its name everywhere: the name is a static argument of the compiled
programs (a new name compiles a new program, a new call with the same name does not), and it
is what genome files, exports and formulas record. Every entry holds

* ``jax``: the function the kernels apply, elementwise on a float32 array;
* ``numpy``: its plain reference, elementwise on a float64 array (what
  `eant2_jax.reference.interpret` applies);
* ``source``: the same function as a ``jax.numpy`` expression in ``a`` (for exports that
  must run without eant2_jax), or None where there is none;
* ``doc``: its definition in one line.

The built-ins: ``identity``, ``tanh``, ``sigmoid`` (``1 / (1 + exp(-a))``) and ``relu`` as
they always were (unscaled: the paper's), and the other activations of neat-python
(``neat/activations.py``, version 0.92, the definitions TensorNEAT also follows) with
neat-python's own input scaling and clamping: ``sin(5a)``, ``exp(-5a^2)`` and
``0.2 softplus(5a)``. neat-python's ``inv`` (1/a) is left out: its pole makes float32 and
float64 disagree without bound near a = 0.

Add your own with `register` (``eant2_jax.register_activation``). This module imports
nothing from the rest of eant2_jax.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ACTIVATIONS", "Activation", "get", "names", "register"]

# neat-python's SELU constants (Klambauer et al. 2017).
_SELU_LAMBDA = 1.0507009873554804934193349852946
_SELU_ALPHA = 1.6732632423543772848170429916717


@dataclasses.dataclass(frozen=True)
class Activation:
    """One activation function, in JAX and in NumPy (module docstring)."""

    name: str
    jax: Callable[[jax.Array], jax.Array]
    numpy: Callable[[np.ndarray], np.ndarray]
    source: str | None
    doc: str


def _np_sigmoid(a):
    # exp(-logaddexp(0, -a)) = 1 / (1 + exp(-a)), without overflow for large negative a.
    return np.exp(-np.logaddexp(0.0, -a))


_BUILTIN = (
    # name, jax, numpy, source (a jax.numpy expression in `a`), definition
    ("identity", lambda a: a, lambda a: a, "a", "a"),
    ("tanh", jnp.tanh, np.tanh, "jnp.tanh(a)", "tanh(a)"),
    ("sigmoid", jax.nn.sigmoid, _np_sigmoid, "jax.nn.sigmoid(a)", "1 / (1 + exp(-a))"),
    ("relu", jax.nn.relu, lambda a: np.maximum(a, 0.0), "jax.nn.relu(a)", "max(a, 0)"),
    (
        "sin",
        lambda a: jnp.sin(jnp.clip(5.0 * a, -60.0, 60.0)),
        lambda a: np.sin(np.clip(5.0 * a, -60.0, 60.0)),
        "jnp.sin(jnp.clip(5.0 * a, -60.0, 60.0))",
        "sin(clip(5a, -60, 60)) (neat-python)",
    ),
    (
        "gauss",
        lambda a: jnp.exp(-5.0 * jnp.square(jnp.clip(a, -3.4, 3.4))),
        lambda a: np.exp(-5.0 * np.square(np.clip(a, -3.4, 3.4))),
        "jnp.exp(-5.0 * jnp.square(jnp.clip(a, -3.4, 3.4)))",
        "exp(-5 clip(a, -3.4, 3.4)^2) (neat-python)",
    ),
    ("abs", jnp.abs, np.abs, "jnp.abs(a)", "|a|"),
    (
        "clamped",
        lambda a: jnp.clip(a, -1.0, 1.0),
        lambda a: np.clip(a, -1.0, 1.0),
        "jnp.clip(a, -1.0, 1.0)",
        "clip(a, -1, 1)",
    ),
    (
        "softplus",
        lambda a: 0.2 * jax.nn.softplus(jnp.clip(5.0 * a, -60.0, 60.0)),
        lambda a: 0.2 * np.logaddexp(0.0, np.clip(5.0 * a, -60.0, 60.0)),
        "0.2 * jax.nn.softplus(jnp.clip(5.0 * a, -60.0, 60.0))",
        "0.2 log(1 + exp(clip(5a, -60, 60))) (neat-python)",
    ),
    (
        "elu",
        lambda a: jnp.where(a > 0, a, jnp.expm1(jnp.minimum(a, 0.0))),
        lambda a: np.where(a > 0, a, np.expm1(np.minimum(a, 0.0))),
        "jnp.where(a > 0, a, jnp.expm1(jnp.minimum(a, 0.0)))",
        "a if a > 0 else exp(a) - 1",
    ),
    (
        "selu",
        lambda a: _SELU_LAMBDA * jnp.where(a > 0, a, _SELU_ALPHA * jnp.expm1(jnp.minimum(a, 0.0))),
        lambda a: _SELU_LAMBDA * np.where(a > 0, a, _SELU_ALPHA * np.expm1(np.minimum(a, 0.0))),
        f"{_SELU_LAMBDA!r} * jnp.where(a > 0, a, {_SELU_ALPHA!r} * jnp.expm1(jnp.minimum(a, 0.0)))",
        "lambda (a if a > 0 else alpha (exp(a) - 1)), lambda = 1.0507, alpha = 1.6733",
    ),
    (
        "lelu",
        lambda a: jnp.where(a > 0, a, 0.005 * a),
        lambda a: np.where(a > 0, a, 0.005 * a),
        "jnp.where(a > 0, a, 0.005 * a)",
        "a if a > 0 else 0.005 a (neat-python's leaky ReLU)",
    ),
    ("square", jnp.square, np.square, "jnp.square(a)", "a^2"),
    ("cube", lambda a: a * a * a, lambda a: a * a * a, "a * a * a", "a^3"),
    (
        "log",
        lambda a: jnp.log(jnp.maximum(a, 1e-7)),
        lambda a: np.log(np.maximum(a, 1e-7)),
        "jnp.log(jnp.maximum(a, 1e-7))",
        "log(max(a, 1e-7)) (neat-python)",
    ),
    (
        "exp",
        lambda a: jnp.exp(jnp.clip(a, -60.0, 60.0)),
        lambda a: np.exp(np.clip(a, -60.0, 60.0)),
        "jnp.exp(jnp.clip(a, -60.0, 60.0))",
        "exp(clip(a, -60, 60)) (neat-python)",
    ),
    (
        "hat",
        lambda a: jnp.maximum(0.0, 1.0 - jnp.abs(a)),
        lambda a: np.maximum(0.0, 1.0 - np.abs(a)),
        "jnp.maximum(0.0, 1.0 - jnp.abs(a))",
        "max(0, 1 - |a|)",
    ),
)

ACTIVATIONS: dict[str, Activation] = {
    name: Activation(name, fj, fn, src, doc) for name, fj, fn, src, doc in _BUILTIN
}
BUILTIN = frozenset(ACTIVATIONS)

# Where register() compares a new pair (float32 JAX against float64 NumPy) before accepting it.
_CHECK_POINTS = np.linspace(-4.0, 4.0, 81)
_CHECK_RTOL, _CHECK_ATOL = 1e-4, 1e-5


def names() -> list[str]:
    """The known activation names, sorted."""
    return sorted(ACTIVATIONS)


def get(name: str) -> Activation:
    """The activation called ``name``; ValueError listing the known ones."""
    try:
        return ACTIVATIONS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown activation {name!r}; known: {', '.join(names())}") from None


def register(
    name: str,
    jax_fn: Callable[[jax.Array], jax.Array],
    numpy_fn: Callable[[np.ndarray], np.ndarray],
    *,
    source: str | None = None,
    doc: str | None = None,
    overwrite: bool = False,
) -> Activation:
    """Add an activation under ``name`` (usable as ``hidden=name`` / ``output=name``).

    The two functions must agree: they are compared on 81 points in [-4, 4] (float32 JAX
    against float64 NumPy, ``|jax - numpy| <= 1e-4 |numpy| + 1e-5``; NaN where both are NaN)
    and the activation is refused if they do not.

    Args:
      name: a Python identifier (it appears in formulas and genome files).
      jax_fn: elementwise JAX function of one array.
      numpy_fn: the same function in NumPy (the reference interpreter's).
      source: optional ``jax.numpy`` expression in ``a`` (e.g. ``"jnp.tanh(2.0 * a)"``) for
        `eant2_jax.export.to_jax_source`; without it the activation cannot be exported
        as source.
      doc: its definition in one line (default: the source, or the name).
      overwrite: replace an existing user activation (built-ins cannot be replaced). Compiled
        programs that used the old function are dropped (``jax.clear_caches``): names are
        static in compiled programs, so a stale one would otherwise run the old function.

    Returns:
      The `Activation`.
    """
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"activation name must be a Python identifier, got {name!r}")
    if name in BUILTIN:
        raise ValueError(f"activation {name!r} is built in and cannot be replaced")
    if name in ACTIVATIONS and not overwrite:
        raise ValueError(f"activation {name!r} is already registered (pass overwrite=True)")
    if not (callable(jax_fn) and callable(numpy_fn)):
        raise TypeError("register: jax_fn and numpy_fn must be callables of one array")
    x = _CHECK_POINTS.astype(np.float32)
    got = np.asarray(jax_fn(jnp.asarray(x)), np.float64)
    want = np.asarray(numpy_fn(x.astype(np.float64)), np.float64)
    if got.shape != x.shape or want.shape != x.shape:
        raise ValueError(
            f"activation {name!r}: the functions must be elementwise (shape {x.shape} in, "
            f"got {got.shape} from jax_fn and {want.shape} from numpy_fn)"
        )
    bad = ~(
        np.isclose(got, want, rtol=_CHECK_RTOL, atol=_CHECK_ATOL, equal_nan=True)
        | ((got == want) & np.isinf(want))
    )
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"activation {name!r}: jax_fn and numpy_fn disagree at a = {x[i]:g} "
            f"({got[i]!r} against {want[i]!r})"
        )
    entry = Activation(name, jax_fn, numpy_fn, source, doc or source or name)
    if name in ACTIVATIONS:
        jax.clear_caches()
    ACTIVATIONS[name] = entry
    return entry
