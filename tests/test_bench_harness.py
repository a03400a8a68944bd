"""The benchmark harness: common options, output files, and the no-overwrite rule."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench import harness
from bench.common import BenchInputError, Column, markdown_table

ROOT = Path(__file__).resolve().parents[1]


def _suite(calls: list) -> harness.Suite:
    """A suite that measures nothing: one row per ``--rows``, saved after each."""

    def options(p):
        p.add_argument("--rows", type=int, default=2)

    def run(args, save):
        calls.append(args)
        payload = {"device_kind": "test", "platform": "cpu", "config": harness.settings(args)}
        payload["rows"] = []
        for i in range(args.rows):
            payload["rows"].append({"i": i, "value": 0.5 * i})
            save(payload)
        return payload

    return harness.Suite(
        name="dummy",
        title="Dummy",
        description="A test suite.",
        options=options,
        run=run,
        render=lambda p: markdown_table(p["rows"], [Column("i", "i"), Column("value", "v")]),
        repeats=3,
        min_repeats=2,
    )


def test_run_writes_json_and_markdown_with_a_header(tmp_path, capsys):
    calls = []
    out = tmp_path / "dummy.json"
    payload = harness.main(_suite(calls), ["--out", str(out), "--rows", "3"])
    assert json.loads(out.read_text()) == payload
    assert payload["config"] == {"quick": False, "repeats": 3, "rows": 3}  # no --out, --force
    md = out.with_suffix(".md").read_text()
    assert md.startswith("Dummy on **test** (cpu)")
    assert md.count("\n| ") == 3 + 2
    assert capsys.readouterr().out.strip() == md.strip()


def test_existing_results_are_not_overwritten_without_force(tmp_path):
    calls = []
    out = tmp_path / "dummy.json"
    out.write_text('{"committed": true}\n')
    before = out.read_bytes()
    with pytest.raises(BenchInputError, match="exists; pass --force"):
        harness.main(_suite(calls), ["--out", str(out)])
    assert out.read_bytes() == before
    assert not out.with_suffix(".md").exists()
    assert calls == []  # refused before measuring anything
    # The markdown alone counts too.
    md = tmp_path / "other.md"
    md.write_text("committed\n")
    with pytest.raises(BenchInputError, match="other.md exists"):
        harness.main(_suite(calls), ["--out", str(tmp_path / "other.json")])
    assert md.read_text() == "committed\n" and not (tmp_path / "other.json").exists()
    # --force replaces both files.
    payload = harness.main(_suite(calls), ["--out", str(out), "--force"])
    assert json.loads(out.read_text()) == payload != {"committed": True}
    assert len(calls) == 1


def test_render_rewrites_only_the_markdown_and_needs_force_over_it(tmp_path):
    calls = []
    out = tmp_path / "dummy.json"
    harness.main(_suite(calls), ["--out", str(out)])
    data, md = out.read_bytes(), out.with_suffix(".md")
    md.write_text("old\n")
    with pytest.raises(BenchInputError, match="pass --force to rewrite"):
        harness.main(_suite(calls), ["--render", str(out)])
    assert md.read_text() == "old\n"
    harness.main(_suite(calls), ["--render", str(out), "--force"])
    assert md.read_text().startswith("Dummy on") and out.read_bytes() == data
    assert len(calls) == 1


def test_repeats_below_the_suite_minimum_are_refused():
    with pytest.raises(BenchInputError, match="at least 2"):
        harness.parse_args(_suite([]), ["--repeats", "1"])


@pytest.mark.slow
def test_command_line_refusal_is_one_line_and_exit_2(tmp_path):
    out = tmp_path / "scaling.json"
    out.write_text("{}\n")
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "scaling", "--quick", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "exists; pass --force" in lines[0], proc.stderr
    assert out.read_text() == "{}\n"


def test_run_options_add_the_named_shared_options_in_one_group():
    import argparse

    p = argparse.ArgumentParser()
    harness.run_options(p, task="servo", seed=3, first_seed=None, helps={"task": "what runs"})
    args = p.parse_args([])
    assert vars(args) == {"task": "servo", "seed": 3, "first_seed": None}
    args = p.parse_args(["--task", "xor", "--seed", "7", "--first-seed", "2"])
    assert (args.task, args.seed, args.first_seed) == ("xor", 7, 2)
    with pytest.raises(SystemExit):
        p.parse_args(["--population", "5"])  # not named: not added
    group = next(g for g in p._action_groups if g.title.startswith("run options"))
    helps = {a.dest: a.help for a in group._group_actions}
    assert helps["task"] == "what runs (default servo)"
    assert helps["first_seed"] == harness.RUN_OPTIONS["first_seed"][1]  # no default to name
    with pytest.raises(ValueError, match="not a shared run option: steps"):
        harness.run_options(argparse.ArgumentParser(), steps=3)


def test_suites_define_shared_options_only_through_run_options():
    """No suite's ``_options`` adds --task, --population, --generations, --seed, --seeds or
    --first-seed itself: each has one definition, in the harness."""
    import ast

    shared = {"--" + name.replace("_", "-") for name in harness.RUN_OPTIONS}
    found = []
    for path in sorted((ROOT / "bench").glob("bench_*.py")):
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if isinstance(fn, ast.FunctionDef) and fn.name == "_options":
                for call in ast.walk(fn):
                    if (
                        isinstance(call, ast.Call)
                        and getattr(call.func, "attr", None) == "add_argument"
                        and call.args
                        and getattr(call.args[0], "value", None) in shared
                    ):
                        found.append(f"{path.name}: {call.args[0].value}")
    assert not found, found


def test_device_tag_names_the_platform_and_the_model():
    from bench.common import device_tag

    assert device_tag("cpu", "cpu") == "cpu"
    assert device_tag("gpu", "NVIDIA H100 80GB HBM3") == "gpu-h100"
    assert device_tag("gpu", "NVIDIA H200") == "gpu-h200"
    assert device_tag("gpu", "NVIDIA GeForce RTX 4090") == "gpu-rtx4090"
    assert device_tag("gpu", "NVIDIA A100-SXM4-80GB") == "gpu-a100"


@pytest.mark.slow
def test_library_digest_names_the_code_wherever_it_was_copied(tmp_path):
    # A device gets the package as a plain copy, `kernels/` placed inside `eant2_jax/`, and no
    # git: its result files' `library_sha256` must equal this checkout's, and change with one
    # byte of the library.
    import shutil

    from bench.common import environment, library_digest

    here = library_digest()
    assert environment()["library_sha256"] == here and len(here) == 64
    copy = tmp_path / "pkg"
    ignore = shutil.ignore_patterns("__pycache__")
    for name in ("eant2_jax", "bench"):
        shutil.copytree(ROOT / name, copy / name, ignore=ignore)
    shutil.copytree(ROOT / "kernels", copy / "eant2_jax" / "kernels", ignore=ignore)
    probe = "import bench.common as c, eant2_jax; print(eant2_jax.__file__, c.library_digest())"

    def digest():
        out = subprocess.run(
            [sys.executable, "-c", probe],
            cwd=copy,
            capture_output=True,
            text=True,
            env={"PYTHONPATH": str(copy), "JAX_PLATFORMS": "cpu"},
        )
        assert out.returncode == 0, out.stderr[-2000:]
        where, value = out.stdout.split()
        assert where.startswith(str(copy))  # the copy was hashed, not the installed package
        return value

    assert digest() == here
    with open(copy / "eant2_jax" / "kernels" / "cmaes.py", "a") as f:
        f.write("\n")
    assert digest() != here
