"""3-DOF visual servoing on a batched MJX arm: the paper's benchmark (section V.B).

A SCARA-type arm (``arm.xml`` beside this file) moves an eye-in-hand camera over a table; the
camera sees 5 markers on an object. A controller reads the 10 image measurements (each
marker's image position minus its position in the goal image, taken at the goal pose:
teach-by-showing) and answers with 3 joint increments; the arm executes them, and the cost of
the move is the mean image distance between each marker and its goal position afterwards, plus
penalties. The task's cost is the mean over 1023 fixed start poses (paper: "the simulation of
1023 robot movements"); fitness = -cost (paper fig. 8).

Everything is batched over (networks x start poses) in one jit-compiled call: the network's
forward pass over all starts, the joint targets, the arm (MJX's forward kinematics along the
arm's chain, `eant2_jax.kernels.kinematics`, or position servos integrated with ``mjx.step``
inside ``lax.scan``), the projection and the cost.

Every constant is documented here and in ``docs/tasks.md``:

* **Camera**: pinhole, focal length ``FOCAL_PX = 500`` px, image ``640 x 480`` px, principal
  point ``(320, 240)``; looks straight down from 0.40 m above the markers (MuJoCo camera
  "eye", fovy 51.282 degrees, is the same pinhole).
* **Normalised image coordinates**: ``u_n = (u - 320) / 320``, ``v_n = (v - 240) / 320``
  (one unit = half the image width, the same scale on both axes so that distances are
  isotropic); the image is ``|u_n| < 1``, ``|v_n| < 0.75``. Inputs and costs use these units.
* **Inputs** (10): ``(u_n, v_n)`` of markers 0..4 minus the same at the goal pose, in the order
  ``u0, v0, u1, v1, ..., u4, v4``. Over the training starts they lie in about [-1, 1].
* **Outputs** (3): the network's outputs ``y`` (identity output neurons by default) become
  joint increments ``dq = MAX_STEP * tanh(y)``, ``MAX_STEP = 0.1 x`` each joint's range
  (0.349, 0.524, 0.593 rad); the new target is clipped to the joint range.
* **Move cost**: ``mean_k |s_k - s*_k|`` (image distance of marker k from its goal position,
  normalised units) ``+ 0.1`` per marker outside the image ``+ 0.1`` per joint at a limit
  (its command ``q + dq`` reached or passed the range and was clipped).
* **Start poses**: ``q* + U(-(0.2, 0.3, 0.4), +(0.2, 0.3, 0.4))`` rad around the goal pose
  ``q*``, kept only if all 5 markers are inside the image; NumPy generator seeded
  ``[2009, 0]`` (training) and ``[2009, 1]`` (held out, a disjoint set for generalisation).
* **Modes**: ``kinematic`` (default): the new joint angles are the clipped targets, the camera
  pose comes from the arm's forward kinematics (``mjx.kinematics``'s values). ``dynamic``: the
  position servos track the target for ``substeps = 60`` ``mjx.step`` calls of 5 ms (0.3 s)
  from the arm's current state, and the pose reached is measured. Both modes use
  `stripped_model` (``arm.xml`` without its visual-only parts). Its joint limit
  *constraints* are off: targets are clamped to the ranges and the servos are critically
  damped, so a joint passes a limit by at most about 1 mrad (0.7 seen, < 2 tested), while
  the constraint solver would make a step several times slower.
* ``moves_per_start > 1``: closed-loop servoing; the network is applied again to the new
  measurements, carrying its recurrent state (and the arm its velocity), and the start's cost
  is the mean over its moves. Default 1, as in the paper.

The cost is deterministic: the PRNG key of `Servo.cost` is unused.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import pytree
from ..kernels import kinematics as kin
from ..kernels import network as kn

__all__ = [
    "ARM_XML",
    "FOCAL_PX",
    "IBVS_GAINS",
    "IMAGE_SIZE",
    "LIMIT_PENALTY",
    "MAX_STEP_FRACTION",
    "MODES",
    "NORM_PX",
    "N_MARKERS",
    "OUTSIDE_PENALTY",
    "PRINCIPAL_POINT",
    "SEED",
    "START_HALF_WIDTH",
    "SUBSTEPS",
    "Servo",
    "ibvs_start_costs",
    "project",
    "servo",
    "start_poses",
    "stripped_model",
]

# The scene (camera, arm, start poses, models) lives in its own module; its public names are
# part of this module's API too.
from .servo_scene import (  # noqa: F401
    _OPTICAL,
    ARM_XML,
    FOCAL_PX,
    HALF_EXTENT,
    IBVS_GAINS,
    IMAGE_SIZE,
    LIMIT_PENALTY,
    MAX_STEP_FRACTION,
    MODES,
    N_MARKERS,
    NORM_PX,
    OUTSIDE_PENALTY,
    PRINCIPAL_POINT,
    SEED,
    START_HALF_WIDTH,
    SUBSTEPS,
    _mjx_model,
    arm_scene,
    draw_start_poses,
    features_host,
    mjx_numerics,
    outside_image,
    project,
    project_components,
    stack_image,
    start_poses,
    stripped_arm,
    stripped_model,
)


@pytree.dataclass
class Servo:
    """The visual servoing task (see the module docstring for every constant).

    The arm's pose comes from `eant2_jax.kernels.kinematics` (MJX's forward kinematics
    written along the arm's chain of hinges: the same values as ``mjx.kinematics`` to the last
    bit, in a few fused operations, without importing MJX); the dynamic mode's physics from
    ``mjx.step``. Both models are pytree *leaf fields*, not static fields: ``mjx.Model`` is
    itself a pytree whose array fields are leaves and whose NumPy fields (joint types, tree
    structure) are static metadata hashed and compared by content. So the task's arrays are
    passed into jit as arguments (never baked into a program), and two separately built tasks
    with equal options share one compiled program. A static field would need the model to be
    hashable, which an object holding JAX arrays is not.

    Attributes:
      model: the MJX arm, `stripped_model` (no geoms, no limit constraints), in dynamic mode;
        ``None`` in kinematic mode, which never imports MJX (a cost of a process's start).
      chain: the arm's chain of hinges from the world to the camera site
        (`eant2_jax.kernels.kinematics.Chain` of `stripped_model`).
      q_start: ``[N, 3]`` start joint angles (rad).
      x_start: ``[N, 10]`` the 10 normalised image measurements at each start.
      q_test, x_test: the same for the disjoint held-out start poses.
      goal: ``[5, 2]`` goal image (normalised coordinates).
      markers: ``[5, 3]`` marker world positions (the object is fixed).
      q_lo, q_hi: ``[3]`` joint ranges (rad).
      max_step: ``[3]`` largest joint increment of one move (rad).
      camera_site, camera_body: ids in ``model`` of the camera site and its body (static).
      mode: ``"kinematic"`` or ``"dynamic"`` (static).
      moves_per_start: moves per start pose, closed loop (static).
      substeps: ``mjx.step`` calls per move in dynamic mode (static).
      hidden, output: activation names of the networks' hidden and output neurons (static).
    """

    model: Any  # mjx.Model in dynamic mode, else None
    chain: kin.Chain
    q_start: jax.Array
    x_start: jax.Array
    q_test: jax.Array
    x_test: jax.Array
    goal: jax.Array
    markers: jax.Array
    q_lo: jax.Array
    q_hi: jax.Array
    max_step: jax.Array
    camera_site: int = pytree.field(pytree_node=False)
    camera_body: int = pytree.field(pytree_node=False)
    mode: str = pytree.field(pytree_node=False, default="kinematic")
    moves_per_start: int = pytree.field(pytree_node=False, default=1)
    substeps: int = pytree.field(pytree_node=False, default=SUBSTEPS)
    hidden: str = pytree.field(pytree_node=False, default="tanh")
    output: str = pytree.field(pytree_node=False, default="identity")

    @property
    def n_inputs(self) -> int:
        return 2 * N_MARKERS

    @property
    def n_outputs(self) -> int:
        return 3

    @property
    def n_starts(self) -> int:
        return self.q_start.shape[0]

    # ------------------------------------------------------------------ one arm, one pose
    def features(self, q: jax.Array) -> jax.Array:
        """``[5, 2]`` normalised marker image coordinates at joint angles ``q`` ``[3]``."""
        return stack_image(self._image(q))

    def _image(self, q: jax.Array) -> list[tuple]:
        """`features` on components, ``[(u_k, v_k)]``: batched, the kinematics, the projection
        and the move's cost stay elementwise and fuse (`eant2_jax.kernels.kinematics`)."""
        pos, rows = kin.site_pose(self.chain, q)
        return project_components(pos, rows, self.markers)

    def measure(self, q: jax.Array) -> jax.Array:
        """``[10]`` network inputs at ``q``: image coordinates minus the goal image."""
        return (self.features(q) - self.goal).reshape(-1)

    def move_cost(self, s: jax.Array, at_limit: jax.Array) -> jax.Array:
        """Cost of one move from the image ``s`` ``[5, 2]`` after it and ``bool[3]`` limits."""
        return self._move_cost([kin.components(uv) for uv in s], kin.components(at_limit))

    def _move_cost(self, image: list[tuple], at_limit: tuple) -> jax.Array:
        """`move_cost` on components: the image as `_image` gives it, the limits' 3 flags."""
        dist, outside = [], []
        for k, (u, v) in enumerate(image):
            du, dv = u - self.goal[k, 0], v - self.goal[k, 1]
            dist.append(jnp.sqrt(du * du + dv * dv))
            outside.append(outside_image(u, v))
        dtype = dist[0].dtype
        return (
            sum(dist[1:], dist[0]) / len(dist)
            + OUTSIDE_PENALTY * sum(o.astype(dtype) for o in outside)
            + LIMIT_PENALTY * sum(a.astype(dtype) for a in at_limit)
        )

    def simulate(self, q: jax.Array, qd: jax.Array, target: jax.Array):
        """``substeps`` physics steps of the servos tracking ``target``; ``(q, qd)`` after."""
        from .mjx_quiet import mjx

        d0 = mjx.make_data(self.model).replace(ctrl=target)

        # Only (qpos, qvel) are carried: nothing else of mjx.Data is state for this model
        # (no activations, no constraints, hence no solver warm start), and a small carry
        # lets XLA drop every other field of each step.
        def body(carry, _):
            with mjx_numerics():
                d = mjx.step(self.model, d0.replace(qpos=carry[0], qvel=carry[1]))
            return (d.qpos, d.qvel), None

        (q, qd), _ = jax.lax.scan(body, (q, qd), None, length=self.substeps)
        return q, qd

    def move(self, q: jax.Array, qd: jax.Array, dq: jax.Array):
        """Execute joint increments ``dq`` ``[3]`` from ``(q, qd)``.

        Returns:
          ``(q, qd, x, cost)`` after the move: joint angles and velocities, the 10 new
          measurements and the move's cost.
        """
        command = q + dq
        at_limit = (command <= self.q_lo) | (command >= self.q_hi)
        target = jnp.clip(command, self.q_lo, self.q_hi)
        if self.mode == "kinematic":
            q_new, qd_new = target, qd
        else:
            q_new, qd_new = self.simulate(q, qd, target)
        image = self._image(q_new)
        x = (stack_image(image) - self.goal).reshape(-1)
        return q_new, qd_new, x, self._move_cost(image, kin.components(at_limit))

    def episode(self, policy: Callable, state0: Any, q0: jax.Array, x0: jax.Array) -> jax.Array:
        """Mean move cost of one controller from one start pose (one arm, no batch).

        Args:
          policy: ``(state, q, x) -> (dq, state)``: joint increments from the joint angles
            ``[3]`` and the 10 measurements ``x``, with a controller state carried between
            moves.
          state0: the controller's state before the first move.
          q0, x0: start joint angles and the measurements there.
        """

        def one(carry):
            q, qd, x, state = carry
            dq, state = policy(state, q, x)
            q, qd, x, c = self.move(q, qd, dq)
            return (q, qd, x, state), c

        carry = (q0, jnp.zeros_like(q0), x0, state0)
        if self.moves_per_start == 1:
            return one(carry)[1]
        _, costs = jax.lax.scan(lambda c, _: one(c), carry, None, length=self.moves_per_start)
        return jnp.mean(costs)

    # -------------------------------------------------------------------- controllers
    def network_policy(self, net: kn.Network) -> Callable:
        """A network as a controller: ``dq = max_step * tanh(y)``; its state is ``h`` ``[H]``."""

        def policy(h, q, x):
            del q  # the network sees the image only
            y, h = kn.step(net, x, h, hidden=self.hidden, output=self.output)
            return self.max_step * jnp.tanh(y), h

        return policy

    def image_jacobian(self, q: jax.Array) -> jax.Array:
        """``[10, 3]`` d(measurements)/d(joint angles) by the classic IBVS construction.

        The point-feature interaction matrix (normalised coordinates, known depth Z;
        Chaumette & Hutchinson 2006, eq. 11) times the arm Jacobian of the camera (its linear
        and angular velocity per joint velocity, rotated into the optical frame).

        The arm Jacobian is built from the joint anchors and axes of the arm's kinematics
        (`eant2_jax.kernels.kinematics.forward`, ``mjx.kinematics``'s values; hinge j:
        ``axis_j x (camera - anchor_j)`` and ``axis_j``), which is what ``mjx.jac`` computes
        for a chain of hinges.
        """
        d = kin.forward(self.chain, q)
        pos, mat = d.site_xpos, d.site_xmat
        # Every joint is an ancestor of the camera (a serial arm); [nv, 3] each.
        jacp = jnp.cross(d.xaxis, pos[None, :] - d.xanchor)
        jacr = d.xaxis
        to_optical = jnp.asarray(_OPTICAL, mat.dtype) @ mat.T  # world -> optical frame
        v = jnp.dot(to_optical, jacp.T, precision="highest")  # [3, nv] linear velocity
        w = jnp.dot(to_optical, jacr.T, precision="highest")  # [3, nv] angular velocity
        twist = jnp.concatenate([v, w], axis=0)  # [6, nv]
        # Metric normalised coordinates x = X/Z, y = Y/Z (optical frame) and depths Z.
        rel = self.markers - pos[None, :]
        pc = (rel[:, :, None] * mat[None, :, :]).sum(axis=1)
        z = -pc[:, 2]
        x, y = pc[:, 0] / z, -pc[:, 1] / z
        one, zero = jnp.ones_like(x), jnp.zeros_like(x)
        # ds/dt = L (v, w) for a point feature (x, y) at depth Z.
        lx = jnp.stack([-one / z, zero, x / z, x * y, -(1 + x * x), y], axis=-1)
        ly = jnp.stack([zero, -one / z, y / z, 1 + y * y, -x * y, -x], axis=-1)
        interaction = jnp.stack([lx, ly], axis=1).reshape(2 * N_MARKERS, 6)
        return (FOCAL_PX / NORM_PX) * jnp.dot(interaction, twist, precision="highest")

    def ibvs_policy(self, gain: jax.Array) -> Callable:
        """Image-based visual servoing: ``dq = clip(-gain * pinv(J(q)) x, +-max_step)``."""

        def policy(state, q, x):
            dq = -gain * jnp.dot(jnp.linalg.pinv(self.image_jacobian(q)), x, precision="highest")
            return jnp.clip(dq, -self.max_step, self.max_step), state

        return policy

    # ------------------------------------------------------------------------- costs
    def cost(self, key: jax.Array, nets: kn.Network) -> jax.Array:
        """Mean move cost ``[*batch]`` over the start poses (the key is unused).

        The leading batch dims of ``nets`` are flattened into one, then every network runs on
        every start pose as one batched computation (``vmap`` over networks of ``vmap`` over
        starts: one forward pass, one batched arm, one projection).
        """
        del key
        return _network_costs(self, nets, self.q_start, self.x_start)

    def held_out(self) -> Servo:
        """The same task on the held-out start poses (training and held-out sets swapped)."""
        return self.replace(
            q_start=self.q_test, x_start=self.x_test, q_test=self.q_start, x_test=self.x_start
        )

    def generalisation(self, nets: kn.Network) -> jax.Array:
        """Costs ``[*batch]`` of ``nets`` on the held-out start poses (jit-compiled)."""
        return jit_cost(self.held_out(), nets)

    def start_costs(self, policy: Callable, state0: Any = None) -> jax.Array:
        """``[N]`` cost of one hand-written controller from each start pose.

        Args:
          policy: ``(state, q, x) -> (dq, state)`` as in `episode`.
          state0: its state before the first move (the same at every start).
        """
        return jax.vmap(functools.partial(self.episode, policy, state0))(self.q_start, self.x_start)

    def baselines(self) -> dict[str, float]:
        """Costs of the reference controllers, by the task's own cost (host side).

        Returns:
          ``zero``: no move (the mean initial error, the start poses being penalty free);
          ``ibvs``: image-based visual servoing with the best gain of ``IBVS_GAINS`` (see
          `ibvs_gain`); ``ibvs_gain1``: the same with gain 1 (one Gauss-Newton step).
        """
        gains, costs = self.ibvs_sweep()
        return {
            "zero": float(costs[0]),
            "ibvs": float(costs[1:].min()),
            "ibvs_gain1": float(costs[gains.index(1.0)]),
        }

    def ibvs_gain(self) -> float:
        """The gain of ``IBVS_GAINS`` with the lowest task cost."""
        gains, costs = self.ibvs_sweep()
        return gains[1 + int(np.argmin(costs[1:]))]

    def ibvs_sweep(self) -> tuple[tuple[float, ...], np.ndarray]:
        """``(gains, task cost of IBVS at each gain)`` for gain 0 (no move) and ``IBVS_GAINS``.

        One compiled call on the host. Gain 0 is the zero controller exactly: its increments are
        (signed) zeros.
        """
        gains = (0.0, *IBVS_GAINS)
        costs = ibvs_start_costs(self, jnp.asarray(gains, jnp.float32))
        return gains, np.asarray(costs).mean(axis=1)


def flatten_networks(nets: kn.Network) -> tuple[kn.Network, tuple[int, ...]]:
    batch = nets.bias.shape[:-1]
    n = int(np.prod(batch, dtype=np.int64))
    flat = jax.tree.map(lambda a: a.reshape((n,) + a.shape[len(batch) :]), nets)
    return flat, batch


def _network_costs(task: Servo, nets: kn.Network, q0: jax.Array, x0: jax.Array) -> jax.Array:
    """Mean move cost ``[*batch]`` of networks over start poses ``q0`` ``[S, 3]``, ``x0``.

    ``vmap`` over networks of ``vmap`` over starts of one whole episode (network, arm, cost).
    The first move's inputs are data shared by every network, so the forward pass is one
    matrix product per network over all starts. The arm as one flat batch of ``N * S``
    instead (``bench/bench_servo.py``, ``task_flat``) gives the same numbers and was no
    faster on a GPU and slower on a CPU.
    """
    flat, batch = flatten_networks(nets)

    def one_net(net):
        run = functools.partial(task.episode, task.network_policy(net), jnp.zeros_like(net.bias))
        return jnp.mean(jax.vmap(run)(q0, x0))

    return jax.vmap(one_net)(flat).reshape(batch)


@jax.jit
def jit_cost(task: Servo, nets: kn.Network) -> jax.Array:
    return task.cost(None, nets)


@jax.jit
def ibvs_start_costs(task: Servo, gains: jax.Array) -> jax.Array:
    """``[G, N]`` cost of IBVS at each of ``gains`` ``[G]`` from each start pose (jit)."""
    return jax.vmap(lambda g: task.start_costs(task.ibvs_policy(g)))(gains)


# ------------------------------------------------------------------------------ factory
def servo(
    *,
    mode: str = "kinematic",
    moves_per_start: int = 1,
    n_starts: int = 1023,
    substeps: int = SUBSTEPS,
    held_out: bool = False,
    hidden: str = "tanh",
    output: str = "identity",
) -> Servo:
    """The 3-DOF visual servoing task (``tasks.make("servo", ...)``).

    Args:
      mode: ``"kinematic"`` (default; targets reached exactly, the arm's kinematics) or
        ``"dynamic"`` (position servos, ``substeps`` ``mjx.step`` calls per move).
      moves_per_start: moves per start pose, closed loop (1 = the paper).
      n_starts: number of start poses (1023 = the paper); smaller sets are prefixes.
      substeps: physics steps of 5 ms per move in dynamic mode (default 60 = 0.3 s).
      held_out: score on the held-out start poses instead of the training ones.
      hidden, output: activation names for hidden and output neurons. Output neurons are
        ``identity`` by default: the task itself bounds the increments with ``tanh``.

    Returns:
      The `Servo` task.

    Raises:
      ValueError: an unknown mode or activation, or a count that is not a positive integer.
    """
    if mode not in MODES:
        raise ValueError(f"servo: mode must be one of {', '.join(MODES)}; got {mode!r}")
    for name, value, top in (
        ("moves_per_start", moves_per_start, 10_000),
        ("n_starts", n_starts, 1_000_000),
        ("substeps", substeps, 100_000),
    ):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"servo: {name} must be an integer; got {value!r}")
        if not 1 <= value <= top:
            raise ValueError(f"servo: {name} must be in [1, {top}]; got {value}")
    kn.activation(hidden), kn.activation(output)
    arm = arm_scene()
    mj, camera_site, camera_body = stripped_arm()
    # MJX (and its import) only where its physics runs.
    model = _mjx_model()[0] if mode == "dynamic" else None
    sets = [start_poses(n_starts, held_out=h) for h in (held_out, not held_out)]
    (q_tr, s_tr), (q_te, s_te) = sets
    goal = arm.goal[None]

    def f32(a):
        # Converted on the host, then copied with device_put: jnp.asarray/astype compile a
        # small XLA program per shape (8 here, each a cold-start cost on a GPU).
        return jax.device_put(np.asarray(a, np.float32))

    return Servo(
        model=model,
        chain=kin.Chain.from_model(mj, camera_site),
        q_start=f32(q_tr),
        x_start=f32((s_tr - goal).reshape(len(q_tr), -1)),
        q_test=f32(q_te),
        x_test=f32((s_te - goal).reshape(len(q_te), -1)),
        goal=f32(arm.goal),
        markers=f32(arm.markers),
        q_lo=f32(arm.q_lo),
        q_hi=f32(arm.q_hi),
        max_step=f32(MAX_STEP_FRACTION * (arm.q_hi - arm.q_lo)),
        camera_site=camera_site,
        camera_body=camera_body,
        mode=mode,
        moves_per_start=int(moves_per_start),
        substeps=int(substeps),
        hidden=hidden,
        output=output,
    )
