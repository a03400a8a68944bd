"""A check the environment adapters' tests share (gymnax, brax): a batch of networks gets
one finite cost each, and a second task built alike compiles nothing new."""

from __future__ import annotations

import jax
import numpy as np
from compiles import count_compiles

from eant2_jax import tasks
from eant2_jax.compiler import networks
from eant2_jax.exploration import initial_genome

_cost = jax.jit(lambda task, key, nets: task.cost(key, nets))


def batch_costs(spec: str, options: dict, n_in: int, n_out: int):
    """``(task, nets [2, 3], cost [2, 3])`` of six random minimal networks on
    ``tasks.make(spec, **options)``, after the checks above."""
    task = tasks.make(spec, **options)
    assert (task.n_inputs, task.n_outputs) == (n_in, n_out)
    rng = np.random.default_rng(0)
    genomes = [initial_genome(rng, n_in, n_out, weight_scale=0.5) for _ in range(6)]
    nets = jax.tree.map(lambda a: a.reshape(2, 3, *a.shape[1:]), networks(genomes, n_in))
    cost = np.asarray(_cost(task, jax.random.key(0), nets))
    assert cost.shape == (2, 3) and np.all(np.isfinite(cost))
    again = tasks.make(spec, **options)
    with count_compiles() as c:
        _cost(again, jax.random.key(1), nets)
    assert c.count == 0
    return task, nets, cost
