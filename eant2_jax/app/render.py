"""``eant2 render``: an animation of a network's behaviour on its task (GIF; MP4 with ffmpeg).

The network is a genome file (`eant2_jax.genomefile`) or a run directory's champion
(``best.genome``, read through `eant2_jax.rundir.RunDir`). Its task is the one the file's
header records, rebuilt by itself only when it is registered (`eant2_jax.tasks.is_registered`);
a user's task (``module:factory``, ``file.py:factory``) is never imported because a file names
it: the user names it again with ``--task`` (docs/reliability.md, "Trust").

What is drawn (`eant2_jax.app.draw`, matplotlib on the Agg backend, no display):

* the servo task (`eant2_jax.tasks.servo`): the arm moving, closed loop, from start poses
  chosen by the key towards the goal pose (top view, from the arm's forward kinematics), and
  the camera's image: goal image features (rings) against the current ones (dots);
* a gymnax environment (`eant2_jax.tasks.gymnax_task`): one episode, drawn by gymnax's own
  visualizer (``gymnax.visualize``) where it has one that runs here, else by matplotlib
  (CartPole, Pendulum).

The states are the task's own: a rollout calls the task's own step functions (``Servo.move``
and ``network_policy``; the environment's ``reset`` and ``step`` with the episode's key
schedule of `eant2_jax.tasks.episodic.rollout`), so its costs and returns equal the task's
(tests/test_render.py). Everything random comes from the key of ``--seed``.
"""

from __future__ import annotations

import argparse
import functools
import json
import threading
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Episode",
    "ServoMoves",
    "add_arguments",
    "command",
    "gymnax_episode",
    "network_of",
    "read_source",
    "servo_moves",
    "task_kind",
    "task_of",
]


# ------------------------------------------------------------------------ the network
def read_source(path: str) -> tuple[Any, str]:
    """The genome file at ``path``, or the champion of the run directory ``path`` is:
    ``(GenomeFile, name)``. Read as data, within bounds (one-line ValueError otherwise)."""
    from eant2_jax.genomefile import GenomeFile, read_text
    from eant2_jax.rundir import RunDir

    p = Path(path)
    if not p.is_dir():
        return GenomeFile.parse(read_text(p), source=str(p)), p.name
    with RunDir.open(p, lock=False) as rundir:
        committed = rundir.read()
    if not committed.best:
        raise ValueError(f"{p}: the run directory has no best.genome yet")
    spec = GenomeFile.parse(committed.best, source=str(p / "best.genome"))
    if spec.task is None and isinstance(committed.config.get("task"), str):
        import dataclasses

        options = committed.config.get("task_options")
        spec = dataclasses.replace(
            spec,
            task=committed.config["task"],
            task_options=options if isinstance(options, dict) else None,
        )
    return spec, f"{p.name}/best.genome"


def task_of(spec: Any, source: str, *, task: str | None = None, options: dict | None = None):
    """The task to play ``spec`` on: ``task`` when the user names it (built with the file's
    recorded options, then ``options``), else the file's recorded task if it is registered.

    Raises:
      ValueError: one line: no task recorded or named, a user task not named again, or a
        task the genome does not fit.
    """
    import eant2_jax
    from eant2_jax.tasks import is_registered

    from . import process

    recorded = spec.task
    merged = {**(spec.task_options or {}), **(options or {})}
    if task is not None:
        if recorded is not None and task != recorded and not is_registered(recorded):
            merged = dict(options or {})  # another user task: the recorded options are not its
        process.user_modules()  # a spec typed on the command line may name the user's module
        built = eant2_jax.tasks.make(task, **merged)
    elif recorded is None:
        raise ValueError(f"{source}: no task recorded; name one with --task SPEC")
    elif not is_registered(recorded):
        raise ValueError(
            f"{source}: its task {recorded!r:.80} is user code, which is not run because a "
            "file names it; name it again: eant2 render SOURCE --task SPEC"
        )
    else:
        built = eant2_jax.tasks.make(recorded, **merged)
    try:
        eant2_jax.tasks.check_task(built, [spec.genome], what=f"task {task or recorded!r}")
    except ValueError as e:
        raise ValueError(f"{source}: the genome does not fit: {e}") from None
    return built


def network_of(spec: Any, task: Any):
    """The compiled network (one, no batch dimension) of ``spec`` for ``task``'s inputs; the
    file's activations must be the task's (a mismatch is one-line GenomeFileError)."""
    from eant2_jax.compiler import networks

    spec.with_activations(task.hidden, task.output)
    return jax.tree.map(lambda a: a[0], networks([spec.genome], int(task.n_inputs)))


