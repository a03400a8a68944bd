"""Gradient fine-tuning: an optax optimiser polishes the weights of many structures at once.

EANT2 tunes weights with CMA-ES (paper III.A), which needs nothing but costs. Where a task's
cost is differentiable in the weights (a regression such as XOR, the kinematic servo task),
gradient descent can polish what CMA-ES found, or replace it. This module runs any optax
``GradientTransformation`` on the same padded batch CMA-ES tunes
(`eant2_jax.compiler.compile_genomes`): structures of different sizes in one bucket, ONE
compiled program for all of them, ``jax.value_and_grad`` of the task's cost through the
compiled networks (`eant2_jax.kernels.network`'s differentiable path).

The rules, as tested (tests/test_finetune.py):

* a row's gradient is the gradient of its own cost only (the batch's costs are independent,
  so the gradient of their sum is each cost's gradient in its own row);
* padding genes get a zero gradient and a zero update: their weights stay exactly 0;
* the optimiser runs once per structure (``vmap`` over its ``init`` and ``update``), so
  transformations that look at the whole parameter vector (``clip_by_global_norm``)
  see one structure's genes, and a batch gives what each structure alone would;
* a structure whose cost or gradient is not finite at a step skips that step (its weights
  and optimiser state stay as they were);
* the result is the best point seen (every step evaluates the current weights; the point
  after the last update is evaluated too), so fine-tuning never returns a worse network
  than it was given on a task whose cost does not depend on the key;
* step ``t`` draws the task's key ``fold_in(key, t)``: the same key, optimiser and steps
  give the same weights to the bit.

Structures keep their genes (nothing is pruned here): a genome that CMA-ES pruned comes in
with its genes already dropped. docs/finetune.md shows where to call `finetune` in a driver
of one's own (after `eant2_jax.strategy.exploit`) and what it was measured to gain.
"""

from __future__ import annotations

import functools
import math
import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .compiler import Bucket, compile_genomes, network_batch
from .evaluate import as_genomes
from .genome import Genome
from .kernels.network import Layout, Network
from .tasks.base import Task, check_costs, check_task

__all__ = [
    "DEFAULT_LEARNING_RATE",
    "FineTuned",
    "State",
    "default_optimizer",
    "score",
    "finetune",
    "init",
    "run_chunk",
    "value_and_grad",
]

DEFAULT_LEARNING_RATE = 1e-2


@functools.cache
def default_optimizer() -> optax.GradientTransformation:
    """``optax.adam(DEFAULT_LEARNING_RATE)``, one object for the process: the optimiser is
    part of the compiled program's cache key, and ``optax.adam(...)`` builds new functions
    at each call (pass the same object again to reuse a program)."""
    return optax.adam(DEFAULT_LEARNING_RATE)


class State(NamedTuple):
    """The fine-tuning state of a batch of ``G`` structures with ``P`` gene slots.

    Attributes:
      weights: ``[G, P]`` current weights; 0 on padding genes (and stays 0).
      opt_state: the optimiser's state, one per row (leaves with a leading ``G``).
      best_weights: ``[G, P]`` the weights of the lowest cost seen.
      best_cost: ``[G]`` that cost (inf until a finite cost is seen).
      start_cost: ``[G]`` the cost of the weights the state was made with (NaN before the
        first step).
      step: ``int32[]`` steps taken.
    """

    weights: jax.Array
    opt_state: Any
    best_weights: jax.Array
    best_cost: jax.Array
    start_cost: jax.Array
    step: jax.Array


def plain_networks(layout: Layout, weights: jax.Array) -> Network:
    """The networks ``[G]`` of a compiled batch with plain dense products (``reads=None``).

    `eant2_jax.kernels.network.step` keeps a non-finite value away from the neurons that do
    not read it (its non-finite rule); with finite values the plain products give the same
    sums. Differentiated, the rule's program is much larger to compile (its products are
    written out term by term), and where a value is not finite the gradient is not usable
    anyway (that row skips the step). So costs here equal the task's own
    (`eant2_jax.cost`) wherever they are finite, up to the rounding of another program.
    """
    return network_batch(layout, weights).replace(reads=None)


