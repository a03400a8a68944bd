"""The field protocol's summary (docs/protocol.md section 3): per environment and reporting
budget, each method's median test return with its bootstrap 95% interval, the median paired
difference (eant2_jax minus TensorNEAT, same seed) with its interval and the verdict, and
the wall time each method's champion took to reach TensorNEAT's median final return; and
per environment the seeds on which eant2_jax's test return is at least TensorNEAT's, at
TensorNEAT's evaluation count and at TensorNEAT's wall time (`seed_counts`: issue 41's "on
most seeds", docs/protocol.md section 3).

Intervals: percentile bootstrap, 10,000 resamples from ``jax.random.key(0)``
(`eant2_jax.app.report_stats.bootstrap_interval`, the protocol's "Verdicts"). A **win**
needs the difference's interval to lie above 0, a **loss** below 0; anything else is a
**tie**.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bench.common import Column, markdown_table

__all__ = [
    "median_interval",
    "render_summary",
    "return_at",
    "seed_counts",
    "summarise",
    "verdict",
    "wall_to_target",
]

A, B = "eant2", "tensorneat"


def median_interval(values) -> tuple[float, float, float] | None:
    """``(median, low, high)`` with the percentile bootstrap interval; None if empty."""
    from eant2_jax.app.report_stats import bootstrap_interval, median

    values = np.asarray([v for v in values if v is not None], np.float64)
    if values.size == 0:
        return None
    return bootstrap_interval([values], median)


def verdict(interval: tuple[float, float, float] | None) -> str | None:
    """``win`` (interval above 0), ``loss`` (below 0), else ``tie``; None without pairs."""
    if interval is None:
        return None
    _, low, high = interval
    return "win" if low > 0 else "loss" if high < 0 else "tie"


def wall_to_target(curve: list[dict], target: float) -> float:
    """Wall seconds (from process start) of the first generation whose champion's test
    return reaches ``target``; inf if none does."""
    hit = next((p for p in curve if p["test_return"] >= target), None)
    return math.inf if hit is None else float(hit["wall_s"])


def return_at(curve: list[dict], wall_s: float) -> float:
    """The test return of the last judged champion at or before ``wall_s``; -inf if none."""
    done = [p for p in curve if p["wall_s"] <= wall_s]
    return float(max(done, key=lambda p: p["wall_s"])["test_return"]) if done else -math.inf


def _at_last_budget(judged: dict) -> float:
    """The test return of a method's champion at its last reporting budget (-inf if none)."""
    last = (judged.get("budgets") or [{}])[-1].get("test_return")
    return -math.inf if last is None else float(last)


def seed_counts(seeds: list[dict[str, Any]]) -> list[dict]:
    """Per environment, over the seeds where both methods were judged: ``evals``, how many
    seeds have eant2_jax's test return at the last reporting budget (TensorNEAT's evaluation
    count) at least TensorNEAT's there; ``wall``, how many have eant2_jax's last judged
    champion at or before the wall time of TensorNEAT's last judged champion (`return_at`)
    at least that champion's test return; ``most``: each count above half the seeds. A
    method without a champion there counts as -inf."""
    out = []
    for env in dict.fromkeys(s["env"] for s in seeds):
        pairs = [s["judged"] for s in seeds
                 if s["env"] == env and A in s["judged"] and B in s["judged"]]  # fmt: skip
        if not pairs:
            continue
        evals = sum(_at_last_budget(j[A]) >= _at_last_budget(j[B]) for j in pairs)
        wall = 0
        for j in pairs:
            # TensorNEAT without a judged champion: -inf at any time.
            last = max(j[B]["curve"], key=lambda p: p["wall_s"], default=None)
            at = math.inf if last is None else last["wall_s"]
            wall += return_at(j[A]["curve"], at) >= return_at(j[B]["curve"], at)
        n = len(pairs)
        out.append({"env": env, "seeds": n, "evals": int(evals), "wall": int(wall),
                    "most": {"evals": 2 * evals > n, "wall": 2 * wall > n}})  # fmt: skip
    return out


