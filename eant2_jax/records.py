"""The records of a run: its individuals, its state after a generation, one record per
generation and what a run returns. Each is plain data with a strict JSON form
(`eant2_jax.jsonio`): the run directory's checkpoint and logs hold them
(`eant2_jax.checkpoint`), and a run resumed from them goes on exactly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .config import MAX_BUCKET
from .genome import MAX_ID, Genome
from .jsonio import as_float, typed_fields
from .pruning import PruneAttempt
from .tuning import Search

__all__ = [
    "RUN_DEPENDENT",
    "GenerationRecord",
    "Individual",
    "RunResult",
    "RunState",
    "check_key",
    "key_data",
    "key_from_data",
]


@dataclasses.dataclass(frozen=True)
class Individual:
    """A member of the population: its genome (with tuned weights) and its cost."""

    genome: Genome
    cost: float
    origin: str = "init"  # the operator that made it, or "init"
    # With EANT2Config.inherit_search: the final CMA-ES search of its tuning, on its genes.
    search: Search | None = dataclasses.field(default=None, compare=False, repr=False)

    def to_json(self) -> dict:
        d = {"genome": str(self.genome), "cost": self.cost, "origin": self.origin}
        if self.search is not None:
            d["search"] = self.search.to_json()
        return d

    @classmethod
    def from_json(cls, d: dict) -> Individual:
        if not isinstance(d, dict) or not isinstance(d.get("genome"), str):
            raise ValueError("an individual is not an object with a genome text")
        fields = {"genome", "cost", "origin", "search"}
        if not isinstance(d.get("origin", "init"), str) or set(d) - fields:
            raise ValueError(f"an individual has bad fields {sorted(d)}")
        genome = Genome.parse(d["genome"])
        search = None
        if "search" in d:
            search = Search.from_json(d["search"], genome.n_params, "an individual's search")
        return cls(genome, as_float(d.get("cost"), "cost"), d.get("origin", "init"), search)


@dataclasses.dataclass(frozen=True)
class RunState:
    """Everything needed to continue a run after a completed generation."""

    generation: int
    population: tuple[Individual, ...]
    next_id: int
    evaluations: int
    key: tuple[int, ...]  # raw key data of the run's PRNG key
    wall_s: float = 0.0
    # The padding bucket (neurons, genes, sweeps) the run has grown to (`grow_bucket`): the
    # default CMA-ES popsize follows it, so a resume must go on from it, not from scratch.
    # None in checkpoints written before it was recorded.
    bucket: tuple[int, int, int] | None = None

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["population"] = [ind.to_json() for ind in self.population]
        d["key"] = list(self.key)
        if self.bucket is None:
            del d["bucket"]
        else:
            d["bucket"] = list(self.bucket)
        return d

    @classmethod
    def from_json(cls, d: dict) -> RunState:
        """The state as `to_json` wrote it; a ValueError names a bad field."""
        if not isinstance(d, dict):
            raise ValueError("the state is not a JSON object")
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"the state has unknown field(s) {unknown}")
        # The limits of the configs and genomes: a checkpoint edited past them would build
        # programs or write ids that no later resume accepts (docs/reliability.md).
        for name, top in (("generation", MAX_ID), ("next_id", MAX_ID), ("evaluations", 2**63 - 1)):
            v = d.get(name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= top:
                raise ValueError(
                    f"the state's {name} must be an integer in [0, {top}], got {v!r:.40}"
                )
        pop = d.get("population")
        if not isinstance(pop, list) or not pop:
            raise ValueError("the state's population must be a non-empty list")
        return cls(
            generation=d["generation"],
            population=tuple(Individual.from_json(x) for x in pop),
            next_id=d["next_id"],
            evaluations=d["evaluations"],
            key=check_key(d.get("key"), "the state's key"),
            wall_s=as_float(d.get("wall_s", 0.0), "wall_s"),
            bucket=_check_bucket(d.get("bucket")),
        )

    def best(self) -> Individual:
        return self.population[0]

    def cost_stats(self) -> tuple[float | None, float | None]:
        """The population's cost mean and standard deviation (ddof 0) over its finite costs
        (None, None when none is finite)."""
        costs = np.array([ind.cost for ind in self.population], np.float64)
        costs = costs[np.isfinite(costs)]
        if not costs.size:
            return None, None
        return float(np.mean(costs)), float(np.std(costs))


@dataclasses.dataclass(frozen=True)
class GenerationRecord:
    """One completed generation, as the run directory's ``generations.jsonl`` holds it.

    Attributes:
      generation: its number (0: the initial population).
      best_cost, best_size, best_neurons, best_genome: the best individual after selection
        (size = number of genes = weights).
      mean_size: mean size of the population.
      evaluations: cost evaluations of the run so far.
      wall_s: wall time of the run so far; generation_s: of this generation.
      prune_attempts, prune_accepted: pruning attempts in this generation, and accepted ones.
      population: individuals kept; exploited: structures tuned in this generation.
      compiles, compile_s, cache_hits, cache_misses: this generation's XLA programs
        compiled (or loaded from the persistent cache), the seconds spent tracing, lowering
        and compiling them, and the persistent cache's hits and misses
        (`eant2_jax.programs.stats`; 0 in records written before they existed). Like the wall
        times they depend on the process, not on the run: ``RUN_DEPENDENT`` names them.
      generation_evaluations: cost evaluations spent in this generation (``evaluations``
        minus the previous record's); a progress rate divides those of its own process by
        its own time. None in records written before it existed.
      mean_cost, cost_std: the population's cost after selection, its mean and standard
        deviation (ddof 0, as neat-python's StatisticsReporter), over the individuals whose
        cost is finite (None if none is, and in records written before they existed).
      batch_fill: the share of the generation's exploitation batch that searched: its
        row-iterations in which a row ran a CMA-ES search, over all rows times the engine's
        iterations (`eant2_jax.strategy.batch_fill`). A lock-step group shares one batch
        and one fill. None where nothing was tuned, and in records written before it
        existed.
    """

    generation: int
    best_cost: float
    best_size: int
    mean_size: float
    best_neurons: int
    evaluations: int
    wall_s: float
    prune_attempts: int
    prune_accepted: int
    population: int
    exploited: int
    generation_s: float
    best_genome: str
    compiles: int = 0
    compile_s: float = 0.0
    cache_hits: int = 0
    cache_misses: int = 0
    generation_evaluations: int | None = None
    mean_cost: float | None = None
    cost_std: float | None = None
    batch_fill: float | None = None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> GenerationRecord:
        """The record as `to_json` wrote it; a ValueError names a bad field."""
        return cls(**typed_fields(cls, d, "a generation record"))


# The record fields that depend on the process and machine (timing, compilation), not on
# the run: two runs of one key and config agree on every other field.
RUN_DEPENDENT = ("wall_s", "generation_s", "compiles", "compile_s", "cache_hits", "cache_misses")


class RunResult(NamedTuple):
    """What `run` returns.

    Attributes:
      population: the final population, best first.
      best: the best genome.
      generations: one `GenerationRecord` per generation.
      pruning: one `PruneAttempt` per pruning attempt.
      solution: the network that passed ``solution_test`` (the run stopped there; it need
        not be the best by cost), or None.
    """

    population: list[Individual]
    best: Genome
    generations: list[GenerationRecord]
    pruning: list[PruneAttempt]
    solution: Individual | None = None


def key_data(key: jax.Array) -> tuple[int, ...]:
    """A PRNG key's raw data as integers (as checkpoints and ``config.json`` hold it)."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return tuple(int(k) for k in np.asarray(key, dtype=np.uint32).ravel())


def _check_bucket(data) -> tuple[int, int, int] | None:
    """A checkpoint's bucket: absent (None), or three integers in [1, MAX_BUCKET]."""
    if data is None:
        return None
    if not (
        isinstance(data, list)
        and len(data) == 3
        and all(
            isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_BUCKET for v in data
        )
    ):
        raise ValueError(
            f"the state's bucket must be [neurons, genes, sweeps] integers in [1, {MAX_BUCKET}], "
            f"got {data!r:.60}"
        )
    return tuple(data)


def check_key(data, what: str) -> tuple[int, ...]:
    """Raw key data as JSON holds it: a non-empty list of uint32 words."""
    if (
        not isinstance(data, list)
        or not 1 <= len(data) <= 8
        or not all(isinstance(k, int) and not isinstance(k, bool) for k in data)
        or not all(0 <= k < 2**32 for k in data)
    ):
        raise ValueError(f"{what} must be a list of 1 to 8 integers in [0, 2**32)")
    return tuple(data)


def key_from_data(data: Sequence[int]) -> jax.Array:
    """A typed PRNG key from its raw data (as stored in checkpoints and config.json)."""
    return jax.random.wrap_key_data(jnp.asarray(np.array(data, dtype=np.uint32)))
