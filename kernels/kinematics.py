"""Forward kinematics of a serial chain of hinge joints, as MJX computes it, in a few ops.

``mjx.kinematics`` walks a general body tree (`mujoco.mjx._src.scan.body_tree`): for a
3-link arm it traces about 1,700 small jitted helpers (half of tracing the servo task's
program), gathers and scatters every level's bodies into the model-wide arrays, and brings
in MJX's import (with trimesh and scipy). When a task needs only the
pose of one site on a chain of hinges, the same arithmetic written straight along the chain
is a handful of elementwise operations that XLA fuses whole.

The formulas are MJX's, in MJX's order (``smooth.kinematics`` with ``math.rotate``,
``math.quat_mul``, ``math.axis_angle_to_quat`` and ``support.local_to_global``), on scalar
components: a vector is a tuple of its 3 components, a quaternion ``(w, x, y, z)`` of 4, a
matrix a tuple of rows. Batched with ``jax.vmap``, every component is one array of the batch
and the whole walk is elementwise, with no stacking, slicing or small products in between,
so XLA fuses it into a few kernels (``python -m bench servo`` measures the task's moves
against ``mjx.kinematics``). MJX's two dot products
per rotation are written as sums, so a pose equals ``mjx.kinematics``'s to float32 rounding
(tests/test_kinematics.py: within 6e-7 + 2e-6 relative on random joint angles and random
chains, and against MuJoCo C in float64), not always to the last bit on a CPU, where XLA's
dot rounds its own way.

Written for ONE configuration ``q``; batch with ``jax.vmap``. This module imports nothing
from the rest of eant2_jax (nor MuJoCo, but for `Chain.from_model`, which reads a
``mujoco.MjModel``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import pytree

__all__ = [
    "Chain",
    "ChainPose",
    "components",
    "forward",
    "quat_mul",
    "quat_to_mat",
    "rotate",
    "site_pose",
]

_HINGE = 3  # mujoco.mjtJoint.mjJNT_HINGE

Vec = tuple  # of 3 components (scalars, or arrays of one batch)
Quat = tuple  # of 4 components, (w, x, y, z)


def components(a: Any) -> tuple:
    """The components of a vector ``[k]`` (JAX or NumPy), a tuple of ``k`` scalars."""
    return tuple(a[..., i] for i in range(a.shape[-1]))


def _rotate(vec: Vec, quat: Quat) -> Vec:
    """``vec`` rotated by the unit quaternion ``quat`` (MJX's formula, on components)."""
    s, u = quat[0], quat[1:]
    uv = u[0] * vec[0] + u[1] * vec[1] + u[2] * vec[2]
    uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
    cross = (u[1] * vec[2] - u[2] * vec[1], u[2] * vec[0] - u[0] * vec[2],
             u[0] * vec[1] - u[1] * vec[0])  # fmt: skip
    ss, s2 = s * s - uu, 2 * s
    return tuple(2 * (uv * u[i]) + ss * vec[i] + s2 * cross[i] for i in range(3))


def _quat_mul(u: Quat, v: Quat) -> Quat:
    """The quaternion product ``u * v`` (MJX's formula, on components)."""
    return (
        u[0] * v[0] - u[1] * v[1] - u[2] * v[2] - u[3] * v[3],
        u[0] * v[1] + u[1] * v[0] + u[2] * v[3] - u[3] * v[2],
        u[0] * v[2] - u[1] * v[3] + u[2] * v[0] + u[3] * v[1],
        u[0] * v[3] + u[1] * v[2] - u[2] * v[1] + u[3] * v[0],
    )


def _quat_to_mat(q: Quat) -> tuple[Vec, Vec, Vec]:
    """The rows of the rotation matrix of the unit quaternion ``q`` (MJX's formula)."""
    o = [[q[i] * q[j] for j in range(4)] for i in range(4)]  # MJX's outer product
    return (
        (o[0][0] + o[1][1] - o[2][2] - o[3][3], 2 * (o[1][2] - o[0][3]), 2 * (o[1][3] + o[0][2])),
        (2 * (o[1][2] + o[0][3]), o[0][0] - o[1][1] + o[2][2] - o[3][3], 2 * (o[2][3] - o[0][1])),
        (2 * (o[1][3] - o[0][2]), 2 * (o[2][3] + o[0][1]), o[0][0] - o[1][1] - o[2][2] + o[3][3]),
    )


def rotate(vec: jax.Array, quat: jax.Array) -> jax.Array:
    """``vec`` ``[3]`` rotated by the unit quaternion ``quat`` ``[4]`` (MJX's formula)."""
    return jnp.stack(_rotate(components(vec), components(quat)))


def quat_mul(u: jax.Array, v: jax.Array) -> jax.Array:
    """The quaternion product ``u * v`` (MJX's formula)."""
    return jnp.stack(_quat_mul(components(u), components(v)))


def quat_to_mat(q: jax.Array) -> jax.Array:
    """``[3, 3]`` rotation matrix of the unit quaternion ``q`` (MJX's formula)."""
    return jnp.stack([jnp.stack(row) for row in _quat_to_mat(components(q))])


def _axis_angle_to_quat(axis: Vec, angle: jax.Array) -> Quat:
    """The quaternion of a rotation by ``angle`` about the unit ``axis`` (MJX's values)."""
    s, c = jnp.sin(angle * 0.5), jnp.cos(angle * 0.5)
    return (c, axis[0] * s, axis[1] * s, axis[2] * s)


def axis_angle_to_quat(axis: jax.Array, angle: jax.Array) -> jax.Array:
    """The quaternion of a rotation by ``angle`` about the unit ``axis`` ``[3]``.

    MJX's values, built by stacking: MJX's ``jnp.insert`` is a scatter, which XLA's
    deterministic GPU mode turns into a sort (docs/benchmarks.md, "Reproducibility on GPU").
    """
    return jnp.stack(_axis_angle_to_quat(components(axis), angle))


@pytree.dataclass
class Chain:
    """A serial chain of hinge joints ending in one site, as plain arrays (a pytree).

    Link ``i`` is a body with one hinge joint, child of link ``i - 1``; link 0's parent is
    the chain's ``base`` body (fixed in the world). The site is fixed to the last link.

    Attributes:
      base_pos, base_quat: ``[3]``, ``[4]`` the base body's pose in the world.
      body_pos, body_quat: ``[L, 3]``, ``[L, 4]`` each link's frame in its parent's.
      jnt_pos, jnt_axis: ``[L, 3]`` each hinge's anchor and (unit) axis in its link's frame.
      qpos0: ``[L]`` the joint angles at which each link's frame is ``body_pos/body_quat``.
      site_pos, site_quat: ``[3]``, ``[4]`` the site's frame in the last link's.
    """

    base_pos: jax.Array
    base_quat: jax.Array
    body_pos: jax.Array
    body_quat: jax.Array
    jnt_pos: jax.Array
    jnt_axis: jax.Array
    qpos0: jax.Array
    site_pos: jax.Array
    site_quat: jax.Array

    @property
    def n_joints(self) -> int:
        return self.qpos0.shape[-1]

    @classmethod
    def from_model(cls, model: Any, site: int, dtype: Any = np.float32) -> Chain:
        """The chain from the world to ``site`` of a ``mujoco.MjModel`` (host side).

        Every body between the world and the site's body must carry exactly one hinge joint,
        except a first run of fixed bodies (the base), and the model's joints must be exactly
        these, in chain order (so ``q`` is the model's ``qpos``).

        Raises:
          ValueError: the model is not such a chain (naming what breaks it).
        """
        nsite = int(model.nsite)
        if not 0 <= int(site) < nsite:
            raise ValueError(f"Chain.from_model: site {site} is not in [0, {nsite})")
        path = []
        body = int(model.site_bodyid[site])
        while body != 0:
            path.append(body)
            body = int(model.body_parentid[body])
        path.reverse()
        jointed = [b for b in path if int(model.body_jntnum[b]) > 0]
        base = path[: len(path) - len(jointed)]
        if path[len(base) :] != jointed:
            raise ValueError(
                "Chain.from_model: a body without a joint lies between two jointed bodies "
                f"on the path to site {site} (bodies {path})"
            )
        for b in jointed:
            j = int(model.body_jntadr[b])
            if int(model.body_jntnum[b]) != 1 or int(model.jnt_type[j]) != _HINGE:
                raise ValueError(
                    f"Chain.from_model: body {b} must carry exactly one hinge joint "
                    f"(it has {int(model.body_jntnum[b])}, type {int(model.jnt_type[j])})"
                )
        if not jointed:
            raise ValueError(f"Chain.from_model: no joint between the world and site {site}")
        joints = [int(model.body_jntadr[b]) for b in jointed]
        if joints != list(range(int(model.njnt))) or int(model.nq) != len(joints):
            raise ValueError(
                "Chain.from_model: the model's joints must be exactly the chain's hinges, in "
                f"order (chain joints {joints}, njnt {int(model.njnt)}, nq {int(model.nq)})"
            )
        # The base's pose does not depend on q: MuJoCo C's own kinematics (float64) gives it.
        pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])  # the world
        if base:
            import mujoco

            data = mujoco.MjData(model)
            mujoco.mj_kinematics(model, data)
            pos, quat = data.xpos[base[-1]].copy(), data.xquat[base[-1]].copy()

        def a(x):
            # Converted on the host, then copied: jnp.asarray of a host array compiled a
            # one-operation program per new shape (a cold-start cost on a GPU).
            return jax.device_put(np.asarray(x, dtype))

        return cls(
            base_pos=a(pos),
            base_quat=a(quat),
            body_pos=a(model.body_pos[jointed]),
            body_quat=a(model.body_quat[jointed]),
            jnt_pos=a(model.jnt_pos[joints]),
            jnt_axis=a(model.jnt_axis[joints]),
            qpos0=a(model.qpos0[joints]),
            site_pos=a(model.site_pos[site]),
            site_quat=a(model.site_quat[site]),
        )


