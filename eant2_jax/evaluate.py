"""The public forward pass: many genomes, one compiled program per bucket."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from .compiler import compile_genomes
from .genome import Genome
from .kernels import network as kn

__all__ = ["as_genomes", "evaluate", "rollout_batch"]


def as_genomes(genomes: Genome | str | Sequence[Genome | str]) -> list[Genome]:
    """Accept one genome or a sequence of them, as `Genome` or text."""
    if isinstance(genomes, Genome | str):
        genomes = [genomes]
    out = []
    for g in genomes:
        if isinstance(g, str):
            g = Genome.parse(g)
        elif not isinstance(g, Genome):
            raise TypeError(f"expected a Genome or its text form, got {type(g).__name__}")
        out.append(g)
    if not out:
        raise ValueError("no genomes given")
    return out


@functools.partial(jax.jit, static_argnames=("hidden", "output"))
def rollout_batch(
    layout: kn.Layout, params: jax.Array, inputs: jax.Array, *, hidden: str, output: str
) -> jax.Array:
    """Run a batch of compiled networks over shared input streams.

    Args:
      layout: batched layout, leading dim ``G``.
      params: ``[G, P]`` parameter vectors.
      inputs: ``[T, M, n_in]`` M independent streams.
      hidden, output: activation names (static).

    Returns:
      ``[G, T, M, n_out]``.
    """

    def one(lay, p):
        net = kn.network(lay, p)
        run = functools.partial(kn.rollout, net, hidden=hidden, output=output)
        return jax.vmap(run, in_axes=1, out_axes=1)(inputs)

    return jax.vmap(one)(layout, params)


def evaluate(
    genomes: Genome | str | Sequence[Genome | str],
    inputs: ArrayLike,
    *,
    hidden: str = "tanh",
    output: str = "identity",
) -> jax.Array:
    """Evaluate genomes on input sequences.

    Genomes of different sizes are padded into one bucket (see `eant2_jax.compiler`),
    so a later call whose genomes fall in the same bucket, with inputs of the same shape,
    reuses the compiled program. The program does not grow with the genomes' depth (past 64
    sweeps a step loops over them), but each step of each stream costs about the depth
    times the neurons squared in multiply-adds (docs/genome.md, Deep networks).

    Args:
      genomes: a `Genome` (or its text) or a sequence of them, all with the same
        number of outputs.
      inputs: ``[T, M, n_in]``: T time steps of M independent streams, each stream with its
        own recurrent state (all zeros before the first step).
      hidden: activation of hidden neurons: a name of ``eant2_jax.kernels.activations``
        (tanh, sigmoid, relu, identity, sin, gauss, ... or one registered with
        ``eant2_jax.register_activation``).
      output: activation of root (output) neurons.

    Returns:
      ``float32[len(genomes), T, M, n_out]``.
    """
    kn.activation(hidden), kn.activation(output)  # clear error for unknown names
    genomes = as_genomes(genomes)
    x = np.asarray(inputs)
    if x.ndim != 3:
        raise ValueError(f"inputs must have shape [T, M, n_in], got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.number) or np.iscomplexobj(x):
        raise TypeError(f"inputs must be real numeric values, got dtype {x.dtype}")
    batch = compile_genomes(genomes, n_inputs=x.shape[2])
    ys = rollout_batch(
        batch.layout, batch.weights, jnp.asarray(x, jnp.float32), hidden=hidden, output=output
    )
    return ys[: batch.count]
