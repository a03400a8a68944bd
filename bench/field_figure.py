"""Learning curves of the field benchmark's result files (bench/bench_field.py):
``python -m bench field figure OUT.png RESULT.json [RESULT.json ...]``."""

from __future__ import annotations

import json
from pathlib import Path

from bench.bench_field import ENVS, METHODS
from bench.common import BenchInputError

__all__ = ["figure"]

_COLORS = {"eant2": "tab:blue", "tensorneat": "tab:orange"}
_LABELS = {"eant2": "eant2_jax", "tensorneat": "TensorNEAT"}


def figure(out: str | Path, results: list[str | Path]) -> Path:
    """Learning curves of field result files as one PNG: a row per environment, the test
    return of each run's champion against evaluations (left) and against wall seconds from
    process start (right), one line per seed and method.

    ``python -m bench field figure OUT.png RESULT.json [RESULT.json ...]``; refuses to
    replace an existing ``OUT``.

    Raises:
      BenchInputError: a missing or unreadable result file, one without runs, or ``OUT``
        already there.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    if out.exists():
        raise BenchInputError(f"{out} exists; the figure never replaces a file")
    runs: list[dict] = []
    devices = set()
    for path in results:
        try:
            payload = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise BenchInputError(f"{path}: not a readable field result ({e})") from None
        if not isinstance(payload, dict) or not payload.get("runs"):
            raise BenchInputError(f"{path}: a field result with runs was expected")
        runs += payload["runs"]
        info = payload.get("environment", {})
        devices.add(f"{info.get('device_kind', '?')}, {str(info.get('date_utc', '?'))[:10]}")
    envs = [e for e in ENVS if any(r["env"] == e for r in runs)]
    fig, axes = plt.subplots(len(envs), 2, figsize=(10, 2.6 * len(envs)), squeeze=False)
    for row, env in zip(axes, envs, strict=True):
        for r in sorted((r for r in runs if r["env"] == env), key=lambda r: r["seed"]):
            pts = [p for p in r.get("curve", []) if "test_return" in p]
            if not pts:
                continue
            y = [p["test_return"] for p in pts]
            style = {"color": _COLORS[r["method"]], "drawstyle": "steps-post", "alpha": 0.8,
                     "linestyle": "-" if r["method"] == "eant2" else "--"}  # fmt: skip
            row[0].plot([p["evaluations"] for p in pts], y, **style)
            row[1].plot([p["wall_s"] for p in pts], y, **style)
        row[0].set_ylabel(f"{env}\ntest return")
        row[0].set_xlabel("evaluations")
        row[1].set_xlabel("wall s from process start")
    handles = [plt.Line2D([], [], color=_COLORS[m], linestyle="-" if m == "eant2" else "--",
                          label=_LABELS[m]) for m in METHODS]  # fmt: skip
    fig.suptitle("; ".join(sorted(devices)) + "; one line per seed", y=0.995, fontsize=9)
    fig.legend(handles=handles, loc="upper center", ncol=2, bbox_to_anchor=(0.5, 0.985))
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
