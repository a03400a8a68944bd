"""The servo task's scene: camera, arm, markers, start poses and the MuJoCo/MJX models.

Everything here is fixed data or host-side set-up; `eant2_jax.tasks.servo` builds the
batched task on it. Every constant is documented in that module's docstring and in
``docs/tasks.md``.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import threading
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ..kernels import kinematics as kin

if TYPE_CHECKING:
    from mujoco import mjx

# MJX itself is imported only where its physics runs (`_mjx_model`, the dynamic mode): the
# kinematic mode computes the arm's pose with eant2_jax.kernels.kinematics, and MJX's import
# (trimesh, scipy, its warp probe) is a cost of every process's start.

ARM_XML = Path(__file__).with_name("arm.xml")

# ----------------------------------------------------------------------------- constants
FOCAL_PX = 500.0  # focal length, pixels (both axes)
IMAGE_SIZE = (640, 480)  # width, height, pixels
PRINCIPAL_POINT = (320.0, 240.0)  # pixels
NORM_PX = 320.0  # pixels per normalised image unit: half the image width
HALF_EXTENT = (IMAGE_SIZE[0] / 2 / NORM_PX, IMAGE_SIZE[1] / 2 / NORM_PX)  # (1.0, 0.75)
N_MARKERS = 5
START_HALF_WIDTH = (0.2, 0.3, 0.4)  # rad, half-widths of the uniform start box around q*
MAX_STEP_FRACTION = 0.1  # largest joint increment of one move, as a fraction of the range
OUTSIDE_PENALTY = 0.1  # added per marker outside the image after the move
LIMIT_PENALTY = 0.1  # added per joint whose command reached or passed its range
SUBSTEPS = 60  # mjx.step calls per move in dynamic mode (x 5 ms = 0.3 s)
SEED = 2009  # start poses: np.random.default_rng([SEED, 0]) training, [SEED, 1] held out
MODES = ("kinematic", "dynamic")
# Gains tried by Servo.baselines() for image-based visual servoing (the best one is reported).
IBVS_GAINS = tuple(round(0.4 + 0.05 * i, 2) for i in range(25))  # 0.40, 0.45, ..., 1.60

_CAMERA_SITE = "camera"
_CAMERA_BODY = "wrist"  # the body the camera is fixed to (for the arm Jacobian)
_MARKER_SITES = tuple(f"marker{k}" for k in range(N_MARKERS))
# Optical frame (x right, y down, z forward) from MuJoCo's camera frame (x right, y up,
# looking along -z).
_OPTICAL = np.diag([1.0, -1.0, -1.0])


# ----------------------------------------------------------------------------- projection
def project(cam_pos, cam_mat, points):
    """Normalised image coordinates of world points seen by the pinhole camera.

    Works on NumPy (float64, host) and JAX arrays alike; written for ONE camera.

    Args:
      cam_pos: ``[3]`` optical centre in the world frame.
      cam_mat: ``[3, 3]`` camera frame in the world frame (columns: MuJoCo camera axes x
        right, y up, -z viewing direction; ``site_xmat`` reshaped).
      points: ``[K, 3]`` world points (in front of the camera).

    Returns:
      ``[K, 2]``: ``((u - 320) / 320, (v - 240) / 320)`` with ``u = 320 + 500 X / Z`` and
      ``v = 240 + 500 Y / Z`` in the optical frame (X right, Y down, Z forward).
    """
    rows = tuple(kin.components(r) for r in cam_mat)
    image = project_components(kin.components(cam_pos), rows, points)
    return stack_image(image, np if isinstance(points, np.ndarray) else jnp)


def stack_image(image: list[tuple], xp=jnp):
    """``[K, 2]`` from `project_components`'s ``[(u_k, v_k)]`` (``xp``: NumPy or JAX)."""
    return xp.stack([xp.stack(uv) for uv in image])


def project_components(cam_pos, cam_rows, points) -> list[tuple]:
    """`project` on components: ``[(u_k, v_k)]`` of the ``K`` points, from the optical centre's
    3 components and the camera frame's rows (`eant2_jax.kernels.kinematics.site_pose`), so
    that batched under ``jax.vmap`` the projection fuses with the kinematics before it."""
    scale = FOCAL_PX / NORM_PX
    image = []
    for k in range(points.shape[0]):
        rel = [points[k, i] - cam_pos[i] for i in range(3)]
        # Camera-frame coordinates rel @ cam_mat, as sums of products: no matrix unit (TF32
        # on GPUs) is involved.
        pc = [rel[0] * cam_rows[0][j] + rel[1] * cam_rows[1][j] + rel[2] * cam_rows[2][j]
              for j in range(3)]  # fmt: skip
        x, y, z = pc[0], -pc[1], -pc[2]
        image.append((scale * x / z, scale * y / z))
    return image


