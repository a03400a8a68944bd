"""Cold start: wall time of an ``eant2 run`` from process start, with an empty and a warm
compilation cache.

Each case starts ``eant2 run TASK`` in a fresh process (as a user does) and times, from just
before the process starts, each generation's progress line and the process's exit. ``cold``
runs with a new, empty cache directory (``EANT2_CACHE_DIR``), ``warm`` again with the cache
the cold run left. ``--pythonpath`` runs another install of eant2_jax side by side (e.g. the
previous version, to compare in one call on one device).

Run: ``python -m bench coldstart [--task servo] [--population 5] [--generations 1]``.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import harness
from bench.common import (
    BenchInputError,
    Column,
    child_env,
    eant2_argv,
    environment,
    markdown_table,
)

_GEN = re.compile(r"^gen (\d+)/\d+ \|")


def _one(args, cache: str, pythonpath: str | None) -> dict[str, Any]:
    """One ``eant2 run`` in a new process: seconds to each generation's line and to exit."""
    env = child_env(pythonpath, EANT2_CACHE_DIR=cache)
    with tempfile.TemporaryDirectory() as tmp:
        cmd = eant2_argv(
            "run", args.task, "--population", str(args.population), "--generations",
            str(args.generations), "--seed", str(args.seed), "--out", str(Path(tmp) / "run"),
            *args.extra,
        )  # fmt: skip
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True, cwd=tmp)  # fmt: skip
        gens, compiling, lines = {}, 0, []
        for line in proc.stderr:
            lines.append(line)
            m = _GEN.match(line)
            if m:
                gens[int(m.group(1))] = time.perf_counter() - t0
            compiling += "compiling" in line
        proc.wait()
        total = time.perf_counter() - t0
        best = [ln for ln in proc.stdout.read().splitlines() if ln.startswith("best cost")]
    if proc.returncode:
        raise RuntimeError(f"eant2 run failed ({proc.returncode}): {''.join(lines[-20:])}")
    return {"generations_s": [gens[g] for g in sorted(gens)], "total_s": total,
            "compiling_events": compiling, "best": best[-1] if best else None}  # fmt: skip


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    payload: dict[str, Any] = {"environment": environment(), "config": harness.settings(args),
                               "rows": []}  # fmt: skip
    installs = [("this", None)] + [(f"other:{p}", p) for p in args.pythonpath]
    # Rounds alternate the installs, so that a drift of the machine (another tenant, a
    # clock) falls on all of them alike.
    for rnd in range(args.rounds):
        for label, path in installs:
            with tempfile.TemporaryDirectory() as cache:
                for case in ("cold", "warm"):
                    r = _one(args, cache, path)
                    payload["rows"].append({"install": label, "cache": case, "round": rnd, **r})
                    save(payload)
    return payload


def medians(rows: list[dict]) -> list[dict]:
    """Per install and cache, the median over rounds of each generation's time and of the
    time to exit (the rows of one (install, cache) have the same generations)."""
    out = []
    for key in dict.fromkeys((r["install"], r["cache"]) for r in rows):
        group = [r for r in rows if (r["install"], r["cache"]) == key]
        gens = list(zip(*(r["generations_s"] for r in group), strict=True))
        out.append({
            "install": key[0], "cache": key[1], "round": f"median of {len(group)}",
            "generations_s": [statistics.median(g) for g in gens],
            "total_s": statistics.median(r["total_s"] for r in group),
            "compiling_events": group[0]["compiling_events"],
            "same_run": _same_run(group),
        })  # fmt: skip
    return out


def _same_run(rows: list[dict]) -> str:
    """Whether every run in ``rows`` printed the same best network (cost and weights, to the
    last printed digit): "yes", "no", or "—" where the runs did not print it."""
    best = {r.get("best") for r in rows}
    if None in best:
        return "—"
    return "yes" if len(best) == 1 else "no"


def _render(payload: dict) -> str:
    rows = payload["rows"]
    across = "".join(
        f"\n\n{label}: every run printed the same best network: {_same_run(group)}"
        for label in dict.fromkeys(r["install"] for r in rows)
        for group in [[r for r in rows if r["install"] == label]]
    )
    if len({r.get("round", 0) for r in rows}) < 2:
        return markdown_table(rows, COLUMNS) + across
    return (markdown_table(medians(rows), COLUMNS) + across + "\n\nEach round:\n\n"
            + markdown_table(rows, COLUMNS))  # fmt: skip


def _options(p: argparse.ArgumentParser) -> None:
    harness.run_options(p, task="servo", population=5, generations=1, seed=0)
    p.add_argument("--pythonpath", nargs="*", default=[],
                   help="other installs of eant2_jax to time side by side")  # fmt: skip
    p.add_argument("--rounds", type=int, default=1,
                   help="cold and warm runs of each install, N times, alternating")  # fmt: skip
    p.add_argument("--extra", nargs=argparse.REMAINDER, default=[],
                   help="further arguments of eant2 run (last)")  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    if args.rounds < 1:
        raise BenchInputError("--rounds must be at least 1")
    if args.quick:
        args.task, args.population, args.generations = "xor", 2, 1


COLUMNS = [
    Column("install", "install"),
    Column("cache", "cache"),
    Column(lambda r: r.get("round", 0), "round"),
    Column(
        lambda r: " / ".join(f"{s:.1f}" for s in r["generations_s"]), "s to end of gen 0 / 1 / ..."
    ),  # fmt: skip
    Column("total_s", "s to exit", "{:.1f}"),
    Column("compiling_events", '"compiling" events'),
    Column(lambda r: r.get("same_run", ""), "same best network"),
]

SUITE = harness.Suite(
    name="coldstart",
    title="Cold start from process start",
    description=__doc__,
    options=_options,
    run=run,
    render=_render,
    prepare=_prepare,
)

main = SUITE.main
