"""Throughput of the visual servoing task (``eant2_jax.tasks.servo``) against MJX's raw rates.

One *move* is one network applied to one start pose, the arm moved, the markers projected and
the move scored. A cost call on ``N`` networks over the 1023 start poses does ``N * 1023``
moves; the batch (population x moves) is swept from 1e3 to 4e6 by ``N``.

Measured, each on the same device in the same run:

* ``task``: ``Servo.cost`` end to end (the public jit-compiled entry, ``servo.jit_cost``):
  network forward pass, increments, arm, projection, cost, mean over starts. Networks are
  random EANT2 genomes compiled by ``eant2_jax.compiler``: ``minimal`` (33 genes, every
  output reads every input: EANT2's start network; bucket H/P/sweeps 4/48/1) and ``paper``
  (~66 genes, the size of the paper's final networks; bucket 16/96/8). Modes ``kinematic``
  and ``dynamic`` (60 ``mjx.step`` of 5 ms per move); one closed-loop row
  (``moves_per_start = 5``).
* ``task_flat``: the same cost written with the arm as one flat batch of ``N * 1023`` (the
  task nests ``vmap`` over starts in ``vmap`` over networks); same numbers, other speed.
* ``bare_mjx_kinematics``: the reference rate: ``vmap`` over joint angles of
  ``mjx.kinematics`` (the task's model, ``mjx.Data`` with only ``qpos`` set) plus the 5-point
  projection and the mean image distance: the task's arm and cost without the network.
* ``hand_fk``: the same with the SCARA forward kinematics written by hand (closed form).
* ``mjx_step_raw``: MJX's raw step rate on the task's model: ``lax.scan`` of ``vmap(mjx.step)``
  carrying the whole ``mjx.Data`` (as ``mjx.benchmark`` does), 60 steps, same batch as the
  dynamic rows; ``mjx_step_raw_limits`` the same on the full ``arm.xml`` with its joint
  limit constraints on (what the task avoids); ``mjx_benchmark`` MJX's own
  ``mujoco.mjx.benchmark`` at one batch, for reference.

Timing: the first call (tracing + XLA compilation + one run) and then 1 to 7 steady-state
calls (fewer when a call takes seconds), each ended by ``block_until_ready``; the median is
reported and ``compile_s`` = first - median. Rows run in priority order until ``--budget-s``
is spent; the JSON is rewritten after every row, so an interrupted run keeps what it measured.

Run from the repository root::

    python -m bench servo                     # full sweep (sized for a GPU)
    python -m bench servo --quick             # a CPU-sized smoke run
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time
import traceback
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench import harness
from bench.common import environment, random_population
from bench.servo_tables import render
from eant2_jax.compiler import compile_genomes, network_batch
from eant2_jax.kernels import network as kn

N_INPUTS = 10
NETS = {"minimal": 33, "paper": 65}
KIN_NETS = (1, 16, 128, 1024, 4096)
DYN_NETS = (1, 16, 128, 1024)
PAPER_NETS = (128, 1024, 4096)
QUICK_KIN_NETS = (1, 4)
QUICK_DYN_NETS = (1,)
QUICK_PAPER_NETS = (4,)


# ----------------------------------------------------------------------------- helpers
def measure(fn: Callable[[], Any], *, max_repeats: int = 7) -> dict[str, Any]:
    """First call (compile + run), then steady-state calls: fewer when each takes seconds."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    while True:
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
        total = sum(times)
        if len(times) >= max_repeats or total > 3.0 or (len(times) >= 2 and total > 1.0):
            break
    median = statistics.median(times)
    return {
        "first_call_s": first,
        "median_s": median,
        "min_s": min(times),
        "times_s": times,
        "compile_s": max(first - median, 0.0),
    }