def _outside(s):
    """``bool[K]`` markers outside the image, from ``[K, 2]`` normalised coordinates."""
    return outside_image(s[:, 0], s[:, 1])


def outside_image(u, v):
    """Whether a marker at normalised coordinates ``(u, v)`` lies outside the image."""
    return (abs(u) >= HALF_EXTENT[0]) | (abs(v) >= HALF_EXTENT[1])


# ``mjx._src.math.axis_angle_to_quat`` without a scatter: the same values, bit for bit.
#
# MJX writes ``jnp.insert(axis * s, 0, c)``, which JAX lowers to a scatter. Batched over the
# millions of arm poses of a servo iteration, XLA's deterministic GPU mode
# (``--xla_gpu_deterministic_ops``, on by default in the ``eant2`` command line) expands each
# such scatter into a sort, which made a servo iteration several times slower. A
# concatenation of
# the same numbers is no scatter, and deterministic by construction.
axis_angle_to_quat = kin.axis_angle_to_quat


# Why a patch: the scatter sits inside MJX's forward kinematics (``smooth.kinematics`` ->
# ``math.axis_angle_to_quat``; also ``math.quat_integrate``), which offers no hook. It is
# applied only while this module's own MJX code is traced (`mjx_numerics`), reference-
# counted so that concurrent runs in threads nest, and it returns equal values to the last
# bit (tests/test_servo.py checks both against MJX's own function), so other MJX code traced
# meanwhile by another thread computes exactly what it would have.
_PATCH_LOCK = threading.Lock()
_PATCH_DEPTH = 0


@functools.cache
def find_mjx_math():
    """MJX's math module and its own ``axis_angle_to_quat``, or None (read once, at first
    use: importing MJX is left to the code that runs it)."""
    from . import mjx_quiet  # noqa: F401  (drop MJX's lines about an absent warp)

    try:
        from mujoco.mjx._src import math as mjx_math
    except ImportError:  # another MJX layout: run MJX's code as it is
        return None
    original = getattr(mjx_math, "axis_angle_to_quat", None)
    return (mjx_math, original) if callable(original) else None


@contextlib.contextmanager
def _scatter_free_mjx():
    global _PATCH_DEPTH
    found = find_mjx_math()
    if found is None:
        yield
        return
    mjx_math, original = found
    with _PATCH_LOCK:
        _PATCH_DEPTH += 1
        mjx_math.axis_angle_to_quat = axis_angle_to_quat
    try:
        yield
    finally:
        with _PATCH_LOCK:
            _PATCH_DEPTH -= 1
            if not _PATCH_DEPTH:
                mjx_math.axis_angle_to_quat = original


@contextlib.contextmanager
def mjx_numerics():
    """The numerics MJX code runs under here.

    MJX relies on implicit rank promotion internally, which this project's tests turn into an
    error for its own code (tests/conftest.py); its small float32 products must not use
    TF32 on GPUs (1e-3 relative error), so that GPU and CPU runs score alike; and its
    quaternion of a hinge angle is built without a scatter (`axis_angle_to_quat`).
    """
    with (
        jax.numpy_rank_promotion("allow"),
        jax.default_matmul_precision("highest"),
        _scatter_free_mjx(),
    ):
        yield


# ------------------------------------------------------------------------ the arm (host)
class _Arm(NamedTuple):
    """Host-side facts read once from ``arm.xml`` (float64)."""

    mj: mujoco.MjModel
    camera_site: int
    marker_sites: tuple[int, ...]
    q_goal: np.ndarray  # [3]
    q_lo: np.ndarray  # [3]
    q_hi: np.ndarray  # [3]
    markers: np.ndarray  # [5, 3] world positions
    goal: np.ndarray  # [5, 2] normalised image coordinates at the goal pose


