"""LAPACK-backed matrix functions that are safe on several CPU devices: `eigh` and `solve`
of ONE matrix, with the same bits under ``vmap`` as jaxlib's batched kernels.

On a CPU backend with more than one device, a batch is handled one matrix at a time
(``lax.map``) instead of by jaxlib's batched LAPACK kernel. That kernel splits its batch over
XLA's CPU thread pool and waits for it from a thread of the same pool; when every device's
program holds a thread of the pool in such a wait (two devices on two cores), nothing runs
the batch and the process hangs (docs/reliability.md, "Several CPU devices"). LAPACK treats
each matrix of a batch alone, so both ways give the same bits (tests/test_distributed.py).
Elsewhere (one CPU device, GPUs) these are ``jnp.linalg.eigh`` and ``jnp.linalg.solve``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["eigh", "solve"]


def _one_at_a_time(fn: Callable) -> Callable:
    """``fn`` of one matrix (its arguments unbatched), mapped over a vmapped batch."""

    @jax.custom_batching.custom_vmap
    def single(*args):
        return fn(*args)

    @single.def_vmap
    def batched(axis_size, in_batched, *args):
        out_batched = jax.tree.map(lambda _: any(in_batched), jax.eval_shape(fn, *args))
        if not any(in_batched):
            return single(*args), out_batched
        args = [a if b else jnp.broadcast_to(a, (axis_size, *a.shape))
                for a, b in zip(args, in_batched, strict=True)]  # fmt: skip
        return jax.lax.map(lambda xs: single(*xs), tuple(args)), out_batched

    return single


def _several_cpu_devices() -> bool:
    return jax.default_backend() == "cpu" and jax.device_count() > 1


_eigh = _one_at_a_time(lambda a: tuple(jnp.linalg.eigh(a)))
_solve = _one_at_a_time(jnp.linalg.solve)


def eigh(a: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``jnp.linalg.eigh`` of ONE symmetric matrix ``[n, n]``: ``(eigenvalues, vectors)``."""
    return _eigh(a) if _several_cpu_devices() else tuple(jnp.linalg.eigh(a))


def solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """``jnp.linalg.solve(a, b)`` of ONE matrix ``a`` ``[n, n]`` and ``b`` ``[n, k]``."""
    return _solve(a, b) if _several_cpu_devices() else jnp.linalg.solve(a, b)
