"""Drawings of behaviour (``eant2 render``'s animations) and of networks with their weights
(``eant2 show``), matplotlib on the Agg backend: files only, never a window.

Every file goes through `eant2_jax.app.outputs` (whole, never through a link). An animation
is a GIF written by matplotlib's ``PillowWriter``, or an MP4 by its ``FFMpegWriter`` where
ffmpeg is installed (one-line error otherwise).
"""

from __future__ import annotations

import importlib.util
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import outputs
from .netdraw import draw_network, network_figure
from .report_figures import pyplot

__all__ = [
    "MARKER_COLOURS",
    "draw_network",
    "gymnax_animation",
    "network_figure",
    "save_animation",
    "servo_animation",
]

MARKER_COLOURS = ("#d62728", "#2ca02c", "#1f4fd6", "#e0a800", "#9b30b8")  # docs/img's
DPI = 80
# gymnax's visualizers for Gymnasium's classic-control environments render with pygame.
_GYM_CLASSIC = (
    "Acrobot-v1",
    "CartPole-v1",
    "Pendulum-v1",
    "MountainCar-v0",
    "MountainCarContinuous-v0",
)
_GYMNAX_OTHERS = (
    "Catch-bsuite",
    "Asterix-MinAtar",
    "Breakout-MinAtar",
    "Freeway-MinAtar",
    "Seaquest-MinAtar",
    "SpaceInvaders-MinAtar",
    "Pong-misc",
    "PointRobot-misc",
    "MetaMaze-misc",
    "FourRooms-misc",
)


def check_format(out: Path) -> None:
    """One-line ValueError unless ``out`` is a .gif, or an .mp4 with ffmpeg installed."""
    suffix = out.suffix.lower()
    if suffix == ".gif":
        return
    if suffix != ".mp4":
        raise ValueError(f"{out}: an animation is a .gif or an .mp4")
    from matplotlib import animation

    if not animation.writers.is_available("ffmpeg"):
        raise ValueError(f"{out}: an .mp4 needs ffmpeg, which is not installed here; write a .gif")


def _writer(out: Path, fps: int):
    from matplotlib import animation

    check_format(out)
    if out.suffix.lower() == ".mp4":
        return animation.FFMpegWriter(fps=fps)
    return animation.PillowWriter(fps=fps)


def save_animation(
    fig: Any,
    update: Callable[[int], None],
    n_frames: int,
    out: Path,
    *,
    fps: int,
    overwrite: bool,
    frame: Path | None = None,
    dpi: int = DPI,
) -> int:
    """Draw ``n_frames`` frames (``update(i)`` then a grab) into ``out``; the last frame also
    into the PNG ``frame``. Written whole through `eant2_jax.app.outputs`; returns the count."""
    out = Path(out)
    writer = _writer(out, fps)
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / f"animation{out.suffix.lower()}"
        with writer.saving(fig, str(target), dpi):
            for i in range(n_frames):
                update(i)
                writer.grab_frame()
        data = target.read_bytes()
    _folder(out)
    outputs.write_bytes(out, data, overwrite=overwrite)
    if frame is not None:
        _folder(frame)
        outputs.save_figure(fig, frame, overwrite=overwrite, dpi=dpi)
    return n_frames


def _folder(path: Path) -> None:
    if not path.parent.exists():  # a dangling link there is refused by make_folder
        outputs.make_folder(path.parent)