class ChainPose(NamedTuple):
    """`forward`'s result: what ``mjx.kinematics`` gives for the chain's joints and site."""

    xanchor: jax.Array  # [L, 3] each hinge's anchor in the world (mjx.Data.xanchor)
    xaxis: jax.Array  # [L, 3] each hinge's axis in the world (mjx.Data.xaxis)
    site_xpos: jax.Array  # [3] the site's position (mjx.Data.site_xpos[site])
    site_xmat: jax.Array  # [3, 3] the site's orientation (mjx.Data.site_xmat[site])


def _add(a: Vec, b: Vec) -> Vec:
    return tuple(x + y for x, y in zip(a, b, strict=True))


def _sub(a: Vec, b: Vec) -> Vec:
    return tuple(x - y for x, y in zip(a, b, strict=True))


def _link(pos: Vec, quat: Quat, link: tuple, angle: jax.Array) -> tuple:
    """MJX's ``smooth.kinematics`` for one link: ``(pos, quat, anchor, axis)``, the frame
    after the link's joint and the joint's anchor and axis in the world. ``link`` is
    ``(body_pos, body_quat, jnt_pos, jnt_axis, qpos0)`` of that link."""
    body_pos, body_quat, jnt_pos, axis, qpos0 = link
    jnt_pos, axis = components(jnt_pos), components(axis)
    pos = _add(pos, _rotate(components(body_pos), quat))
    quat = _quat_mul(quat, components(body_quat))
    anchor = _add(_rotate(jnt_pos, quat), pos)
    world_axis = _rotate(axis, quat)
    quat = _quat_mul(quat, _axis_angle_to_quat(axis, angle - qpos0))
    pos = _sub(anchor, _rotate(jnt_pos, quat))  # off-centre rotation
    return pos, quat, anchor, world_axis


