"""Draw the figures of docs/tasks.md (visual servoing) with matplotlib, from the task's model.

No OpenGL is needed: bodies and sites come from MuJoCo C's kinematics of ``arm.xml`` and the
camera view from the task's own projection. Run from the repository root::

    python docs/img/servo_figures.py        # writes docs/img/servo_arm.png, servo_camera.png
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from eant2_jax.tasks import servo as sv  # noqa: E402

OUT = Path(__file__).resolve().parent
MARKER_COLOURS = ["#d62728", "#2ca02c", "#1f4fd6", "#e0a800", "#9b30b8"]


def pose(q: np.ndarray) -> dict[str, np.ndarray]:
    """World positions of the arm's joints, the camera and its frame at joint angles ``q``."""
    arm = sv.arm_scene()
    m, d = arm.mj, mujoco.MjData(arm.mj)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    body = {
        n: d.xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)].copy()
        for n in ("link1", "link2", "wrist")
    }
    return {
        **body,
        "camera": d.site_xpos[arm.camera_site].copy(),
        "camera_mat": d.site_xmat[arm.camera_site].reshape(3, 3).copy(),
    }


def footprint(p: dict[str, np.ndarray]) -> np.ndarray:
    """``[5, 3]`` the image's corners on the marker plane (closed polygon)."""
    half_w, half_h = 320 / sv.FOCAL_PX * 0.40, 240 / sv.FOCAL_PX * 0.40
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * [half_w, half_h]
    r = p["camera_mat"]
    return np.array([p["camera"] + r[:, 0] * x + r[:, 1] * y - [0, 0, 0.40] for x, y in corners])


def draw_arm(ax, p, *, alpha=1.0, label=None):
    chain = np.array([[0, 0, 0], [0, 0, 0.60], p["link2"], p["wrist"]])
    ax.plot(
        chain[:2, 0],
        chain[:2, 1],
        chain[:2, 2],
        color="0.3",
        lw=9,
        alpha=alpha,
        solid_capstyle="round",
    )
    ax.plot(
        chain[1:, 0],
        chain[1:, 1],
        chain[1:, 2],
        color="#d9731a",
        lw=6,
        alpha=alpha,
        solid_capstyle="round",
        label=label,
    )
    spindle = np.array([p["wrist"], p["wrist"] + [0, 0, -0.16]])
    ax.plot(spindle[:, 0], spindle[:, 1], spindle[:, 2], color="0.55", lw=4, alpha=alpha)
    cam = p["camera"]
    ax.plot(
        [spindle[1, 0], cam[0]],
        [spindle[1, 1], cam[1]],
        [spindle[1, 2], cam[2]],
        color="k",
        lw=3,
        alpha=alpha,
    )
    ax.scatter(*cam, color="k", s=25, alpha=alpha)
    fp = footprint(p)
    for c in fp[:4]:
        ax.plot(
            [cam[0], c[0]],
            [cam[1], c[1]],
            [cam[2], c[2]],
            color="#1f77b4",
            lw=0.7,
            alpha=0.6 * alpha,
        )
    ax.plot(fp[:, 0], fp[:, 1], fp[:, 2], color="#1f77b4", lw=1.2, alpha=alpha)