def networks(kind: str, count: int, seed: int = 0) -> tuple[kn.Network, dict[str, int]]:
    """``count`` compiled networks of one size class: 64 random genomes, tiled."""
    genomes = random_population(seed, min(count, 64), NETS[kind])
    batch = compile_genomes(genomes, N_INPUTS, pad_count=False)
    reps = -(-count // len(genomes))

    def tile(a):
        return jnp.tile(a, (reps,) + (1,) * (a.ndim - 1))[:count]

    layout = jax.tree.map(tile, batch.layout)
    weights = tile(batch.weights)
    nets = jax.jit(network_batch)(layout, weights)
    b = batch.bucket
    genes = float(np.mean([g.n_params for g in genomes]))
    return nets, {"neurons": b.neurons, "genes_bucket": b.genes, "sweeps": b.sweeps, "genes": genes}


# ------------------------------------------------------------------------ references
def bare_kinematics(task, q: jax.Array) -> jax.Array:
    """``[B]`` mean image distance after ``mjx.kinematics`` + projection at each of ``q``."""

    def one(qi):
        s = task.features(qi)
        return jnp.mean(jnp.sqrt(jnp.sum(jnp.square(s - task.goal), axis=-1)))

    return jax.vmap(one)(q)


# arm.xml: shoulder at the origin's vertical, links 0.35 and 0.30 m, camera 0.05 m beside the
# wrist axis, 0.40 m above the marker faces; the camera's axes are the world's rotated by
# q1 + q2 + q3 (MuJoCo camera frame: y up, looking down).
_L1, _L2, _OFF, _DEPTH = 0.35, 0.30, 0.05, 0.40


def hand_fk(task, q: jax.Array) -> jax.Array:
    """``bare_kinematics`` with the closed-form SCARA kinematics instead of MJX."""
    from eant2_jax.tasks.servo import FOCAL_PX, NORM_PX

    def one(qi):
        a1, a12, yaw = qi[0], qi[0] + qi[1], qi[0] + qi[1] + qi[2]
        c, s = jnp.cos(yaw), jnp.sin(yaw)
        cx = _L1 * jnp.cos(a1) + _L2 * jnp.cos(a12) + _OFF * c
        cy = _L1 * jnp.sin(a1) + _L2 * jnp.sin(a12) + _OFF * s
        rx, ry = task.markers[:, 0] - cx, task.markers[:, 1] - cy
        x_cam, y_cam = c * rx + s * ry, -s * rx + c * ry
        img = jnp.stack([x_cam, -y_cam], axis=-1) * (FOCAL_PX / NORM_PX / _DEPTH)
        return jnp.mean(jnp.sqrt(jnp.sum(jnp.square(img - task.goal), axis=-1)))

    return jax.vmap(one)(q)


@jax.jit
def flat_costs(task, nets: kn.Network) -> jax.Array:
    """The task's cost with the arm as ONE flat batch (the alternative to the task's nested vmap).

    The network runs as ``vmap`` over networks of ``vmap`` over starts (the first move's
    inputs are shared data: one matrix product per network over all starts); the arm, the
    projection and the move cost run on ONE flat batch of ``N * S`` arms.
    """
    from eant2_jax.tasks.servo import flatten_networks

    q0, x0 = task.q_start, task.x_start
    flat, batch = flatten_networks(nets)
    n, s = flat.bias.shape[0], q0.shape[0]

    def step(net, x, h):
        return kn.step(net, x, h, hidden=task.hidden, output=task.output)

    def forward(x, h):
        """``(y [N, S, 3], h [N, S, H])``; ``h`` None: the first move, inputs ``x`` ``[S, 10]``
        shared by every network and a zero state."""
        if h is None:

            def first(net):
                h0 = jnp.zeros_like(net.bias)
                return jax.vmap(lambda xi: step(net, xi, h0))(x)

            return jax.vmap(first)(flat)
        return jax.vmap(lambda net, xs, hs: jax.vmap(functools.partial(step, net))(xs, hs))(
            flat, x, h
        )

    arm = jax.vmap(task.move)

    def one_move(carry):
        q, qd, x, h = carry
        y, h = forward(x, h)
        dq = (task.max_step[None, None, :] * jnp.tanh(y)).reshape(n * s, 3)
        q, qd, x, cost = arm(q, qd, dq)
        return (q, qd, x.reshape(n, s, -1), h), cost.reshape(n, s)

    q = jnp.broadcast_to(q0[None], (n, s, 3)).reshape(n * s, 3)
    carry, cost = one_move((q, jnp.zeros_like(q), x0, None))
    if task.moves_per_start > 1:
        _, rest = jax.lax.scan(
            lambda c, _: one_move(c), carry, None, length=task.moves_per_start - 1
        )
        cost = (cost + jnp.sum(rest, axis=0)) / task.moves_per_start
    return jnp.mean(cost, axis=1).reshape(batch)


def raw_step_fn(model, nstep: int):
    """``lax.scan`` of ``vmap(mjx.step)`` over a batched ``mjx.Data`` (as mjx.benchmark)."""
    from mujoco import mjx

    @jax.jit
    def run(d):
        def body(d, _):
            with jax.numpy_rank_promotion("allow"):
                return jax.vmap(lambda di: mjx.step(model, di))(d), None

        d, _ = jax.lax.scan(body, d, None, length=nstep)
        return d

    return run


def raw_data(model, q: jax.Array):
    """A batched ``mjx.Data`` at joint angles ``q`` ``[B, 3]``, servo targets 0.1 rad away."""
    from mujoco import mjx

    return jax.jit(jax.vmap(lambda qi: mjx.make_data(model).replace(qpos=qi, ctrl=qi + 0.1)))(q)


def random_q(task, count: int) -> jax.Array:
    half = jnp.asarray((0.2, 0.3, 0.4), jnp.float32)
    goal = jnp.mean(task.q_start, axis=0)  # near q*; the draws only need to be plausible
    u = jax.random.uniform(jax.random.key(1), (count, 3), minval=-1.0, maxval=1.0)
    return goal[None, :] + u * half[None, :]


# ------------------------------------------------------------------------------ sweep
def run(args: argparse.Namespace, save_payload: harness.Save) -> dict[str, Any]:
    """Measure the rows in priority order until ``--budget-s`` is spent; the payload."""
    from mujoco import mjx

    from eant2_jax import tasks
    from eant2_jax.tasks import servo as sv

    t_start = time.perf_counter()
    kin_nets = QUICK_KIN_NETS if args.quick else KIN_NETS
    dyn_nets = QUICK_DYN_NETS if args.quick else DYN_NETS
    paper_nets = QUICK_PAPER_NETS if args.quick else PAPER_NETS
    n_starts = 1023
    payload: dict[str, Any] = {
        "benchmark": "servo",
        "environment": environment(),
        "config": {
            "n_starts": n_starts,
            "substeps": sv.SUBSTEPS,
            "kin_nets": list(kin_nets),
            "dyn_nets": list(dyn_nets),
            "nets": NETS,
            "budget_s": args.budget_s,
        },
        "rows": [],
        "skipped": [],
        "checks": {},
    }
    try:
        import subprocess

        smi = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        )
        payload["environment"]["nvidia_smi"] = smi.stdout.strip() or None
    except Exception:  # noqa: BLE001 - not an NVIDIA machine
        payload["environment"]["nvidia_smi"] = None

    def save():
        payload["elapsed_s"] = time.perf_counter() - t_start
        save_payload(payload)

    def row(name: str, fn: Callable, fn_args: tuple, moves: int, steps: int = 0, **extra):
        if time.perf_counter() - t_start > args.budget_s:
            payload["skipped"].append({"kind": name, "moves": moves, **extra})
            harness.log(f"skip {name} {extra} (budget)")
            return None
        try:
            m = measure(lambda: fn(*fn_args))
        except Exception as e:  # noqa: BLE001 - keep measuring the rest; record the failure
            payload["rows"].append({"kind": name, "moves": moves, "error": repr(e), **extra})
            harness.log(traceback.format_exc())
            save()
            return None
        r = {"kind": name, "moves": moves, **extra, **m}
        r["moves_per_s"] = moves / m["median_s"]
        if steps:
            r["steps"] = steps
            r["steps_per_s"] = steps / m["median_s"]
        payload["rows"].append(r)
        harness.log(
            f"{name:22s} {json.dumps(extra):60s} moves {moves:9d} "
            f"median {m['median_s'] * 1e3:9.3f} ms  {r['moves_per_s']:.3g} moves/s  "
            f"first {m['first_call_s']:.2f} s"
        )
        save()
        return r

    kin = tasks.make("servo", n_starts=n_starts)
    dyn = tasks.make("servo", mode="dynamic", n_starts=n_starts)
    cost = sv.jit_cost
    flat = flat_costs
    bare = jax.jit(bare_kinematics)
    bare_nested = jax.jit(lambda task, q: jax.vmap(functools.partial(bare_kinematics, task))(q))
    hand = jax.jit(hand_fk)

    # Agreement of the references (same poses): hand FK vs MJX, in image units.
    q_check = random_q(kin, 4096)
    payload["checks"]["hand_fk_vs_mjx_max_abs"] = float(
        jnp.max(jnp.abs(hand(kin, q_check) - bare(kin, q_check)))
    )
    payload["checks"]["baselines_kinematic"] = kin.baselines()
    payload["checks"]["ibvs_gain_kinematic"] = kin.ibvs_gain()
    # Costs of 16 fixed networks: compare across devices (CPU results in the docs).
    payload["checks"]["costs_minimal_16"] = np.asarray(
        cost(kin, networks("minimal", 16)[0])
    ).tolist()
    save()

    # 1. kinematic mode, minimal networks, and the bare references at the same batches.
    for n in kin_nets:
        moves = n * n_starts
        nets, info = networks("minimal", n)
        row("task", cost, (kin, nets), moves, mode="kinematic", net="minimal", n_nets=n, **info)
        row("task_flat", flat, (kin, nets), moves, mode="kinematic", net="minimal", n_nets=n)
        q = random_q(kin, moves)
        row("bare_mjx_kinematics", bare, (kin, q), moves)
        row("bare_mjx_kinematics_nested", bare_nested, (kin, q.reshape(n, n_starts, 3)), moves)
        row("hand_fk", hand, (kin, q), moves)
        del nets, q

    # 2. dynamic mode, minimal networks, and MJX's raw step at the same batches.
    raw = raw_step_fn(dyn.model, sv.SUBSTEPS)
    for n in dyn_nets:
        moves = n * n_starts
        steps = moves * sv.SUBSTEPS
        nets, info = networks("minimal", n)
        row(
            "task", cost, (dyn, nets), moves, steps, mode="dynamic", net="minimal", n_nets=n, **info
        )
        if n in (128, dyn_nets[-1]):
            row(
                "task_flat",
                flat,
                (dyn, nets),
                moves,
                steps,
                mode="dynamic",
                net="minimal",
                n_nets=n,
            )
        del nets
        d = raw_data(dyn.model, random_q(dyn, moves))
        row("mjx_step_raw", raw, (d,), moves, steps)
        del d

    # 3. kinematic mode, paper-size networks.
    for n in paper_nets:
        nets, info = networks("paper", n)
        row(
            "task", cost, (kin, nets), n * n_starts, mode="kinematic", net="paper", n_nets=n, **info
        )
        del nets

    # 4. closed loop, and the dynamic mode with paper-size networks at the largest batch.
    n = dyn_nets[-1]
    loop = tasks.make("servo", n_starts=n_starts, moves_per_start=5)
    nets, info = networks("minimal", n)
    row(
        "task",
        cost,
        (loop, nets),
        5 * n * n_starts,
        mode="kinematic",
        net="minimal",
        n_nets=n,
        moves_per_start=5,
        **info,
    )
    n = dyn_nets[-1]
    nets, info = networks("paper", n)
    row(
        "task",
        cost,
        (dyn, nets),
        n * n_starts,
        n * n_starts * sv.SUBSTEPS,
        mode="dynamic",
        net="paper",
        n_nets=n,
        **info,
    )
    del nets

    # 5. what the limit constraints would cost: MJX's raw step on the full arm.xml.
    import mujoco

    full = mjx.put_model(mujoco.MjModel.from_xml_path(str(sv.ARM_XML)))
    raw_full = raw_step_fn(full, sv.SUBSTEPS)
    for n in [m for m in dyn_nets if m in (1, 128)]:
        moves = n * n_starts
        d = raw_data(full, random_q(dyn, moves))
        row("mjx_step_raw_limits", raw_full, (d,), moves, moves * sv.SUBSTEPS)
        del d

    # 6. MJX's own benchmark utility on the task's model (solver settings are its defaults).
    if time.perf_counter() - t_start < args.budget_s:
        try:
            batch = 1024 if args.quick else 65536
            jit_s, run_s, steps = mjx.benchmark(
                sv.stripped_model(), nstep=sv.SUBSTEPS, batch_size=batch
            )
            payload["rows"].append({
                "kind": "mjx_benchmark", "moves": batch, "steps": steps, "compile_s": jit_s,
                "median_s": run_s, "steps_per_s": steps / run_s, "moves_per_s": batch / run_s,
            })  # fmt: skip
        except Exception as e:  # noqa: BLE001
            payload["rows"].append({"kind": "mjx_benchmark", "error": repr(e)})
        save()
    harness.log(f"done in {time.perf_counter() - t_start:.1f} s")
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--budget-s", type=float, default=330.0, help="stop starting rows after this")


SUITE = harness.Suite(
    name="servo",
    title="Visual servoing task throughput",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
)

main = SUITE.main
