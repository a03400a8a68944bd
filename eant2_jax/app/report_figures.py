"""The report's drawings (host side, matplotlib): fitness and size against generation (the
paper's figure 8), cond(C) against CMA-ES iteration (figure 7). Networks as graphs (figure 6)
are drawn by `eant2_jax.app.netdraw`.

Each ``*_figure`` function returns a figure; the report saves them through
`eant2_jax.app.outputs` (whole, never through a link).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..genome import GeneKind, Genome

__all__ = [
    "MAX_DRAWN_INPUTS",
    "MAX_INCHES",
    "condition_figure",
    "fitness_figure",
    "genome_stats",
    "pyplot",
]

_STYLES = ["-", "--", "-.", ":"]
_MARKERS = ["o", "s", "^", "D", "v", "P", "X", "*"]

MAX_DRAWN_INPUTS = 64
MAX_INCHES = 60  # a drawing of a wide or deep genome is squeezed, not megapixels wide


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only; never a window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def genome_stats(genome: Genome) -> dict:
    """Counts of a genome's genes by kind, and its sizes."""
    kinds = {k.name.lower(): 0 for k in GeneKind}
    for g in genome:
        kinds[g.kind.name.lower()] += 1
    return {
        "parameters": genome.n_params,
        "inputs_read": genome.n_inputs,
        "outputs": genome.n_outputs,
        "neurons": genome.n_neurons,
        "hidden_neurons": genome.n_neurons - genome.n_outputs,
        "depth": genome.depth(),
        "genes": kinds,
    }


def _caps(axes, runs: Sequence) -> None:
    """Mark the target fitness (one shared ``target_cost``) and the generation budget when
    a run stopped before it."""
    targets = {r.target_cost for r in runs}
    if len(targets) == 1 and None not in targets:
        axes[0].axhline(-targets.pop(), color="0.3", lw=1, ls=(0, (6, 3)), label="target")
    budgets = {r.budget for r in runs if r.budget is not None}
    if budgets and any(len(r.generations) < (r.budget or 0) + 1 for r in runs):
        for ax in axes:
            for b in sorted(budgets):
                ax.axvline(b, color="0.5", lw=1, ls=":", label=f"budget ({b} generations)")


def fitness_figure(runs: Sequence, arms: Sequence[str]):
    """Fitness and size of the best against generation: every run a thin line, each arm's
    mean a thick one with its own line style and marker (arms that overlap stay apart),
    integer generation ticks, and the caps that apply marked: the target fitness (``-``
    the runs' ``target_cost``) and the generation budget when a run stopped before it.

    Args:
      runs: `eant2_jax.app.report_runs.LoadedRun`s.
      arms: the arms to draw, in legend order.

    Returns:
      The matplotlib figure (two axes).
    """
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for k, arm in enumerate(arms):
        rs = [r for r in runs if r.arm == arm]
        style = {
            "color": colours[k % len(colours)],
            "ls": _STYLES[k % len(_STYLES)],
            "marker": _MARKERS[k % len(_MARKERS)],
        }
        for r in rs:
            gens = [g.generation for g in r.generations]
            axes[0].plot(gens, [-g.best_cost for g in r.generations], lw=0.7, alpha=0.4,
                         color=style["color"], ls=style["ls"])  # fmt: skip
            axes[1].plot(gens, [g.best_size for g in r.generations], lw=0.7, alpha=0.4,
                         color=style["color"], ls=style["ls"])  # fmt: skip
        # The mean over the generations every run of the arm reached.
        n = min(len(r.generations) for r in rs)
        gens = np.arange(n)
        fit = np.array([[-g.best_cost for g in r.generations[:n]] for r in rs]).mean(0)
        size = np.array([[g.best_size for g in r.generations[:n]] for r in rs]).mean(0)
        every = max(1, n // 12)
        label = f"{arm} (mean of {len(rs)})"
        for ax, y in ((axes[0], fit), (axes[1], size)):
            ax.plot(gens, y, lw=2.2, markevery=every, ms=5, label=label, **style)
    _caps(axes, runs)
    axes[0].set(xlabel="generation", ylabel="fitness = -cost", title="fitness of the best")
    axes[1].set(xlabel="generation", ylabel="parameters", title="size of the best")
    for a in axes:
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    return fig


def condition_figure(condition: dict):
    """cond(C) against CMA-ES iteration, the original network's runs against the pruned
    one's (``condition`` as `eant2_jax.app.condition.condition_experiment` returns it; an
    older file holds one run per network)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, colour, label in (
        ("before", "C0", f"original ({condition.get('size_before')} params)"),
        ("after", "C1", f"pruned ({condition.get('size_after')} params)"),
    ):
        curves = condition[name]
        if curves and not isinstance(curves[0], list):  # one run (older condition.json)
            curves = [curves]
        for i, c in enumerate(curves):
            ax.semilogy(c, color=colour, lw=0.8, label=label if i == 0 else None)
    ax.set(xlabel="CMA-ES iteration", ylabel="cond(C)", title="condition of C")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