# ---------------------------------------------------------------------------- servo
def _arm_geometry(task: Any, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([..., 4, 3] joint anchors then the camera, [..., 5, 3] the image's corners on the
    marker plane)`` at joint angles ``q`` ``[..., 3]``, from the arm's forward kinematics."""
    import jax

    from ..kernels import kinematics as kin
    from ..tasks.servo import FOCAL_PX, HALF_EXTENT, NORM_PX

    flat = np.asarray(q, np.float32).reshape(-1, q.shape[-1])
    pose = jax.vmap(lambda qi: kin.forward(task.chain, qi))(flat)
    anchors, cam, mat = (
        np.asarray(a, np.float64) for a in (pose.xanchor, pose.site_xpos, pose.site_xmat)
    )
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * HALF_EXTENT
    # A ray through normalised image point (u, v): optical (u, v, 1) * NORM/FOCAL; the
    # camera frame's columns are (x right, y up, -viewing direction).
    rays = np.stack(
        [
            corners[:, 0] * NORM_PX / FOCAL_PX,
            -corners[:, 1] * NORM_PX / FOCAL_PX,
            -np.ones(len(corners)),
        ],
        axis=-1,
    )
    dirs = np.einsum("nij,kj->nki", mat, rays)
    depth = float(np.asarray(task.markers)[0, 2])
    t = (depth - cam[:, None, 2]) / dirs[..., 2]
    foot = cam[:, None, :] + t[..., None] * dirs
    joints = np.concatenate([anchors, cam[:, None, :]], axis=1)
    return joints.reshape(*q.shape[:-1], 4, 3), foot.reshape(*q.shape[:-1], 5, 3)


def _servo_axes(fig: Any, task: Any, goal_joints: np.ndarray):
    """The two panels (top view, camera image) with what does not move."""
    from ..tasks.servo import HALF_EXTENT

    top, img = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1.0]})
    markers = np.asarray(task.markers)
    top.add_patch(pyplot().Rectangle((0.0, -0.6), 0.9, 1.2, color="#efe9dd", zorder=0))
    top.plot(
        goal_joints[:, 0],
        goal_joints[:, 1],
        "-o",
        color="0.75",
        lw=5,
        ms=4,
        label="goal pose",
        zorder=1,
    )
    top.scatter(markers[:, 0], markers[:, 1], c=MARKER_COLOURS, s=14, zorder=4)
    top.set(xlim=(-0.15, 0.95), ylim=(-0.45, 0.6), aspect="equal", title="arm (top view, m)")
    top.tick_params(labelsize=7)
    goal = np.asarray(task.goal)
    w, h = HALF_EXTENT
    img.add_patch(pyplot().Rectangle((-w, -h), 2 * w, 2 * h, fill=False, color="0.3"))
    img.scatter(
        goal[:, 0],
        goal[:, 1],
        s=90,
        facecolors="none",
        edgecolors=MARKER_COLOURS,
        linewidths=1.6,
        label="goal image",
    )
    img.set(
        xlim=(-w * 1.05, w * 1.05),
        ylim=(h * 1.05, -h * 1.05),
        aspect="equal",
        title="camera image (normalised)",
    )
    img.tick_params(labelsize=7)
    return top, img


def servo_animation(
    task: Any,
    moves: Any,
    out: Path,
    *,
    title: str = "",
    fps: int = 3,
    frame: Path | None = None,
    overwrite: bool = False,
    dpi: int = DPI,
    size: tuple[float, float] = (8.0, 3.8),
) -> int:
    """Animate `eant2_jax.app.render.ServoMoves`: one frame per pose (each start pose,
    then each move after it), the arm above and the camera image beside. Returns the count."""
    from ..tasks.servo_scene import arm_scene

    check_format(Path(out))
    plt = pyplot()
    n_starts, n_poses = moves.q.shape[:2]
    joints, foot = _arm_geometry(task, moves.q)
    goal_joints, _ = _arm_geometry(task, np.asarray(arm_scene().q_goal)[None])
    image = moves.x.reshape(n_starts, n_poses, -1, 2) + np.asarray(task.goal)
    fig = plt.figure(figsize=size)
    try:
        top, img = _servo_axes(fig, task, goal_joints[0])
        (arm,) = top.plot([], [], "-o", color="#d9822b", lw=4, ms=5, label="arm", zorder=3)
        (fov,) = top.plot([], [], "-", color="#1f77b4", lw=1, label="camera view", zorder=2)
        top.legend(loc="upper left", fontsize=6, frameon=False)
        dots = img.scatter(
            image[0, 0, :, 0],
            image[0, 0, :, 1],
            s=28,
            c=MARKER_COLOURS,
            label="current image",
            zorder=3,
        )
        trails = [img.plot([], [], "-", color=c, lw=0.8, alpha=0.7)[0] for c in MARKER_COLOURS]
        img.legend(loc="lower left", fontsize=6, frameon=False)
        head = fig.suptitle("", fontsize=9)

        def update(i: int) -> None:
            s, m = divmod(i, n_poses)
            arm.set_data(joints[s, m, :, 0], joints[s, m, :, 1])
            fov.set_data(foot[s, m, :, 0], foot[s, m, :, 1])
            dots.set_offsets(image[s, m])
            for k, line in enumerate(trails):
                line.set_data(image[s, : m + 1, k, 0], image[s, : m + 1, k, 1])
            cost = f"move cost {moves.cost[s, m - 1]:.4f}" if m else "start pose"
            head.set_text(
                f"{title}\nstart {s + 1}/{n_starts} (pose {moves.starts[s]}), "
                f"move {m}/{n_poses - 1}: {cost}"
            )

        fig.tight_layout(rect=(0, 0, 1, 0.88))  # room for the two lines of the title
        return save_animation(
            fig, update, n_starts * n_poses, out, fps=fps, overwrite=overwrite, frame=frame, dpi=dpi
        )
    finally:
        plt.close(fig)


