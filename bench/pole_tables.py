"""The pole suite's tables (bench/bench_pole.py): the published figures, a task's row and a
protocol variant's row (docs/protocol.md, section 4: the Wilson interval of the solved share,
the bootstrap median of the evaluations to solve), and their markdown."""

from __future__ import annotations

import math
import statistics
from typing import Any

import numpy as np

from bench.common import Column, markdown_table
from eant2_jax.app.report_stats import bootstrap_interval, median

__all__ = [
    "ACCOUNTING",
    "PROTOCOL",
    "PROTOCOL_ACCOUNTING",
    "PUBLISHED",
    "Z95",
    "protocol_row",
    "render",
    "task_row",
    "wilson_interval",
]

# Gomez, Schmidhuber & Miikkulainen (2008), JMLR 9: table 3 (DPV) and table 4 (DPNV, damping
# fitness); mean evaluations to solve.
PUBLISHED = {
    "dpv": {"NEAT": 3600, "ESP": 3800, "CMA-ES": 895, "CoSyNE": 954},
    "dpnv": {"NEAT": 6929, "ESP": 26342, "CMA-ES": 6061, "CoSyNE": 3416},
}


ACCOUNTING = (
    "one evaluation = one network run by the task's cost during evolution (every CMA-ES "
    "candidate and every network a pruning attempt evaluates, of every structure tuned in "
    "lock-step with the solving one), up to the iteration after which the solution test "
    "passed; the test's own runs (100,000 steps, 625 starts) are not counted (Gomez et al. "
    "2008's rule)"
)


# docs/protocol.md, section 4: variant -> (task, recurrent-ready start, solution rule).
PROTOCOL = {
    "dpnv-rr-champion": ("dpnv", True, "champion"),
    "dpnv-rr-structure": ("dpnv", True, "structure"),
    "dpnv-champion": ("dpnv", False, "champion"),
    "dpnv-structure": ("dpnv", False, "structure"),
    "dpv-champion": ("dpv", False, "champion"),
    "dpv-structure": ("dpv", False, "structure"),
}
Z95 = 1.959963984540054  # the standard normal's 97.5% quantile


PROTOCOL_ACCOUNTING = (
    "one evaluation = one network run by the task's cost during evolution (every CMA-ES "
    "candidate and every network a pruning attempt evaluates, of every structure of the "
    "generation); the solution test's own runs are not counted. Rule champion: the test runs "
    "once per generation on the champion after selection, and a solved run counts the whole "
    "generation whose champion passed. Rule structure: the test runs on every structure's "
    "improved best after every CMA-ES iteration, and a solved run counts up to the iteration "
    "after which a network passed"
)


def task_row(name: str, runs: list[dict], budget: int) -> dict:
    """One task's line of the plain table: success rate, evaluations, generalisation."""
    ok = [r for r in runs if r["solved"]]
    evals = [r["evaluations"] for r in ok]
    charged = [r["evaluations"] if r["solved"] else budget for r in runs]
    gen = [r["check"]["generalisation"] for r in ok]
    return {
        "task": name,
        "seeds": len(runs),
        "success_rate": len(ok) / len(runs),
        "mean_evals_solved": statistics.mean(evals) if evals else None,
        "median_evals_solved": statistics.median(evals) if evals else None,
        "mean_evals_failures_as_budget": statistics.mean(charged),
        "median_evals_failures_as_budget": statistics.median(charged),
        "wall_per_solved_s": (sum(r["wall_s"] for r in runs) / len(ok)) if ok else None,
        "median_wall_solved_s": statistics.median([r["wall_s"] for r in ok]) if ok else None,
        "generalisation_mean": statistics.mean(gen) if gen else None,
        "generalisation_min": min(gen) if gen else None,
        "generalisation_max": max(gen) if gen else None,
        **{f"published_{k}": v for k, v in PUBLISHED[name].items()},
    }


