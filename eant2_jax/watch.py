"""The solution test of a search (`eant2_jax.tuning.tune`'s ``solution_test``): the
engine's ``halt`` between chunks of iterations."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from . import distributed
from . import exploitation as ex
from .genome import Genome
from .pruning import prune_genome

__all__ = ["Watch"]


class Watch:
    """The ``halt`` of `exploitation.run` that tests each structure's best network whenever
    it is one not tested yet (after each chunk of iterations; a rejected pruning attempt
    restores an earlier best) and halts the search at the first that passes ``test``, in
    batch order."""

    def __init__(self, genomes: Sequence[Genome], test: Callable[[Genome], bool]):
        self.genomes, self.test = genomes, test
        self.tested: list[set[bytes]] = [set() for _ in genomes]
        self.found: tuple[int, Genome, float] | None = None

    def __call__(self, st: ex.ExploitState) -> bool:
        best_x, best_cost, mask = distributed.gather((st.cma.best_x, st.cma.best_cost, st.cma.mask))
        best_x, best_cost = np.asarray(best_x, np.float64), np.asarray(best_cost, np.float64)
        mask = np.asarray(mask)
        for i, g in enumerate(self.genomes):
            n = g.n_params
            seen = best_x[i, :n].tobytes() + mask[i, :n].tobytes()
            if not np.isfinite(best_cost[i]) or seen in self.tested[i]:
                continue
            self.tested[i].add(seen)
            network = prune_genome(g, mask[i, :n], best_x[i, :n])
            if self.test(network):
                self.found = (i, network, float(best_cost[i]))
                return True
        return False
