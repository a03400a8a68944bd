"""The visual servoing task (``eant2_jax.tasks.servo``) against hand computations and MuJoCo C.

References, all independent of the task's JAX code:

* the pinhole projection of the goal image and of one start pose, computed here from the
  arm's dimensions (SCARA forward kinematics by hand) and the camera constants;
* every move of a network, recomputed in NumPy float64: the network's dense step, the
  increments, the clipping, MuJoCo C's kinematics (``mj_kinematics``) and the cost;
* the image Jacobian of IBVS against central finite differences of MuJoCo C's kinematics.

Tolerances (float32 eps = 6e-8; image coordinates are O(1)):

* projection, hand vs MuJoCo C (both float64): ``1e-9``; the keyframe's goal angles are
  rounded to 1e-6 rad, which moves the goal image by up to 5e-6, hence ``1e-5`` where the
  hand computation assumes the exact goal pose.
* MJX float32 vs NumPy float64 costs: ``2e-5`` absolute: float32 rounding in the kinematics
  (angles ~1 rad, lengths ~0.5 m: ~1e-7 m) magnified by f / Z / 320 = 3.9 per metre, through
  two moves and a network of O(1) weights; largest seen 1.1e-7 (24 networks).
* zero controller vs the mean initial error: ``1e-6`` relative (the same data, float32 vs
  float64 rounding of a mean of 1023 distances; largest seen 8e-8).
* image Jacobian vs finite differences: ``1e-4`` of its largest entry (float32 products of
  O(1) terms against a float64 difference with truncation error ~h^2 = 1e-10).
* kinematic vs dynamic mode for IBVS: the servos end within ~1e-3 rad of their targets after
  0.3 s (arm.xml); 1e-3 rad at the camera's lever arms (0.3 to 0.6 m) is up to 0.6 mm, i.e.
  2.3e-3 normalised image units. Per start ``5e-3``, on the mean ``1e-3``, over the first
  256 start poses; largest seen 3.0e-3 and 3.2e-4 (all 1023 alike).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from compiles import count_compiles

from eant2_jax import tasks
from eant2_jax.kernels import network as kn
from eant2_jax.tasks import servo as sv

# The arm's dimensions as written in arm.xml (metres), for the hand computations.
SHOULDER = np.array([0.0, 0.0, 0.60])
L1, L2 = 0.35, 0.30
CAMERA_IN_WRIST = np.array([0.05, 0.0, -0.19])
OBJECT = np.array([0.56, 0.10, 0.005])
MARKERS_IN_OBJECT = np.array(
    [
        [0.075, 0.000, 0.005],
        [0.015, 0.055, 0.005],
        [-0.060, 0.035, 0.005],
        [-0.045, -0.045, 0.005],
        [0.030, -0.065, 0.005],
    ]
)
GOAL_DEPTH = 0.40  # camera at z = 0.41, marker faces at z = 0.01


@pytest.fixture(scope="module")
def task() -> sv.Servo:
    return tasks.make("servo")


@pytest.fixture(scope="module")
def sweep(task):
    return task.ibvs_sweep()


def hand_image(q: np.ndarray) -> np.ndarray:
    """``[5, 2]`` normalised image coordinates by hand: SCARA kinematics + pinhole."""
    q1, q2, q3 = q
    wrist = SHOULDER + np.array(
        [L1 * np.cos(q1) + L2 * np.cos(q1 + q2), L1 * np.sin(q1) + L2 * np.sin(q1 + q2), 0.0]
    )
    yaw = q1 + q2 + q3
    c, s = np.cos(yaw), np.sin(yaw)
    cam = wrist + np.array(
        [
            c * CAMERA_IN_WRIST[0] - s * CAMERA_IN_WRIST[1],
            s * CAMERA_IN_WRIST[0] + c * CAMERA_IN_WRIST[1],
            CAMERA_IN_WRIST[2],
        ]
    )
    rel = OBJECT + MARKERS_IN_OBJECT - cam
    # Camera x = world x rotated by yaw, camera y likewise; optical Y = -camera y, Z = depth.
    x_cam = c * rel[:, 0] + s * rel[:, 1]
    y_cam = -s * rel[:, 0] + c * rel[:, 1]
    depth = -rel[:, 2]
    u = 320.0 + 500.0 * x_cam / depth
    v = 240.0 + 500.0 * (-y_cam) / depth
    return np.stack([(u - 320.0) / 320.0, (v - 240.0) / 320.0], axis=-1)


# ----------------------------------------------------------------------------- options
def test_registry_and_interface(task):
    assert isinstance(task, sv.Servo)
    assert isinstance(task, tasks.Task)
    assert (task.n_inputs, task.n_outputs, task.n_starts) == (10, 3, 1023)
    assert (task.mode, task.moves_per_start, task.hidden, task.output) == (
        "kinematic",
        1,
        "tanh",
        "identity",
    )
    assert task.x_start.dtype == jnp.float32 and task.q_start.shape == (1023, 3)


@pytest.mark.parametrize(
    "options",
    [
        {"mode": "physical"},
        {"moves_per_start": 0},
        {"moves_per_start": 1.5},
        {"n_starts": True},
        {"n_starts": 0},
        {"substeps": -3},
        {"hidden": "softsign"},
        {"output": "step"},
        {"colour": "red"},
    ],
)
def test_bad_options(options):
    with pytest.raises(ValueError):
        tasks.make("servo", **options)


# --------------------------------------------------------------------- image and poses
def test_goal_image_by_hand(task):
    """At the goal the camera is 0.40 m above the plate's centre, axes aligned: marker k at
    offset (a, b) appears at u = 320 + 500 a / 0.4, v = 240 - 500 b / 0.4 pixels."""
    px = np.stack(
        [
            320 + 500 * MARKERS_IN_OBJECT[:, 0] / GOAL_DEPTH,
            240 - 500 * MARKERS_IN_OBJECT[:, 1] / GOAL_DEPTH,
        ],
        axis=-1,
    )
    assert px[0].tolist() == [413.75, 240.0]  # marker 0: 93.75 px right of the centre
    by_hand = (px - [320, 240]) / 320
    np.testing.assert_allclose(sv.arm_scene().goal, by_hand, atol=1e-5, rtol=0)
    np.testing.assert_allclose(np.asarray(task.goal), by_hand, atol=1e-5, rtol=0)
    np.testing.assert_allclose(hand_image(sv.arm_scene().q_goal), by_hand, atol=1e-5, rtol=0)


def test_one_start_pose_by_hand(task):
    q, s = sv.start_poses(1023)
    np.testing.assert_allclose(s[0], hand_image(q[0]), atol=1e-9, rtol=0)
    # The task's inputs: the same image minus the goal image, (u0, v0, ..., u4, v4), float32.
    x = (hand_image(q[0]) - hand_image(sv.arm_scene().q_goal)).reshape(10)
    np.testing.assert_allclose(np.asarray(task.x_start[0]), x, atol=1e-6, rtol=0)


@pytest.mark.parametrize("held_out", [False, True])
def test_start_poses(held_out):
    q, s = sv.start_poses(1023, held_out=held_out)
    assert q.shape == (1023, 3) and s.shape == (1023, 5, 2)
    # Every marker strictly inside the 640 x 480 image at every start.
    assert np.all(np.abs(s[..., 0]) < 1.0) and np.all(np.abs(s[..., 1]) < 0.75)
    # Inside the documented box around the goal pose, and spread over it.
    off = (q - sv.arm_scene().q_goal) / np.asarray(sv.START_HALF_WIDTH)
    assert np.all(np.abs(off) <= 1) and np.all(np.abs(off).max(axis=0) > 0.98)
    # Inputs of about [-1, 1].
    assert np.abs(s - sv.arm_scene().goal).max() < 1.0
    # Deterministic, and a smaller set is a prefix.
    np.testing.assert_array_equal(sv.start_poses(10, held_out=held_out)[0], q[:10])
    np.testing.assert_array_equal(sv.draw_start_poses.__wrapped__(5, held_out)[0], q[:5])


def test_training_and_held_out_sets_are_disjoint(task):
    a, b = sv.start_poses(1023)[0], sv.start_poses(1023, held_out=True)[0]
    gaps = np.abs(a[:, None, :] - b[None, :, :]).max(axis=-1)
    assert gaps.min() > 1e-6
    swapped = task.held_out()
    np.testing.assert_array_equal(np.asarray(swapped.q_start), np.asarray(task.q_test))
    np.testing.assert_array_equal(np.asarray(swapped.held_out().q_start), np.asarray(task.q_start))


# ------------------------------------------------------------------------- move costs
@pytest.mark.slow
def test_move_cost_penalties(task):
    goal = np.asarray(task.goal)
    inside = goal + 0.1
    assert float(task.move_cost(jnp.asarray(goal), jnp.zeros(3, bool))) == 0.0
    base = float(task.move_cost(jnp.asarray(inside), jnp.zeros(3, bool)))
    np.testing.assert_allclose(base, 0.1 * np.sqrt(2), rtol=1e-6)
    # One marker out on the right, one below the image; two joints at a limit.
    out = inside.copy()
    out[0, 0], out[1, 1] = 1.0, -0.8
    expect = np.linalg.norm(out - goal, axis=-1).mean() + 2 * sv.OUTSIDE_PENALTY
    np.testing.assert_allclose(
        float(task.move_cost(jnp.asarray(out), jnp.zeros(3, bool))), expect, rtol=1e-6
    )
    limits = jnp.asarray([True, False, True])
    np.testing.assert_allclose(
        float(task.move_cost(jnp.asarray(inside), limits)), base + 2 * sv.LIMIT_PENALTY, rtol=1e-6
    )


# -------------------------------------------------------------------------- baselines
@pytest.mark.slow
def test_zero_controller_cost_is_mean_initial_error(task, sweep):
    gains, costs = sweep
    assert gains[0] == 0.0
    _, s = sv.start_poses(1023)
    initial = np.linalg.norm(s - sv.arm_scene().goal, axis=-1).mean()
    np.testing.assert_allclose(costs[0], initial, rtol=1e-6)
    np.testing.assert_allclose(task.baselines()["zero"], initial, rtol=1e-6)


@pytest.mark.slow
def test_ibvs_reduces_the_error(task, sweep):
    """docs/tasks.md: zero 0.2797, IBVS 0.0594 at gain 0.95 (factor 4.7), gain 1 0.0603."""
    base = task.baselines()
    assert set(base) == {"zero", "ibvs", "ibvs_gain1"}
    assert base["zero"] / base["ibvs"] > 4.5
    assert base["ibvs"] <= base["ibvs_gain1"] < base["zero"] / 4
    assert task.ibvs_gain() == 0.95
    gains, costs = sweep
    assert costs[1:].min() == base["ibvs"]
    # Too small and too large gains are both worse: the optimum is inside the sweep.
    assert costs[1] > base["ibvs"] and costs[-1] > base["ibvs"]


@pytest.mark.slow
def test_image_jacobian_matches_finite_differences(task):
    arm = sv.arm_scene()
    d = mujoco.MjData(arm.mj)
    q = sv.start_poses(3)[0]
    jac = np.asarray(jax.jit(jax.vmap(task.image_jacobian))(jnp.asarray(q, jnp.float32)))
    h = 1e-5
    for i in range(3):
        fd = np.zeros((10, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            up = sv.features_host(arm, d, q[i] + e)
            down = sv.features_host(arm, d, q[i] - e)
            fd[:, j] = (up - down).reshape(10) / (2 * h)
        np.testing.assert_allclose(jac[i], fd, atol=1e-4 * np.abs(fd).max(), rtol=0)


# ------------------------------------------------------------------ physics modes
DYNAMIC_STARTS = 256  # start poses simulated in dynamic mode (the first of the task's)


@pytest.mark.slow
def test_kinematic_and_dynamic_modes_agree_for_ibvs(task, sweep):
    gain = task.ibvs_gain()
    gains = jnp.asarray([0.0, gain], jnp.float32)
    # The kinematic costs at gain 0 and the chosen gain, taken from the whole sweep's gains
    # (the sweep fixture's compiled program; each gain's row is computed on its own).
    swept = sweep[0]
    kin = np.asarray(sv.ibvs_start_costs(task, jnp.asarray(swept, jnp.float32)))
    # The dynamic mode on a prefix of the same start poses (each start's cost is its own).
    kin = kin[[swept.index(0.0), swept.index(gain)], :DYNAMIC_STARTS]
    dynamic = tasks.make("servo", mode="dynamic", n_starts=DYNAMIC_STARTS)
    dyn = np.asarray(sv.ibvs_start_costs(dynamic, gains))
    # Gain 0: the servos hold the arm at rest exactly where it is.
    np.testing.assert_allclose(dyn[0], kin[0], rtol=1e-6)
    np.testing.assert_allclose(dyn[1], kin[1], atol=5e-3, rtol=0)
    assert abs(dyn[1].mean() - kin[1].mean()) < 1e-3


def test_stripped_model_moves_like_the_full_model():
    """The task simulates arm.xml without its visual parts (MuJoCo C, float64): the camera
    pose and 60 servo steps from the same state are the same, bit for bit or nearly."""
    full, stripped = sv.arm_scene().mj, sv.stripped_model()
    assert stripped.ngeom == 0 and stripped.nsite == 1 and stripped.nbody == full.nbody - 1
    df, ds = mujoco.MjData(full), mujoco.MjData(stripped)
    cam_f = sv.arm_scene().camera_site
    cam_s = mujoco.mj_name2id(stripped, mujoco.mjtObj.mjOBJ_SITE, "camera")
    q, _ = sv.start_poses(4)
    for qi in q:
        for m, d in ((full, df), (stripped, ds)):
            mujoco.mj_resetData(m, d)
            d.qpos[:] = qi
            d.ctrl[:] = qi[::-1] * 0.1 + sv.arm_scene().q_goal * 0.9
            mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(ds.site_xpos[cam_s], df.site_xpos[cam_f], atol=1e-12)
        np.testing.assert_allclose(ds.site_xmat[cam_s], df.site_xmat[cam_f], atol=1e-12)
        for _ in range(60):  # the limits are far: the full model's constraints stay inactive
            mujoco.mj_step(full, df)
            mujoco.mj_step(stripped, ds)
        np.testing.assert_allclose(ds.qpos, df.qpos, atol=1e-9)
        np.testing.assert_allclose(ds.qvel, df.qvel, atol=1e-7)


def test_servos_stay_within_the_joint_ranges():
    """The task's dynamic model has no limit constraints: check, with MuJoCo C on the same
    model, that the largest move the task can command (MAX_STEP, from rest) onto a limit,
    for every combination of directions, ends within 2 mrad of the limits (seen: 0.7)."""
    arm = sv.arm_scene()
    mj = sv.stripped_model()
    d = mujoco.MjData(mj)
    step = sv.MAX_STEP_FRACTION * (arm.q_hi - arm.q_lo)
    worst = -np.inf
    for signs in itertools.product([-1.0, 1.0], repeat=3):
        target = np.where(np.asarray(signs) > 0, arm.q_hi, arm.q_lo)
        mujoco.mj_resetData(mj, d)
        d.qpos[:] = target - np.asarray(signs) * step
        d.ctrl[:] = target
        for _ in range(sv.SUBSTEPS):
            mujoco.mj_step(mj, d)
            worst = max(worst, float(np.max(np.maximum(d.qpos - arm.q_hi, arm.q_lo - d.qpos))))
    assert worst < 2e-3


# ------------------------------------------------------------- networks, jit and vmap
def random_nets(seed: int, batch: tuple[int, ...], hidden: int = 6, sweeps: int = 2):
    """Networks with ``hidden`` neuron slots (3 roots) and random weights; the first is all
    zeros (it never moves the arm)."""
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch))
    h = hidden
    w_ff = np.tril(rng.normal(scale=0.7, size=(n, h, h)), k=-1)
    w_in = rng.normal(scale=0.7, size=(n, h, 10))
    bias = rng.normal(scale=0.3, size=(n, h))
    w_rec = rng.normal(scale=0.5, size=(n, h, h))
    w_out = np.zeros((n, 3, h))
    roots = (h - 3, h - 2, h - 1)  # slots of the three output neurons
    for r, slot in enumerate(roots):
        w_out[:, r, slot] = rng.normal(size=n)
    for a in (w_ff, w_in, bias, w_rec, w_out):
        a[0] = 0.0
    is_root = np.zeros((n, h), bool)
    is_root[:, list(roots)] = True
    arrays = dict(
        w_in=w_in, bias=bias, w_ff=w_ff, w_rec=w_rec, w_out=w_out, is_root=is_root,
        neuron_mask=np.ones((n, h), bool),
    )  # fmt: skip
    nets = kn.Network(
        **{k: jnp.asarray(v.reshape(batch + v.shape[1:])) for k, v in arrays.items()},
        sweeps=sweeps,
    )
    return nets, arrays


def reference_cost(arrays: dict, i: int, task: sv.Servo, moves: int) -> float:
    """NumPy float64 cost of network ``i``: dense steps, increments, MuJoCo C kinematics."""
    arm = sv.arm_scene()
    d = mujoco.MjData(arm.mj)
    w = {k: np.asarray(v[i], np.float64) for k, v in arrays.items()}
    w_f32 = {k: v.astype(np.float32).astype(np.float64) for k, v in w.items()}
    step = sv.MAX_STEP_FRACTION * (arm.q_hi - arm.q_lo)
    q0s = np.asarray(task.q_start, np.float64)
    x0s = np.asarray(task.x_start, np.float64)
    total = 0.0
    for q, x in zip(q0s, x0s, strict=True):
        h = np.zeros(len(w["bias"]))
        start_cost = 0.0
        for _ in range(moves):
            base = w_f32["w_in"] @ x + w_f32["bias"] + w_f32["w_rec"] @ h
            h = np.zeros_like(base)
            for _ in range(2):
                a = base + w_f32["w_ff"] @ h
                h = np.where(w["is_root"], a, np.tanh(a))  # identity roots, tanh hidden
            y = w_f32["w_out"] @ h
            command = q + step * np.tanh(y)
            at_limit = (command <= arm.q_lo) | (command >= arm.q_hi)
            q = np.clip(command, arm.q_lo, arm.q_hi)
            s = sv.features_host(arm, d, q)
            outside = (np.abs(s[:, 0]) >= 1) | (np.abs(s[:, 1]) >= 0.75)
            start_cost += (
                np.linalg.norm(s - arm.goal, axis=-1).mean()
                + sv.OUTSIDE_PENALTY * outside.sum()
                + sv.LIMIT_PENALTY * at_limit.sum()
            )
            x = (s - arm.goal).reshape(10)
        total += start_cost / moves
    return total / len(q0s)


@pytest.mark.slow
def test_network_costs_under_jit_and_vmap_match_numpy():
    """Closed loop (2 moves per start, recurrent state carried) on 16 starts; a [2, 3] batch
    of networks (vmapped inside the cost) under jit; a second task built alike reuses the
    compiled program, and so does the held-out set."""
    task = tasks.make("servo", n_starts=16, moves_per_start=2)
    nets, arrays = random_nets(0, (2, 3))
    got = np.asarray(sv.jit_cost(task, nets))
    assert got.shape == (2, 3) and got.dtype == np.float32
    # The zero network: every move costs the initial error.
    _, s = sv.start_poses(16)
    initial = np.linalg.norm(s - sv.arm_scene().goal, axis=-1).mean()
    np.testing.assert_allclose(got[0, 0], initial, rtol=1e-6)
    for i in range(6):
        np.testing.assert_allclose(got.reshape(6)[i], reference_cost(arrays, i, task, 2), atol=2e-5)
    # Same options, new weights: the same compiled program.
    again = tasks.make("servo", n_starts=16, moves_per_start=2)
    other = random_nets(1, (2, 3))[0]
    with count_compiles() as c:
        assert np.all(np.isfinite(np.asarray(sv.jit_cost(again, other))))
        # The held-out poses: the same program, other poses, other costs.
        held = np.asarray(task.generalisation(nets))
    assert held.shape == (2, 3) and held[0, 0] != got[0, 0]
    assert c.count == 0


@pytest.mark.slow
def test_kinematics_is_scatter_free_and_mjx_is_left_as_it_was():
    """The kinematic cost has no float scatter that a GPU adds in any order (XLA's
    deterministic mode made one servo iteration 3.6x slower by sorting MJX's quaternion
    scatters); the quaternion built instead equals MJX's own to the bit; and MJX's function
    is back in place outside the task's code, also after nested uses."""
    from compiles import nondeterministic_scatters
    from mujoco.mjx._src import math as mjx_math

    from eant2_jax.tasks import servo_scene as scene

    found = scene.find_mjx_math()
    assert found is not None
    original = found[1]
    assert mjx_math.axis_angle_to_quat is original
    task = tasks.make("servo", n_starts=4)
    nets, _ = random_nets(0, (2,))
    assert nondeterministic_scatters(jax.make_jaxpr(task.cost)(None, nets)) == []
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(64, 3)).astype(np.float32)
    angles = rng.uniform(-7, 7, size=64).astype(np.float32)
    ours = jax.jit(jax.vmap(scene.axis_angle_to_quat))(axes, angles)
    theirs = jax.jit(jax.vmap(original))(axes, angles)
    np.testing.assert_array_equal(np.asarray(ours), np.asarray(theirs))
    with scene.mjx_numerics():
        with scene.mjx_numerics():
            assert mjx_math.axis_angle_to_quat is scene.axis_angle_to_quat
        assert mjx_math.axis_angle_to_quat is scene.axis_angle_to_quat
    assert mjx_math.axis_angle_to_quat is original
