"""`jax.random.fold_in` and a scalar `jax.random.normal` of threefry keys, rounds unrolled.

The same bits as `jax.random` (tested against it on fresh keys), for the draws the engine
makes on every iteration. On a CPU JAX lowers threefry's five rounds as a loop (a smaller
program); XLA:CPU runs that loop's body trip by trip with its state copied on each, so every
draw site became 5 loop trips and about 65 copies per engine iteration. Written out, a draw
is one fusion (docs/design.md, "Threefry written out on a CPU").

Other backends (JAX's own lowering is unrolled there), other PRNG implementations and
float64 normals use `jax.random` itself. Everything here is for ONE key; batch with vmap.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import DTypeLike

__all__ = ["fold_in", "normal"]

_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))
_PARITY = np.uint32(0x1BD11BDA)  # Threefry's key-schedule constant (Salmon et al. 2011)


def _written_out(key: jax.Array) -> bool:
    """Whether this module's own rounds serve ``key`` (a CPU program, a threefry key)."""
    return jax.default_backend() == "cpu" and str(jax.random.key_impl(key)) == "threefry2x32"


def _rotate_left(x: jax.Array, r: int) -> jax.Array:
    return (x << np.uint32(r)) | (x >> np.uint32(32 - r))


def _hash(k1: jax.Array, k2: jax.Array, x1: jax.Array, x2: jax.Array):
    """Threefry-2x32 with 20 rounds of the uint32 pair ``(x1, x2)`` under key ``(k1, k2)``,
    as JAX computes it (its ``threefry2x32`` primitive), written out."""
    ks = (k1, k2, k1 ^ k2 ^ _PARITY)
    x = [x1 + ks[0], x2 + ks[1]]
    for i in range(5):
        for r in _ROTATIONS[i % 2]:
            x[0] = x[0] + x[1]
            x[1] = x[0] ^ _rotate_left(x[1], r)
        x[0] = x[0] + ks[(i + 1) % 3]
        x[1] = x[1] + ks[(i + 2) % 3] + np.uint32(i + 1)
    return x[0], x[1]


def fold_in(key: jax.Array, data: jax.Array) -> jax.Array:
    """`jax.random.fold_in(key, data)` for one typed key and one ``uint32`` datum."""
    if not _written_out(key):
        return jax.random.fold_in(key, data)
    k1, k2 = jax.random.key_data(key)
    # JAX folds in threefry(key, seed(data)), the seed being the pair (data >> 32, data).
    out = _hash(k1, k2, jnp.zeros((), jnp.uint32), jnp.asarray(data, jnp.uint32))
    return jax.random.wrap_key_data(jnp.stack(out), impl="threefry2x32")


def normal(key: jax.Array, dtype: DTypeLike = jnp.float32) -> jax.Array:
    """`jax.random.normal(key, (), dtype)`: one standard normal."""
    if not _written_out(key) or np.dtype(dtype) != np.float32:
        return jax.random.normal(key, (), dtype)
    k1, k2 = jax.random.key_data(key)
    zero = jnp.zeros((), jnp.uint32)
    b1, b2 = _hash(k1, k2, zero, zero)  # the counter of a scalar draw is 0
    # A scalar's 32 random bits: both words xor-ed with partitionable threefry (JAX's
    # default), the first word alone without it.
    bits = b1 ^ b2 if jax.config.jax_threefry_partitionable else b1
    # `jax.random.uniform` on [nextafter(-1, 0), 1): 23 random mantissa bits under the
    # exponent of 1.0, minus 1, scaled; then `normal` is sqrt(2) erfinv(u).
    lo = np.nextafter(np.float32(-1), np.float32(0), dtype=np.float32)
    hi = np.float32(1)
    one = np.array(1.0, np.float32).view(np.uint32)
    floats = jax.lax.bitcast_convert_type((bits >> np.uint32(9)) | one, jnp.float32)
    floats = floats - jnp.float32(1)
    u = jnp.maximum(jnp.float32(lo), floats * (jnp.float32(hi) - jnp.float32(lo)) + lo)
    return jnp.float32(np.sqrt(2)) * jax.lax.erf_inv(u)
