"""Generations to a target for a batch of seeds, shared by the CMA-ES reference tests."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def evals_to_target(step, init_state, seeds, target, max_gens):
    """Generations until best-so-far < target, per seed (-1 if not reached); traceable."""

    def one(seed):
        def cond(c):
            return (c[2] < 0) & (c[1] < max_gens)

        def body(c):
            state, g, hit, key = c
            key, sub = jax.random.split(key)
            state, best = step(state, sub)
            hit = jnp.where((hit < 0) & (best < target), g + 1, hit)
            return state, g + 1, hit, key

        return jax.lax.while_loop(cond, body, (init_state, 0, -1, jax.random.key(seed)))[2]

    return jax.vmap(one)(seeds)