def summarise(seeds: list[dict[str, Any]], budgets: dict[str, list[int]]) -> list[dict]:
    """Rows (environment, budget) from the per-seed records (each: ``env``, ``seed``,
    ``judged``: method -> `bench.field_champions.judge_run`'s output)."""
    rows = []
    for env in budgets:
        mine = sorted((s for s in seeds if s["env"] == env), key=lambda s: s["seed"])
        if not mine:
            continue
        for k, b in enumerate(budgets[env]):
            row: dict[str, Any] = {"env": env, "budget": b, "seeds": len(mine)}
            got = {m: [s["judged"].get(m, {}).get("budgets", [{}] * (k + 1))[k].get("test_return")
                       for s in mine] for m in (A, B)}  # fmt: skip
            for m in (A, B):
                row[m] = median_interval(got[m])
                row[f"{m}_n"] = sum(v is not None for v in got[m])
            diffs = [a - b for a, b in zip(got[A], got[B], strict=True)
                     if a is not None and b is not None]  # fmt: skip
            row["pairs"] = len(diffs)
            row["difference"] = median_interval(diffs)
            row["verdict"] = verdict(row["difference"])
            rows.append(row)
        final = [s["judged"].get(B, {}).get("budgets", [{}])[-1].get("test_return") for s in mine]
        final = [v for v in final if v is not None]
        if final:
            target = float(np.median(final))
            last = rows[-1]
            last["target"] = target
            for m in (A, B):
                walls = [wall_to_target(s["judged"][m]["curve"], target)
                         for s in mine if m in s["judged"]]  # fmt: skip
                last[f"{m}_wall"] = median_interval(walls) if walls else None
                last[f"{m}_reached"] = sum(math.isfinite(w) for w in walls)
    return rows


def _ci(v, digits: int = 4) -> str:
    if v is None:
        return "—"
    est, low, high = v

    def f(x):
        return "inf" if math.isinf(x) else f"{x:.{digits}g}"

    return f"{f(est)} [{f(low)}, {f(high)}]"


def render_summary(rows: list[dict], counts: list[dict] | None = None) -> str:
    cols = [
        Column("env", "env"),
        Column("budget", "budget (evaluations)"),
        Column(lambda r: f"{r[f'{A}_n']} / {r[f'{B}_n']}", "seeds (eant2 / TN)"),
        Column(lambda r: _ci(r[A]), "eant2_jax median test return [95%]"),
        Column(lambda r: _ci(r[B]), "TensorNEAT median test return [95%]"),
        Column(lambda r: _ci(r["difference"]), "median paired difference [95%]"),
        Column(lambda r: r["verdict"] or "—", "verdict"),
    ]
    md = markdown_table(rows, cols)
    walls = [r for r in rows if "target" in r]
    if walls:
        wcols = [
            Column("env", "env"),
            Column(lambda r: f"{r['target']:.4g}", "TensorNEAT's median final return"),
            Column(lambda r: f"{_ci(r.get(f'{A}_wall'), 3)} ({r.get(f'{A}_reached', 0)})",
                   "eant2_jax wall s to it [95%] (seeds reaching)"),
            Column(lambda r: f"{_ci(r.get(f'{B}_wall'), 3)} ({r.get(f'{B}_reached', 0)})",
                   "TensorNEAT wall s to it [95%] (seeds reaching)"),
        ]  # fmt: skip
        md += "\n" + markdown_table(walls, wcols)
    if counts:

        def k_of_n(what):
            return lambda r: f"{r[what]} of {r['seeds']}" + (" (most)" if r["most"][what] else "")

        ccols = [
            Column("env", "env"),
            Column(k_of_n("evals"), "seeds with eant2_jax >= TensorNEAT at TN's evaluations"),
            Column(k_of_n("wall"), "seeds with eant2_jax >= TensorNEAT at TN's wall time"),
        ]
        md += "\n" + markdown_table(counts, ccols)
    return md
