"""Fuzz of what eant2 reads (issues 16 and 40): run directories, genome texts, reproduction
manifests, genome headers, program-store entries and environment task options.

One small real run directory is made once (``eant2 run xor --generations 2 --population 2``
through the Python API). Each case copies it and applies one random mutation drawn from a
seeded generator (byte flips, truncations, appended garbage, JSON fields replaced by values
of random types, symlinks to an outside file, swapped, deleted or non-regular files, random
genome texts in ``best.genome``), then checks it through the code paths of ``eant2
resume`` and ``eant2 report`` (:func:`eant2_jax.loop.validate`, the report's
``load_runs``), in-process. Genome-text cases mutate a genome's text and parse it as ``eant2
show`` does (then its statistics and its compiled layout). Every case is classified:

* ``error``: a clean one-line error (a ValueError, ``eant2: error: ...`` at the CLI);
* ``accepted``: accepted, and what was read equals the committed run exactly;
* ``traceback``: any other exception (a bug);
* ``silent_wrong``: accepted with records or state that differ from the committed run (a bug);
* ``lost``: a file outside the directory changed, or the committed bytes changed (a bug).

A sample of accepted directories is really resumed for one more generation and compared
with the uninterrupted run of as many generations.

Run directories also get hostile tasks: ``config.json`` naming ``os:system`` with a shell
command, a task file or module shipped in the directory (``task.py:make_task``, resolved
from the directory as ``cd DIR; eant2 resume .`` would), with the checkpoint's checksum of
``config.json`` recomputed as an attacker would; each is resumed with no task given
(`eant2_jax.resume`), which must refuse it without running anything. ``json_field_forged``
edits ``config.json`` with its checksum recomputed too, so that the edit reaches the
checks behind the checksum. A sixth class, ``executed``, counts cases after which the
marker file every hostile payload creates exists.

The other targets are modules of `bench.fuzz` (manifests, headers, store, options), each
with its own mutations and case count (``--manifests``, ``--headers``, ``--store``,
``--options``; 0 skips one).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import jax
import numpy as np

import eant2_jax
from bench import harness
from bench.common import Column, environment, markdown_table
from bench.fuzz import headers, manifests, options, store
from bench.fuzz.common import CLASSES, Marker, classify, hostile_tasks, json_paths, set_path
from eant2_jax import EANT2Config, ExploitConfig, Genome, tasks
from eant2_jax.rundir import BEST, CHECKPOINT, CONFIG, GENERATIONS, PRUNING

FILES = (CONFIG, GENERATIONS, PRUNING, BEST, CHECKPOINT)
CONFIG_ = EANT2Config(population=2, exploit=ExploitConfig(max_iters=40, pruner="covariance"))
GENERATIONS_ = 2
META = {"task": "xor", "task_options": {}, "seed": 0}
RANDOM_VALUES = [None, True, False, 0, -1, 1, 2, 2**40, 1.5, -0.0, 1e308, "", "x", "inf",
                 "nan", [], [0], [0, 0], {}, {"a": 1}, [[[]]], 10**30]  # fmt: skip


def _options(p: argparse.ArgumentParser) -> None:
    helps = {
        "cases": "corrupted run directories",
        "genomes": "corrupted genome texts",
        "resumes": "accepted cases really resumed",
        "manifests": "mutated reproduce.json",
        "headers": "mutated genome-file headers",
        "store": "mutated program-store entries",
        "options": "random task option sets",
    }
    for name, text in helps.items():
        p.add_argument(f"--{name}", type=int, default=DEFAULTS[name], help=text)
    harness.run_options(p, seed=0, helps={"seed": "seed of the mutations' PRNG key"})


DEFAULTS = {"cases": 10_000, "genomes": 5_000, "resumes": 3, "manifests": 2_000,
            "headers": 2_000, "store": 200, "options": 1_000}  # fmt: skip
# --quick: about 560 cases, most of them of the cheap in-process targets; each target and
# each task family of the options still drawn (tests/test_bench_fuzz.py runs it once).
QUICK = {"cases": 200, "genomes": 200, "resumes": 1, "manifests": 100, "headers": 50,
         "store": 16, "options": 20}  # fmt: skip


def _prepare(args: argparse.Namespace) -> None:
    """--quick sizes for the counts left at their defaults (``--quick --store 0`` skips the
    store)."""
    if args.quick:
        for name, n in QUICK.items():
            if getattr(args, name) == DEFAULTS[name]:
                setattr(args, name, n)


def _records(d: Path) -> tuple[list, list, dict]:
    v = eant2_jax.loop.validate(str(d), tasks.make("xor"))
    strip = [
        {k: x for k, x in r.to_json().items() if k not in eant2_jax.loop.RUN_DEPENDENT}
        for r in v.records
    ]
    state = None if v.state is None else v.state.to_json()
    return strip, [p.to_json() for p in v.pruning], state


# ------------------------------------------------------------------------------ mutations


def mutate(rng: np.random.Generator, d: Path, outside: Path) -> str:
    """Apply one random mutation to run directory ``d``; returns its name."""
    kind = rng.choice(
        [
            "flip",
            "truncate",
            "append",
            "json_field",
            "json_line_field",
            "symlink",
            "swap",
            "delete",
            "fifo",
            "dir",
            "genome",
            "offset",
            "json_field_forged",
        ]  # fmt: skip
    )
    name = FILES[rng.integers(len(FILES))]
    p = d / name
    if kind == "flip" and p.stat().st_size:
        data = bytearray(p.read_bytes())
        for _ in range(rng.integers(1, 4)):
            i = rng.integers(len(data))
            data[i] ^= 1 << rng.integers(8)
        p.write_bytes(bytes(data))
    elif kind == "truncate":
        data = p.read_bytes()
        p.write_bytes(data[: rng.integers(len(data) + 1)])
    elif kind == "append":
        junk = [b"\n", b"{}\n", b'{"generation": 3}\n', b"\xff\xfe", b"[[[[", b"NaN\n"]
        with open(p, "ab") as f:
            f.write(junk[rng.integers(len(junk))])
    elif kind in ("json_field", "offset") and name in (CONFIG, CHECKPOINT):
        obj = json.loads(p.read_text())
        paths = list(json_paths(obj))
        if kind == "offset" and name == CHECKPOINT:
            path = ("offsets", [GENERATIONS, PRUNING][rng.integers(2)])
            value = int(obj["offsets"][path[1]]) + int(rng.integers(-300, 300))
        else:
            path = paths[rng.integers(len(paths))]
            value = RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
        obj = set_path(obj, path, value)
        p.write_text(json.dumps(obj))
    elif kind == "json_line_field" and name in (GENERATIONS, PRUNING) and p.stat().st_size:
        lines = p.read_text().splitlines()
        i = rng.integers(len(lines))
        obj = json.loads(lines[i])
        paths = list(json_paths(obj))
        obj = set_path(
            obj, paths[rng.integers(len(paths))], RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
        )
        lines[i] = json.dumps(obj)
        p.write_text("\n".join(lines) + "\n")
    elif kind == "symlink":
        p.unlink()
        p.symlink_to(outside)
    elif kind == "swap":
        other = d / FILES[rng.integers(len(FILES))]
        tmp = d / "swap.tmp"
        os.replace(p, tmp)
        os.replace(other, p) if other != p else None
        os.replace(tmp, other)
    elif kind == "delete":
        p.unlink()
    elif kind == "fifo":
        p.unlink()
        os.mkfifo(p)
    elif kind == "dir":
        p.unlink()
        p.mkdir()
    elif kind == "genome":
        (d / BEST).write_text(mutate_text(rng, (d / BEST).read_text()))
    elif kind == "json_field_forged":
        obj = json.loads((d / CONFIG).read_text())
        paths = list(json_paths(obj))[1:]
        value = RANDOM_VALUES[rng.integers(len(RANDOM_VALUES))]
        forge_config(d, set_path(obj, paths[rng.integers(len(paths))], value))
        name = CONFIG
    else:
        return "none"
    return f"{kind}:{name}"


def forge_config(d: Path, config: dict) -> None:
    """Write ``config.json`` and recompute its checksum in the checkpoint, as an attacker
    who edits a directory would (the checksums detect accidents, they do not authenticate)."""
    data = json.dumps(config).encode()
    (d / CONFIG).write_bytes(data)
    ckpt = json.loads((d / CHECKPOINT).read_text())
    ckpt["sha256"][CONFIG] = hashlib.sha256(data).hexdigest()
    (d / CHECKPOINT).write_text(json.dumps(ckpt) + "\n")


def check_hostile(d: Path, spec: str, task_options: dict) -> str | tuple[str, str]:
    """Resume a directory whose config.json names ``spec`` with no task given, from inside
    it (its folder on sys.path, as ``cd DIR; python -m ...`` has): it must be refused."""
    config = json.loads((d / CONFIG).read_text())
    forge_config(d, {**config, "task": spec, "task_options": task_options})
    with contextlib.chdir(d):
        sys.path.insert(0, str(d))
        try:
            eant2_jax.resume(str(d), generations=GENERATIONS_ + 1)
        finally:
            sys.path.remove(str(d))
    return "silent_wrong", f"resumed a directory naming {spec!r}"


def mutate_text(rng: np.random.Generator, text: str) -> str:
    """A random corruption of a genome's text."""
    pieces = ["N", "I", "B", "F", "R", "/", "*", " ", "0", "9", "-", ".", "e", "\u0663",
              "99999999999", "nan", "inf", "1e999", "N0/1*1", "I20000*1", "\x00", "\n"]  # fmt: skip
    chars = list(text)
    for _ in range(rng.integers(1, 4)):
        op = rng.integers(3)
        i = rng.integers(len(chars) + 1)
        if op == 0 and chars:
            del chars[min(i, len(chars) - 1)]
        elif op == 1:
            chars.insert(i, pieces[rng.integers(len(pieces))])
        else:
            tokens = "".join(chars).split()
            if tokens:
                tokens.insert(rng.integers(len(tokens) + 1), tokens[rng.integers(len(tokens))])
            chars = list(" ".join(tokens))
    return "".join(chars)


