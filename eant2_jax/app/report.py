"""Reports of runs: ``report(dirs, out)`` writes ``report.md``, its figures and
``summary.json`` for run directories (see `eant2_jax.rundir`), grouped into arms by their
pruner:

* fitness (= -cost) and size of the best individual against generation, every run a thin
  line and each arm's mean a thick one (the paper's figure 8; `report_figures`);
* cond(C) against CMA-ES iteration for a network before and after pruning, when the
  directory holds the V.A experiment's ``condition.json`` (figure 7);
* the best network drawn as a graph (figure 6);
* a table per arm: final fitness and size (mean +- sd), size reduction, generations and
  evaluations to reach 99% of the final fitness, and Welch t-test p-values against the
  reference arm (``none``, the arm without pruning, unless another is named;
  `report_stats`);
* the protocol's verdicts (docs/protocol.md; `report_verdicts`, also ``verdicts.json``):
  size difference with its 95% interval, cost equivalence by TOST at ±3%, evaluations to a
  common target with a bootstrap interval, each claim held / not held / undecided.

Runs are only compared when they ran the same task with the same options and the same
configuration, pruning apart (`report_runs`): anything else raises `MixedRunsError` naming
the difference, unless ``allow_mixed``.

The report is written through `eant2_jax.app.outputs` (whole files, never through a link),
never inside a run directory it reads, and every string read from a run's files (task
names, arms, field names) is `escape`\\ d: it shows on one line, with no Markdown of its own.
"""

from __future__ import annotations

import json
import unicodedata
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..genome import Genome
from ..rundir import CONFIG, LOGS
from . import outputs, report_runs
from .netdraw import draw_network
from .report_figures import condition_figure, fitness_figure, genome_stats, pyplot
from .report_runs import (
    LoadedRun,
    MixedRunsError,
    check_comparable,
    load_runs,
    mixed_message,
    setting,
    upto,
)
from .report_stats import condition_peaks, reference_arm, summarise
from .report_verdicts import protocol_verdicts, target_figure, verdict_lines

__all__ = [
    "LoadedRun",
    "MixedRunsError",
    "check_comparable",
    "default_folder",
    "escape",
    "REPORT_FILES",
    "fitness_figure",
    "genome_stats",
    "load_runs",
    "reference_arm",
    "report",
    "setting",
    "summarise",
    "upto",
]

# Characters that mean something to Markdown (or HTML inside it) anywhere in a line.
_MARKDOWN = set("\\`*_{}[]()#!|<>~&$")
_SHORT = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def escape(value: object) -> str:
    """``str(value)`` safe inside one line of Markdown: its Markdown characters
    backslash-escaped, line breaks and other control or format characters (U+2028
    included) written as ``\\n``, ``\\uXXXX``. For strings read from data files."""
    out = []
    for ch in str(value):
        if ch in _MARKDOWN:
            out.append("\\" + ch)
        elif ch in _SHORT:
            out.append(_SHORT[ch])
        elif unicodedata.category(ch)[0] == "C" or unicodedata.category(ch) in ("Zl", "Zp"):
            out.append(f"\\u{ord(ch):04x}" if ord(ch) <= 0xFFFF else f"\\U{ord(ch):08x}")
        else:
            out.append(ch)
    return "".join(out)


def default_folder(dirs: Sequence[str | Path]) -> Path:
    """Where ``eant2 report`` writes without ``--out``: ``report`` beside the first run
    directory (beside it even when it is named ``.``)."""
    return Path(dirs[0]).resolve().parent / "report"


# The files a report writes (the condition figures only with a condition experiment).
REPORT_FILES = (
    "report.md",
    "summary.json",
    "verdicts.json",
    "fitness_size.png",
    "cost_evaluations.png",
    "condition.png",
    "best_network.png",
    "pruned_network.png",
)


def _is_run_directory(path: Path) -> bool:
    return all((path / name).is_file() for name in (CONFIG, *LOGS))


def _refuse_inside(out: Path, dirs: Sequence[str | Path]) -> None:
    """ValueError if ``out`` is a run directory (of ``dirs`` or any other) or lies inside
    one: a report never writes into a run."""
    where = out.resolve()
    for d in dirs:
        run = Path(d).resolve()
        if where == run or run in where.parents:
            raise ValueError(
                f"{out}: inside the run directory {d}; a report is never written into a run "
                "it reads (name another --out)"
            )
    for folder in (where, *where.parents):
        if _is_run_directory(folder):
            raise ValueError(
                f"{out}: inside the run directory {folder}; a report is never written into "
                "a run (name another --out)"
            )


