"""Supervised regression: mean squared error over a data set (the smallest useful task)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from .. import pytree
from ..kernels import network as kn
from .base import map_networks

__all__ = ["XOR_SOLVED", "Regression", "regression", "xor"]


@pytree.dataclass
class Regression:
    """Mean squared error of the network outputs against targets.

    Attributes:
      inputs: ``[T, M, n_in]`` M independent sequences of T steps (T = 1 for plain data).
      targets: ``[T, M, n_out]``.
      hidden, output: activation names (static).
      solved_cost: the mean squared error at or below which the task counts as solved, or
        None (static; a run stops there unless told otherwise, `eant2_jax.EANT2Config`'s
        ``stop_when_solved``).
    """

    inputs: jax.Array
    targets: jax.Array
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="identity")
    solved_cost: float | None = pytree.field(pytree_node=False, default=None)

    @property
    def n_inputs(self) -> int:
        return self.inputs.shape[-1]

    @property
    def n_outputs(self) -> int:
        return self.targets.shape[-1]

    def predict(self, net: kn.Network) -> jax.Array:
        """Outputs ``[T, M, n_out]`` of ONE network on the task's inputs."""
        run = functools.partial(kn.rollout, net, hidden=self.hidden, output=self.output)
        return jax.vmap(run, in_axes=1, out_axes=1)(self.inputs)

    def cost(self, key: jax.Array, nets: kn.Network) -> jax.Array:
        """Mean squared error ``[*batch]`` (the key is unused: the task is deterministic)."""
        del key

        def one(net):
            return jnp.mean(jnp.square(self.predict(net) - self.targets))

        return map_networks(one, nets)


def regression(
    inputs: ArrayLike,
    targets: ArrayLike,
    *,
    hidden: str = "tanh",
    output: str = "identity",
    solved_cost: float | None = None,
) -> Regression:
    """A regression task from data.

    Args:
      inputs: ``[N, n_in]`` examples (each one step), or ``[T, M, n_in]`` sequences.
      targets: ``[N, n_out]`` or ``[T, M, n_out]`` to match.
      hidden: activation name of hidden neurons.
      output: activation name of output neurons.
      solved_cost: the mean squared error that solves the task (a run stops there by
        default), or None (no known level).

    Returns:
      The `Regression` task.
    """
    kn.activation(hidden), kn.activation(output)
    x = np.asarray(inputs, dtype=np.float32)
    y = np.asarray(targets, dtype=np.float32)
    if x.ndim == 2:
        x = x[None]
    if y.ndim == 2:
        y = y[None]
    if x.ndim != 3 or y.ndim != 3:
        raise ValueError(
            f"regression: inputs and targets must be [N, d] or [T, M, d]; "
            f"got {np.shape(inputs)} and {np.shape(targets)}"
        )
    if x.shape[:2] != y.shape[:2]:
        raise ValueError(
            f"regression: inputs {x.shape} and targets {y.shape} differ in their leading dims"
        )
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError("regression: empty data set")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError("regression: inputs and targets must be finite")
    if solved_cost is not None:
        if isinstance(solved_cost, bool) or not isinstance(solved_cost, int | float):
            raise ValueError(f"regression: solved_cost must be a number, got {solved_cost!r:.60}")
        if not (np.isfinite(solved_cost) and solved_cost >= 0):
            raise ValueError(f"regression: solved_cost must be >= 0 and finite, got {solved_cost}")
        solved_cost = float(solved_cost)
    return Regression(
        jnp.asarray(x), jnp.asarray(y), hidden=hidden, output=output, solved_cost=solved_cost
    )


# XOR is solved when every output is on the right side of 0.5. A mean squared error of at
# most 0.04 over the four patterns bounds each squared error by 4 * 0.04, each error by 0.4.
XOR_SOLVED = 0.04


def xor(*, hidden: str = "tanh", output: str = "identity") -> Regression:
    """XOR: 2 inputs, 1 output, the four patterns; solved when every output is on the right
    side of 0.5, which a cost (mean squared error) of at most ``XOR_SOLVED`` = 0.04
    guarantees: the task's ``solved_cost``."""
    x = [[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]]
    y = [[0.0], [1.0], [1.0], [0.0]]
    return regression(x, y, hidden=hidden, output=output, solved_cost=XOR_SOLVED)
