"""The task protocol: what a network is scored on.

A task knows its numbers of inputs and outputs, names the activations its networks use, and
turns a batch of compiled networks (any leading batch shape) plus a PRNG key into a batch of
costs (lower is better), as a pure JAX function. Tasks are frozen pytrees, so they are passed
INTO jit-compiled functions as arguments: two tasks of the same kind and shapes share one
compiled program, and a task's data is never baked into a program as a constant.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol, runtime_checkable

import jax

from ..kernels.network import Network

__all__ = ["ReportingTask", "Task", "map_networks"]


@runtime_checkable
class Task(Protocol):
    """What the exploitation engine needs of a task."""

    @property
    def n_inputs(self) -> int: ...

    @property
    def n_outputs(self) -> int: ...

    @property
    def hidden(self) -> str: ...

    @property
    def output(self) -> str: ...

    def cost(self, key: jax.Array, nets: Network) -> jax.Array:
        """Costs ``[*batch]`` of networks with leading batch shape ``[*batch]``.

        The same key is used for every network of the call (common random numbers), so
        candidates of one CMA-ES iteration are ranked on the same draw.
        """
        ...


@runtime_checkable
class ReportingTask(Task, Protocol):
    """A task that can also report on its own terms (optional; the servo task does).

    ``eant2 reproduce`` and `eant2_jax.app.experiments.reproduce` add both to their
    report when the task has them.
    """

    def baselines(self) -> dict[str, float]:
        """Costs of reference controllers by the task's own cost, by name (host side)."""
        ...

    def generalisation(self, nets: Network) -> jax.Array:
        """Costs ``[*batch]`` of ``nets`` on held-out cases (not seen during evolution)."""
        ...


def map_networks(fn: Callable[[Network], jax.Array], nets: Network) -> jax.Array:
    """Apply a one-network function over any leading batch shape of ``nets``.

    Args:
      fn: maps ONE network to a scalar (or any array).
      nets: networks with leading batch shape ``[*batch]`` (read off ``nets.bias``).

    Returns:
      ``fn``'s results stacked as ``[*batch, ...]``.
    """
    batch = nets.bias.shape[:-1]
    for _ in batch:
        fn = jax.vmap(fn)
    return fn(nets)
