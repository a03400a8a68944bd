"""The report's drawings (host side, matplotlib): networks as graphs (the paper's figure 6),
fitness and size against generation (figure 8), cond(C) against CMA-ES iteration (figure 7).

Each ``*_figure`` function returns a figure; `draw_genome` saves one through
`eant2_jax.app.outputs` (whole, never through a link).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..genome import GeneKind, Genome
from ..pruning import kept_genes
from . import outputs

__all__ = [
    "MAX_DRAWN_INPUTS",
    "MAX_INCHES",
    "condition_figure",
    "draw_genome",
    "fitness_figure",
    "genome_figure",
    "genome_stats",
    "pyplot",
]

# Node faces of network drawings (nodes and legend).
_FACE = {"input": "#e8f0ff", "bias": "#f0f0f0", "hidden": "#fff8e6", "output": "#ffe9c7"}
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


def draw_genome(
    genome: Genome,
    path: str | Path,
    *,
    pruned: Genome | None = None,
    title: str | None = None,
    n_inputs: int | None = None,
    overwrite: bool = True,
) -> Path:
    """Draw a network as a graph (inputs bottom, outputs top) into a PNG, with a legend.

    Solid black: a neuron's own inputs (inputs, biases, sub-neurons); solid blue: forward
    jumpers; dashed red: recurrent jumpers. With ``pruned`` (the same network after
    pruning), connections that pruning removed are drawn dotted grey. The bias node is drawn
    only when a gene reads it.

    Args:
      genome: the network to draw (the unpruned one when ``pruned`` is given).
      path: PNG file to write (whole, never through a link: `eant2_jax.app.outputs`); a
        missing folder is created.
      pruned: optional pruned version of ``genome`` (gene order preserved).
      title: figure title.
      n_inputs: number of input nodes to show (default: those the genome reads).
      overwrite: when false, an existing file at ``path`` is refused (`outputs.OutputError`).

    Returns:
      The path written.
    """
    plt = pyplot()
    path = Path(path)
    fig = genome_figure(genome, pruned=pruned, title=title, n_inputs=n_inputs)
    try:
        if not path.parent.exists():  # a dangling link there is refused by make_folder
            outputs.make_folder(path.parent)
        outputs.save_figure(fig, path, overwrite=overwrite, dpi=110, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def _levels(genome: Genome) -> tuple[dict[int, int], int]:
    """Each neuron's row (inputs at 0, a neuron one above its deepest current-step source,
    outputs on the top row) and the top row."""
    level: dict[int, int] = {}
    for i in reversed(range(len(genome))):
        g = genome[i]
        if g.kind != GeneKind.NEURON:
            continue
        lv = 1
        for s in (genome[c] for c in genome.children(i)):
            if s.kind == GeneKind.NEURON or s.kind == GeneKind.FORWARD:
                lv = max(lv, level[s.ref] + 1)
        level[g.ref] = lv
    top = max(level.values()) + 1
    for r in genome.roots:
        level[genome[r].ref] = top
    return level, top


def _positions(genome: Genome, n_in: int) -> tuple[dict, int, int]:
    """Node positions ``{(kind, id): (x, y)}``, the widest row and the top row."""
    level, top = _levels(genome)
    pos: dict[tuple[str, int], tuple[float, float]] = {}
    # Every input up to MAX_DRAWN_INPUTS; beyond, only those read (a genome reading input
    # 20000 alone must not draw 20001 nodes).
    shown = (
        list(range(n_in))
        if n_in <= MAX_DRAWN_INPUTS
        else sorted({g.ref for g in genome if g.kind == GeneKind.INPUT})
    )
    for k, j in enumerate(shown):
        pos[("in", j)] = (k - (len(shown) - 1) / 2, 0.0)
    if any(g.kind == GeneKind.BIAS for g in genome):
        pos[("bias", 0)] = (len(shown) / 2 + 0.8, 0.0)
    rows: dict[int, list[int]] = {}
    for nid in genome.neuron_ids:
        rows.setdefault(level[nid], []).append(nid)
    for lv, ids in rows.items():
        if lv == top:
            ids = [genome[r].ref for r in genome.roots]
        for k, nid in enumerate(ids):
            pos[("n", nid)] = (k - (len(ids) - 1) / 2, float(lv))
    widest = max([len(shown), *(len(ids) for ids in rows.values())])
    return pos, widest, top


def _edge(ax, g, src, dst, style: dict) -> None:
    """One connection: an arrow (bent for a recurrent jumper), or a small loop above a
    neuron reading its own previous output."""
    if src == dst:
        from matplotlib.patches import Arc

        ax.add_patch(
            Arc((dst[0] + 0.12, dst[1] + 0.18), 0.32, 0.34, theta1=-60, theta2=240,
                color=style["color"], lw=style["lw"], ls=style["ls"], zorder=2)
        )  # fmt: skip
        return
    rad = 0.3 if g.kind == GeneKind.RECURRENT else 0.0
    ax.annotate(
        "",
        xy=dst,
        xytext=src,
        arrowprops={
            "arrowstyle": "-|>",
            "connectionstyle": f"arc3,rad={rad}",
            "shrinkA": 9,
            "shrinkB": 9,
            "color": style["color"],
            "lw": style["lw"],
            "linestyle": style["ls"],
        },
    )


def _edges(ax, genome: Genome, pos: dict, removed: set[int]) -> None:
    for i, g in enumerate(genome):
        p = genome.parent[i]
        if p < 0:
            continue
        dst = pos[("n", genome[p].ref)]
        style = {"color": "black", "lw": 1.2, "ls": "-"}
        if g.kind == GeneKind.INPUT:
            src = pos[("in", g.ref)]
        elif g.kind == GeneKind.BIAS:
            src = pos[("bias", 0)]
        else:
            src = pos[("n", g.ref)]
            if g.kind == GeneKind.FORWARD:
                style = {"color": "tab:blue", "lw": 1.2, "ls": "-"}
            elif g.kind == GeneKind.RECURRENT:
                style = {"color": "tab:red", "lw": 1.0, "ls": "--"}
        if i in removed:
            style = {"color": "0.6", "lw": 1.0, "ls": ":"}
        _edge(ax, g, src, dst, style)


def _nodes(ax, genome: Genome, pos: dict) -> None:
    roots = {genome[r].ref for r in genome.roots}
    for (kind, ident), (x, y) in pos.items():
        if kind == "in":
            label, face = f"x{ident}", _FACE["input"]
        elif kind == "bias":
            label, face = "1", _FACE["bias"]
        else:
            label, face = f"N{ident}", _FACE["output" if ident in roots else "hidden"]
        ax.scatter([x], [y], s=520, c=face, edgecolors="black", zorder=3)
        ax.text(x, y, label, ha="center", va="center", fontsize=8, zorder=4)


def _legend(ax, genome: Genome, pos: dict, removed: set[int]) -> None:
    from matplotlib.lines import Line2D

    kinds = {g.kind for g in genome}

    def node(face: str, label: str):
        return Line2D([], [], ls="", marker="o", ms=10, mfc=_FACE[face], mec="black", label=label)

    legend = [node("input", "network input")]
    if ("bias", 0) in pos:
        legend.append(node("bias", "bias (1)"))
    legend += [node("hidden", "hidden neuron"), node("output", "output neuron")]
    legend.append(Line2D([], [], color="black", lw=1.2, label="input of a neuron"))
    if GeneKind.FORWARD in kinds:
        legend.append(Line2D([], [], color="tab:blue", lw=1.2, label="forward jumper"))
    if GeneKind.RECURRENT in kinds:
        legend.append(Line2D([], [], color="tab:red", lw=1.0, ls="--", label="recurrent jumper"))
    if removed:
        legend.append(Line2D([], [], color="0.6", lw=1.0, ls=":", label="removed by pruning"))
    ax.legend(handles=legend, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8,
              frameon=False)  # fmt: skip


def genome_figure(
    genome: Genome,
    *,
    pruned: Genome | None = None,
    title: str | None = None,
    n_inputs: int | None = None,
):
    """The figure `draw_genome` saves (arguments as there)."""
    plt = pyplot()
    n_in = max(n_inputs or 0, genome.n_inputs)
    removed = _removed_genes(genome, pruned) if pruned is not None else set()
    pos, widest, top = _positions(genome, n_in)
    fig, ax = plt.subplots(
        figsize=(min(MAX_INCHES, max(6, widest * 0.8)), min(MAX_INCHES, 1.6 * (top + 1)))
    )
    _edges(ax, genome, pos, removed)
    _nodes(ax, genome, pos)
    ax.set_axis_off()
    _legend(ax, genome, pos, removed)
    stats = f"{genome.n_params} parameters, {genome.n_neurons} neurons"
    if pruned is not None:
        stats += f"; pruned: {pruned.n_params} parameters (dotted grey: removed)"
    ax.set_title((title + "\n" if title else "") + stats, fontsize=9)
    return fig


def _removed_genes(genome: Genome, pruned: Genome) -> set[int]:
    """Gene indices of ``genome`` missing from ``pruned`` (pruning keeps gene order)."""
    return set(range(len(genome))) - set(kept_genes(genome, pruned))


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