def _refuse_overwrite(out: Path) -> None:
    """`outputs.OutputError` naming the first of a report's files already in ``out``."""
    for name in REPORT_FILES:
        if outputs.exists(out / name):
            raise outputs.OutputError(
                f"{out}: holds a report ({name}); not overwriting it (name another --out, "
                "or --force replaces it)"
            )


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "—"
    if isinstance(x, float) and (abs(x) >= 1e4 or (abs(x) < 1e-3 and x != 0)):
        return f"{x:.{digits - 1}e}"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def _fmt_list(values: list[float]) -> str:
    return "[" + ", ".join(f"{v:.3g}" for v in values) + "]"


def _figures(runs: list[LoadedRun], arms: list[str], condition: dict | None, out: Path) -> list:
    """Draw the report's figures into ``out``; their file names."""
    plt = pyplot()
    fig = fitness_figure(runs, arms)
    try:
        outputs.save_figure(fig, out / "fitness_size.png", dpi=110)
    finally:
        plt.close(fig)
    figures = ["fitness_size.png"]
    if condition is not None:
        fig = condition_figure(condition)
        try:
            outputs.save_figure(fig, out / "condition.png", dpi=110)
        finally:
            plt.close(fig)
        figures.append("condition.png")
    best_run = min(runs, key=lambda r: r.generations[-1].best_cost)
    best = Genome.parse(best_run.generations[-1].best_genome)
    title = f"best network ({best_run.arm})"
    draw_network(best, out / "best_network.png", title=title)
    figures.append("best_network.png")
    if condition is not None and "genome_before" in condition and "genome_after" in condition:
        draw_network(
            Genome.parse(condition["genome_before"]),
            out / "pruned_network.png",
            pruned=Genome.parse(condition["genome_after"]),
            title="network before and after pruning",
        )
        figures.append("pruned_network.png")
    return figures


def _header(runs: list[LoadedRun], summary: dict, mixed: list[str], upto_: int | None,
            extra: dict) -> list[str]:  # fmt: skip
    lines = ["# EANT2 report", ""]
    tasks = sorted({r.task or "(not recorded)" for r in runs})
    lines.append(f"Task: {', '.join(map(escape, tasks))}; {len(runs)} runs in {len(summary)} arms.")
    if mixed:
        lines.append(
            f"**Mixed runs** (reported together on request): they differ in "
            f"{', '.join(map(escape, mixed))}. "
            "Each arm's mean covers the generations all its runs reached."
        )
    if upto_ is not None:
        lines.append(f"Every run is read up to generation {upto_} (`--upto`).")
    if "device" in extra:
        lines.append(f"Device: {escape(extra['device'])}.")
    if "wall_s" in extra:
        last = " (of its last part: the reproduction was resumed)" if extra.get("resumed") else ""
        lines.append(f"Wall time: {extra['wall_s']:.1f} s{last}.")
    return lines


def _table(summary: dict) -> list[str]:
    lines = [
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
            f"| {escape(arm)} | {s['runs']} | {_fmt(s['fitness_mean'])} ± "
            f"{_fmt(s['fitness_sd'], 2)} | "
            f"{s['size_mean']:.1f} ± {s['size_sd']:.1f} | {red or '—'} | "
            f"{s['generations_to_99']:.1f} | {s['evaluations_to_99']:.3g} | {to_ref} | "
            f"{s['prune_accepted']}/{s['prune_attempts']} | {_fmt(s['p_fitness'], 3)} | "
            f"{_fmt(s['p_size'], 3)} |"
        )
    return lines


def _reference_note(reference: str | None) -> str:
    if reference is None:
        return (
            "No p-values or size reductions: there is no reference arm (no arm without "
            "pruning; name one with --reference)."
        )
    what = " (no pruning)" if reference == "none" else ""
    return (
        f"Reference arm: `{escape(reference)}`{what}. p-values: Welch's t-test of each arm "
        "against it; size reduction relative to it. Evaluations to 99%: until a run's "
        "fitness first reached 99% of its own final fitness; to the reference's 99%: of "
        "the reference arm's mean final fitness (the same target for every arm; mean over "
        "the runs that reached it, and how many did)."
    )


def _sections(extra: dict, condition: dict | None) -> list[str]:
    """Baselines, generalisation, the condition experiment and notes."""
    lines: list[str] = []
    if "baselines" in extra:
        lines += [
            "Baselines (same cost): "
            + ", ".join(f"{escape(k)} {_fmt(float(v))}" for k, v in extra["baselines"].items()),
            "",
        ]
    if "generalisation" in extra:
        lines += [
            "Generalisation (cost of each run's best on the held-out set, mean ± sd): "
            + ", ".join(
                f"{escape(k)} {_fmt(float(np.mean(v)))} ± {_fmt(float(np.std(v)), 2)}"
                for k, v in extra["generalisation"].items()
            ),
            "",
        ]
    if "held_out" in extra:
        lines += [
            "Held-out cost (each run's best on new start poses from `jax.random.key(7000)`, "
            "docs/protocol.md; mean ± sd): "
            + ", ".join(
                f"{escape(k)} {_fmt(float(np.mean(v)))} ± {_fmt(float(np.std(v)), 2)}"
                for k, v in extra["held_out"].items()
            ),
            "",
        ]
    if condition is not None:
        peaks = {k: condition_peaks(condition, k) for k in ("before", "after")}
        lines += [
            f"Condition experiment (V.A): peak cond(C) per initialisation "
            f"{_fmt_list(peaks['before'])} for the original network "
            f"({escape(condition.get('size_before'))} parameters) and "
            f"{_fmt_list(peaks['after'])} after "
            f"pruning ({escape(condition.get('size_after'))}); medians "
            f"{np.median(peaks['before']):.3g} and {np.median(peaks['after']):.3g}.",
            "",
        ]
    if "notes" in extra:
        lines += [extra["notes"], ""]
    return lines