# ------------------------------------------------------------------------ the rollouts
class ServoMoves(NamedTuple):
    """Closed-loop moves of one network from S start poses (`servo_moves`).

    Attributes:
      starts: ``[S]`` indices into the task's start poses.
      q: ``[S, M + 1, 3]`` joint angles, before the first move and after each.
      x: ``[S, M + 1, 10]`` the network's inputs there (image minus goal image).
      cost: ``[S, M]`` each move's cost (`eant2_jax.tasks.servo.Servo.move`).
    """

    starts: Any
    q: Any
    x: Any
    cost: Any


@functools.partial(jax.jit, static_argnames=("moves",))
def _servo_moves(task, net, starts, moves: int):
    policy = task.network_policy(net)

    def one(q0, x0):
        # Servo.episode's loop, keeping every pose: the same policy and move functions.
        def body(carry, _):
            q, qd, x, h = carry
            dq, h = policy(h, q, x)
            q, qd, x, c = task.move(q, qd, dq)
            return (q, qd, x, h), (q, x, c)

        carry = (q0, jnp.zeros_like(q0), x0, jnp.zeros_like(net.bias))
        _, (qs, xs, cs) = jax.lax.scan(body, carry, None, length=moves)
        return jnp.concatenate([q0[None], qs]), jnp.concatenate([x0[None], xs]), cs

    return jax.vmap(one)(task.q_start[starts], task.x_start[starts])


def servo_moves(task: Any, net: Any, key: Any, *, starts: int, moves: int) -> ServoMoves:
    """``moves`` closed-loop moves of ``net`` from ``starts`` start poses of ``task``, drawn
    without replacement by ``key`` (host arrays)."""
    n = int(task.n_starts)
    if not 1 <= starts <= n:
        raise ValueError(f"--starts must be in [1, {n}] (the task's start poses), got {starts}")
    idx = jax.random.choice(key, n, (starts,), replace=False)
    q, x, cost = _servo_moves(task, net, idx, int(moves))
    return ServoMoves(np.asarray(idx), np.asarray(q), np.asarray(x), np.asarray(cost))


class Episode(NamedTuple):
    """One episode of one network in an environment task (`gymnax_episode`).

    Attributes:
      states: the environment's state before each step taken (a pytree of ``[T, ...]``).
      actions: ``[T, ...]`` the actions taken; rewards: ``[T]`` their rewards.
      ret: the episode's return, as ``task.episode`` gives it.
      length: steps of the whole episode; ``T = min(length, steps)`` are kept.
    """

    states: Any
    actions: Any
    rewards: Any
    ret: float
    length: int


class _Recording:
    """The task, but for ``play``: its ``step`` also hands each step's state (before the
    step), action and reward to the host (an ordered ``io_callback`` into `_record`)."""

    def __init__(self, task: Any):
        self._task = task

    def __getattr__(self, name: str) -> Any:
        return getattr(self._task, name)

    def play(self, net, key, reset, step):
        from jax.experimental import io_callback

        def recorded(k, state, action):
            out = step(k, state, action)
            io_callback(_record, None, state, action, out[2], ordered=True)
            return out

        return self._task.play(net, key, reset, recorded)


# Where `_record` puts the rows of the episode being recorded (`gymnax_episode`): one
# compiled program serves every call, so its callback cannot hold a caller's list, and the
# callback runs on the runtime's thread; one recording at a time (`_LOCK`).
_SINK: list[list] = []
_LOCK = threading.Lock()


def _record(*row) -> None:
    _SINK[-1].append(row)


@jax.jit
def _recorded_episode(task, net, key):
    return type(task).episode(_Recording(task), net, key)


def gymnax_episode(task: Any, net: Any, key: Any, *, steps: int | None = None) -> Episode:
    """The episode ``task.episode(net, key)`` plays, with its states (host arrays); at most
    ``steps`` of them are kept (default all).

    It is the task's own ``episode`` (its reset and step, `eant2_jax.tasks.episodic.rollout`'s
    loop and key schedule), run with a ``play`` that records every step on the host.
    """
    rows: list = []
    with _LOCK:
        _SINK.append(rows)
        try:
            ret, length = _recorded_episode(task, net, key)
            jax.effects_barrier()  # every callback has run
        finally:
            _SINK.pop()
    length = int(length)
    # The loop runs blocks of steps: the steps after the episode's end are masked, dropped.
    rows = rows[: length if steps is None else min(length, int(steps))]
    if not rows:
        raise ValueError("the episode has no step to draw")
    states, actions, rewards = (
        jax.tree.map(lambda *a: np.stack(a), *col) for col in zip(*rows, strict=True)
    )
    return Episode(states, actions, rewards, float(ret), length)


