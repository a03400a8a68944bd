"""The condition experiment as docs/protocol.md, section 2 fixes it: several evolved
networks, each before pruning, after the covariance pruner's removals and after as many
removals at random and by magnitude (`eant2_jax.app.condition_controls`), each from the
same random initialisations; float64 CMA-ES state and float64 evaluation, no pruning, cond(C)
recorded every iteration; a positive control (an injected exact duplicate); the endpoints and
paired verdicts of `eant2_jax.app.condition_endpoints`; and whether exactly flat directions
(scaling symmetries, shared entries) account for the growth.

Every run of the experiment goes in ONE batch (`iterate`): its rows are padded to one gene
count, and the masked CMA-ES (`eant2_jax.kernels.cmaes`) computes cond(C) over each row's
own coordinates only, so padding adds no eigenvalue. The engine (`eant2_jax.exploitation`)
evaluates networks in float32 whatever its state's dtype; `iterate` is its CMA-ES iteration
without pruning or stop rules (the same keys, `cmaes.ask`/`tell` and cost call), with the
networks and the task in a dtype of the caller's choice (tests/test_condition_protocol.py
checks it against the engine in float32, to the bit).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..compiler import compile_genomes
from ..engine_state import default_popsize
from ..exploitation import init as engine_init
from ..genome import GeneKind, Genome
from ..kernels import cmaes, threefry
from ..kernels import network as kn
from ..pruning import kept_genes
from ..tasks.base import Task
from .condition import prune_rounds, recording_config
from .condition_controls import flat_directions, remove_like, with_duplicate
from .condition_endpoints import endpoints, paired_claim

__all__ = [
    "PRUNE_ROUNDS",
    "VERSIONS",
    "cast_task",
    "flat_share",
    "iterate",
    "protocol_experiment",
    "summarise",
]

VERSIONS = ("original", "pruned", "random", "magnitude")
# The pruning rounds' settings (`eant2_jax.app.condition.condition_experiment`'s defaults).
PRUNE_ROUNDS = {"rounds": 10, "iters": 2000, "window": 100, "sigma0": 0.1, "candidates": 4}


def cast_task(task: Task, dtype) -> Task:
    """``task`` with every floating-point array of it in ``dtype`` (its constants: start
    poses, the arm's chain, ...), so that a cost is computed in that dtype throughout."""

    def cast(a):
        if isinstance(a, (jax.Array, np.ndarray)) and jnp.issubdtype(a.dtype, jnp.floating):
            return jnp.asarray(a, dtype)
        return a

    return jax.tree.map(cast, task)


@functools.partial(jax.jit, static_argnames=("length", "eval_dtype"))
def _chunk(cma, params, keys, start, layout, task, task_key, *, length, eval_dtype):
    """``length`` CMA-ES iterations of every row from iteration ``start``: the engine's
    iteration without pruning (`eant2_jax.engine_step.step`: row keys fold the iteration,
    the task's key the tick), networks in ``eval_dtype``: ``(cma, cond [length, rows])``."""

    def body(cma, t):
        it = (start + t).astype(jnp.uint32)
        row_keys = jax.vmap(threefry.fold_in, in_axes=(0, None))(keys, it)
        x, _ = jax.vmap(cmaes.ask)(row_keys, cma, params)
        nets = jax.vmap(jax.vmap(kn.network, in_axes=(None, 0)))(layout, x.astype(eval_dtype))
        f = task.cost(threefry.fold_in(task_key, it), nets)
        cma = jax.vmap(cmaes.tell)(cma, x, f, params)
        return cma, cma.cond

    return jax.lax.scan(body, cma, jnp.arange(length, dtype=jnp.int32))


def iterate(
    state,
    layout: kn.Layout,
    task: Task,
    task_key: jax.Array,
    *,
    iters: int,
    chunk: int,
    eval_dtype="float64",
    on_chunk: Callable[[int, np.ndarray, object], None] | None = None,
    start: int = 0,
    cond: np.ndarray | None = None,
):
    """``iters`` CMA-ES iterations of every row of an engine state (`eant2_jax.exploitation.
    init`), none stopped or pruned, cond(C) recorded after each.

    Args:
      state: the engine's `ExploitState` ``[rows]`` (its ``cma``, ``params``, ``key``).
      layout: the rows' batched layout; task: the task (cast it with `cast_task`).
      task_key: the task's key (folded with the iteration).
      iters, chunk: iterations in all, and per compiled call (``iters`` a multiple of it).
      eval_dtype: the dtype the networks are evaluated in.
      on_chunk: called with the iterations done, the ``cond [done, rows]`` so far and the
        CMA-ES state.
      start, cond: go on from iteration ``start``, ``state.cma`` being the state after it
        and ``cond [start, rows]`` the record so far (a resumed run).

    Returns:
      ``(cma, cond)``: the final CMA-ES state and ``cond [iters, rows]`` (NumPy float64).
    """
    if iters % chunk:
        raise ValueError(f"iters {iters} is not a multiple of the chunk {chunk}")
    if start % chunk or (cond is not None and len(cond) != start):
        raise ValueError(f"cannot go on from iteration {start} with chunks of {chunk}")
    cma = state.cma
    parts = [] if cond is None else [np.asarray(cond, np.float64)]
    for first in range(start, iters, chunk):
        cma, c = _chunk(
            cma,
            state.params,
            state.key,
            jnp.int32(first),
            layout,
            task,
            task_key,
            length=chunk,
            eval_dtype=jnp.dtype(eval_dtype).name,
        )
        parts.append(np.asarray(c, np.float64))
        if on_chunk is not None:
            on_chunk(first + chunk, np.concatenate(parts), cma)
    return cma, np.concatenate(parts)


def flat_share(genome: Genome, mean, C, *, hidden: str, output: str, n_inputs: int) -> dict:
    """How much of cond(C) the exactly flat directions of ``genome`` at ``mean`` account for
    (`eant2_jax.app.condition_controls.flat_directions`): ``directions`` (their rank),
    ``top_alignment`` (the norm of C's top eigenvector's projection on their span, 0 to 1),
    ``log10_cond`` and ``log10_cond_off_flat`` (cond of C compressed to their orthogonal
    complement, which is at most cond(C)) and ``share``: the fraction of log10 cond(C) the
    compression removes."""
    n = len(genome)
    c = np.asarray(C, np.float64)[:n, :n]
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    log_cond = float(np.log10(lam[-1] / lam[0]))
    v = flat_directions(
        genome, np.asarray(mean)[:n], hidden=hidden, output=output, n_inputs=n_inputs
    )
    rank, top, off = 0, 0.0, log_cond
    if len(v):
        u, s, _ = np.linalg.svd(v.T, full_matrices=True)
        rank = int(np.sum(s > s[0] * 1e-10))
        span, rest = u[:, :rank], u[:, rank:]
        top = float(np.linalg.norm(span.T @ vec[:, -1]))
        lam_rest = np.linalg.eigvalsh(rest.T @ c @ rest)
        off = float(np.log10(lam_rest[-1] / lam_rest[0]))
    share = (log_cond - off) / log_cond if log_cond > 0 else 0.0
    return {
        "directions": rank,
        "top_alignment": top,
        "log10_cond": log_cond,
        "log10_cond_off_flat": off,
        "share": share,
    }


def _versions(genome, task, net_key, prune, saved=None) -> tuple[dict, list]:
    """A network's versions ``{name: (genome, kept indices)}`` and the pruner's records
    (those of ``saved``, a resumed run's network record, without pruning again)."""
    if saved is None:
        pruned, removed = prune_rounds(genome, task, jax.random.fold_in(net_key, 0), **prune)
    else:
        pruned, removed = Genome.parse(saved["genome_pruned"]), saved["removed"]
    kept = np.asarray(kept_genes(genome, pruned), np.int64)
    if len(kept) != len(pruned):
        raise ValueError("the pruned genome is not a sub-sequence of the original")
    count = len(genome) - len(pruned)
    versions = {"original": (genome, np.arange(len(genome))), "pruned": (pruned, kept)}
    versions["random"] = remove_like(
        genome, count, rule="random", key=jax.random.fold_in(net_key, 1)
    )
    versions["magnitude"] = remove_like(genome, count, rule="magnitude")
    if saved is not None and any(str(g) != saved[f"genome_{v}"] for v, (g, _) in versions.items()):
        raise ValueError("the resumed run's networks are not these networks' versions")
    return versions, removed


def protocol_experiment(
    genomes: Sequence[Genome],
    task: Task,
    *,
    network_keys: Sequence[jax.Array],
    init_keys: Sequence[jax.Array],
    iters: int = 10_000,
    chunk: int = 1000,
    sigma0: float = 0.5,
    weight_scale: float = 0.5,
    max_condition: float = 1e14,
    prune: dict | None = None,
    on_chunk: Callable[[int, dict], None] | None = None,
    resume: dict | None = None,
) -> dict:
    """docs/protocol.md, section 2 (JAX's x64 mode must be on).

    Network ``n`` (key ``network_keys[n]``: its pruning rounds from ``fold_in(key, 0)``, as
    `eant2_jax.app.condition.prune_rounds` prunes; its random control from ``fold_in(key,
    1)``) gives four versions (`VERSIONS`); initialisation ``j`` of it draws ``weight_scale *
    N(0, 1)`` weights from ``fold_in(fold_in(init_keys[j], n), 0)`` and its CMA-ES key
    ``fold_in(..., 1)``, the same for the four versions (each takes the draws on the genes
    it kept). The positive control is network 0 with an exact duplicate of its first input
    connection (the duplicate's weight equal to its twin's), from network 0's draws and keys.
    All rows run as one batch: `iterate`, ``iters`` iterations, float64, step size
    ``sigma0``, cond(C) bounded at ``max_condition``, one popsize (the CMA-ES default of the
    largest network). Versions that are the same network from the same draws run once.

    ``on_chunk(done, partial)`` gets before the first chunk (``done`` 0, after the pruning
    rounds) and after each chunk the result so far and, under
    ``"checkpoint"``, what ``resume`` takes to go on from there: ``networks`` (the versions,
    so the pruning rounds are not run again), ``done``, ``cond`` and ``cma`` (the CMA-ES
    state's arrays by field).

    Returns:
      ``rows`` (per run: network, version, init, size, ``log10_cond [iters]``, best cost,
      `flat_share` at the end), ``networks`` (sizes, genomes, pruning records), ``popsize``,
      ``iters`` and the settings.
    """
    prune = {**PRUNE_ROUNDS, **(prune or {})}
    saved = None if resume is None else resume["networks"]
    rows, starts, keys, networks, dup = _plan(
        genomes, task, network_keys, init_keys, weight_scale, prune, saved
    )
    source, first = _distinct_runs(rows, starts)
    popsize = default_popsize(max(len(g) for g in genomes))
    config = recording_config(sigma0, iters, max_condition, "float64")
    batch, state = _initial_state(starts, keys, first, task, config, popsize)
    meta = {
        "networks": networks,
        "popsize": popsize,
        "iters": iters,
        "sigma0": sigma0,
        "weight_scale": weight_scale,
        "max_condition": max_condition,
        "prune": prune,
        "duplicate_gene": dup,
        "distinct_runs": len(first),
    }

    def progress(done, cond, cma):
        if on_chunk is not None:
            point = {
                "networks": networks,
                "done": done,
                "cond": cond,
                "cma": {f.name: np.asarray(getattr(cma, f.name)) for f in dataclasses.fields(cma)},
            }
            on_chunk(done, dict(meta, rows=_rows(rows, cond[:, source]), checkpoint=point))

    cma, cond = _run(state, batch.layout, task, iters, chunk, progress, resume)
    return dict(meta, rows=_final_rows(rows, starts, source, cma, cond, task))


def _run(state, layout, task, iters, chunk, progress, resume) -> tuple:
    """``(cma, cond)`` of the distinct runs after ``iters`` iterations (`iterate`, float64),
    from the start or from ``resume``'s checkpoint; ``progress`` as `iterate`'s ``on_chunk``."""
    start, cond = 0, None
    if resume is not None:
        start, cond = int(resume["done"]), np.asarray(resume["cond"], np.float64)
        state = _resumed(state, resume["cma"])
    else:  # a checkpoint before the first chunk: the pruning rounds are not run again
        progress(0, np.zeros((0, state.cma.mean.shape[0])), state.cma)
    return iterate(
        state,
        layout,
        cast_task(task, jnp.float64),
        jax.random.key(0),
        iters=iters,
        chunk=min(chunk, iters),
        on_chunk=progress,
        start=start,
        cond=cond,
    )


def _final_rows(rows, starts, source, cma, cond, task) -> list[dict]:
    """The rows with their ``log10_cond`` traces, best costs and `flat_share` at the end
    (``source``: each row's distinct run)."""
    out_rows = _rows(rows, cond[:, source])
    mean, C, best = (np.asarray(a, np.float64)[source] for a in (cma.mean, cma.C, cma.best_cost))
    for i, (r, g) in enumerate(zip(out_rows, starts, strict=True)):
        r["best_cost"] = float(best[i])
        r["flat"] = flat_share(
            g, mean[i], C[i], hidden=task.hidden, output=task.output, n_inputs=task.n_inputs
        )
    return out_rows


def _distinct_runs(rows, starts):
    """Versions that are the same network (the pruner removed nothing, or a control chose
    the pruner's genes) from the same draws and key run once: the same trajectory.
    ``(source, first)``: each row's distinct run, and each distinct run's first row."""
    unique: dict[tuple, int] = {}
    source = np.array(
        [
            unique.setdefault((r["network"], r["init"], str(g)), len(unique))
            for r, g in zip(rows, starts, strict=True)
        ]
    )
    return source, [source.tolist().index(u) for u in range(len(unique))]


def _initial_state(starts, keys, first, task, config, popsize):
    """The batch and engine state of the distinct runs (rows ``first`` of ``starts`` and
    ``keys``): each run's mean at its start weights."""
    starts, keys = [starts[i] for i in first], [keys[i] for i in first]
    batch = compile_genomes(starts, task.n_inputs, pad_count=False)
    means = np.zeros(batch.weights.shape, np.float64)
    for u, genome in enumerate(starts):
        means[u, : len(genome)] = genome.weights
    state = engine_init(
        jnp.stack(keys), jnp.asarray(means), batch.layout.gene_mask, config, popsize=popsize
    )
    return batch, state


def _resumed(state, saved_cma):
    """``state`` with a checkpoint's CMA-ES arrays (refused unless their shapes fit)."""
    cma = state.cma.replace(**{k: jnp.asarray(v) for k, v in saved_cma.items()})
    if jax.tree.map(jnp.shape, cma) != jax.tree.map(jnp.shape, state.cma):
        raise ValueError("the resumed run's state does not fit these runs")
    return state.replace(cma=cma)


def _plan(genomes, task, network_keys, init_keys, weight_scale, prune, saved=None):
    """Every run of the experiment (`protocol_experiment`'s rule): ``(rows, starts, keys,
    networks, duplicate gene)``, a row, start genome and CMA-ES key per run."""
    rows, starts, keys, networks = [], [], [], []
    for n, (genome, net_key) in enumerate(zip(genomes, network_keys, strict=True)):
        versions, removed = _versions(
            genome, task, net_key, prune, None if saved is None else saved[n]
        )
        if n == 0:
            dup = next(i for i, g in enumerate(genome.genes) if g.kind == GeneKind.INPUT)
            versions["duplicate"] = (with_duplicate(genome, dup), None)
        networks.append(
            {
                "size": len(genome),
                "removed": removed,
                **{f"genome_{v}": str(g) for v, (g, _) in versions.items()},
            }
        )
        for j, init_key in enumerate(init_keys):
            k = jax.random.fold_in(init_key, n)
            w = weight_scale * np.asarray(
                jax.random.normal(jax.random.fold_in(k, 0), (len(genome),), jnp.float64)
            )
            for name, (g, kept) in versions.items():
                x = np.insert(w, dup + 1, w[dup]) if kept is None else w[kept]
                rows.append({"network": n, "version": name, "init": j, "size": len(g)})
                starts.append(g.with_weights(x))
                keys.append(jax.random.fold_in(k, 1))
    return rows, starts, keys, networks, dup


def _rows(rows: list[dict], cond: np.ndarray) -> list[dict]:
    """The rows with their ``log10_cond`` traces (``cond [done, rows]``)."""
    log_cond = np.log10(np.maximum(cond, 1.0)).T
    return [dict(r, log10_cond=log_cond[i]) for i, r in enumerate(rows)]


def summarise(result: dict, at=(1000, 5000, 10000)) -> dict:
    """Endpoints per run (with ``peak``, the largest log10 cond(C)), and the paired claims
    at each iteration of ``at`` reached: ``pruned``, ``random`` and ``magnitude`` each lower
    than ``original``; ``pruned`` lower than ``random`` and than ``magnitude``; the positive
    control (``duplicate`` against ``original`` on network 0) and the flat directions' share
    per version."""
    rows = result["rows"]
    for r in rows:
        e = endpoints(np.asarray(r["log10_cond"])[None], at)
        r["endpoints"] = {k: v[0] for k, v in e.items()}
        r["endpoints"]["peak"] = float(np.max(r["log10_cond"]))
    by = {(r["network"], r["version"], r["init"]): r for r in rows}
    done = len(rows[0]["log10_cond"])
    claims = []
    pairs = [
        ("pruned", "original"),
        ("random", "original"),
        ("magnitude", "original"),
        ("pruned", "random"),
        ("pruned", "magnitude"),
    ]
    keys = sorted({(n, j) for n, v, j in by if v == "original"})
    for k in [k for k in at if k <= done]:
        for a, b in pairs:
            va = [by[n, a, j]["endpoints"][f"at_{k}"] for n, j in keys]
            vb = [by[n, b, j]["endpoints"][f"at_{k}"] for n, j in keys]
            claims.append({"claim": f"{a} lower than {b}", "iteration": k, **paired_claim(va, vb)})
    nets = sorted({n for n, _ in keys})
    if done >= at[-1] and len(nets) > 1:
        # Not the protocol's verdict: the initialisations of one network are not independent
        # networks; the same claim on the networks' means (as many pairs as networks).
        k = at[-1]
        for a, b in pairs[:3]:
            va, vb = (
                [
                    np.mean([by[n, v, j]["endpoints"][f"at_{k}"] for m, j in keys if m == n])
                    for n in nets
                ]
                for v in (a, b)
            )
            claims.append(
                {
                    "claim": f"{a} lower than {b} (network means)",
                    "iteration": k,
                    **paired_claim(va, vb),
                }
            )
    bound = np.log10(result["max_condition"])
    dup = [r for r in rows if r["version"] == "duplicate"]
    orig0 = [by[0, "original", r["init"]] for r in dup]
    reached = [bool(np.max(r["log10_cond"]) >= bound - 1e-3) for r in dup]
    stayed = [bool(np.max(r["log10_cond"]) < bound - 1e-3) for r in orig0]
    positive = {
        "duplicate_reached_bound": reached,
        "without_duplicate_below_bound": stayed,
        "detects": all(reached) and all(stayed),
    }
    if done >= at[-1] and len(dup) > 1:
        positive["claim"] = paired_claim(
            [r["endpoints"][f"at_{at[-1]}"] for r in orig0],
            [r["endpoints"][f"at_{at[-1]}"] for r in dup],
        )
    flat = {}
    for v in {r["version"] for r in rows if "flat" in r}:
        fs = [r["flat"] for r in rows if r["version"] == v]
        flat[v] = {
            k: float(np.median([f[k] for f in fs]))
            for k in ("share", "top_alignment", "log10_cond", "log10_cond_off_flat")
        }
    return {"claims": claims, "positive_control": positive, "flat": flat, "done": done}
