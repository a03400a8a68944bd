"""A batch's spare rows as restarts (``ExploitConfig.spare_rows``; docs/algorithm.md, "Spare
rows").

A batch holds more rows than structures wherever ``min_rows`` or the bucket series pads it
(a run pads every generation to the rows of its largest, so that one program serves them
all: `eant2_jax.programs.guesses.generation_rows`). An idle padding row costs a device about
what a live one does. With ``spare_rows="restarts"`` `eant2_jax.tuning.tune` gives each such
row another independent CMA-ES search of one of the batch's structures:

* **Which structure.** Row ``j`` searches structure ``j % count`` (``count`` structures;
  round robin in input order), from the row's own start key (the key the padding row would
  have had: the structures' own rows are the searches they get without restarts) and from
  the structure's warm start, if it has one.
* **What comes back.** One result per structure: the search with the lowest final cost
  (on a noisy task the cost on fresh episodes, `eant2_jax.tuning.tune` step 7; ties go to
  the lower row, so to the structure's own), with that search's stop reason, pruning
  attempts and search distribution, and the evaluations of all its searches together.
  ``Tuned.history`` and ``Tuned.state`` keep every row.
* **Not** the rows that only round a batch up to a multiple of a mesh's devices: those stay
  idle, so that a mesh changes placement only, never the searches.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from .tuning import Tuned

__all__ = ["best_of", "spread"]


def spread(
    genomes: Sequence[Any], start: Sequence[Any] | None, rows: int
) -> tuple[list[Any], list[Any] | None]:
    """The genomes (and warm starts) of a batch of ``rows`` rows whose spare rows search
    again: row ``j`` holds genome ``j % len(genomes)``."""
    count = len(genomes)
    genomes = [genomes[j % count] for j in range(max(rows, count))]
    if start is not None:
        start = [start[j % count] for j in range(len(genomes))]
    return genomes, start


def best_of(tuned: Tuned, count: int) -> Tuned:
    """A `eant2_jax.tuning.Tuned` of ``count`` structures from one of the rows `spread`
    made: each structure's search of the lowest cost, with every search's evaluations."""
    rows = len(tuned.genomes)
    costs = np.asarray(tuned.costs, np.float64)
    costs = np.where(np.isnan(costs), np.inf, costs)
    pick = [i + count * int(np.argmin(costs[i::count])) for i in range(count)]
    solution = tuned.solution
    if solution is not None:  # the network that passed the test is its structure's result
        pick[solution % count], solution = solution, solution % count
    owner = {j: i for i, j in enumerate(pick)}
    spent = np.asarray(tuned.evaluations, np.int64)
    return dataclasses.replace(
        tuned,
        genomes=[tuned.genomes[j] for j in pick],
        costs=[tuned.costs[j] for j in pick],
        evaluations=[int(spent[i:rows:count].sum()) for i in range(count)],
        stop_reasons=[tuned.stop_reasons[j] for j in pick],
        pruning=[
            dataclasses.replace(r, structure=owner[r.structure])
            for r in tuned.pruning
            if r.structure in owner
        ],
        search_costs=[tuned.search_costs[j] for j in pick],
        solution=solution,
        searches=None if tuned.searches is None else [tuned.searches[j] for j in pick],
        picked=None if tuned.picked is None else [tuned.picked[j] for j in pick],
    )
