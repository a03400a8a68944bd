"""A network drawn with its weights (matplotlib, Agg): ``eant2 show``'s drawing.

Inputs at the bottom, outputs at the top, each neuron one row above its deepest current-step
source. Every connection is an arrow whose colour (blue negative, red positive, on one
symmetric scale with a colour bar) and width give its weight, and whose line gives its kind:
solid for a neuron's own input (an input, the bias, a sub-neuron), dash-dot for a forward
jumper, dashed and bent for a recurrent jumper; dotted grey for a connection pruning removed.
Small networks carry each weight as a number; an output neuron's own weight (it scales the
neuron's output) is written above it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..genome import GeneKind, Genome
from . import outputs
from .report_figures import MAX_DRAWN_INPUTS, MAX_INCHES, pyplot

__all__ = ["LABEL_MAX", "draw_network", "network_figure"]

LABEL_MAX = 40  # networks of at most this many weights have each weight written on its edge
_FACE = {"input": "#e8f0ff", "bias": "#f0f0f0", "hidden": "#fff8e6", "output": "#ffe9c7"}
_LINE = {GeneKind.FORWARD: "-.", GeneKind.RECURRENT: "--"}  # the rest: solid


def _layout(genome: Genome, n_in: int) -> tuple[dict, int, int]:
    """Node positions ``{(kind, id): (x, y)}``, the widest row and the top row."""
    level: dict[int, int] = {}
    for i in reversed(range(len(genome))):
        g = genome[i]
        if g.kind == GeneKind.NEURON:
            sources = (genome[c] for c in genome.children(i))
            deps = [
                level[s.ref] + 1 for s in sources if s.kind in (GeneKind.NEURON, GeneKind.FORWARD)
            ]
            level[g.ref] = max([1, *deps])
    top = max(level.values()) + 1
    for r in genome.roots:
        level[genome[r].ref] = top
    shown = (
        list(range(n_in))
        if n_in <= MAX_DRAWN_INPUTS
        else sorted({g.ref for g in genome if g.kind == GeneKind.INPUT})
    )
    pos = {("in", j): (k - (len(shown) - 1) / 2, 0.0) for k, j in enumerate(shown)}
    if any(g.kind == GeneKind.BIAS for g in genome):
        pos[("bias", 0)] = (len(shown) / 2 + 0.8, 0.0)
    rows: dict[int, list[int]] = {}
    for nid in genome.neuron_ids:
        rows.setdefault(level[nid], []).append(nid)
    rows[top] = [genome[r].ref for r in genome.roots]
    for lv, ids in rows.items():
        for k, nid in enumerate(ids):
            pos[("n", nid)] = (k - (len(ids) - 1) / 2, float(lv))
    return pos, max([len(shown), *(len(ids) for ids in rows.values())]), top


def _connections(genome: Genome, pos: dict) -> list[tuple[int, tuple, tuple]]:
    """``(gene index, source, destination)`` of every gene that feeds a neuron."""
    out = []
    for i, g in enumerate(genome):
        p = genome.parent[i]
        if p < 0:
            continue
        if g.kind == GeneKind.INPUT:
            src = pos.get(("in", g.ref))
        elif g.kind == GeneKind.BIAS:
            src = pos[("bias", 0)]
        else:
            src = pos[("n", g.ref)]
        if src is not None:
            out.append((i, src, pos[("n", genome[p].ref)]))
    return out


def _edge(ax, kind, src, dst, colour, lw: float, ls: str) -> None:
    if src == dst:  # a neuron reading its own previous output
        from matplotlib.patches import Arc

        ax.add_patch(
            Arc(
                (dst[0] + 0.12, dst[1] + 0.18),
                0.32,
                0.34,
                theta1=-60,
                theta2=240,
                color=colour,
                lw=lw,
                ls=ls,
                zorder=2,
            )
        )
        return
    rad = 0.3 if kind == GeneKind.RECURRENT else 0.0
    ax.annotate(
        "",
        xy=dst,
        xytext=src,
        arrowprops={
            "arrowstyle": "-|>",
            "connectionstyle": f"arc3,rad={rad}",
            "shrinkA": 9,
            "shrinkB": 9,
            "color": colour,
            "lw": lw,
            "linestyle": ls,
        },
    )


def _nodes(ax, genome: Genome, pos: dict, label_roots: bool) -> None:
    roots = {genome[r].ref: genome[r].weight for r in genome.roots}
    for (kind, ident), (x, y) in pos.items():
        if kind == "in":
            label, face = f"x{ident}", _FACE["input"]
        elif kind == "bias":
            label, face = "1", _FACE["bias"]
        else:
            label, face = f"N{ident}", _FACE["output" if ident in roots else "hidden"]
        ax.scatter([x], [y], s=520, c=face, edgecolors="black", zorder=3)
        ax.text(x, y, label, ha="center", va="center", fontsize=8, zorder=4)
        if kind == "n" and ident in roots and label_roots:
            ax.text(x + 0.2, y + 0.12, f"×{roots[ident]:.3g}", ha="left", fontsize=7, zorder=4)


def _legend(ax, genome: Genome, pos: dict, removed: set[int]) -> None:
    from matplotlib.lines import Line2D

    kinds = {g.kind for g in genome}

    def node(face: str, label: str):
        return Line2D([], [], ls="", marker="o", ms=10, mfc=_FACE[face], mec="black", label=label)

    handles = [node("input", "network input")]
    if ("bias", 0) in pos:
        handles.append(node("bias", "bias (1)"))
    handles += [node("hidden", "hidden neuron"), node("output", "output neuron")]
    handles.append(Line2D([], [], color="black", lw=1.2, label="input of a neuron"))
    for kind, text in (
        (GeneKind.FORWARD, "forward jumper"),
        (GeneKind.RECURRENT, "recurrent jumper"),
    ):
        if kind in kinds:
            handles.append(Line2D([], [], color="black", lw=1.2, ls=_LINE[kind], label=text))
    if removed:
        handles.append(Line2D([], [], color="0.6", lw=1.0, ls=":", label="removed by pruning"))
    handles.append(Line2D([], [], color="black", lw=3.0, label="width, colour: weight"))
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False
    )


def _removed(genome: Genome, pruned: Genome) -> set[int]:
    """Indices of ``genome``'s genes that pruning removed (gene order is preserved)."""
    from ..pruning import kept_genes

    return set(range(len(genome))) - set(kept_genes(genome, pruned))


