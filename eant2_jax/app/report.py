"""Reports of runs: figures, statistics and network drawings (host side, matplotlib).

``report(dirs, out)`` reads run directories (see `eant2_jax.rundir`), groups them into
arms by their pruner, and writes ``report.md`` with

* fitness (= -cost) and size of the best individual against generation, every run a thin
  line and each arm's mean a thick one (the paper's figure 8);
* cond(C) against CMA-ES iteration for a network before and after pruning, when the
  directory holds the V.A experiment's ``condition.json`` (figure 7);
* the best network drawn as a graph (figure 6);
* a table per arm: final fitness and size (mean +- sd), size reduction, generations and
  evaluations to reach 99% of the final fitness, and Welch t-test p-values against the
  reference arm (``none``, the arm without pruning, unless another is named).

Runs are only compared when they ran the same task with the same options and the same
configuration, pruning apart (the arms differ in it): anything else raises
`MixedRunsError` naming the difference, unless ``allow_mixed``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..genome import GeneKind, Genome
from ..loop import GenerationRecord
from ..pruning import PruneAttempt, kept_genes

__all__ = [
    "LoadedRun",
    "MixedRunsError",
    "check_comparable",
    "draw_genome",
    "fitness_figure",
    "genome_figure",
    "genome_stats",
    "load_runs",
    "reference_arm",
    "report",
    "setting",
    "summarise",
]

# Node faces of network drawings (nodes and legend).
_FACE = {"input": "#e8f0ff", "bias": "#f0f0f0", "hidden": "#fff8e6", "output": "#ffe9c7"}


class MixedRunsError(ValueError):
    """Run directories that differ in their task or configuration (beyond pruning)."""


MAX_DRAWN_INPUTS = 64
MAX_INCHES = 60  # a drawing of a wide or deep genome is squeezed, not megapixels wide


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; never a window
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
) -> Path:
    """Draw a network as a graph (inputs bottom, outputs top) into a PNG, with a legend.

    Solid black: a neuron's own inputs (inputs, biases, sub-neurons); solid blue: forward
    jumpers; dashed red: recurrent jumpers. With ``pruned`` (the same network after
    pruning), connections that pruning removed are drawn dotted grey. The bias node is drawn
    only when a gene reads it.

    Args:
      genome: the network to draw (the unpruned one when ``pruned`` is given).
      path: PNG file to write.
      pruned: optional pruned version of ``genome`` (gene order preserved).
      title: figure title.
      n_inputs: number of input nodes to show (default: those the genome reads).

    Returns:
      The path written.
    """
    plt = _pyplot()
    path = Path(path)
    fig = genome_figure(genome, pruned=pruned, title=title, n_inputs=n_inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def genome_figure(
    genome: Genome,
    *,
    pruned: Genome | None = None,
    title: str | None = None,
    n_inputs: int | None = None,
):
    """The figure `draw_genome` saves (arguments as there)."""
    plt = _pyplot()
    from matplotlib.lines import Line2D

    n_in = max(n_inputs or 0, genome.n_inputs)
    removed = _removed_genes(genome, pruned) if pruned is not None else set()
    # Levels: inputs at 0, each neuron one above its deepest current-step source.
    level: dict[int, int] = {}
    for i in reversed(range(len(genome))):
        g = genome[i]
        if g.kind != GeneKind.NEURON:
            continue
        srcs = [genome[c] for c in genome.children(i)]
        lv = 1
        for s in srcs:
            if s.kind == GeneKind.NEURON or s.kind == GeneKind.FORWARD:
                lv = max(lv, level[s.ref] + 1)
        level[g.ref] = lv
    top = max(level.values()) + 1
    for r in genome.roots:  # outputs on the top row
        level[genome[r].ref] = top
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
    n_in = len(shown)
    if any(g.kind == GeneKind.BIAS for g in genome):
        pos[("bias", 0)] = (n_in / 2 + 0.8, 0.0)
    rows: dict[int, list[int]] = {}
    for nid in genome.neuron_ids:
        rows.setdefault(level[nid], []).append(nid)
    for lv, ids in rows.items():
        if lv == top:
            ids = [genome[r].ref for r in genome.roots]
        for k, nid in enumerate(ids):
            pos[("n", nid)] = (k - (len(ids) - 1) / 2, float(lv))

    widest = max([n_in, *(len(ids) for ids in rows.values())])
    fig, ax = plt.subplots(
        figsize=(min(MAX_INCHES, max(6, widest * 0.8)), min(MAX_INCHES, 1.6 * (top + 1)))
    )
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
        if src == dst:  # a neuron reading its own previous output: a small loop above it
            from matplotlib.patches import Arc

            ax.add_patch(
                Arc(
                    (dst[0] + 0.12, dst[1] + 0.18),
                    0.32,
                    0.34,
                    theta1=-60,
                    theta2=240,
                    color=style["color"],
                    lw=style["lw"],
                    ls=style["ls"],
                    zorder=2,
                )
            )
            continue
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
                **{k: v for k, v in (("color", style["color"]), ("lw", style["lw"]))},
                "linestyle": style["ls"],
            },
        )
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
    ax.set_axis_off()
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
    stats = f"{genome.n_params} parameters, {genome.n_neurons} neurons"
    if pruned is not None:
        stats += f"; pruned: {pruned.n_params} parameters (dotted grey: removed)"
    ax.set_title((title + "\n" if title else "") + stats, fontsize=9)
    return fig


def _removed_genes(genome: Genome, pruned: Genome) -> set[int]:
    """Gene indices of ``genome`` missing from ``pruned`` (pruning keeps gene order)."""
    return set(range(len(genome))) - set(kept_genes(genome, pruned))


@dataclasses.dataclass(frozen=True)
class LoadedRun:
    """One run directory as the report reads it.

    Attributes:
      dir: its path; arm: its arm label (the pruner unless the run names one); task: the
      task's name (None if not recorded); seed: the seed (None if not recorded).
      generations: its `GenerationRecord`s; pruning: its `PruneAttempt`s.
      setting: what must agree between runs that are compared (`setting`).
      budget: generations asked for (None if not recorded); target_cost: the run's stop
      target (None if none).
    """

    dir: str
    arm: str
    task: str | None
    seed: int | None
    generations: list[GenerationRecord]
    pruning: list[PruneAttempt]
    setting: dict = dataclasses.field(default_factory=dict)
    budget: int | None = None
    target_cost: float | None = None


# Fields of config.json that may differ between compared runs: the arms differ in pruning,
# runs in their seed, and devices are placement only (the results are identical).
_FREE = {"format", "seed", "key", "arm", "devices"}


def setting(meta: dict) -> dict:
    """What a run's ``config.json`` says that runs compared in one report must share: the task,
    its options, the generations asked for and the configuration, pruning fields, seed and
    devices left out. Flat ``{"config.exploit.max_iters": 1000, ...}``."""
    flat: dict = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict) and prefix != "task_options":
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        else:
            flat[prefix] = value

    walk("", {k: v for k, v in meta.items() if k not in _FREE})
    flat.setdefault("task", None)
    flat.setdefault("task_options", {})
    flat.pop("config.devices", None)
    for k in [k for k in flat if k.startswith("config.exploit.") and "prune" in k]:
        del flat[k]  # pruner, prune_window, ...: what the arms compare
    return flat


def check_comparable(runs: Sequence[LoadedRun]) -> list[str]:
    """The fields in which ``runs`` differ (empty: they may be compared)."""
    fields = sorted({k for r in runs for k in r.setting}, key=lambda k: (k != "task", k))
    return [f for f in fields if len({json.dumps(r.setting.get(f)) for r in runs}) > 1]


def _mixed_message(runs: Sequence[LoadedRun], fields: list[str]) -> str:
    first = fields[0]
    a = runs[0]
    b = next(
        r for r in runs if json.dumps(r.setting.get(first)) != json.dumps(a.setting.get(first))
    )
    more = f" (and {len(fields) - 1} more: {', '.join(fields[1:4])})" if len(fields) > 1 else ""
    name = first.removeprefix("config.").removeprefix("exploit.")
    return (
        f"runs differ in {name}: {a.dir} has {json.dumps(a.setting.get(first))}, {b.dir} has "
        f"{json.dumps(b.setting.get(first))}{more}; pass --allow-mixed to report them together"
    )


def _peaks(condition: dict, which: str) -> list[float]:
    """Peak cond(C) of each run of the condition experiment (one run in older files)."""
    curves = condition[which]
    if curves and not isinstance(curves[0], list):
        curves = [curves]
    return [float(max(c)) for c in curves]


def _fmt_list(values: list[float]) -> str:
    return "[" + ", ".join(f"{v:.3g}" for v in values) + "]"


def load_runs(dirs: Sequence[str | Path]) -> list[LoadedRun]:
    """Read run directories: config, generation records and arm label of each."""
    from ..loop import validate

    runs = []
    for d in dirs:
        # Checked as resume checks it, reading only what was committed (so a live run is
        # read consistently, without its lock).
        v = validate(str(d), lock=False)
        meta = v.committed.config
        if not v.records:
            raise ValueError(f"{d}: no completed generation to report")
        config = meta.get("config", {})
        arm = meta.get("arm", v.config.exploit.pruner)
        task, seed = meta.get("task", meta.get("task_type", "?")), meta.get("seed")
        if not isinstance(arm, str) or not isinstance(task, str):
            raise ValueError(f"{d}: config.json's arm and task must be names")
        budget = meta.get("generations")
        target = config.get("target_cost") if isinstance(config, dict) else None
        runs.append(
            LoadedRun(
                dir=str(d),
                arm=arm,
                task=task,
                seed=seed if isinstance(seed, int) else None,
                generations=v.records,
                pruning=v.pruning,
                setting=setting(meta),
                budget=budget if isinstance(budget, int) else None,
                target_cost=target if isinstance(target, int | float) else None,
            )
        )
    return runs


def _upto(run: LoadedRun, generation: int) -> LoadedRun:
    """``run`` read up to ``generation`` (ValueError if it has not reached it)."""
    if isinstance(generation, bool) or not isinstance(generation, int) or generation < 0:
        raise ValueError(f"upto must be a generation >= 0, got {generation!r}")
    last = run.generations[-1].generation
    if last < generation:
        raise ValueError(f"{run.dir}: its last generation is {last}, before {generation}")
    return dataclasses.replace(
        run,
        generations=[g for g in run.generations if g.generation <= generation],
        pruning=[p for p in run.pruning if p.generation is None or p.generation <= generation],
    )


def _first_within(gens: list[GenerationRecord], cost: float) -> GenerationRecord | None:
    """The first generation whose best cost came within 1% of ``cost`` (None: none did)."""
    return next((g for g in gens if g.best_cost <= cost + 0.01 * abs(cost)), None)


def _to_target(gens: list[GenerationRecord]) -> tuple[int, int]:
    """Generation and evaluations at which the best cost first came within 1% of its final
    value (i.e. the fitness reached 99% of its final value)."""
    g = _first_within(gens, gens[-1].best_cost) or gens[-1]
    return g.generation, g.evaluations


def reference_arm(arms: Sequence[str], reference: str | None = None) -> str | None:
    """The arm p-values and size reductions are computed against: ``reference`` if given
    (ValueError if no arm has that name), else ``none`` (no pruning) if there is one."""
    if reference is not None:
        if reference not in arms:
            raise ValueError(f"no arm {reference!r} to compare against; arms: {', '.join(arms)}")
        return reference
    return "none" if "none" in arms else None


def summarise(runs: list[LoadedRun], *, reference: str | None = None) -> dict[str, dict]:
    """Per arm: final fitness/size mean and sd, size reduction, time to 99%, p-values
    against the `reference_arm`."""
    from scipy import stats

    arms: dict[str, list[LoadedRun]] = {}
    for r in runs:
        arms.setdefault(r.arm, []).append(r)
    out: dict[str, dict] = {}
    for arm, rs in arms.items():
        fit = np.array([-r.generations[-1].best_cost for r in rs])
        size = np.array([r.generations[-1].best_size for r in rs], float)
        reach = np.array([_to_target(r.generations) for r in rs], float)
        out[arm] = {
            "runs": len(rs),
            "fitness": fit,
            "size": size,
            "fitness_mean": float(fit.mean()),
            "fitness_sd": float(fit.std(ddof=1)) if len(rs) > 1 else 0.0,
            "size_mean": float(size.mean()),
            "size_sd": float(size.std(ddof=1)) if len(rs) > 1 else 0.0,
            "generations_to_99": float(reach[:, 0].mean()),
            "evaluations_to_99": float(reach[:, 1].mean()),
            "prune_accepted": int(sum(sum(x.accepted for x in r.pruning) for r in rs)),
            "prune_attempts": int(sum(len(r.pruning) for r in rs)),
        }
    reference = reference_arm(list(out), reference)
    for arm, s in out.items():
        # Time to the reference arm's quality: each arm's "to 99%" is to its own final
        # fitness, so an arm that ends better is charged for its later gains; this is the
        # same target for every arm (99% of the reference's mean final fitness).
        s["evaluations_to_reference"] = s["reached_reference"] = None
        if reference is not None:
            target = -out[reference]["fitness_mean"]
            hits = [_first_within(r.generations, target) for r in arms[arm]]
            reached = [h.evaluations for h in hits if h is not None]
            s["reached_reference"] = len(reached)
            s["evaluations_to_reference"] = float(np.mean(reached)) if reached else None
        if reference is None or arm == reference:
            s["size_reduction_pct"] = None
            s["p_fitness"] = s["p_size"] = None
            continue
        ref = out[reference]
        s["size_reduction_pct"] = 100.0 * (1 - s["size_mean"] / ref["size_mean"])
        if s["runs"] > 1 and ref["runs"] > 1:
            s["p_fitness"] = _welch(s["fitness"], ref["fitness"], stats)
            s["p_size"] = _welch(s["size"], ref["size"], stats)
        else:
            s["p_fitness"] = s["p_size"] = None
    return out


def _welch(a, b, stats) -> float | None:
    if np.all(a == a[0]) and np.all(b == b[0]):
        return 1.0 if a[0] == b[0] else 0.0
    p = float(stats.ttest_ind(a, b, equal_var=False).pvalue)
    return None if math.isnan(p) else p


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "—"
    if isinstance(x, float) and (abs(x) >= 1e4 or (abs(x) < 1e-3 and x != 0)):
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


_STYLES = ["-", "--", "-.", ":"]
_MARKERS = ["o", "s", "^", "D", "v", "P", "X", "*"]


def fitness_figure(runs: Sequence[LoadedRun], arms: Sequence[str]):
    """Fitness and size of the best against generation: every run a thin line, each arm's
    mean a thick one with its own line style and marker (arms that overlap stay apart),
    integer generation ticks, and the caps that apply marked: the target fitness (``-``
    the runs' ``target_cost``) and the generation budget when a run stopped before it.

    Returns:
      The matplotlib figure (two axes).
    """
    plt = _pyplot()
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
    targets = {r.target_cost for r in runs}
    if len(targets) == 1 and None not in targets:
        axes[0].axhline(-targets.pop(), color="0.3", lw=1, ls=(0, (6, 3)), label="target")
    budgets = {r.budget for r in runs if r.budget is not None}
    if budgets and any(len(r.generations) < (r.budget or 0) + 1 for r in runs):
        for ax in axes:
            for b in sorted(budgets):
                ax.axvline(b, color="0.5", lw=1, ls=":", label=f"budget ({b} generations)")
    axes[0].set(xlabel="generation", ylabel="fitness = -cost", title="fitness of the best")
    axes[1].set(xlabel="generation", ylabel="parameters", title="size of the best")
    for a in axes:
        a.xaxis.set_major_locator(MaxNLocator(integer=True))
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    return fig


def report(
    dirs: Sequence[str | Path],
    out: str | Path,
    *,
    extra: dict | None = None,
    condition: dict | None = None,
    allow_mixed: bool = False,
    reference: str | None = None,
    upto: int | None = None,
) -> Path:
    """Write ``report.md`` and its figures for the given run directories.

    Args:
      dirs: run directories (arms are told apart by their pruner, or an ``arm`` field in
        their ``config.json``).
      out: folder for ``report.md`` and the PNGs (created; existing files of the same names
        are replaced, nothing else is touched). Nothing is written when the runs are refused.
      extra: optional sections: ``baselines`` (dict name -> cost), ``generalisation`` (dict
        arm -> list of held-out costs), ``wall_s``, ``device``, ``notes`` (markdown).
      condition: optional V.A experiment result: ``{"before": [cond...], "after": [...],
        "size_before": n, "size_after": m}``.
      allow_mixed: report runs of different tasks or configurations together (the report
        says how they differ); otherwise they raise `MixedRunsError`.
      reference: the arm p-values are computed against (default ``none`` if present).
      upto: read every run only up to this generation (arms compared at equal generations
        when some runs were stopped early); a run that has not reached it is refused.

    Returns:
      The path of ``report.md``.
    """
    runs = load_runs(dirs)  # every directory checked before anything is written
    if upto is not None:
        runs = [_upto(r, upto) for r in runs]
    plt = _pyplot()
    out = Path(out)
    mixed = check_comparable(runs)
    if mixed and not allow_mixed:
        raise MixedRunsError(_mixed_message(runs, mixed))
    summary = summarise(runs, reference=reference)
    reference = reference_arm(list(summary), reference)
    extra = extra or {}
    out.mkdir(parents=True, exist_ok=True)

    fig = fitness_figure(runs, list(summary))
    fig.savefig(out / "fitness_size.png", dpi=110)
    plt.close(fig)

    figures = ["fitness_size.png"]
    if condition is not None:
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
        fig.savefig(out / "condition.png", dpi=110)
        plt.close(fig)
        figures.append("condition.png")

    best_run = min(runs, key=lambda r: r.generations[-1].best_cost)
    best = Genome.parse(best_run.generations[-1].best_genome)
    draw_genome(best, out / "best_network.png", title=f"best network ({best_run.arm})")
    figures.append("best_network.png")
    if condition is not None and "genome_before" in condition and "genome_after" in condition:
        draw_genome(
            Genome.parse(condition["genome_before"]),
            out / "pruned_network.png",
            pruned=Genome.parse(condition["genome_after"]),
            title="network before and after pruning",
        )
        figures.append("pruned_network.png")

    lines = ["# EANT2 report", ""]
    tasks = sorted({r.task or "(not recorded)" for r in runs})
    lines.append(f"Task: {', '.join(tasks)}; {len(runs)} runs in {len(summary)} arms.")
    if mixed:
        lines.append(
            f"**Mixed runs** (reported together on request): they differ in {', '.join(mixed)}. "
            "Each arm's mean covers the generations all its runs reached."
        )
    if upto is not None:
        lines.append(f"Every run is read up to generation {upto} (`--upto`).")
    if "device" in extra:
        lines.append(f"Device: {extra['device']}.")
    if "wall_s" in extra:
        last = " (of its last part: the reproduction was resumed)" if extra.get("resumed") else ""
        lines.append(f"Wall time: {extra['wall_s']:.1f} s{last}.")
    lines += [
        "",
        "| arm | runs | final fitness (mean ± sd) | size (mean ± sd) | size reduction | "
        "generations to 99% | evaluations to 99% | evaluations to the reference's 99% | "
        "pruned (accepted/attempts) | p (fitness) | p (size) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for arm, s in summary.items():
        red = None if s["size_reduction_pct"] is None else f"{s['size_reduction_pct']:.1f}%"
        to_ref = "—"
        if s.get("reached_reference") is not None:
            mean = s["evaluations_to_reference"]
            shown = "—" if mean is None else f"{mean:.3g}"
            to_ref = f"{shown} ({s['reached_reference']}/{s['runs']})"
        lines.append(
            f"| {arm} | {s['runs']} | {_fmt(s['fitness_mean'])} ± {_fmt(s['fitness_sd'], 2)} | "
            f"{s['size_mean']:.1f} ± {s['size_sd']:.1f} | {red or '—'} | "
            f"{s['generations_to_99']:.1f} | {s['evaluations_to_99']:.3g} | {to_ref} | "
            f"{s['prune_accepted']}/{s['prune_attempts']} | {_fmt(s['p_fitness'], 3)} | "
            f"{_fmt(s['p_size'], 3)} |"
        )
    if reference is None:
        note = (
            "No p-values or size reductions: there is no reference arm (no arm without "
            "pruning; name one with --reference)."
        )
    else:
        what = " (no pruning)" if reference == "none" else ""
        note = (
            f"Reference arm: `{reference}`{what}. p-values: Welch's t-test of each arm "
            "against it; size reduction relative to it. Evaluations to 99%: until a run's "
            "fitness first reached 99% of its own final fitness; to the reference's 99%: of "
            "the reference arm's mean final fitness (the same target for every arm; mean over "
            "the runs that reached it, and how many did)."
        )
    lines += ["", note, ""]
    if "baselines" in extra:
        lines += [
            "Baselines (same cost): "
            + ", ".join(f"{k} {_fmt(float(v))}" for k, v in extra["baselines"].items()),
            "",
        ]
    if "generalisation" in extra:
        lines += [
            "Generalisation (cost of each run's best on the held-out set, mean ± sd): "
            + ", ".join(
                f"{k} {_fmt(float(np.mean(v)))} ± {_fmt(float(np.std(v)), 2)}"
                for k, v in extra["generalisation"].items()
            ),
            "",
        ]
    if condition is not None:
        peaks = {k: _peaks(condition, k) for k in ("before", "after")}
        lines += [
            f"Condition experiment (V.A): peak cond(C) per initialisation "
            f"{_fmt_list(peaks['before'])} for the original network "
            f"({condition.get('size_before')} parameters) and {_fmt_list(peaks['after'])} after "
            f"pruning ({condition.get('size_after')}); medians {np.median(peaks['before']):.3g} "
            f"and {np.median(peaks['after']):.3g}.",
            "",
        ]
    if "notes" in extra:
        lines += [extra["notes"], ""]
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out / "summary.json").write_text(
        json.dumps(
            {
                arm: {k: v for k, v in s.items() if not isinstance(v, np.ndarray)}
                for arm, s in summary.items()
            },
            indent=2,
        )
        + "\n",
        encoding="utf-8",
    )
    return path
