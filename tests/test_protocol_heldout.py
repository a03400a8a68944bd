"""The protocol's held-out cost (docs/protocol.md, section 1): new servo start poses from a
named key, drawn by the task's own rule, and the task's own cost on them."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from eant2_jax.app.heldout import fresh_servo_poses, fresh_servo_task, held_out_costs
from eant2_jax.compiler import networks
from eant2_jax.genome import Genome
from eant2_jax.tasks import servo_scene as sc


def test_fresh_poses_follow_the_tasks_rule_and_repeat_for_their_key():
    q, s = fresh_servo_poses(jax.random.key(7000), 40)
    arm = sc.arm_scene()
    assert q.shape == (40, 3) and s.shape == (40, 5, 2)
    assert np.all(np.abs(q - arm.q_goal) <= np.asarray(sc.START_HALF_WIDTH))
    # Every marker inside the image, recomputed with MuJoCo here.
    import mujoco

    d = mujoco.MjData(arm.mj)
    for qi, si in zip(q, s, strict=True):
        np.testing.assert_array_equal(sc.features_host(arm, d, qi), si)
        assert np.all(np.abs(si[:, 0]) < 1.0) and np.all(np.abs(si[:, 1]) < 0.75)
    q2, _ = fresh_servo_poses(jax.random.key(7000), 40)
    np.testing.assert_array_equal(q, q2)
    np.testing.assert_array_equal(fresh_servo_poses(jax.random.key(7000), 10)[0], q[:10])
    other, _ = fresh_servo_poses(jax.random.key(7001), 40)
    assert not np.any(np.all(other == q, axis=1))
    # Apart from the task's own training and held-out poses.
    for held in (False, True):
        known, _ = sc.start_poses(40, held_out=held)
        assert not np.any(np.all(np.isclose(known[:, None], q[None]), axis=-1))


@pytest.mark.slow
def test_the_held_out_cost_is_the_tasks_cost_on_the_new_poses():
    """The cost on the new poses is the task's: a task given the same poses as its held-out
    set scores the same as `held_out_costs` (the training poses swapped in by
    ``held_out()``), and a non-servo task has none."""
    from eant2_jax import tasks
    from eant2_jax.tasks.servo import jit_cost

    task = tasks.make("servo", n_starts=16)
    genomes = [Genome.parse("N0/2*1 I0*0.3 I1*-0.2 N1/1*1 I2*0.4 N2/1*1 I3*0.1")]
    nets = networks(genomes * 2, task.n_inputs)
    got = held_out_costs(task, nets)
    fresh = fresh_servo_task(task, jax.random.key(7000), 16)
    swapped = task.replace(q_test=fresh.q_start, x_test=fresh.x_start)
    want = np.asarray(swapped.generalisation(nets))
    np.testing.assert_array_equal(got, want)
    assert got.shape == (2,) and np.isfinite(got).all()
    assert not np.allclose(got, np.asarray(jit_cost(task, nets)))
    xor = [Genome.parse("N0/2*1 I0*1 I1*1")]
    assert held_out_costs(tasks.make("xor"), networks(xor, 2)) is None
