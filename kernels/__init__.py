"""Pure-JAX kernels of eant2_jax, importable as ``eant2_jax.kernels``.

Each kernel is written for ONE example and batched by the caller with ``jax.vmap``. The
modules here import nothing from the rest of the package, so other JAX code can use them
alone.
"""
