"""The protocol's held-out cost (docs/protocol.md, section 1, endpoint 3): a champion's cost
on start poses that no run, and no choice of settings, has seen, drawn from a named key.

The servo task's own held-out set (`eant2_jax.tasks.servo`, NumPy generator ``[2009, 1]``)
was reported before the protocol; these poses are new: ``q = q* + U(-START_HALF_WIDTH,
START_HALF_WIDTH)`` with the uniforms from ``jax.random.key(7000)`` (batch ``r`` from
``fold_in(key, r)``), kept in order where every marker lies inside the image, as the task
draws its own sets. The cost is the task's own (`eant2_jax.tasks.servo.jit_cost`) on a copy
of the task whose training poses are these.
"""

from __future__ import annotations

import itertools

import jax
import numpy as np

__all__ = ["HELD_OUT_KEY", "fresh_servo_poses", "fresh_servo_task", "held_out_costs"]

HELD_OUT_KEY = 7000  # docs/protocol.md: the held-out poses' key, jax.random.key(7000)


def fresh_servo_poses(key: jax.Array, n: int = 1023) -> tuple[np.ndarray, np.ndarray]:
    """``(q [n, 3] rad, s [n, 5, 2])``: ``n`` start poses drawn from ``key`` and their marker
    images (host side, float64), by the task's rule (the module's docstring). The same key
    gives the same poses; a smaller ``n`` gives a prefix."""
    from ..tasks import servo_scene as sc

    half = np.asarray(sc.START_HALF_WIDTH, np.float64)

    def offsets():
        for batch in itertools.count():
            u = jax.random.uniform(jax.random.fold_in(key, batch), (1024, 3), minval=-1, maxval=1)
            yield from np.asarray(u, np.float64) * half

    return sc.poses_inside(offsets(), n)


def fresh_servo_task(task, key: jax.Array, n: int = 1023):
    """A copy of the servo ``task`` whose start poses are `fresh_servo_poses` (its mode,
    moves and activations unchanged)."""
    from ..tasks import servo_scene as sc

    q, s = fresh_servo_poses(key, n)
    goal = sc.arm_scene().goal[None]
    x = (s - goal).reshape(len(q), -1)
    return task.replace(
        q_start=jax.device_put(np.asarray(q, np.float32)),
        x_start=jax.device_put(np.asarray(x, np.float32)),
    )


def held_out_costs(task, nets, key: int = HELD_OUT_KEY) -> np.ndarray | None:
    """Costs ``[*batch]`` of ``nets`` on as many new start poses as ``task`` trains on (the
    paper's 1023), from ``jax.random.key(key)``; None for a task other than the servo task
    (it has no rule for new start states)."""
    from ..tasks.servo import Servo, jit_cost

    if not isinstance(task, Servo):
        return None
    fresh = fresh_servo_task(task, jax.random.key(key), int(task.q_start.shape[0]))
    return np.asarray(jit_cost(fresh, nets), np.float64)
