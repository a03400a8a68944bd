"""The servo throughput suite's tables (bench/bench_servo.py): its rows of each kind (task,
bare MJX, hand-written kinematics, raw ``mjx.step``) side by side per batch size, kinematic
and dynamic mode, and their markdown."""

from __future__ import annotations

import json
from typing import Any

from bench.common import Column, markdown_table

__all__ = ["render"]


def _find(rows: list[dict], kind: str, moves: int, **kw) -> dict | None:
    for r in rows:
        if r["kind"] == kind and r["moves"] == moves and all(r.get(k) == v for k, v in kw.items()):
            return r
    return None


def _get(r: dict | None, key: str) -> Any:
    return None if r is None else r.get(key)


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a and b else None


def _kinematic(rows: list[dict]) -> list[dict]:
    """One line per batch: the task's and the references' moves/s at that many moves."""
    out = []
    batches = {r["moves"] for r in rows if r.get("mode") == "kinematic"}
    batches -= {r["moves"] for r in rows if "moves_per_start" in r}
    for mv in sorted(batches):
        t = _find(rows, "task", mv, mode="kinematic", net="minimal")
        tf = _find(rows, "task_flat", mv, mode="kinematic", net="minimal")
        p = _find(rows, "task", mv, mode="kinematic", net="paper")
        b = _find(rows, "bare_mjx_kinematics", mv)
        bn = _find(rows, "bare_mjx_kinematics_nested", mv)
        best_task = max([r["moves_per_s"] for r in (t, tf) if r] or [0]) or None
        best_bare = max([r["moves_per_s"] for r in (b, bn) if r] or [0]) or None
        out.append({
            "moves": mv, "n_nets": (t or p or {}).get("n_nets"),
            "task": _get(t, "moves_per_s"), "task_compile": _get(t, "compile_s"),
            "flat": _get(tf, "moves_per_s"),
            "paper": _get(p, "moves_per_s"), "paper_compile": _get(p, "compile_s"),
            "bare": _get(b, "moves_per_s"), "bare_compile": _get(b, "compile_s"),
            "nested": _get(bn, "moves_per_s"),
            "hand": _get(_find(rows, "hand_fk", mv), "moves_per_s"),
            "ratio": _ratio(best_task, best_bare),
        })  # fmt: skip
    return out


def _dynamic(rows: list[dict]) -> list[dict]:
    """One line per batch: the task's and MJX's raw physics steps/s at that many moves."""
    out = []
    batches = {r["moves"] for r in rows if r.get("mode") == "dynamic"}
    batches |= {r["moves"] for r in rows if r["kind"].startswith("mjx_step")}
    for mv in sorted(batches):
        t = _find(rows, "task", mv, mode="dynamic", net="minimal")
        raw = _find(rows, "mjx_step_raw", mv)
        out.append({
            "moves": mv, "n_nets": _get(t, "n_nets"), "task_moves": _get(t, "moves_per_s"),
            "task": _get(t, "steps_per_s"), "task_compile": _get(t, "compile_s"),
            "flat": _get(_find(rows, "task_flat", mv, mode="dynamic", net="minimal"),
                         "steps_per_s"),
            "raw": _get(raw, "steps_per_s"), "raw_compile": _get(raw, "compile_s"),
            "ratio": _ratio(_get(t, "steps_per_s"), _get(raw, "steps_per_s")),
            "limits": _get(_find(rows, "mjx_step_raw_limits", mv), "steps_per_s"),
        })  # fmt: skip
    return out


def _other(rows: list[dict], substeps: int) -> list[dict]:
    out = []
    for r in rows:
        if r["kind"] == "mjx_benchmark":
            what = f"`mujoco.mjx.benchmark` (task's model, batch {r['moves']}, {substeps} steps)"
        elif r.get("moves_per_start"):
            what = (
                f"task, kinematic, minimal net, closed loop {r['moves_per_start']} "
                f"moves/start, {r['n_nets']} nets"
            )
        elif r.get("mode") == "dynamic" and r.get("net") == "paper":
            what = f"task, dynamic, paper-size net, {r['n_nets']} nets"
        else:
            continue
        out.append({"what": what, **r})
    return out


_G, _S = "{:.3g}", "{:.1f}"
KINEMATIC = [
    Column("moves", "moves", _G), Column("n_nets", "networks"),
    Column("task", "task, minimal net", _G), Column("task_compile", "compile s", _S),
    Column("flat", "task_flat, minimal net", _G),
    Column("paper", "task, paper-size net", _G), Column("paper_compile", "compile s", _S),
    Column("bare", "bare mjx.kinematics + projection", _G),
    Column("bare_compile", "compile s", _S), Column("nested", "bare, nested [nets, 1023]", _G),
    Column("hand", "hand-written FK + projection", _G),
    Column("ratio", "task / best bare", "{:.2f}"),
]  # fmt: skip
DYNAMIC = [
    Column("moves", "moves", _G), Column("n_nets", "networks"),
    Column("task_moves", "task moves/s", _G), Column("task", "task steps/s", _G),
    Column("task_compile", "compile s", _S), Column("flat", "task_flat steps/s", _G),
    Column("raw", "raw mjx.step steps/s (task's model)", _G),
    Column("raw_compile", "compile s", _S), Column("ratio", "task / raw (steps/s)", "{:.2f}"),
    Column("limits", "raw mjx.step steps/s, limit constraints on (full arm.xml)", _G),
]  # fmt: skip
OTHER = [
    Column("what", "what"), Column("moves", "moves", _G), Column("moves_per_s", "moves/s", _G),
    Column("steps_per_s", "steps/s", _G), Column("compile_s", "compile s", _S),
]  # fmt: skip


def render(payload: dict[str, Any]) -> str:
    """The markdown tables of a payload (also usable on a partial run)."""
    rows = [r for r in payload["rows"] if "error" not in r]
    substeps = payload["config"]["substeps"]
    lines = [
        "**Kinematic mode** (moves/s; a move = one network on one start pose: forward pass, "
        "increments, arm, projection, cost):\n",
        markdown_table(_kinematic(rows), KINEMATIC),
        f"**Dynamic mode** ({substeps} `mjx.step` of 5 ms per move; steps/s counts physics "
        "steps):\n",
        markdown_table(_dynamic(rows), DYNAMIC),
    ]
    other = _other(rows, substeps)
    if other:
        lines += ["Other rows:\n", markdown_table(other, OTHER)]
    errors = [r for r in payload["rows"] if "error" in r]
    if errors or payload.get("skipped"):
        lines.append(
            f"Failed rows: {len(errors)}; skipped for time: {len(payload.get('skipped', []))}.\n"
        )
    if payload.get("checks"):
        lines.append("Checks: `" + json.dumps(payload["checks"]) + "`\n")
    return "\n".join(lines)