def _summary_json(summary: dict) -> str:
    return (
        json.dumps(
            {
                arm: {k: v for k, v in s.items() if not isinstance(v, np.ndarray)}
                for arm, s in summary.items()
            },
            indent=2,
        )
        + "\n"
    )


def _strict(value):
    """``value`` with its non-finite numbers as None (``never`` for a target not reached):
    strict JSON."""
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strict(v) for v in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def report(
    dirs: Sequence[str | Path],
    out: str | Path,
    *,
    extra: dict | None = None,
    condition: dict | None = None,
    allow_mixed: bool = False,
    reference: str | None = None,
    upto: int | None = None,
    overwrite: bool = True,
) -> Path:
    """Write ``report.md`` and its figures for the given run directories.

    Args:
      dirs: run directories (arms are told apart by their pruner, or an ``arm`` field in
        their ``config.json``).
      out: folder for ``report.md`` and the PNGs (created; existing files of the same names
        are replaced whole, nothing else is touched). Nothing is written when the runs are
        refused. A link at ``out`` or at one of its files, and an ``out`` that is or lies
        inside a run directory (one of ``dirs`` or any other), are refused
        (`eant2_jax.app.outputs`).
      extra: optional sections: ``baselines`` (dict name -> cost), ``generalisation`` (dict
        arm -> list of costs on the task's held-out set), ``held_out`` (the same on new
        start poses, `eant2_jax.app.heldout`; the verdicts' held-out test reads it, else
        ``generalisation``), ``wall_s``, ``device``, ``notes`` (markdown, written as given:
        the caller escapes what it read from files).
      condition: optional V.A experiment result: ``{"before": [cond...], "after": [...],
        "size_before": n, "size_after": m}``.
      allow_mixed: report runs of different tasks or configurations together (the report
        says how they differ); otherwise they raise `MixedRunsError`.
      reference: the arm p-values are computed against (default ``none`` if present).
      upto: read every run only up to this generation (arms compared at equal generations
        when some runs were stopped early); a run that has not reached it is refused.
      overwrite: when false, an ``out`` already holding any of `REPORT_FILES` is refused
        before anything is written (``eant2 report`` without ``--force``).

    Returns:
      The path of ``report.md``.
    """
    runs = load_runs(dirs)  # every directory checked before anything is written
    if upto is not None:
        runs = [report_runs.upto(r, upto) for r in runs]
    out = Path(out)
    mixed = check_comparable(runs)
    if mixed and not allow_mixed:
        raise MixedRunsError(mixed_message(runs, mixed))
    summary = summarise(runs, reference=reference)
    reference = reference_arm(list(summary), reference)
    extra = extra or {}
    _refuse_inside(out, dirs)
    if not overwrite:
        _refuse_overwrite(out)
    outputs.make_folder(out)
    figures = _figures(runs, list(summary), condition, out)
    lines = _header(runs, summary, mixed, upto, extra) + _table(summary)
    lines += ["", _reference_note(reference), ""]
    verdicts = None
    if len(summary) > 1:
        held = extra.get("held_out", extra.get("generalisation"))
        verdicts = protocol_verdicts(runs, held)
        verdicts["held_out_set"] = "new" if "held_out" in extra else "task" if held else None
        lines += [*verdict_lines(verdicts, escape), ""]
        plt = pyplot()
        fig = target_figure(runs, list(summary), verdicts["target_cost"])
        try:
            outputs.save_figure(fig, out / "cost_evaluations.png", dpi=110)
        finally:
            plt.close(fig)
        lines += ["![cost_evaluations.png](cost_evaluations.png)", ""]
    lines += _sections(extra, condition)
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    path = outputs.write_text(out / "report.md", "\n".join(lines) + "\n")
    outputs.write_text(out / "summary.json", _summary_json(summary))
    if verdicts is not None:
        text = json.dumps(_strict(verdicts), indent=2, allow_nan=False)
        outputs.write_text(out / "verdicts.json", text + "\n")
    return path