# ------------------------------------------------------------------------------ checking
def check_dir(d: Path, reference, outside: Path, outside_bytes: bytes) -> tuple[str, str]:
    from eant2_jax.app.report import load_runs

    try:
        got = _records(d)
        load_runs([d])  # the report's path
    except ValueError as e:  # RunDirError, GenomeError, the CLI's one line
        msg = str(e)
        verdict = "error" if "\n" not in msg and msg else "traceback"
    except Exception:
        return "traceback", traceback.format_exc(limit=3)[-300:]
    else:
        msg = ""
        verdict = "accepted" if json.dumps(got) == json.dumps(reference) else "silent_wrong"
    if outside.read_bytes() != outside_bytes:
        return "lost", "the outside file changed"
    return verdict, msg[:200]


def check_genome(text: str) -> tuple[str, str]:
    from eant2_jax.app.report import genome_stats
    from eant2_jax.compiler import compile_genomes

    try:
        g = Genome.parse(text)
        genome_stats(g)
        if g.n_inputs <= 4096:  # the compiled layout (host side); wider ones are refused
            compile_genomes([g], n_inputs=max(g.n_inputs, 1))
    except ValueError as e:
        return ("error" if "\n" not in str(e) else "traceback"), str(e)[:200]
    except Exception:
        return "traceback", traceback.format_exc(limit=3)[-300:]
    return "accepted", ""


