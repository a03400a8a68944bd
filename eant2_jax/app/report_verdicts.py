"""The protocol's verdicts on a reproduction's arms (docs/protocol.md, section 1).

Per comparison (each arm against ``none``; each ablation and control against ``default``;
``default`` against ``literal``):

* **size**: the difference of the final champions' sizes, Welch's 95% interval, and the
  verdict on the comparison's claim (smaller than ``none`` or ``literal``; larger than
  ``default``, i.e. the part an ablation removes carries some of the reduction);
* **fitness equivalence**: the final champions' costs, TOST at ±3% of the ``none`` arm's
  mean cost (90% interval);
* **held-out cost**: the same test on the champions' held-out costs, where the caller has
  them.

Per arm, **evaluations to a common target**: until a run's best cost first comes within 1%
of the ``none`` arm's median final cost (99% of its fitness); the median over runs (a run
that never reaches it counts as infinitely many) with its percentile bootstrap interval, and
how many reach it. Nothing here prints "equal": equivalence is a TOST verdict or nothing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from .report_stats import bootstrap_interval, first_within, median, tost, verdict, welch_interval

__all__ = ["MARGIN", "comparisons", "protocol_verdicts", "target_figure", "verdict_lines"]

MARGIN = 0.03  # the equivalence margin, relative to the none arm's mean cost


def comparisons(arms: Sequence[str]) -> list[tuple[str, str, str]]:
    """``(arm, against, claim)`` pairs: ``claim`` ``"below"`` (the arm's size is smaller)
    or ``"above"`` (larger)."""
    out = [(a, "none", "below") for a in arms if a != "none" and "none" in arms]
    if "default" in arms and "literal" in arms:
        out.append(("default", "literal", "below"))
    if "default" in arms:
        out += [(a, "default", "above") for a in arms if a not in ("none", "default", "literal")]
    return out


def _final(runs) -> tuple[np.ndarray, np.ndarray]:
    cost = np.array([r.generations[-1].best_cost for r in runs], np.float64)
    size = np.array([r.generations[-1].best_size for r in runs], np.float64)
    return cost, size


def _to_target(runs, target: float) -> np.ndarray:
    hits = [first_within(r.generations, target) for r in runs]
    return np.array([np.inf if h is None else h.evaluations for h in hits], np.float64)


def protocol_verdicts(
    runs: Sequence, held_out: Mapping[str, Sequence[float]] | None = None
) -> dict:
    """The verdicts of `report_verdicts` on loaded runs (`report_runs.LoadedRun`), grouped
    by arm. ``held_out``: each arm's champions' held-out costs, in its runs' order.

    Returns:
      ``{"margin", "target_cost", "comparisons": [...], "to_target": {arm: {...}}}``;
      empty comparisons where an arm has fewer than two runs.
    """
    by_arm: dict[str, list] = {}
    for r in runs:
        by_arm.setdefault(r.arm, []).append(r)
    finals = {a: _final(rs) for a, rs in by_arm.items()}
    base = "none" if "none" in by_arm else next(iter(by_arm))
    margin = MARGIN * abs(float(finals[base][0].mean()))
    target = float(np.median(finals[base][0]))
    out: dict = {"margin": MARGIN, "reference": base, "target_cost": target, "comparisons": []}
    for arm, against, claim in comparisons(list(by_arm)):
        (ca, sa), (cb, sb) = finals[arm], finals[against]
        if min(len(ca), len(cb)) < 2:
            continue
        d, low, high = welch_interval(sa, sb)
        row = {
            "arm": arm,
            "against": against,
            "claim": claim,
            "size": {
                "difference": d,
                "low": low,
                "high": high,
                "verdict": verdict(low, high, claim=claim),
            },  # fmt: skip
            "cost": tost(ca, cb, margin) if margin > 0 else None,
            "held_out": None,
        }
        if held_out is not None and arm in held_out and against in held_out and margin > 0:
            row["held_out"] = tost(held_out[arm], held_out[against], margin)
        out["comparisons"].append(row)
    for arm, rs in by_arm.items():
        evals = _to_target(rs, target)
        est, low, high = bootstrap_interval([evals], median)
        out.setdefault("to_target", {})[arm] = {
            "median": est, "low": low, "high": high,
            "reached": int(np.isfinite(evals).sum()), "runs": len(rs),
        }  # fmt: skip
    return out


def _num(x: float) -> str:
    return "never" if x == np.inf else f"{x:.4g}"


def _interval(t: dict | None, *, pct_of: float | None = None) -> str:
    if t is None:
        return "—"
    text = f"{t['difference']:+.4g} [{t['low']:+.4g}, {t['high']:+.4g}]"
    if pct_of:
        text += f" ({100 * t['difference'] / pct_of:+.1f}%)"
    return text


def verdict_lines(v: dict, escape) -> list[str]:
    """The verdicts as Markdown (``escape``: the report's, for arm names read from files)."""
    lines = [
        "## Verdicts (docs/protocol.md)",
        "",
        f"Size: the final champion's size, difference of means with Welch's 95% interval. "
        f"Cost: the final champion's cost, TOST at ±{100 * v['margin']:.0f}% of the "
        f"`{escape(v['reference'])}` arm's mean cost (90% Welch interval within the margin: "
        "held; wholly outside: not held; else undecided). A difference that is not "
        "significant is never read as equal.",
        "",
        "| arm | against | size difference [95% CI] | claim | verdict | cost difference "
        "[90% CI] | equivalent | held-out difference [90% CI] | equivalent |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in v["comparisons"]:
        claim = "smaller" if c["claim"] == "below" else "larger"
        cost, held = c["cost"], c["held_out"]
        lines.append(
            f"| {escape(c['arm'])} | {escape(c['against'])} | {_interval(c['size'])} | "
            f"{claim} | **{c['size']['verdict']}** | {_interval(cost)} | "
            f"{'—' if cost is None else '**' + cost['verdict'] + '**'} | {_interval(held)} | "
            f"{'—' if held is None else '**' + held['verdict'] + '**'} |"
        )
    where = {"new": "new start poses from `jax.random.key(7000)`", "task": "the task's "
             "held-out set"}.get(v.get("held_out_set"))  # fmt: skip
    if where:
        lines += ["", f"Held-out: the final champions' costs on {where}, the same TOST."]
    lines += [
        "",
        f"Evaluations until a run's best cost first came within 1% of "
        f"{v['target_cost']:.4g} (the `{escape(v['reference'])}` arm's median final cost): "
        "median over runs (a run that never did counts as never) with its percentile "
        "bootstrap 95% interval (10,000 resamples, key 0), and how many runs reached it.",
        "",
        "| arm | reached | median evaluations [95% CI] |",
        "|---|---|---|",
    ]
    for arm, t in v["to_target"].items():
        lines.append(
            f"| {escape(arm)} | {t['reached']}/{t['runs']} | {_num(t['median'])} "
            f"[{_num(t['low'])}, {_num(t['high'])}] |"
        )
    return lines


def target_figure(runs: Sequence, arms: Sequence[str], target: float):
    """The protocol's curves: each run's best cost against evaluations (log scale), one
    colour per arm, and the common target (1% above ``target``, the reference arm's median
    final cost) as a dashed line."""
    from .report_figures import pyplot

    plt = pyplot()
    # Up to 20 arms in colours apart (the protocol has 11); the best cost holds between
    # the generations that record it (steps).
    tab20 = plt.get_cmap("tab20").colors
    colours = tab20[::2] + tab20[1::2]  # the ten strong colours first, then their pale pairs
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k, arm in enumerate(arms):
        colour = colours[k % len(colours)]
        for i, r in enumerate(x for x in runs if x.arm == arm):
            ax.plot([g.evaluations for g in r.generations], [g.best_cost for g in r.generations],
                    color=colour, lw=0.8, alpha=0.6, drawstyle="steps-post",
                    label=arm if i == 0 else None)  # fmt: skip
    ax.axhline(target + 0.01 * abs(target), color="0.2", lw=1, ls="--", label="target")
    ax.set(xlabel="evaluations", ylabel="best cost", title="best cost against evaluations")
    ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
