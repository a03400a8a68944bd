"""Reproduction manifests (``reproduce.json``): mutated, then read as ``eant2 resume DIR``
reads a reproduction before it runs anything (`eant2_jax.app.manifest.read_manifest`, then
`resume_task`, which rebuilds the recorded task).

Mutations: a JSON field replaced by a value of a random type, byte flips, truncation,
appended garbage, deep nesting, an oversized file, a link, a FIFO or a directory in its
place, and hostile tasks (`bench.fuzz.common.hostile_tasks`: a shell command, a shipped
task file or module). Accepted means every setting read back equals the file's and the
task built is the recorded one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from bench.fuzz.common import Marker, Tally, classify, hostile_tasks, json_paths, set_path
from eant2_jax import EANT2Config, ExploitConfig, tasks
from eant2_jax.app import manifest as mf

RANDOM_VALUES = [None, True, False, 0, -1, 1, 2, 2**31, 2**32, 2**63, 1.5, -0.0, 1e308, "",
                 "x", "all", "float64", "none", "os:system", [], [0], ["none"], {}, {"a": 1},
                 [[[]]], 10**30]  # fmt: skip
KINDS = ("field", "field", "field", "hostile", "flip", "truncate", "append", "deep", "huge",
         "symlink", "fifo", "dir", "task_options")  # fmt: skip


def base() -> dict:
    """A valid manifest: xor, two arms, one run each."""
    return {
        "version": mf.MANIFEST_VERSION,
        "task_meta": {"task": "xor", "task_options": {}},
        "runs": 1,
        "generations": 1,
        "pruners": ["none", "covariance"],
        "config": EANT2Config(population=2).to_dict(),
        "seed": 0,
        "devices": 1,
        "workers_per_device": 1,
        "condition": False,
        "condition_iters": 10,
        "condition_inits": 2,
        "condition_dtype": "float32",
        "lockstep": False,
    }


def mutate(rng, d: Path, outside: Path, hostile: list) -> tuple[str, dict | None]:
    """Write a mutated ``d/reproduce.json``; returns the kind and the manifest (None where
    the file is not the JSON of a dict)."""
    kind = KINDS[rng.integers(len(KINDS))]
    p = d / mf.MANIFEST
    m = base()
    if kind == "field":
        paths = list(json_paths(m))[1:]
        m = set_path(
            m, paths[rng.integers(len(paths))], RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
        )
    elif kind == "task_options":
        key = ["hidden", "output", "bogus", "inputs", "targets"][rng.integers(5)]
        m["task_meta"]["task_options"] = {key: RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]}
    elif kind == "hostile":
        spec, options = hostile[rng.integers(len(hostile))]
        m["task_meta"] = {"task": spec, "task_options": options}
    if kind == "deep":
        p.write_text('{"version": 1, "task_meta": ' + "[" * 100_000 + "]" * 100_000 + "}")
        return kind, None
    if kind == "huge":
        p.write_text(json.dumps({**m, "pad": "x" * (2 << 20)}))
        return kind, None
    if kind in ("symlink", "fifo", "dir"):
        outside.write_text(json.dumps(m)) if kind == "symlink" else None
        if kind == "symlink":
            p.symlink_to(outside)
        elif kind == "fifo":
            os.mkfifo(p)
        else:
            p.mkdir()
        return kind, None
    data = bytearray(json.dumps(m).encode())
    if kind == "flip":
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(len(data))] ^= 1 << rng.integers(8)
    elif kind == "truncate":
        data = data[: rng.integers(len(data))]
    elif kind == "append":
        data += [b"\n{}", b"]", b"\xff", b" \n", b"NaN"][rng.integers(5)]
    p.write_bytes(bytes(data))
    try:
        parsed = json.loads(bytes(data))
    except ValueError:
        return kind, None
    return kind, parsed if isinstance(parsed, dict) else None


def _same(out: dict, m: dict) -> bool:
    """Whether the settings read back equal the file's."""
    for name in ("runs", "generations", "seed", "workers_per_device", "condition",
                 "condition_iters", "condition_inits", "condition_dtype", "pruners"):  # fmt: skip
        if out[name] != m[name] or type(out[name]) is not type(m[name]):
            return False
    if out["devices"] != m["devices"] or out["lockstep"] != m.get("lockstep", False):
        return False
    return out["task_meta"] == m["task_meta"]


def _equal(read, written) -> bool:
    """Equal as data: numbers by value (an integer read back as the float nearest it),
    booleans apart from numbers, lists item by item."""
    if isinstance(written, bool) or isinstance(read, bool):
        return read is written
    if isinstance(written, int | float) and isinstance(read, int | float):
        return read == written or (isinstance(read, float) and read == float(written))
    if isinstance(written, list) and isinstance(read, list | tuple):
        return len(read) == len(written) and all(map(_equal, read, written))
    return read == written


def _within(read: dict, written: dict, where: str = "config") -> str | None:
    """The first field the file wrote that is read back otherwise (defaults fill the
    others), or None."""
    for k, v in written.items():
        if isinstance(v, dict):
            if not isinstance(read.get(k), dict):
                return f"{where}.{k}"
            wrong = _within(read[k], v, f"{where}.{k}")
            if wrong:
                return wrong
        elif not (_equal(read.get(k), v) or (v is None and read.get(k) == _none_means(where, k))):
            return f"{where}.{k}: wrote {v!r:.40}, read {read.get(k)!r:.40}"
    return None


def _none_means(where: str, name: str):
    """The value a configuration constructed with ``name=None`` holds (a field whose None
    stands for a default, e.g. ``max_condition``: 1e7 for float32), or a sentinel."""
    cls = {"config": EANT2Config, "config.exploit": ExploitConfig}.get(where)
    try:
        return cls(**{name: None}).to_dict()[name]
    except (TypeError, ValueError, KeyError):
        return _NOTHING


_NOTHING = object()


def check(d: Path, m: dict | None, marker: Marker) -> str:
    out = mf.read_manifest(d)
    if m is None:
        return "silent_wrong"  # a file that is no JSON object was accepted
    with contextlib.chdir(d):
        sys.path.insert(0, str(d))
        try:
            task = mf.resume_task(out["task_meta"], str(d / mf.MANIFEST))
        finally:
            sys.path.remove(str(d))
    spec = tasks.spec_of(task)
    wrong = _within(out["config"].to_dict(), m["config"])
    if not _same(out, m) or spec != m["task_meta"] or wrong:
        diff = {k: (m[k], out[k]) for k in m if k != "config" and k in out and out[k] != m[k]}
        return "silent_wrong", f"read {str(diff)[:200]}; {wrong}; task {spec}"
    return "accepted"


def run(rng: np.random.Generator, n: int, tmp: Path) -> Tally:
    """``n`` mutated manifests, each in a fresh directory under ``tmp``."""
    tally, marker = Tally("reproduce.json"), Marker(tmp)
    mf.check_manifest(base(), "base")  # the base is valid
    outside = tmp / "outside-manifest.json"
    for i in range(n):
        d = tmp / f"manifest{i}"
        d.mkdir()
        hostile = hostile_tasks(marker, d)
        kind, m = mutate(rng, d, outside, hostile)
        verdict, detail = classify(lambda: check(d, m, marker), marker)  # noqa: B023
        tally.add(kind, verdict, detail, case=i)
        shutil.rmtree(d, ignore_errors=True)
    return tally