# ---------------------------------------------------------------------------- gymnax
def _cartpole(ax: Any, params: Any) -> Callable[[Any], None]:
    """Cart and pole, drawn from a CartPole state (x, theta); returns the frame's update."""
    limit = float(params.x_threshold)
    pole = 2.0 * float(params.length)  # Gymnasium's drawing: the pole is 2 * length long
    ax.set(xlim=(-limit * 1.1, limit * 1.1), ylim=(-0.3, pole + 0.3), aspect="equal")
    ax.set_xlabel("cart position (the dotted lines end the episode)", fontsize=7)
    ax.tick_params(labelsize=7)
    ax.axhline(0.0, color="0.4", lw=1)
    for side in (-limit, limit):
        ax.axvline(side, color="0.7", lw=1, ls=":")
    cart = pyplot().Rectangle((0, 0), 0.5, 0.3, color="#444444", zorder=2)
    ax.add_patch(cart)
    (rod,) = ax.plot([], [], "-", color="#c8793c", lw=5, solid_capstyle="round", zorder=3)
    ax.set_yticks([])

    def update(state: Any) -> None:
        x, theta = float(state.x), float(state.theta)
        cart.set_xy((x - 0.25, -0.15))
        rod.set_data([x, x + pole * np.sin(theta)], [0.15, 0.15 + pole * np.cos(theta)])

    return update


def _pendulum(ax: Any, params: Any) -> Callable[[Any], None]:
    """A pendulum from its state (theta, 0 = upright); returns the frame's update."""
    ax.set(xlim=(-1.3, 1.3), ylim=(-1.3, 1.3), aspect="equal")
    ax.set_xticks([]), ax.set_yticks([])
    (rod,) = ax.plot([], [], "-o", color="#c8793c", lw=6, ms=8)

    def update(state: Any) -> None:
        t = float(state.theta)
        rod.set_data([0.0, np.sin(t)], [0.0, np.cos(t)])

    return update


_OWN = {"CartPole-v1": _cartpole, "Pendulum-v1": _pendulum}


def gymnax_renderer(env_name: str) -> str:
    """Who draws ``env_name``: ``"gymnax"`` (its own visualizer, where it runs here; the
    classic-control ones need pygame) or ``"matplotlib"`` (this module's drawing)."""
    if env_name in _GYM_CLASSIC and importlib.util.find_spec("pygame") is not None:
        return "gymnax"
    if env_name in _OWN:
        return "matplotlib"
    if env_name in _GYMNAX_OTHERS:
        return "gymnax"
    raise ValueError(
        f"gymnax:{env_name} has no drawing here (gymnax's visualizer draws "
        f"{', '.join(_GYMNAX_OTHERS + _GYM_CLASSIC)}; the classic-control ones need pygame)"
    )


def gymnax_animation(
    task: Any,
    episode: Any,
    out: Path,
    *,
    title: str = "",
    fps: int = 25,
    frame: Path | None = None,
    overwrite: bool = False,
    dpi: int = DPI,
    size: tuple[float, float] = (5.0, 3.2),
) -> int:
    """Animate `eant2_jax.app.render.Episode`: one frame per step, the state the network
    acted in, with the step, its action and the return so far. Returns the count."""
    import jax

    check_format(Path(out))
    n = len(np.asarray(episode.rewards))
    if n == 0:
        raise ValueError("the episode has no step to draw")
    states = [jax.tree.map(lambda a, t=t: a[t], episode.states) for t in range(n)]
    returns = np.cumsum(np.asarray(episode.rewards, np.float64))
    if gymnax_renderer(task.env_name) == "gymnax":
        return _gymnax_visualizer(task, states, returns, out, fps, frame, overwrite, dpi)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=size)
    try:
        draw = _OWN[task.env_name](ax, task.env_params)
        actions = np.asarray(episode.actions)

        def update(t: int) -> None:
            draw(states[t])
            action = ", ".join(f"{a:.3g}" for a in np.ravel(actions[t]))
            ax.set_title(
                f"{title}\n{task.env_name}: step {t + 1}/{episode.length}, action {action}, "
                f"return {returns[t]:g}",
                fontsize=8,
            )

        update(0)  # the title's two lines are there when the layout is made
        fig.tight_layout()
        return save_animation(
            fig, update, n, out, fps=fps, overwrite=overwrite, frame=frame, dpi=dpi
        )
    finally:
        plt.close(fig)


def _gymnax_visualizer(task, states, returns, out, fps, frame, overwrite, dpi) -> int:
    """gymnax's own ``Visualizer`` (its figure, its drawing), frames grabbed as ours are."""
    from gymnax.visualize import Visualizer

    pyplot()  # the Agg backend before gymnax's pyplot figure
    vis = Visualizer(task.env, task.env_params, states, returns)
    try:
        vis.init()

        def update(t: int) -> None:
            vis.update(t)

        return save_animation(
            vis.fig, update, len(states), out, fps=fps, overwrite=overwrite, frame=frame, dpi=dpi
        )
    finally:
        pyplot().close(vis.fig)