@functools.cache
def arm_scene() -> _Arm:
    mj = mujoco.MjModel.from_xml_path(str(ARM_XML))
    site = functools.partial(mujoco.mj_name2id, mj, mujoco.mjtObj.mjOBJ_SITE)
    cam = site(_CAMERA_SITE)
    markers = tuple(site(n) for n in _MARKER_SITES)
    q_goal = np.array(mj.key("goal").qpos, dtype=np.float64)
    d = mujoco.MjData(mj)
    d.qpos[:] = q_goal
    mujoco.mj_kinematics(mj, d)
    points = np.array(d.site_xpos[list(markers)])
    goal = project(d.site_xpos[cam].copy(), d.site_xmat[cam].reshape(3, 3).copy(), points)
    return _Arm(
        mj=mj,
        camera_site=cam,
        marker_sites=markers,
        q_goal=q_goal,
        q_lo=np.array(mj.jnt_range[:, 0]),
        q_hi=np.array(mj.jnt_range[:, 1]),
        markers=points,
        goal=goal,
    )


def features_host(arm: _Arm, d: mujoco.MjData, q: np.ndarray) -> np.ndarray:
    """``[5, 2]`` normalised marker coordinates at joint angles ``q`` (MuJoCo C, float64)."""
    d.qpos[:] = q
    mujoco.mj_kinematics(arm.mj, d)
    c = arm.camera_site
    return project(d.site_xpos[c].copy(), d.site_xmat[c].reshape(3, 3).copy(), arm.markers)


def poses_inside(offsets, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(q [n, 3], s [n, 5, 2])``: the first ``n`` poses ``q* + offset`` (``offsets``: an
    iterator of ``[3]`` offsets in radians) at which every marker lies inside the image, with
    their marker images (host side, float64): the task's rule for start poses."""
    arm = arm_scene()
    d = mujoco.MjData(arm.mj)
    qs, ss = [], []
    for offset in offsets:
        if len(qs) == n:
            break
        q = arm.q_goal + offset
        s = features_host(arm, d, q)
        if not np.any(_outside(s)):
            qs.append(q)
            ss.append(s)
    return np.stack(qs), np.stack(ss)


@functools.cache
def draw_start_poses(n: int, held_out: bool) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng([SEED, int(held_out)])
    half = np.asarray(START_HALF_WIDTH)
    q, s = poses_inside((rng.uniform(-half, half) for _ in itertools.count()), n)
    q.flags.writeable = False
    s.flags.writeable = False
    return q, s


def start_poses(n_starts: int = 1023, *, held_out: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The task's start poses and their marker images (host side, float64, read-only).

    Draws ``q = q* + U(-START_HALF_WIDTH, START_HALF_WIDTH)`` from
    ``np.random.default_rng([SEED, 0])`` (``[SEED, 1]`` if ``held_out``) and keeps the first
    ``n_starts`` poses at which every marker lies inside the image. A smaller ``n_starts``
    gives a prefix of a larger one.

    Returns:
      ``(q [n_starts, 3] rad, s [n_starts, 5, 2] normalised image coordinates)``.
    """
    return draw_start_poses(int(n_starts), bool(held_out))


# ------------------------------------------------------------------------------ the task


def stripped_model() -> mujoco.MjModel:
    """``arm.xml`` with only what the task simulates: the arm's bodies, joints, servos and
    camera site.

    Removed: every geom (all visual only and massless: the links' masses and inertias are
    given explicitly), the fixed object with its marker sites (the markers' world positions are
    task data), the MuJoCo camera and the light. Kinematics and dynamics are unchanged
    (tests/test_servo.py compares both with the full model); MJX has fewer bodies and sites to
    carry through every kinematics call.

    The joint limit *constraints* are switched off (``mjDSBL_LIMIT``): the servo targets are
    clamped to the joint ranges and the servos are critically damped, so the limits are never
    passed by more than about 1 mrad (tested), and without constraints a step has no constraint
    rows and no solver to run.
    """
    spec = mujoco.MjSpec.from_file(str(ARM_XML))
    for geom in list(spec.geoms):
        spec.delete(geom)
    for site in list(spec.sites):
        if site.name != _CAMERA_SITE:
            spec.delete(site)
    for element in [*spec.cameras, *spec.lights, spec.body("object")]:
        spec.delete(element)
    mj = spec.compile()
    mj.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT
    return mj


@functools.cache
def stripped_arm() -> tuple[mujoco.MjModel, int, int]:
    """`stripped_model`, its camera site id and the id of the body carrying the camera."""
    mj = stripped_model()
    site = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, _CAMERA_SITE)
    body = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, _CAMERA_BODY)
    return mj, site, body


@functools.cache
def _mjx_model() -> tuple[mjx.Model, int, int]:
    """The task's MJX model, its camera site id and the id of the body carrying the camera."""
    from .mjx_quiet import mjx

    mj, site, body = stripped_arm()
    return mjx.put_model(mj), site, body