def wilson_interval(solved: int, runs: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval of a proportion ``solved / runs`` (95% for the default
    ``z``): ``(low, high)``, within [0, 1] also at 0 and ``runs`` successes."""
    if runs < 1 or not 0 <= solved <= runs:
        raise ValueError(
            f"wilson_interval needs 0 <= solved <= runs and runs >= 1, got {solved}/{runs}"
        )
    p, z2 = solved / runs, z * z
    centre = (p + z2 / (2 * runs)) / (1 + z2 / runs)
    half = z * math.sqrt(p * (1 - p) / runs + z2 / (4 * runs * runs)) / (1 + z2 / runs)
    return max(0.0, centre - half), min(1.0, centre + half)


def protocol_row(variant: str, runs: list[dict], budget: int) -> dict:
    """One variant's line of the protocol's table (docs/protocol.md, section 4)."""
    task, recurrent, rule = PROTOCOL[variant]
    ok = [r for r in runs if r["solved"]]
    low, high = wilson_interval(len(ok), len(runs))
    # An unsolved run never reaches a solution: infinite evaluations in the median.
    reached = np.array([r["evaluations"] if r["solved"] else np.inf for r in runs], np.float64)
    est, m_low, m_high = bootstrap_interval([reached], median)
    evals = [r["evaluations"] for r in ok]
    return {
        "variant": variant,
        "task": task,
        "start": "recurrent-ready" if recurrent else "minimal",
        "solution_rule": rule,
        "seeds": len(runs),
        "solved": len(ok),
        "solved_text": f"{len(ok)}/{len(runs)} [{low:.2f}, {high:.2f}]",
        "solved_low": low,
        "solved_high": high,
        "median_evals": est,
        "median_low": m_low,
        "median_high": m_high,
        "median_text": " ".join([_count(est), f"[{_count(m_low)}, {_count(m_high)}]"]),
        "mean_evals_solved": statistics.mean(evals) if evals else None,
        "mean_evals_failures_as_budget": statistics.mean(
            r["evaluations"] if r["solved"] else budget for r in runs
        ),
        "solved_in_generation_0": sum(r["generations"] == 0 for r in ok),
        "tests_per_run": statistics.mean(r.get("tests", 0) for r in runs),
        "published_mean": PUBLISHED[task],
    }


def _count(x: float) -> str:
    return "never" if math.isinf(x) else f"{x:,.0f}"


PROTOCOL_COLUMNS = [
    Column("variant", "variant"),
    Column("seeds", "seeds"),
    Column("solved_text", "solved [Wilson 95%]"),
    Column("median_text", "median evals to solve [bootstrap 95%]"),
    Column("mean_evals_solved", "mean evals (solved)", "{:,.0f}"),
    Column("mean_evals_failures_as_budget", "mean evals (fail = budget)", "{:,.0f}"),
    Column("solved_in_generation_0", "solved in gen. 0"),
    Column("tests_per_run", "tests / run", "{:.1f}"),
]


COLUMNS = [
    Column("task", "task"),
    Column("seeds", "seeds"),
    Column("success_rate", "solved", "{:.0%}"),
    Column("mean_evals_solved", "mean evals (solved)", "{:.0f}"),
    Column("median_evals_solved", "median evals (solved)", "{:.0f}"),
    Column("mean_evals_failures_as_budget", "mean evals (fail = budget)", "{:.0f}"),
    Column("generalisation_mean", "generalisation (mean, of 625)", "{:.0f}"),
    Column("generalisation_min", "generalisation (min)"),
    Column("wall_per_solved_s", "wall s / solved run", "{:.1f}"),
    Column("published_NEAT", "NEAT"),
    Column("published_ESP", "ESP"),
    Column("published_CMA-ES", "CMA-ES"),
    Column("published_CoSyNE", "CoSyNE"),
]


def render(payload: dict[str, Any]) -> str:
    if payload["config"].get("protocol"):
        return render_protocol(payload)
    seeds = ", ".join(f"{k} {len(v)}" for k, v in payload["runs"].items())
    return (
        f"EANT2 (covariance pruning) to solve double pole balancing; seeds per task: {seeds}; "
        f"budget {payload['config']['budget']} evaluations (failures charged the budget in the "
        "fail = budget column). Published columns: mean evaluations, Gomez et al. 2008. "
        f"Accounting: {payload.get('accounting', 'see bench_pole.py')}. Generalisation: "
        "starts of 625 that the solutions balance for 1,000 steps."
        + (
            f" Whole suite: {payload['wall_total_s']:.0f} s wall with "
            f"{payload['config'].get('workers', 1)} run(s) in flight."
            if "wall_total_s" in payload
            else ""
        )
        + "\n\n"
        + markdown_table(payload["rows"], COLUMNS)
    )


def render_protocol(payload: dict[str, Any]) -> str:
    """The protocol's table (docs/protocol.md, section 4)."""
    config = payload["config"]
    seeds = sorted({r["seed"] for runs in payload["runs"].values() for r in runs})
    span = f"{seeds[0]}-{seeds[-1]}" if seeds else "none yet"
    return (
        f"The protocol's double pole runs (docs/protocol.md, section 4): seeds {span}, "
        f"budget {config['budget']} evaluations. Variant: task, "
        "rr = recurrent-ready start (else the paper's minimal start), the solution test's rule "
        "(champion: the generation's champion once per generation, the published protocol; "
        "structure: every structure's improved best after every CMA-ES iteration). Median "
        "over all seeds, an unsolved run never reaching a solution ('never': half or more "
        "unsolved); percentile bootstrap, key jax.random.key(0), 10,000 resamples. "
        f"Accounting: {payload['accounting']}."
        + (
            f" Whole suite: {payload['wall_total_s']:.0f} s wall with "
            f"{config.get('workers', 1)} run(s) in flight."
            if "wall_total_s" in payload
            else ""
        )
        + "\n\n"
        + markdown_table(payload["rows"], PROTOCOL_COLUMNS)
    )