def figure_arm(q_start: np.ndarray) -> None:
    arm = sv.arm_scene()
    fig = plt.figure(figsize=(11, 5.2))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    table = np.array([[0.0, -0.6], [0.9, -0.6], [0.9, 0.6], [0.0, 0.6], [0.0, -0.6]])
    ax.plot(table[:, 0], table[:, 1], 0 * table[:, 0], color="0.6", lw=1)
    plate = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * 0.09 + [0.56, 0.10]
    ax.plot(plate[:, 0], plate[:, 1], 0.01 + 0 * plate[:, 0], color="0.4", lw=1)
    for k, c in enumerate(MARKER_COLOURS):
        ax.scatter(*arm.markers[k], color=c, s=18)
    draw_arm(ax, pose(arm.q_goal), label="goal pose q*")
    draw_arm(ax, pose(q_start), alpha=0.35, label="a start pose")
    ax.set(
        xlim=(-0.1, 0.8),
        ylim=(-0.45, 0.45),
        zlim=(0, 0.7),
        xlabel="x (m)",
        ylabel="y (m)",
        zlabel="z (m)",
    )
    ax.set_box_aspect((0.9, 0.9, 0.7))
    ax.view_init(elev=24, azim=-62)
    ax.set_title("SCARA arm, eye-in-hand camera (blue: field of view)")
    ax.legend(loc="upper left", fontsize=8)

    ax = fig.add_subplot(1, 2, 2)
    for q, alpha, name in ((arm.q_goal, 1.0, "goal"), (q_start, 0.4, "start")):
        p = pose(q)
        pts = np.array([[0, 0], p["link2"][:2], p["wrist"][:2], p["camera"][:2]])
        ax.plot(pts[:3, 0], pts[:3, 1], "-o", color="#d9731a", lw=5, alpha=alpha, ms=5)
        ax.plot(pts[2:, 0], pts[2:, 1], "-", color="k", lw=2, alpha=alpha)
        fp = footprint(p)
        ax.plot(
            fp[:, 0],
            fp[:, 1],
            color="#1f77b4",
            alpha=alpha,
            lw=1.2,
            label=f"image footprint, {name}",
        )
    ax.plot(plate[:, 0], plate[:, 1], color="0.4", lw=1)
    for k, c in enumerate(MARKER_COLOURS):
        ax.scatter(*arm.markers[k, :2], color=c, s=20, zorder=3)
        ax.annotate(
            str(k), arm.markers[k, :2], xytext=(3, 3), textcoords="offset points", fontsize=7
        )
    ax.set(
        aspect="equal", xlabel="x (m)", ylabel="y (m)", title="Top view (markers 0-4 on the plate)"
    )
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "servo_arm.png", dpi=110)
    plt.close(fig)


def figure_camera(task: sv.Servo, idx: list[int]) -> None:
    arm = sv.arm_scene()
    q, s = sv.start_poses(1023)
    gain = 0.95
    jac = jax.jit(jax.vmap(task.image_jacobian))(jnp.asarray(q[idx], jnp.float32))
    fig, axes = plt.subplots(1, len(idx), figsize=(5.6 * len(idx), 4.6))
    d = mujoco.MjData(arm.mj)
    step = sv.MAX_STEP_FRACTION * (arm.q_hi - arm.q_lo)
    for ax, i, j in zip(np.atleast_1d(axes), idx, np.asarray(jac), strict=True):
        x = (s[i] - arm.goal).reshape(10)
        dq = np.clip(-gain * np.linalg.pinv(j) @ x, -step, step)
        after = sv.features_host(arm, d, np.clip(q[i] + dq, arm.q_lo, arm.q_hi))

        def px(a):
            return a * sv.NORM_PX + np.asarray(sv.PRINCIPAL_POINT)

        g, st, af = px(arm.goal), px(s[i]), px(after)
        ax.add_patch(plt.Rectangle((0, 0), 640, 480, fill=False, lw=1.5))
        for k, c in enumerate(MARKER_COLOURS):
            ax.scatter(*g[k], s=90, facecolors="none", edgecolors=c, lw=1.5)
            ax.scatter(*st[k], s=30, color=c)
            ax.scatter(*af[k], s=40, color=c, marker="x")
            ax.annotate("", af[k], st[k], arrowprops={"arrowstyle": "->", "color": c, "lw": 0.8})
        err0 = np.linalg.norm(s[i] - arm.goal, axis=-1).mean()
        err1 = np.linalg.norm(after - arm.goal, axis=-1).mean()
        ax.set(xlim=(-20, 660), ylim=(500, -20), aspect="equal", xlabel="u (px)", ylabel="v (px)")
        ax.set_title(f"start {i}: error {err0:.3f} -> {err1:.3f} after one IBVS move", fontsize=9)
    fig.suptitle(
        "Camera view, 640 x 480, f = 500 px: goal (rings), start (dots), after IBVS (x)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(OUT / "servo_camera.png", dpi=110)
    plt.close(fig)


def main() -> None:
    task = sv.servo()
    q, s = sv.start_poses(1023)
    err = np.linalg.norm(s - sv.arm_scene().goal, axis=-1).mean(axis=-1)
    order = np.argsort(err)
    # A typical start (median error) and a hard one (95th percentile).
    typical, hard = int(order[len(order) // 2]), int(order[int(0.95 * len(order))])
    figure_arm(q[hard])
    figure_camera(task, [typical, hard])


if __name__ == "__main__":
    main()