def network_figure(
    genome: Genome,
    *,
    pruned: Genome | None = None,
    title: str | None = None,
    n_inputs: int | None = None,
):
    """The figure `draw_network` saves (arguments as there)."""
    from matplotlib import cm, colors

    plt = pyplot()
    pos, widest, top = _layout(genome, max(n_inputs or 0, genome.n_inputs))
    removed = _removed(genome, pruned) if pruned is not None else set()
    edges = _connections(genome, pos)
    scale = max([abs(float(genome[i].weight)) for i, _, _ in edges] + [1e-12])
    norm = colors.Normalize(vmin=-scale, vmax=scale)
    cmap = plt.get_cmap("coolwarm")
    label = genome.n_params <= LABEL_MAX
    fig, ax = plt.subplots(
        figsize=(min(MAX_INCHES, max(6, widest * 0.9)), min(MAX_INCHES, 1.6 * (top + 1)))
    )
    for i, src, dst in edges:
        g = genome[i]
        w = float(g.weight)
        if i in removed:
            _edge(ax, g.kind, src, dst, "0.6", 1.0, ":")
            continue
        _edge(
            ax, g.kind, src, dst, cmap(norm(w)), 0.6 + 3.0 * abs(w) / scale, _LINE.get(g.kind, "-")
        )
        if label:  # near the head of the arrow; above a neuron's loop onto itself
            x, y = 0.35 * np.asarray(src) + 0.65 * np.asarray(dst)
            if src == dst:
                x, y = x + 0.3, y + 0.4
            ax.text(
                x,
                y,
                f"{w:.2g}",
                fontsize=6,
                ha="center",
                va="center",
                zorder=5,
                bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8},
            )
    _nodes(ax, genome, pos, label)
    ax.set_axis_off()
    _legend(ax, genome, pos, removed)
    bar = fig.colorbar(
        cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.5, pad=0.02, location="left"
    )
    bar.set_label("weight", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    stats = f"{genome.n_params} parameters, {genome.n_neurons} neurons"
    if pruned is not None:
        stats += f"; pruned: {pruned.n_params} parameters (dotted grey: removed)"
    ax.set_title((title + "\n" if title else "") + stats, fontsize=9)
    return fig


def draw_network(
    genome: Genome,
    path: str | Path,
    *,
    pruned: Genome | None = None,
    title: str | None = None,
    n_inputs: int | None = None,
    overwrite: bool = True,
) -> Path:
    """Draw a network with its weights into a PNG, with a legend and a colour bar (module
    docstring): ``eant2 show``'s drawing and the report's.

    Args:
      genome: the network (the unpruned one when ``pruned`` is given).
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
    fig = network_figure(genome, pruned=pruned, title=title, n_inputs=n_inputs)
    try:
        if not path.parent.exists():
            outputs.make_folder(path.parent)
        outputs.save_figure(fig, path, overwrite=overwrite, dpi=110, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path