def run(args: argparse.Namespace, save: harness.Save) -> dict[str, Any]:
    task = tasks.make("xor")
    t0 = time.perf_counter()
    rng = np.random.default_rng(
        np.asarray(jax.random.key_data(jax.random.key(args.seed)), np.uint32)
    )
    with tempfile.TemporaryDirectory(prefix="fuzz-rundir-") as tmp:
        tmp = Path(tmp)
        tmp.chmod(0o700)  # the program store refuses a folder others may write
        base = tmp / "base"
        eant2_jax.run(task, key=jax.random.key(0), config=CONFIG_, generations=GENERATIONS_,
                      out=str(base), meta=META)  # fmt: skip
        reference = _records(base)
        base_bytes = {n: (base / n).read_bytes() for n in FILES}
        outside = tmp / "outside.txt"
        outside_bytes = b"precious data outside the run directory\n" * 400
        outside.write_bytes(outside_bytes)
        counts = {c: 0 for c in CLASSES}
        by_kind: dict[str, dict[str, int]] = {}
        bugs, accepted_dirs = [], []
        for i in range(args.cases):
            d = tmp / f"case{i}"
            shutil.copytree(base, d, symlinks=True)
            kind = "none"
            while kind == "none":  # a mutation that does not apply to the file drawn: again
                kind = mutate(rng, d, outside)
            verdict, msg = check_dir(d, reference, outside, outside_bytes)
            counts[verdict] += 1
            by_kind.setdefault(kind.split(":")[0], {c: 0 for c in CLASSES})[verdict] += 1
            if verdict not in ("error", "accepted"):
                bugs.append({"case": i, "mutation": kind, "class": verdict, "detail": msg})
            if verdict == "accepted" and kind != "none" and len(accepted_dirs) < args.resumes:
                accepted_dirs.append(d)
            else:
                shutil.rmtree(d, ignore_errors=True)
            if i % 1000 == 999:
                harness.log(f"{i + 1} directories: {counts}")
        marker = Marker(tmp)
        for i, (spec, opts) in enumerate(hostile_tasks(marker, tmp)):  # each one, in turn
            for j in range(max(1, args.cases // 500)):
                d = tmp / f"hostile{i}-{j}"
                shutil.copytree(base, d, symlinks=True)
                hostile_tasks(marker, d)  # the task files, shipped in the directory
                verdict, msg = classify(lambda: check_hostile(d, spec, opts), marker)  # noqa: B023
                counts[verdict] += 1
                by_kind.setdefault("hostile", dict.fromkeys(CLASSES, 0))[verdict] += 1
                if verdict not in ("error", "accepted"):
                    bugs.append({"hostile": spec, "class": verdict, "detail": msg[:300]})
                shutil.rmtree(d, ignore_errors=True)
        genome_counts = {c: 0 for c in CLASSES}
        texts = [str(Genome.parse(r["best_genome"])) for r in reference[0]]
        for i in range(args.genomes):
            verdict, msg = check_genome(mutate_text(rng, texts[rng.integers(len(texts))]))
            genome_counts[verdict] += 1
            if verdict not in ("error", "accepted"):
                bugs.append({"genome_case": i, "class": verdict, "detail": msg})
        # Real resumes of accepted (mutated) directories: one more generation each, equal to
        # the uninterrupted run of GENERATIONS_ + 1 generations, committed bytes kept.
        full = eant2_jax.run(task, key=jax.random.key(0), config=CONFIG_,
                             generations=GENERATIONS_ + 1)  # fmt: skip
        want = [{k: x for k, x in r.to_json().items() if k not in eant2_jax.loop.RUN_DEPENDENT}
                for r in full.generations]  # fmt: skip
        resumed = []
        for d in accepted_dirs:
            res = eant2_jax.resume(str(d), task, generations=GENERATIONS_ + 1)
            got = [{k: x for k, x in r.to_json().items() if k not in eant2_jax.loop.RUN_DEPENDENT}
                   for r in res.generations]  # fmt: skip
            kept = all(
                (d / n).read_bytes().startswith(base_bytes[n]) for n in (GENERATIONS, PRUNING)
            )
            resumed.append({"dir": d.name, "equal_to_uninterrupted": got == want, "kept": kept})
            if got != want or not kept:
                bugs.append({"resume": d.name, "class": "silent_wrong" if kept else "lost"})
        rows = [{"what": f"run directories ({k})", **v} for k, v in sorted(by_kind.items())]
        rows.append({"what": "run directories (all)", **counts})
        rows.append({"what": "genome texts", **genome_counts})
        n_bugs = len(bugs)
        targets = [(manifests, args.manifests), (headers, args.headers), (store, args.store),
                   (options, args.options)]  # fmt: skip
        for module, n in targets:
            if n:
                tally = module.run(rng, n, tmp)
                rows += tally.rows()
                bugs += tally.bugs
                n_bugs += tally.n_bugs
                harness.log(f"{rows[-1]['what']}: {rows[-1]}")
    totals = {c: sum(r[c] for r in rows if r["what"].endswith("(all)") or "(" not in r["what"])
              for c in CLASSES}  # fmt: skip
    rows.append({"what": "all targets", **totals})
    return {
        "environment": environment(),
        "config": harness.settings(args),
        "rows": rows,
        "resumed": resumed,
        "bugs": bugs[:100],
        "n_bugs": n_bugs,
        "seconds": time.perf_counter() - t0,
    }


COLUMNS = [Column("what", "cases"), *(Column(c, c) for c in CLASSES)]


def render(payload: dict) -> str:
    resumed = payload.get("resumed", [])
    ok = sum(r["equal_to_uninterrupted"] and r["kept"] for r in resumed)
    return (
        markdown_table(payload["rows"], COLUMNS)
        + f"\nResumed for real: {ok}/{len(resumed)} equal to the uninterrupted run with the "
        f"committed bytes kept. Bugs: {payload.get('n_bugs', 0)}. "
        f"Time: {payload.get('seconds', 0):.0f} s.\n"
    )


SUITE = harness.Suite(
    name="fuzz_rundir",
    title="Fuzz of what eant2 reads",
    description=__doc__,
    options=_options,
    run=run,
    render=render,
    prepare=_prepare,
)

main = SUITE.main
