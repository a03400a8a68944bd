"""CMA-ES iterations on the servo task: this project's batched engine against pycma with the
networks evaluated by vectorised NumPy on the same compiled tensors.

The reference is what a CPU implementation of EANT2 would do: one pycma instance per
structure, each iteration ``ask`` -> NumPy forward pass of all candidates over the 1023 start
poses (dense tensors scattered from the same compiled layout) -> NumPy kinematics of the SCARA
arm, projection and move cost -> ``tell``. The NumPy cost is checked against the JAX task's
cost before timing (``max_rel_err`` in the output). Both sides use the same population size.

Run: ``python -m bench pycma [--structures 20] [--iters 30] [--quick]``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import jax
import numpy as np

from bench import harness
from bench.common import Column, environment, markdown_table, random_population
from eant2_jax import exploitation as ex
from eant2_jax import tasks, tuning
from eant2_jax.kernels import network as kn
from eant2_jax.tasks import servo as sv

# The arm's planar chain (arm.xml): link lengths, camera offset and height (metres).
_L1, _L2, _CAM_X, _CAM_Z = 0.35, 0.30, 0.05, 0.41
_ACT = {"tanh": np.tanh, "identity": lambda a: a}


def numpy_forward(slot, gene_mask, is_root, neuron_mask, sweeps, params, x, n_out, hidden, output):
    """Outputs ``[lambda, N, n_out]`` of one structure's candidates ``params [lambda, P]`` on
    inputs ``x [N, n_in]``, from the compiled layout (float64, vectorised NumPy)."""
    lam, h, n_in = params.shape[0], is_root.shape[0], x.shape[1]
    flat = np.zeros((lam, kn.buffer_size(h, n_in, n_out)))
    rows = np.repeat(np.arange(lam), slot.shape[0])
    np.add.at(flat, (rows, np.tile(slot, lam)), (params * gene_mask).reshape(-1))
    o = np.cumsum([0, h * n_in, h, h * h, h * h])
    w_in = flat[:, o[0] : o[1]].reshape(lam, h, n_in)
    bias = flat[:, o[1] : o[2]]
    w_ff = flat[:, o[2] : o[3]].reshape(lam, h, h)
    w_out = flat[:, o[4] : o[4] + n_out * h].reshape(lam, n_out, h)
    base = np.einsum("lhi,ni->lnh", w_in, x) + bias[:, None, :]  # one step: no recurrent input
    state = np.zeros_like(base)
    for _ in range(sweeps):
        a = base + np.einsum("lhk,lnk->lnh", w_ff, state)
        state = np.where(is_root, _ACT[output](a), _ACT[hidden](a)) * neuron_mask
    return np.einsum("loh,lnh->lno", w_out, state)


def numpy_servo_cost(task: sv.Servo, y: np.ndarray) -> np.ndarray:
    """The kinematic servo cost ``[lambda]`` of network outputs ``y [lambda, N, 3]``."""
    q0 = np.asarray(task.q_start, np.float64)
    lo, hi = np.asarray(task.q_lo, np.float64), np.asarray(task.q_hi, np.float64)
    command = q0 + np.asarray(task.max_step, np.float64) * np.tanh(y)
    at_limit = (command <= lo) | (command >= hi)
    q = np.clip(command, lo, hi)
    a0 = q[..., 0]
    a1 = a0 + q[..., 1]
    phi = a1 + q[..., 2]
    cx = _L1 * np.cos(a0) + _L2 * np.cos(a1) + _CAM_X * np.cos(phi)
    cy = _L1 * np.sin(a0) + _L2 * np.sin(a1) + _CAM_X * np.sin(phi)
    markers = np.asarray(task.markers, np.float64)  # [5, 3]
    rx = markers[:, 0] - cx[..., None]  # [lambda, N, 5]
    ry = markers[:, 1] - cy[..., None]
    rz = markers[:, 2] - _CAM_Z
    c, s = np.cos(phi)[..., None], np.sin(phi)[..., None]
    # Camera frame = R_z(phi): x_c = rel . e_x, y_c = rel . e_y, z_c = rel_z (looking down -z).
    xc, yc = c * rx + s * ry, -s * rx + c * ry
    scale = sv.FOCAL_PX / sv.NORM_PX
    img = np.stack([scale * xc / -rz, scale * -yc / -rz], axis=-1)  # [lambda, N, 5, 2]
    dist = np.sqrt(np.sum((img - np.asarray(task.goal)) ** 2, axis=-1)).mean(axis=-1)
    outside = (np.abs(img[..., 0]) >= sv.HALF_EXTENT[0]) | (
        np.abs(img[..., 1]) >= sv.HALF_EXTENT[1]
    )
    move = dist + sv.OUTSIDE_PENALTY * outside.sum(-1) + sv.LIMIT_PENALTY * at_limit.sum(-1)
    return move.mean(axis=-1)


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--structures", type=int, default=20)
    p.add_argument("--genes", type=int, default=50)
    p.add_argument("--iters", type=int, default=30, help="timed iterations of each side")
    p.add_argument("--moves", type=int, default=1023)


def _prepare(args: argparse.Namespace) -> None:
    if args.quick:
        args.structures, args.iters, args.moves = 2, 3, 32


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    import cma

    task = tasks.make("servo", n_starts=args.moves)
    genomes = random_population(2, args.structures, args.genes)
    keys = jax.random.split(jax.random.key(0), args.structures)
    # The engine's side, prepared as every caller does (compile, popsize, initial state).
    config = ex.ExploitConfig(max_iters=args.iters, chunk=args.iters, patience=10**6,
                              sigma_tol=0.0, tolfun=None, pruner="none")  # fmt: skip
    prep = tuning.prepare(
        genomes, task, key=jax.random.key(0), config=config, keys=keys, pad_count=False
    )
    batch, popsize = prep.batch, prep.popsize
    lay = jax.tree.map(np.asarray, batch.layout)
    x = np.asarray(task.x_start, np.float64)

    def cost_np(i, params):
        y = numpy_forward(
            lay.slot[i],
            lay.gene_mask[i],
            lay.is_root[i],
            lay.neuron_mask[i],
            lay.sweeps,
            params,
            x,
            task.n_outputs,
            task.hidden,
            task.output,
        )
        return numpy_servo_cost(task, y)  # fmt: skip

    # Correctness first: the NumPy cost equals the task's JAX cost on random candidates.
    rng = np.random.default_rng(0)
    trial = np.asarray(batch.weights)[:, None, :] + 0.3 * rng.normal(
        size=(args.structures, 4, batch.bucket.genes)
    )
    want = np.asarray(
        ex.costs(task, jax.random.key(0), batch.layout, trial.astype(np.float32)), np.float64
    )
    got = np.stack([cost_np(i, trial[i]) for i in range(args.structures)])
    max_rel_err = float(np.max(np.abs(got - want) / np.abs(want)))

    # pycma + NumPy: one ES per structure, one iteration = every structure asks and tells.
    es = []
    for i, g in enumerate(genomes):
        opts = {"popsize": popsize, "seed": i + 1, "verbose": -9}
        es.append(cma.CMAEvolutionStrategy(np.asarray(g.weights), 0.5, opts))

    def pycma_iteration():
        for i, e in enumerate(es):
            xs = np.asarray(e.ask())
            full = np.zeros((popsize, batch.bucket.genes))
            full[:, : xs.shape[1]] = xs
            e.tell(list(xs), cost_np(i, full).tolist())

    pycma_iteration()  # warm-up
    t0 = time.perf_counter()
    for _ in range(args.iters):
        pycma_iteration()
    t_pycma = (time.perf_counter() - t0) / args.iters

    # This project: the same structures and popsize, `iters` iterations in one compiled chunk.

    def engine():
        st, _ = ex.run(prep.state, batch.layout, task, key=jax.random.key(1), config=config)
        return jax.block_until_ready(st.evals)

    engine()  # compile
    t0 = time.perf_counter()
    engine()
    t_engine = (time.perf_counter() - t0) / args.iters
    row = {"structures": args.structures, "genes": args.genes, "P": batch.bucket.genes,
           "popsize": popsize, "moves": args.moves, "pycma_numpy_ms": 1e3 * t_pycma,
           "engine_ms": 1e3 * t_engine, "speedup": t_pycma / t_engine,
           "max_rel_err": max_rel_err}  # fmt: skip
    return {"environment": environment(), "config": harness.settings(args), "rows": [row]}


COLUMNS = [
    Column("structures", "S"), Column("genes", "genes"), Column("P", "P"),
    Column("popsize", "popsize"), Column("moves", "moves"),
    Column("pycma_numpy_ms", "pycma + NumPy ms / iteration", "{:.1f}"),
    Column("engine_ms", "batched engine ms / iteration", "{:.3f}"),
    Column("speedup", "speed-up", "{:.0f}x"),
]  # fmt: skip


def render(payload: dict[str, Any]) -> str:
    (row,) = payload["rows"]
    return (
        "Engine on the device named; pycma + NumPy on the host CPU; NumPy cost vs JAX cost "
        f"max relative error {row['max_rel_err']:.1e}.\n\n" + markdown_table([row], COLUMNS)
    )


SUITE = harness.Suite(
    name="pycma",
    title="Batched CMA-ES engine vs pycma + NumPy on the servo task",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