def _links(chain: Chain) -> tuple:
    return chain.body_pos, chain.body_quat, chain.jnt_pos, chain.jnt_axis, chain.qpos0


def _site(chain: Chain, pos: Vec, quat: Quat) -> tuple[Vec, tuple]:
    """``support.local_to_global`` for the site: its position and the rows of its matrix."""
    site_pos = _add(pos, _rotate(components(chain.site_pos), quat))
    return site_pos, _quat_to_mat(_quat_mul(quat, components(chain.site_quat)))


def forward(chain: Chain, q: jax.Array) -> ChainPose:
    """The chain's joint anchors and axes and its site's pose at joint angles ``q`` ``[L]``.

    MJX's ``smooth.kinematics`` for each link in turn (a ``lax.scan`` over the links: one
    link's program whatever the chain's length; written out link by link and batched, XLA's
    compile time grows steeply with the length when the chain is an argument), then
    ``support.local_to_global`` for the site. Every product is elementwise (no matrix unit,
    so no TF32 on GPUs).
    """

    def step(frame, x):
        *link, angle = x
        pos, quat, anchor, axis = _link(*frame, tuple(link), angle)
        return (pos, quat), (jnp.stack(anchor), jnp.stack(axis))

    frame = (components(chain.base_pos), components(chain.base_quat))
    (pos, quat), (anchors, axes) = jax.lax.scan(step, frame, (*_links(chain), q))
    site_pos, mat = _site(chain, pos, quat)
    return ChainPose(anchors, axes, jnp.stack(site_pos), jnp.stack([jnp.stack(r) for r in mat]))


def site_pose(chain: Chain, q: jax.Array) -> tuple[Vec, tuple[Vec, Vec, Vec]]:
    """`forward`'s site pose on components: ``(site_pos, rows of site_mat)``, tuples of
    scalars (arrays of one batch under ``jax.vmap``), for a caller that goes on computing on
    components, so that XLA fuses the walk with what follows (the module docstring). The
    links are written out one by one (no joint anchors or axes are kept, and XLA compiles
    the site's walk alone quickly)."""
    pos, quat = components(chain.base_pos), components(chain.base_quat)
    links = _links(chain)
    for i in range(chain.n_joints):
        pos, quat, _, _ = _link(pos, quat, tuple(x[i] for x in links), q[i])
    return _site(chain, pos, quat)