def value_and_grad(
    layout: Layout, weights: jax.Array, task: Task, key: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """The task's cost of each row of a compiled batch and its gradient in the row's weights.

    Args:
      layout: batched layout ``[G]`` (`eant2_jax.compiler.CompiledBatch.layout`).
      weights: ``[G, P]`` weights in gene order.
      task: a task whose cost is differentiable in the weights.
      key: the task's key for this evaluation.

    Returns:
      ``(costs [G], grads [G, P])``; ``grads`` is exactly 0 on padding genes.
    """

    def total(w):
        costs = check_costs(task, task.cost(key, plain_networks(layout, w)), w.shape[:1])
        # Rows are independent: d(sum)/d(row i) is row i's own cost gradient.
        return jnp.sum(costs), costs

    (_, costs), grads = jax.value_and_grad(total, has_aux=True)(weights)
    return costs, jnp.where(layout.gene_mask, grads, jnp.zeros_like(grads))


def init(weights: jax.Array, optimizer: optax.GradientTransformation) -> State:
    """The state before the first step: the optimiser's state of each row.

    Args:
      weights: ``[G, P]`` start weights (0 on padding).
      optimizer: the optax transformation.
    """
    rows = weights.shape[0]
    inf = jnp.full((rows,), jnp.inf, weights.dtype)
    return State(
        weights=weights,
        opt_state=jax.vmap(optimizer.init)(weights),
        best_weights=weights,
        best_cost=inf,
        start_cost=jnp.full((rows,), jnp.nan, weights.dtype),
        step=jnp.zeros((), jnp.int32),
    )


def _rows(ok: jax.Array, new: Any, old: Any) -> Any:
    """``new`` where ``ok`` (one flag per row), else ``old``, leaf by leaf."""

    def pick(a, b):
        return jnp.where(ok.reshape(ok.shape + (1,) * (a.ndim - 1)), a, b)

    return jax.tree.map(pick, new, old)


def _seen(st: State, costs: jax.Array) -> State:
    """``st`` with ``costs`` (of ``st.weights``) taken into the best point and start cost."""
    better = costs < st.best_cost  # False for NaN
    return st._replace(
        best_weights=_rows(better, st.weights, st.best_weights),
        best_cost=jnp.where(better, costs, st.best_cost),
        start_cost=jnp.where(st.step == 0, costs, st.start_cost),
    )


def _step(st: State, layout: Layout, task: Task, key: jax.Array, optimizer) -> tuple:
    """One step: evaluate the current weights (cost and gradient), keep the best, update."""
    costs, grads = value_and_grad(layout, st.weights, task, jax.random.fold_in(key, st.step))
    st = _seen(st, costs)
    ok = jnp.isfinite(costs) & jnp.all(jnp.isfinite(grads), axis=1)
    grads = jnp.where(ok[:, None], grads, jnp.zeros_like(grads))
    updates, opt_state = jax.vmap(optimizer.update)(grads, st.opt_state, st.weights)
    updates = jnp.where(layout.gene_mask & ok[:, None], updates, jnp.zeros_like(updates))
    weights = optax.apply_updates(st.weights, updates)
    opt_state = _rows(ok, opt_state, st.opt_state)
    return st._replace(weights=weights, opt_state=opt_state, step=st.step + 1), costs


@functools.partial(jax.jit, static_argnames=("optimizer", "steps"))
def run_chunk(
    st: State,
    layout: Layout,
    task: Task,
    key: jax.Array,
    *,
    optimizer: optax.GradientTransformation,
    steps: int,
) -> tuple[State, jax.Array]:
    """``steps`` optimiser steps of every row, as one compiled ``lax.scan``.

    Args:
      st: from `init` or an earlier chunk.
      layout: the batch's layout ``[G]``.
      task: the task (a pytree argument: its data is not baked into the program).
      key: the run's key; step ``t`` evaluates with ``fold_in(key, t)``.
      optimizer: the optax transformation `init` was called with (static: part of the
        program's cache key, by identity).
      steps: steps in this chunk (static).

    Returns:
      ``(state, costs [steps, G])``: the cost of each row before each step's update.
    """

    def body(s, _):
        return _step(s, layout, task, key, optimizer)

    return jax.lax.scan(body, st, None, length=steps)


@jax.jit
def score(st: State, layout: Layout, task: Task, key: jax.Array) -> State:
    """The current weights evaluated (key ``fold_in(key, step)``) and taken into the best
    point: the point after a chunk's last update has not been evaluated yet."""
    costs = check_costs(
        task,
        task.cost(jax.random.fold_in(key, st.step), plain_networks(layout, st.weights)),
        st.weights.shape[:1],
    )
    return _seen(st, costs)


class FineTuned(NamedTuple):
    """What `finetune` returns, in the order of the genomes given.

    Attributes:
      genomes: each structure with the weights of the lowest cost seen (unchanged where no
        cost was finite).
      costs: those costs (inf where none was finite).
      start_costs: the cost of each genome as given.
      history: ``float[steps, len(genomes)]`` the cost before each step's update.
    """

    genomes: list[Genome]
    costs: list[float]
    start_costs: list[float]
    history: np.ndarray


def finetune(
    genomes: Genome | str | Sequence[Genome | str],
    task: Task,
    *,
    key: jax.Array,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 200,
    chunk: int | None = None,
    bucket: Bucket | None = None,
    min_rows: int = 1,
) -> FineTuned:
    """Polish the weights of structures by gradient descent on the task's cost, all at once.

    Args:
      genomes: the structures with their start weights (e.g. `eant2_jax.tune`'s result).
      task: a task whose cost is differentiable in the weights (regression, XOR, the
        kinematic servo task). A cost that is flat almost everywhere (an episode's return
        of a discrete controller) gives zero gradients and nothing moves.
      key: PRNG key; step ``t`` evaluates the task with ``fold_in(key, t)``.
      optimizer: an optax ``GradientTransformation`` (default `default_optimizer`, Adam
        with learning rate `DEFAULT_LEARNING_RATE`).
      steps: optimiser steps (each one cost-and-gradient evaluation per structure).
      chunk: steps per compiled call (default ``steps``: one call).
      bucket: pad to these sizes (default the smallest that fits).
      min_rows: pad the batch to at least this many rows (one program for several calls).

    Returns:
      `FineTuned`.
    """
    genomes = as_genomes(genomes)
    optimizer = default_optimizer() if optimizer is None else optimizer
    if not (
        callable(getattr(optimizer, "init", None)) and callable(getattr(optimizer, "update", None))
    ):
        raise TypeError(
            f"finetune: optimizer must be an optax GradientTransformation (init and update), "
            f"got {type(optimizer).__name__}"
        )
    chunk = steps if chunk is None else chunk
    for name, value in (("steps", steps), ("chunk", chunk)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
            raise ValueError(f"finetune: {name} must be an integer >= 1, got {value!r}")
    check_task(task, genomes)
    batch = compile_genomes(genomes, task.n_inputs, bucket=bucket, min_rows=min_rows)
    st = init(batch.weights, optimizer)
    history, done = [], 0
    while done < steps:
        n = min(chunk, steps - done)
        st, costs = run_chunk(st, batch.layout, task, key, optimizer=optimizer, steps=n)
        history.append(np.asarray(costs)[:, : batch.count])
        done += n
    st = score(st, batch.layout, task, key)
    best_w = np.asarray(st.best_weights, np.float64)
    best_c = np.asarray(st.best_cost, np.float64)
    out, costs = [], []
    for i, g in enumerate(genomes):
        finite = math.isfinite(best_c[i])
        out.append(g.with_weights(best_w[i, : g.n_params]) if finite else g)
        costs.append(float(best_c[i]) if finite else math.inf)
    start = [float(c) for c in np.asarray(st.start_cost, np.float64)[: batch.count]]
    return FineTuned(out, costs, start, np.concatenate(history).astype(np.float64))
