"""Determinism on GPU: what XLA's deterministic mode costs, and whether runs repeat without it.

Two parts (``--parts``), each case in a fresh process with no persistent compilation cache:

* ``iteration``: one batch of ``--structures`` random servo structures of about ``--genes``
  genes (the size of ``eant2 reproduce``'s lock-step batches: 10 runs x 20 structures) run
  by the exploitation engine, without a pruner and with the covariance pruner (``--pruners``;
  ``--quick`` times the first only); the median milliseconds of one engine iteration (over
  ``--repeats`` compiled chunks of ``--chunk`` iterations) with XLA's default GPU programs
  and with ``--xla_gpu_deterministic_ops=true``
  (the ``eant2`` command line's default), for this install and every ``--pythonpath`` one.
* ``repeat``: ``eant2 run TASK --population P --generations G`` twice, each time in a fresh
  process with an empty cache (so XLA compiles and autotunes afresh), with the command
  line's deterministic default and with ``EANT2_GPU_DETERMINISTIC=0``: the best cost of each
  generation and whether the second run's best network equals the first's to the bit
  (``--quick``: without a pruner).

On a CPU both flags give the same programs; the suite is meant for GPUs.

Run: ``python -m bench determinism [--parts iteration,repeat] [--pythonpath OLD_INSTALL]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    child_env,
    eant2_argv,
    eant2_pruner,
    environment,
    markdown_table,
    random_population,
)

FLAG = "--xla_gpu_deterministic_ops=true"

_CHILD = textwrap.dedent(
    """
    import json, sys, time
    import jax
    import numpy as np
    from eant2_jax import exploitation as ex, pruning, tasks, tuning
    from eant2_jax.genome import Genome
    spec = json.loads(open(sys.argv[1]).read())
    genomes = [Genome.parse(t) for t in spec["genomes"]]
    task = tasks.make("servo", mode="kinematic")
    out = {"device": jax.devices()[0].device_kind}
    for pruner in spec["pruners"]:
        conf = ex.ExploitConfig(pruner=pruner)
        prep = tuning.prepare(genomes, task, key=jax.random.key(0), config=conf,
                              pad_count=False)
        tables = prep.tables
        if tables is None:
            tables = pruning.inert_tables(*prep.batch.layout.slot.shape)
        dev = jax.devices()[0]
        call = jax.device_put((prep.state, prep.batch.layout, tables, task), dev)
        st, layout, tables, task_d = call
        key, n = jax.random.key(1), spec["chunk"]
        t0 = time.perf_counter()
        res = ex.run_chunk(st, layout, tables, task_d, key, conf, n)
        jax.block_until_ready(res)
        first = time.perf_counter() - t0
        times = []
        for _ in range(spec["repeats"]):
            t0 = time.perf_counter()
            jax.block_until_ready(ex.run_chunk(st, layout, tables, task_d, key, conf, n)[0])
            times.append(time.perf_counter() - t0)
        out[pruner] = {"first_s": first, "iteration_ms": 1e3 * float(np.median(times)) / n,
                       "best": float(np.min(np.asarray(res[0].cma.best_cost))),
                       "popsize": ex.popsize_of(res[0]),
                       "genes": int(prep.batch.bucket.genes)}
    print(json.dumps(out))
    """
)


# XLA:CPU's choice of emitters, which a --quick child keeps from its caller's XLA_FLAGS: the
# test suite compiles with the faster older ones (tests/conftest.py), and a smoke test's
# children need not compile slower than the suite around them. It changes no result on a GPU.
_CPU_EMITTERS = re.compile(r"--xla_cpu_use_fusion_emitters=\S*")


def _env(pythonpath: str | None, quick: bool, **extra: str) -> dict[str, str]:
    """A child's environment: no persistent cache, XLA_FLAGS only as ``extra`` sets them
    (with ``quick``, plus the caller's choice of XLA:CPU's emitters)."""
    env = child_env(pythonpath, EANT2_CACHE_DIR="", JAX_ENABLE_COMPILATION_CACHE="false",
                    **extra)  # fmt: skip
    kept = _CPU_EMITTERS.findall(os.environ.get("XLA_FLAGS", "")) if quick else []
    flags = " ".join([extra.get("XLA_FLAGS", ""), *kept]).strip()
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    return env


def _iteration(args, label: str, pythonpath: str | None, deterministic: bool) -> dict:
    genomes = random_population(args.seed, args.structures, args.genes)
    with tempfile.TemporaryDirectory() as tmp:
        spec = Path(tmp) / "spec.json"
        spec.write_text(json.dumps({"genomes": [str(g) for g in genomes], "chunk": args.chunk,
                                    "repeats": args.repeats, "pruners": args.pruners}))  # fmt: skip
        env = _env(pythonpath, args.quick, XLA_FLAGS=FLAG if deterministic else "")
        proc = subprocess.run([sys.executable, "-c", _CHILD, str(spec)], env=env, cwd=tmp,
                              capture_output=True, text=True)  # fmt: skip
    if proc.returncode:
        raise RuntimeError(f"iteration case {label} failed: {proc.stderr[-2000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"part": "iteration", "install": label, "deterministic": deterministic, **out}


def _repeat(args, deterministic: bool, index: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        env = _env(None, args.quick, EANT2_GPU_DETERMINISTIC="1" if deterministic else "0")
        env["EANT2_CACHE_DIR"] = str(Path(tmp) / "cache")  # empty: compiled afresh
        run_dir = Path(tmp) / "run"
        cmd = eant2_argv("run", args.task, "--population", str(args.population),
                         "--generations", str(args.generations), "--seed", str(args.seed),
                         "--out", str(run_dir))  # fmt: skip
        if args.quick:  # the engine without a pruner, as the quick iteration part times it
            cmd += ["--pruner", eant2_pruner(args.quick)]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, cwd=tmp, capture_output=True, text=True)
        total = time.perf_counter() - t0
        if proc.returncode:
            raise RuntimeError(f"eant2 run failed: {proc.stderr[-2000:]}")
        gens = [json.loads(s) for s in (run_dir / "generations.jsonl").read_text().splitlines()]
        best = (run_dir / "best.genome").read_text()
        # The last generation's padding bucket (neurons, genes, sweeps): on a GPU, buckets of
        # 8-12 neuron slots run the network step as one fused kernel (kernels/netfused.py).
        bucket = json.loads((run_dir / "checkpoint.json").read_text())["state"]["bucket"]
    return {"part": "repeat", "deterministic": deterministic, "run": index, "total_s": total,
            "best_costs": [g["best_cost"] for g in gens], "best_genome": best,
            "bucket": bucket}  # fmt: skip


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    parts = args.parts.split(",")
    unknown = set(parts) - {"iteration", "repeat"}
    if unknown:
        raise ValueError(f"unknown part(s) {sorted(unknown)}; parts: iteration, repeat")
    rows = payload["rows"]
    if "iteration" in parts:
        installs = [("this", None)] + [(f"other:{p}", p) for p in args.pythonpath]
        for label, path in installs:
            for deterministic in (False, True):
                rows.append(_iteration(args, label, path, deterministic))
                save(payload)
    if "repeat" in parts:
        for deterministic in (True, False):
            first = None
            for index in (1, 2):
                row = _repeat(args, deterministic, index)
                first = first or row
                row["same_as_run_1"] = (
                    row["best_costs"] == first["best_costs"]
                    and row["best_genome"] == first["best_genome"]
                )
                rows.append(row)
                save(payload)
    return payload


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--parts", default="iteration,repeat")
    p.add_argument("--structures", type=int, default=200)
    p.add_argument("--genes", type=int, default=60)
    p.add_argument("--chunk", type=int, default=50)
    p.add_argument("--pruners", nargs="+", default=["none", "covariance"],
                   choices=["none", "covariance"],
                   help="engines timed by the iteration part (none: the tax's base)")  # fmt: skip
    p.add_argument("--repeats", type=int, default=5)
    harness.run_options(
        p,
        task="servo",
        population=5,
        generations=2,
        seed=0,
        helps={"task": "task of the repeat part"},
    )
    p.add_argument("--pythonpath", nargs="*", default=[],
                   help="other installs of eant2_jax to time side by side")  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if "none" not in args.pruners:
        raise BenchInputError("--pruners must include none (the base of the tax)")
    if args.quick:
        args.structures, args.genes, args.chunk, args.repeats = 4, 30, 2, 1
        args.pruners = ["none"]  # one compile per process: a smoke test of the plumbing
        args.task, args.population, args.generations = "xor", 2, 1


def _render(payload: dict) -> str:
    it = [r for r in payload["rows"] if r["part"] == "iteration"]
    rep = [r for r in payload["rows"] if r["part"] == "repeat"]
    out = []
    if it:
        base = {r["install"]: r for r in it if not r["deterministic"]}
        for r in it:
            r["tax"] = r["none"]["iteration_ms"] / base[r["install"]]["none"]["iteration_ms"]
        out.append(markdown_table(it, [
            Column("install", "install"),
            Column(lambda r: "deterministic" if r["deterministic"] else "default", "XLA"),
            Column(lambda r: r["none"]["genes"], "P"),
            Column(lambda r: f"{r['none']['iteration_ms']:.2f}", "ms / iteration"),
            Column(lambda r: f"{r['covariance']['iteration_ms']:.2f}" if "covariance" in r
                   else "—", "ms / iteration, covariance pruner"),
            Column(lambda r: f"{r['none']['first_s']:.1f}", "first chunk s"),
            Column(lambda r: f"{r['tax']:.2f}x", "vs default"),
            Column(lambda r: f"{r['none']['best']:.6g}", "best cost after the chunk"),
        ]))  # fmt: skip
    if rep:
        out.append(markdown_table(rep, [
            Column(lambda r: "on" if r["deterministic"] else "off (EANT2_GPU_DETERMINISTIC=0)",
                   "deterministic ops"),
            Column("run", "run"),
            Column(lambda r: " / ".join(f"{c:.8g}" for c in r["best_costs"]),
                   "best cost per generation"),
            Column(lambda r: "yes" if r["same_as_run_1"] else "no", "same as run 1"),
            Column(lambda r: r.get("bucket") and tuple(r["bucket"]), "last bucket (H, P, sweeps)"),
            Column("total_s", "s", "{:.1f}"),
        ]))  # fmt: skip
    return "\n\n".join(out)


SUITE = harness.Suite(
    name="determinism",
    title="Determinism on GPU: its cost and whether runs repeat",
    description=__doc__,
    options=_options,
    run=run,
    render=_render,
    prepare=_prepare,
)

main = SUITE.main
