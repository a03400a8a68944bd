"""Program-store entries (`eant2_jax.programs.store`): N small programs are stored by one
process, each entry is mutated, and a fresh process looks each program up and runs it
(`bench.fuzz.store_child`), as the next ``eant2 run`` on that cache would.

Mutations: bit flips, truncation, appended bytes, an entry of another program copied in
(another key's), a manifest field replaced, a pickle that creates the marker when
unpickled, a link to an outside file or another entry, a FIFO, a folder, an empty file, a
file other users may write; and the same damage *forged* as an attacker would forge it
(the manifest's size, SHA-256 and key recomputed for the new bytes: checksums detect
accidents, they do not authenticate). The store is data: every case must end in
``accepted`` (the program's result equals the traced one's: the entry was used intact or
ignored and traced again); a crash or a hang of the reading process is a ``traceback``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import selectors
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench.fuzz.common import Marker, Tally

KINDS = ("flip", "flip_forged", "truncate", "truncate_forged", "append", "foreign",
         "foreign_forged", "field", "pickle", "pickle_forged", "symlink_outside",
         "symlink_entry", "fifo", "dir", "empty", "writable")  # fmt: skip
RANDOM_VALUES = [None, True, 0, -1, 2**63, 1.5, "", "x", [], {}, [[[0]], "float32"]]


class _Hostile:
    """Unpickled, it creates the marker."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _split(data: bytes) -> tuple[dict | None, bytes]:
    head, sep, payload = data.partition(b"\n")
    try:
        manifest = json.loads(head)
    except ValueError:
        return None, data
    return (manifest, payload) if sep and isinstance(manifest, dict) else (None, data)


def _forge(manifest: dict | None, payload: bytes, key: str | None = None) -> bytes:
    """An entry whose manifest vouches for ``payload`` (size, SHA-256, and ``key``)."""
    if manifest is None:
        return payload
    manifest = {**manifest, "bytes": len(payload), "sha256": hashlib.sha256(payload).hexdigest()}
    if key is not None:
        manifest["key"] = key
    return json.dumps(manifest, sort_keys=True).encode() + b"\n" + payload


def mutate(rng, p: Path, others: list[Path], outside: Path, marker: Marker) -> str:
    kind = KINDS[rng.integers(len(KINDS))]
    data = p.read_bytes()
    manifest, payload = _split(data)
    forged = kind.endswith("_forged")
    if kind.startswith("flip"):
        body = bytearray(payload if forged else data)
        for _ in range(rng.integers(1, 4)):
            body[rng.integers(len(body))] ^= 1 << rng.integers(8)
        data = _forge(manifest, bytes(body)) if forged else bytes(body)
    elif kind.startswith("truncate"):
        body = payload if forged else data
        body = body[: rng.integers(len(body))]
        data = _forge(manifest, body) if forged else body
    elif kind == "append":
        data += [b"\x00", b"\n{}", b"junk" * 100][rng.integers(3)]
    elif kind.startswith("foreign"):
        other = others[rng.integers(len(others))].read_bytes()
        if forged:
            m2, p2 = _split(other)
            other = _forge(m2, p2, key=manifest.get("key") if manifest else None)
        data = other
    elif kind == "field" and manifest is not None:
        keys = sorted(manifest)
        manifest[keys[rng.integers(len(keys))]] = RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
        data = json.dumps(manifest).encode() + b"\n" + payload
    elif kind.startswith("pickle"):
        bomb = pickle.dumps(_Hostile(str(marker.path)))
        data = _forge(manifest, bomb) if forged else bomb
    if kind in ("symlink_outside", "symlink_entry"):
        p.unlink()
        p.symlink_to(outside if kind == "symlink_outside" else others[0])
    elif kind in ("fifo", "dir"):
        p.unlink()
        os.mkfifo(p) if kind == "fifo" else p.mkdir()
    elif kind == "empty":
        p.write_bytes(b"")
    else:
        p.write_bytes(data)
        if kind == "writable":
            p.chmod(0o666)
    return kind


def _read(folder: Path, marker: Marker, first: int, last: int, wait: float) -> tuple[list, str]:
    """The child's results for cases first..last-1 (fewer if it crashed, or hung: no result
    for ``wait`` seconds), and why it stopped early."""
    cmd = [sys.executable, "-m", "bench.fuzz.store_child", "read", str(folder),
           str(marker.path), str(first), str(last)]  # fmt: skip
    rows, why = [], ""
    with (
        subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL) as child,
        selectors.DefaultSelector() as sel,
    ):
        sel.register(child.stdout, selectors.EVENT_READ)
        limit = wait + 60  # the first case also imports JAX
        while True:
            if not sel.select(timeout=limit):
                child.kill()
                why = f"hung (no result for {limit:.0f} s)"
                break
            line = child.stdout.readline()
            if not line:
                break
            if line.startswith(b"{"):
                rows.append(json.loads(line))
            limit = wait
    rc = child.returncode
    return rows, why or (f"exit status {rc}" if rc else "")


def run(rng: np.random.Generator, n: int, tmp: Path, wait: float = 30.0) -> Tally:
    """``n`` mutated entries, one program each; a case without a result for ``wait``
    seconds hung."""
    tally, marker = Tally("program store"), Marker(tmp)
    cache = tmp / "store-cache"
    cache.mkdir(mode=0o700)
    folder = cache / "eant2-programs"
    cmd = [sys.executable, "-m", "bench.fuzz.store_child", "write", str(folder), str(n)]
    made = json.loads(subprocess.run(cmd, capture_output=True, check=True).stdout)
    entries = {int(i): folder / names[0] for i, names in made.items() if names}
    spare = tmp / "store-spare"  # intact copies, the "another program" of foreign cases
    shutil.copytree(folder, spare)
    others = sorted(spare.iterdir())
    outside = tmp / "outside-store.bin"
    outside_bytes = b"precious data outside the store\n" * 100
    outside.write_bytes(outside_bytes)
    kinds = {i: mutate(rng, p, others, outside, marker) for i, p in entries.items()}
    first = 0
    while first < n:
        rows, why = _read(folder, marker, first, n, wait)
        for row in rows:
            i = row["case"]
            verdict = row["class"]
            if outside.read_bytes() != outside_bytes:
                verdict = "lost"
                outside.write_bytes(outside_bytes)
            tally.add(kinds.get(i, "none"), verdict, row["detail"], case=i)
        first = (rows[-1]["case"] + 1) if rows else first
        if first < n and why:  # the case it was on crashed or hung the process
            tally.add(kinds.get(first, "none"), "traceback", f"reader {why}", case=first)
            first += 1
    return tally
