"""The task protocol: what a network is scored on.

A task knows its numbers of inputs and outputs, names the activations its networks use, and
turns a batch of compiled networks (any leading batch shape) plus a PRNG key into a batch of
costs (lower is better), as a pure JAX function. Tasks are frozen pytrees, so they are passed
INTO jit-compiled functions as arguments: two tasks of the same kind and shapes share one
compiled program, and a task's data is never baked into a program as a constant.

`check_task` checks the protocol before anything runs, and `check_costs` checks
what ``cost`` returns while it is traced; each mistake is one `TaskError` line.
``docs/tasks-custom.md`` walks through writing a task.
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from ..kernels.network import Network, activation

__all__ = [
    "ReportingTask",
    "Task",
    "TaskError",
    "check_costs",
    "check_task",
    "map_networks",
    "solved_cost",
]

PROTOCOL = ("n_inputs", "n_outputs", "hidden", "output", "cost")
_GUIDE = "see docs/tasks-custom.md"


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


# Optional attributes of a task (not part of the protocol's isinstance check):
#   noisy: bool — True when costs depend on the key (random starts, noise). Then
#   eant2_jax.tuning.tune re-evaluates each tuned network on fresh episodes (a key no
#   CMA-ES iteration used) and reports THAT cost, not the best draw seen during the search.
#   default_width: Mapping[str, int] — networks per engine batch where ExploitConfig sets
#   neither width nor popsize, by jax.default_backend() (episodic tasks: {"gpu": 1024});
#   a backend it does not name takes the default popsize (`eant2_jax.tuning.popsize_for`).
#   solved_cost: float | None — the cost at or below which the task counts as solved
#   (XOR, dpv, environments whose return defines it; `solved_cost`). A run with no
#   target_cost of its own stops there (EANT2Config.stop_when_solved). None: unknown.


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


class TaskError(TypeError, ValueError):
    """A task that does not follow the protocol (one line naming what is wrong).

    Both a ``TypeError`` (a wrong kind of object) and a ``ValueError`` (a bad value), so
    callers catching either see it.
    """


def _name(task: Any) -> str:
    return type(task).__name__


def check_task(task: Any, genomes: Sequence[Any] = (), *, what: str | None = None) -> None:
    """Check that ``task`` follows the `Task` protocol (and fits ``genomes``).

    Args:
      task: the object to check.
      genomes: optional genomes that must fit it (outputs equal, inputs within).
      what: how to name the task in messages (default: its type's name).

    Raises:
      TaskError: one line naming the first mistake.
    """
    what = what or f"task {_name(task)}"
    missing = [m for m in PROTOCOL if not hasattr(task, m)]
    if missing:
        raise TaskError(
            f"expected a task: {what} has no {', '.join(missing)} (a task needs n_inputs, "
            f"n_outputs, hidden, output and cost(key, nets); {_GUIDE})"
        )
    for field in ("n_inputs", "n_outputs"):
        n = getattr(task, field)
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
            raise TaskError(f"{what}: {field} must be an int >= 1 (a static size), got {n!r}")
    for field in ("hidden", "output"):
        name = getattr(task, field)
        if not isinstance(name, str):
            raise TaskError(f"{what}: {field} must be an activation name, got {name!r}")
        try:
            activation(name)
        except ValueError as e:
            raise TaskError(f"{what}: {field}: {e}") from None
    if not callable(task.cost):
        raise TaskError(f"{what}: cost must be a method cost(key, nets)")
    try:
        inspect.signature(task.cost).bind(None, None)
    except TypeError:
        raise TaskError(
            f"{what}: cost must take (key, nets); its signature is {inspect.signature(task.cost)}"
        ) from None
    except ValueError:  # no signature to read (a builtin): the call will tell
        pass
    noisy = getattr(task, "noisy", False)
    if not isinstance(noisy, bool | np.bool_):
        raise TaskError(f"{what}: noisy must be True or False, got {noisy!r}")
    width = getattr(task, "default_width", {})
    if not isinstance(width, Mapping) or not all(
        isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 1
        for k, v in width.items()
    ):
        raise TaskError(f"{what}: default_width must map backend names to widths of at least 1, "
                        f"got {width!r:.60}")  # fmt: skip
    solved = getattr(task, "solved_cost", None)
    if solved is not None and (
        isinstance(solved, bool)
        or not isinstance(solved, numbers.Real)
        or not np.isfinite(float(solved))
    ):
        raise TaskError(f"{what}: solved_cost must be a finite number or None, got {solved!r:.60}")
    leaves = jax.tree.leaves(task)
    if len(leaves) == 1 and leaves[0] is task:
        raise TaskError(
            f"{what} is not a JAX pytree: declare its class with @eant2_jax.pytree.dataclass "
            f"(sizes and names as pytree.field(pytree_node=False)); {_GUIDE}"
        )
    for leaf in leaves:
        if not isinstance(leaf, jax.Array | np.ndarray | np.generic | numbers.Number):
            raise TaskError(
                f"{what}: a field holds a {type(leaf).__name__}, which cannot enter a jit-"
                f"compiled function: make it an array or a static field "
                f"(pytree.field(pytree_node=False))"
            )
    for i, g in enumerate(genomes):
        if g.n_outputs != task.n_outputs:
            raise ValueError(
                f"genome {i} has {g.n_outputs} outputs but the task expects {task.n_outputs}"
            )
        if g.n_inputs > task.n_inputs:
            raise ValueError(
                f"genome {i} reads input {g.n_inputs - 1} but the task has {task.n_inputs} inputs"
            )


def solved_cost(task: Any) -> float | None:
    """The task's solved level (its optional ``solved_cost``), a float, or None when the
    task defines none (`check_task` has checked it)."""
    level = getattr(task, "solved_cost", None)
    return None if level is None else float(level)


def check_costs(task: Any, costs: Any, batch: tuple[int, ...]) -> jax.Array:
    """Check, while tracing, what ``task.cost`` returned for networks of shape ``batch``.

    Returns:
      ``costs`` as an array ``[*batch]``.

    Raises:
      TaskError: not one floating-point cost per network.
    """
    try:
        c = jnp.asarray(costs)
    except TypeError:
        raise TaskError(
            f"task {_name(task)}: cost returned a {type(costs).__name__}, not an array of costs"
        ) from None
    if c.shape != tuple(batch):
        raise TaskError(
            f"task {_name(task)}: cost returned shape {c.shape} for networks of batch shape "
            f"{tuple(batch)}; it must return one cost per network (use map_networks)"
        )
    if not jnp.issubdtype(c.dtype, jnp.floating):
        raise TaskError(
            f"task {_name(task)}: cost returned {c.dtype} costs; return floats "
            f"(e.g. cost.astype(jnp.float32))"
        )
    return c
