"""Bucket speculation: which padding bucket a run's batch grows into, and its program
compiled before the generation that needs it.

A generation's structures are padded to a bucket (`grow_bucket`); each new bucket is a new
engine program, seconds to tens of seconds to compile on an accelerator. Two guesses hide
that compilation behind work already going on:

* `compile_first_ahead`: generation 0's program, from shapes alone, before the run's key
  or engine state exist (its structure does not depend on the run's draws by default);
* `compile_next_bucket`: during a generation, the buckets the next one will likely grow
  into, found by dry explorations with throwaway generators (`next_bucket_guesses`).

A guess compiles exactly the program the generation that meets the bucket would compile,
so results never change; a wrong guess costs only its own compilation, and none is made
on a CPU (`eant2_jax.programs.ahead_enabled`).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING

import jax
import numpy as np

from .. import exploitation, programs, tuning
from ..compiler import GENE_FLOOR, NEURON_FLOOR, Bucket, bucket_size
from ..exploration import initial_genome, offspring
from ..genome import Genome
from ..tasks.base import Task

if TYPE_CHECKING:
    from ..config import EANT2Config

__all__ = [
    "GUESS_TRIES",
    "compile_first_ahead",
    "compile_next_bucket",
    "generation_rows",
    "grow_bucket",
    "next_bucket_guesses",
]

# Dry generations per guess (`next_bucket_guesses`).
GUESS_TRIES = 8


def grow_bucket(
    genomes: Sequence[Genome], current: Bucket | None, floor: Sequence[int] | None = None
) -> Bucket:
    """The bucket a generation compiles into: ``current`` while the genomes fit, else one
    with headroom, the smallest bucket for one more neuron, gene and sweep than they need
    (at least two sweeps: a first hidden neuron adds one) and at least ``floor``
    (`EANT2Config.min_bucket`: ``(neurons, genes, sweeps)``).

    Each new bucket is a new program to compile (seconds on a CPU, more on a GPU), while the
    padding costs little (a generation is latency-bound: docs/benchmarks.md). A structure's
    CMA-ES is independent of its padding except through the default popsize, which follows
    the gene bucket (`eant2_jax.tuning.popsize_for`; with ``exploit.width`` also the rows,
    which the configuration and a lock-step group's size fix: `generation_rows`); so the
    bucket is part of the checkpoint (`eant2_jax.records.RunState.bucket`) and a resumed
    run goes on with it."""
    neurons = max(g.n_neurons for g in genomes)
    genes = max(g.n_params for g in genomes)
    depth = max(g.depth() for g in genomes)
    # A series value holds a size iff it is at least the size (every bucket is one).
    if current is not None and (
        neurons <= current.neurons and genes <= current.genes and depth <= current.sweeps
    ):
        return current
    need = (neurons + 1, genes + 1, max(depth + 1, 2))
    if floor is not None:
        need = tuple(max(n, f) for n, f in zip(need, floor, strict=True))
    return Bucket(
        neurons=bucket_size(need[0], NEURON_FLOOR),
        genes=bucket_size(need[1], GENE_FLOOR),
        sweeps=bucket_size(need[2]),
    )


def generation_rows(config: EANT2Config) -> int:
    """Rows of every generation's batch of one run (offspring, and the parents with
    ``reexploit``): one program per bucket."""
    return (config.offspring or config.population) + (config.population if config.reexploit else 0)


def next_bucket_guesses(
    pools: Sequence[Sequence[Genome]],
    gen: int,
    n_inputs: int,
    config: EANT2Config,
    bucket: Bucket,
) -> list[tuple[Bucket, list[Genome]]]:
    """The buckets the batch will likely grow into next, guessed during generation ``gen``,
    and genomes that fill each.

    Among `GUESS_TRIES` dry generations (offspring of every pool in ``pools``: one per run
    of the batch, its current population and this generation's new structures; made with
    throwaway generators, so the runs' own draws are untouched), the most frequent bucket
    that outgrows ``bucket``, and the second most frequent if at least two tries grew into
    it; none if no try outgrew ``bucket``. Only a guess (selection and pruning decide the
    real parents): on a 6-generation XOR run (population 10, key 1) the first named 4 of
    6 new buckets. The second was added for `eant2 reproduce`: with the first alone, its
    covariance arm (a lock-step group of 200 structures) still waited for a new bucket's
    program in two generations on a GPU."""
    grown: dict[Bucket, list[Genome]] = {}
    votes: dict[Bucket, int] = {}
    for t in range(GUESS_TRIES):
        dry = []
        for i, pool in enumerate(pools):
            rng = np.random.default_rng([gen, t, i] if i else [gen, t])
            dry += offspring(rng, pool, n_inputs, 2**30, config)[0]
        b = grow_bucket(dry, bucket, config.min_bucket) if dry else bucket
        if b != bucket:
            grown.setdefault(b, dry)
            votes[b] = votes.get(b, 0) + 1
    ranked = sorted(votes, key=votes.get, reverse=True)[:2]  # ties: the first grown
    return [(b, grown[b]) for i, b in enumerate(ranked) if i == 0 or votes[b] >= 2]


def compile_next_bucket(
    pools: Sequence[Sequence[Genome]],
    gen: int,
    exp_key: jax.Array,
    task: Task,
    config: EANT2Config,
    bucket: Bucket,
    min_rows: int,
) -> threading.Thread | None:
    """On an accelerator, compile the engine programs of the guessed next buckets
    (`next_bucket_guesses`) for batches of ``min_rows`` rows in a background thread while
    generation ``gen`` runs (``exp_key``: its first run's exploitation key). Returns the
    thread, or None where nothing is compiled ahead (a CPU)."""
    if not programs.ahead_enabled():
        return None

    def work():
        try:
            init_key, run_key = jax.random.split(exp_key)
            for b, genomes in next_bucket_guesses(pools, gen, task.n_inputs, config, bucket):
                prep = tuning.prepare(genomes, task, key=init_key, config=config.exploit,
                                      bucket=b, min_rows=min_rows)  # fmt: skip
                exploitation.compile_ahead(prep.state, prep.batch.layout, task, key=run_key,
                                           config=config.exploit, tables=prep.tables)  # fmt: skip
        except Exception:  # noqa: BLE001 - a guess that fails costs nothing but itself
            return

    thread = threading.Thread(target=work, name="eant2-next-bucket", daemon=True)
    thread.start()
    programs.join_at_exit(thread)
    return thread


def compile_first_ahead(task: Task, key: jax.Array, config: EANT2Config, runs: int = 1) -> bool:
    """On an accelerator, start compiling generation 0's engine program at once, from
    shapes alone (`eant2_jax.tuning.compile_ahead`): the generation's keys, its engine start
    and their small programs then compile and run while it does, instead of before it
    (docs/benchmarks.md, "Cold start"). Only where generation 0's structure does not depend
    on the run's draws: minimal starts of full connectivity without initial mutations
    (the defaults); their weights are the only draws, and they do not shape the program.

    `eant2_jax.run` calls it first; a caller may call it sooner, before it has the run's
    key: ``key`` may be its shape (``jax.eval_shape(jax.random.key, seed)``), and the run
    then finds the compilation under way. ``runs``: the runs tuned in one batch (a
    lock-step group's, `eant2_jax.run_lockstep`). Returns whether a compilation was
    started; one that fails to start returns False (generation 0 then compiles its
    program as usual)."""
    if not programs.ahead_enabled():
        return False
    if config.init_mutations or config.init_connectivity < 1:
        return False
    try:
        rng = np.random.default_rng(0)  # weights only, see above
        genome = initial_genome(
            rng,
            task.n_inputs,
            task.n_outputs,
            connectivity=1.0,
            weight_scale=config.init_weight_scale,
            recurrent=config.init_recurrent,
        )
        bucket = grow_bucket([genome], None, config.min_bucket)
        # Generation 0's exploitation key as a shape (`eant2_jax.strategy`: the second of
        # split(fold_in(key, 0))); only its shape shapes the program.
        exp_key = jax.eval_shape(lambda k: jax.random.split(jax.random.fold_in(k, 0))[1], key)
        return tuning.compile_ahead(
            [genome], task, key=exp_key, config=config.exploit, bucket=bucket,
            min_rows=generation_rows(config) * runs,
        )  # fmt: skip
    except Exception:  # noqa: BLE001 - an ahead compile that fails costs nothing but itself
        return False
