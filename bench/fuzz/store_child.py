"""The program-store fuzz's child process (`bench.fuzz.store`): ``write FOLDER N`` stores
N small programs (one key each: arguments of N shapes) and prints which entry file each
made; ``read FOLDER MARKER FIRST LAST`` looks programs FIRST..LAST-1 up in the (mutated)
store once each, as a new process would, runs them, and prints one JSON line per case.
A fresh process, because a process keeps the programs it has read."""

from __future__ import annotations

import json
import sys
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from eant2_jax import tasks
from eant2_jax.programs import store


@jax.jit
def program(task, x):
    """A small program of a task and an array (what the store keys, as the engine's)."""
    return jnp.cumsum(jnp.sin(x) * 3.0) + task.targets.sum()


def _args(i: int):
    return tasks.make("xor"), jnp.linspace(-2.0, 2.0, i + 1, dtype=jnp.float32)


def write(folder: Path, n: int) -> None:
    made = {}
    for i in range(n):
        before = set(folder.glob("*")) if folder.exists() else set()
        args = _args(i)
        store.lookup(program, args, {}, task=args[0])
        made[i] = sorted(p.name for p in set(folder.glob("*")) - before if p.is_file())
    print(json.dumps(made), flush=True)


def read(folder: Path, marker: Path, first: int, last: int) -> None:
    for i in range(first, last):
        args = _args(i)
        try:
            call = store.lookup(program, args, {}, task=args[0])
            want = np.asarray(program(*args))
            got = want if call is None else np.asarray(call(*args))
            same = got.shape == want.shape and np.array_equal(got, want)
            verdict, detail = ("accepted", "") if same else ("silent_wrong", "another result")
        except Exception:  # noqa: BLE001 - a bug, recorded
            verdict, detail = "traceback", traceback.format_exc(limit=4)[-400:]
        if marker.exists():
            marker.unlink()
            verdict = "executed"
        print(json.dumps({"case": i, "class": verdict, "detail": detail}), flush=True)


if __name__ == "__main__":
    folder = Path(sys.argv[2])
    jax.config.update("jax_compilation_cache_dir", str(folder.parent))
    if sys.argv[1] == "write":
        write(folder, int(sys.argv[3]))
    else:
        read(folder, Path(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]))