def task_kind(task: Any) -> str | None:
    """``"servo"``, ``"gymnax"`` or None: which rollout plays ``task`` (a task's module is
    imported already when the task is one of its kind)."""
    import sys

    for kind, module, name in (
        ("servo", "servo", "Servo"),
        ("gymnax", "gymnax_task", "GymnaxTask"),
    ):
        cls = getattr(sys.modules.get(f"eant2_jax.tasks.{module}"), name, None)
        if cls is not None and isinstance(task, cls):
            return kind
    return None


# ------------------------------------------------------------------------ the command
def add_arguments(p: argparse.ArgumentParser) -> None:
    """``eant2 render``'s arguments."""
    from .parser import positive, seed

    p.add_argument("source", help="a genome file, or a run directory (its best.genome)")
    p.add_argument(
        "--task",
        default=None,
        metavar="SPEC",
        help="the task, named again: needed when the file's task is your own code (never "
        "imported because a file names it), or to play the genome on another task",
    )
    p.add_argument(
        "--task-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="option of the task (repeatable), over the recorded ones",
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=0,
        help="seed of the key: the episode, or which start poses (default 0)",
    )
    p.add_argument(
        "--steps",
        type=positive,
        default=None,
        help="servo: moves per start pose (default 6); gymnax: steps drawn at "
        "most (default: the whole episode)",
    )
    p.add_argument(
        "--starts",
        type=positive,
        default=3,
        help="servo: start poses shown, one after another (default 3)",
    )
    p.add_argument(
        "--fps", type=positive, default=None, help="frames per second (default: servo 3, gymnax 25)"
    )
    p.add_argument(
        "--out",
        default=None,
        help="the animation to write, .gif or .mp4 (mp4 needs ffmpeg); default "
        "SOURCE-rollout.gif beside the source",
    )
    p.add_argument(
        "--frame", default=None, metavar="PNG", help="also save the animation's last frame as a PNG"
    )
    p.add_argument("--force", action="store_true", help="replace existing files")


def _out_path(args: argparse.Namespace) -> Path:
    src = Path(args.source)
    out = Path(args.out) if args.out else src.parent / f"{src.name}-rollout.gif"
    for path in (out, Path(args.frame) if args.frame else None):
        if path is not None and (path.exists() or path.is_symlink()) and not args.force:
            raise ValueError(f"{path} exists; not overwriting (use --out or --force)")
    return out


def command(args: argparse.Namespace) -> int:
    """``eant2 render``: write the animation (and ``--frame``), print what it shows."""
    from . import draw
    from .parser import task_options

    out = _out_path(args)
    draw.check_format(out)
    spec, name = read_source(args.source)
    task = task_of(spec, args.source, task=args.task, options=task_options(args.task_option))
    net = network_of(spec, task)
    key = jax.random.key(args.seed)
    frame = Path(args.frame) if args.frame else None
    kind = task_kind(task)
    if kind == "servo":
        moves = servo_moves(task, net, key, starts=args.starts, moves=args.steps or 6)
        frames = draw.servo_animation(
            task, moves, out, title=name, fps=args.fps or 3, frame=frame, overwrite=args.force
        )
        first, last = moves.cost[:, 0].mean(), moves.cost[:, -1].mean()
        print(
            f"servo: starts {moves.starts.tolist()}, {moves.q.shape[1] - 1} moves each; "
            f"mean move cost {first:.4f} after the first move, {last:.4f} after the last"
        )
    elif kind == "gymnax":
        episode = gymnax_episode(task, net, key, steps=args.steps)
        frames = draw.gymnax_animation(
            task, episode, out, title=name, fps=args.fps or 25, frame=frame, overwrite=args.force
        )
        print(
            f"{task.env_name}: return {episode.ret:g} over {episode.length} steps "
            f"(key {args.seed}); {frames} frames"
        )
    else:
        raise ValueError(
            f"eant2 render draws the servo task and gymnax environments, not "
            f"{json.dumps(args.task or spec.task)} ({type(task).__name__})"
        )
    print(f"animation: {out} ({frames} frames)")
    if frame is not None:
        print(f"frame: {frame}")
    return 0
