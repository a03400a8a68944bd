"""Genome files' headers: mutated, then read as ``eant2 show`` and `eant2_jax.load` read
them (`eant2_jax.genomefile.GenomeFile.read`), loaded as a network and exported as
standalone JAX source, which ``to_jax`` executes.

Mutations of the header line: a field replaced by a value of a random type; the task
string replaced by hostile text (triple quotes closing the source's docstring around code
that creates the marker, line separators such as U+2028 followed by genes, control
characters, a very long name); the options nested deep; byte flips and truncation of the
header; another header line; non-UTF-8 bytes. Accepted means the genome and activations
read are the file's, the source is made and ``to_jax`` runs nothing else (a sample of them
is also evaluated and compared with the loaded network).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench.fuzz.common import Marker, Tally, classify
from eant2_jax import Genome, load
from eant2_jax.genomefile import HEADER, GenomeFile

GENOME = "N0/4*1.3 N1/3*-2.1 I0*0.8 I1*-0.7 B*0.2 I0*1.1 I1*0.9 B*-0.5"
BASE = {"format": 1, "hidden": "sigmoid", "output": "identity", "n_inputs": 2,
        "n_outputs": 1, "task": "xor", "task_options": {"hidden": "sigmoid"}}  # fmt: skip
RANDOM_VALUES = [None, True, False, 0, -1, 1, 2, 3, 2**31, 2**63, 10**30, 1.5, -0.0, "", "x",
                 "tanh", "sigmoid", "xor", [], [0], {}, {"a": 1}, [[[]]]]  # fmt: skip
KINDS = ("field", "field", "task", "task", "deep", "flip", "truncate", "second", "bytes")


def hostile_names(marker: Marker) -> list[str]:
    """Task strings that run code or change the genome if pasted into source or split as
    lines: each would create the marker."""
    m = repr(str(marker.path))
    code = f"open({m}, 'w').close()"
    return [
        f'xor"""\n{code}\n"""',
        f"xor'''\n{code}\n'''",
        f'xor""" + {code} + """',
        f'xor"""; {code}; x = """',
        f"xor\u2028{code}",
        f"xor\\\n{code}",
        "xor\u2028N0/1*1 I0*5",
        "xor\u2029N0/1*1 I0*5",
        "xor\x85N0/1*1 I0*5",
        "xor\rN0/1*1 I0*5",
        "xor\x00",
        "xor\x1b[2J",
        "x" * 100_000,
        "a:b.c-d_e",
        "__import__('os').system('touch " + str(marker.path) + "')",
    ]


def mutate(rng, names: list[str]) -> tuple[str, bytes]:
    """A genome file's bytes, its header mutated."""
    kind = KINDS[rng.integers(len(KINDS))]
    header = dict(BASE)
    if kind == "field":
        keys = [*BASE, "extra"]
        header[keys[rng.integers(len(keys))]] = RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
    elif kind == "task":
        header["task"] = names[rng.integers(len(names))]
    elif kind == "deep":
        depth = int(rng.choice([10, 100, 1000, 100_000]))
        header["task_options"] = {"x": "DEEP"}
    line = HEADER + json.dumps(header, ensure_ascii=bool(rng.integers(2)))
    if kind == "deep":  # written as text: json.dumps itself recurses
        line = line.replace('"DEEP"', "[" * depth + "1" + "]" * depth)
    data = bytearray(line.encode("utf-8", "surrogatepass"))
    if kind == "flip":
        for _ in range(rng.integers(1, 4)):
            data[rng.integers(len(data))] ^= 1 << rng.integers(8)
    elif kind == "truncate":
        data = data[: rng.integers(len(data))]
    elif kind == "second":
        data += b"\n" + data
    elif kind == "bytes":
        data[rng.integers(len(data))] = int(rng.choice([0x80, 0xC3, 0xFF, 0xE2]))
    return kind, bytes(data) + b"\n" + GENOME.encode() + b"\n"


def _written(data: bytes) -> dict | None:
    """The header the file's first line holds, as JSON reads it (None if it does not)."""
    line = data.split(b"\n", 1)[0]
    try:
        header = json.loads(line.decode("utf-8")[len(HEADER) :])
    except (ValueError, RecursionError):
        return None
    return header if line.startswith(HEADER.encode()) and isinstance(header, dict) else None


def check(path: Path, data: bytes, sample: bool) -> str | tuple[str, str]:
    spec = GenomeFile.read(path)
    if str(spec.genome) != str(Genome.parse(GENOME)):
        return "silent_wrong", f"read genome {str(spec.genome)[:100]!r}"
    written = _written(data)
    if spec.has_header and (
        written is None
        or (spec.hidden, spec.output) != (written.get("hidden"), written.get("output"))
    ):
        return "silent_wrong", f"read activations {spec.hidden!r}, {spec.output!r}"
    net = load(path)
    net.to_jax_source()
    fn = net.to_jax()
    if sample:  # the exported function computes what the loaded network does
        xs = np.linspace(-1, 1, 2 * net.n_inputs, dtype=np.float32).reshape(1, 2, net.n_inputs)
        if not np.allclose(np.asarray(fn(xs)), np.asarray(net(xs)), rtol=1e-5, atol=1e-6):
            return "silent_wrong", "to_jax computes another network"
    return "accepted"


def run(rng: np.random.Generator, n: int, tmp: Path) -> Tally:
    """``n`` genome files with mutated headers."""
    tally, marker = Tally("genome headers"), Marker(tmp)
    names = hostile_names(marker)
    path = tmp / "case.genome"
    accepted = 0
    for i in range(n):
        kind, data = mutate(rng, names)
        path.write_bytes(data)
        verdict, detail = classify(lambda: check(path, data, accepted % 25 == 0), marker)  # noqa: B023
        accepted += verdict == "accepted"
        tally.add(kind, verdict, detail, case=i)
    return tally
