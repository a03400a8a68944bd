"""Step 7 of `eant2_jax.tuning.tune` on a noisy task: the tuned networks scored again on
fresh draws of the task's cost (the best cost seen during a search is the best of many
draws, an optimistic estimate), the distribution mean scored too, and the lower kept
(``ExploitConfig.recommend``, ``ExploitConfig.rescore``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import programs
from .compiler import compile_genomes, network_batch
from .genome import Genome
from .pruning import prune_genome
from .tasks.base import check_costs

__all__ = ["Rescorer", "cost_batch", "cost_draws", "fresh_cost_call", "rescore"]


def rescore(genomes, tuned, costs, evaluations, mean, mask, solution, config, rescorer):
    """`tune`'s step 7 on a noisy task: each structure's candidates (its best point, and
    with ``config.recommend`` != "best" its distribution mean) scored on ``config.rescore``
    fresh draws of the task's cost, and the one to keep: ``(tuned, costs, evaluations,
    picked)``. The network that passed a solution test stays as it is (only re-scored)."""
    cands: list[tuple[int, str, Genome]] = []
    for i, g in enumerate(genomes):
        has_mean = mean is not None and i != solution and np.isfinite(costs[i])
        if config.recommend != "mean" or not has_mean:
            cands.append((i, "best", tuned[i]))
        if has_mean:
            n = g.n_params
            cands.append((i, "mean", prune_genome(g, mask[i, :n], mean[i, :n])))
    fresh = rescorer([c[2] for c in cands])
    tuned, evaluations = list(tuned), list(evaluations)
    new_costs = [float("inf")] * len(genomes)
    picked = ["best"] * len(genomes)
    seen: set[int] = set()
    for (i, which, g), f in zip(cands, fresh, strict=True):
        evaluations[i] += config.rescore
        f = float(f) if np.isfinite(costs[i]) and np.isfinite(f) else float("inf")
        if i not in seen or f < new_costs[i]:  # the lower fresh cost; a tie keeps the best
            tuned[i], new_costs[i], picked[i] = g, f, which
        seen.add(i)
    return tuned, new_costs, evaluations, picked


class Rescorer:
    """The program that scores tuned networks on fresh episodes (`tune`'s step 7).

    Its inputs' shapes are known before the engine runs: the engine's bucket, and a row
    count fixed by the engine's (twice it when the mean is scored too), so the program is
    compiled once per bucket, not per generation. On an accelerator it is compiled in a
    background thread while the engine runs, off the critical path (a brax episode program
    takes seconds to compile): `eant2_jax.programs.ahead`. Calling it waits for that
    compilation and scores a list of genomes: ``float64[len(genomes)]``.
    """

    def __init__(self, genomes, task, key, config, *, rows, bucket, pad_count):
        self._task, self._key = task, key
        self._rescore = config.rescore
        per_row = 1 if config.recommend == "best" else 2
        self._compile_args = dict(bucket=bucket, min_rows=rows * per_row, pad_count=pad_count)
        self.ahead = None  # the program compiled ahead (`eant2_jax.programs.Program`)
        self.used_ahead = False  # whether the program compiled ahead was the one called
        if programs.ahead_enabled():
            self.ahead = programs.ahead(*self._inputs(genomes))

    def _inputs(self, genomes):
        """The program and its arguments for ``genomes``."""
        return fresh_cost_call(genomes, self._task, self._key, self._rescore, **self._compile_args)

    def __call__(self, genomes) -> np.ndarray:
        fn, args = self._inputs(genomes)
        if self.ahead is None:
            costs = fn(*args)
        else:  # falls back to jit's own path for other shapes than foreseen
            fallbacks = self.ahead.fallbacks
            costs = self.ahead(*args)
            self.used_ahead = self.ahead.fallbacks == fallbacks
        return np.asarray(costs, np.float64)[: len(genomes)]


def fresh_cost_call(genomes, task, key, draws: int, **compile_args):
    """``(program, args)`` that score ``genomes`` on ``draws`` fresh draws of the task's
    cost (`tune`'s step 7): ``program(*args)`` is ``float[rows]``, the mean over the draws.
    ``compile_args`` go to `eant2_jax.compiler.compile_genomes`."""
    batch = compile_genomes(genomes, task.n_inputs, **compile_args)
    # A key no CMA-ES iteration used (those fold the iteration number into run_key).
    fresh_key = jax.random.split(key, 3)[2]
    if draws == 1:  # one draw: the key itself, as runs before `rescore` drew it
        fn, keys = cost_batch, fresh_key
    else:
        fn, keys = cost_draws, jax.random.split(fresh_key, draws)
    return fn, (batch.layout, batch.weights, task, keys)


@jax.jit
def cost_draws(layout, weights, task, keys):
    """The mean cost over ``keys`` (one draw of the task's episodes each), all in one
    batch."""
    nets = network_batch(layout, weights)
    costs = jax.vmap(lambda k: task.cost(k, nets))(keys)
    return check_costs(task, jnp.mean(costs, axis=0), weights.shape[:1])


@jax.jit
def cost_batch(layout, weights, task, key):
    """The task's cost of each network of a compiled batch, one draw with ``key``:
    ``float[rows]``."""
    return check_costs(task, task.cost(key, network_batch(layout, weights)), weights.shape[:1])
