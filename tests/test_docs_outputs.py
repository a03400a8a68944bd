"""The printed outputs in the docs are what the code prints today (see tests/docs_outputs.py;
docs/genome.md and docs/tasks-custom.md are checked by their own tests)."""

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import docs_outputs
import pytest
from docs_outputs import ROOT, example_env, examples, loose, mask, run, same

# One fresh process for several Python examples: each is compiled and run as its own
# `__main__` script with fresh globals, its stdout captured alone; the outputs (or the
# first failure's traceback) come back as JSON on the last line of the process's stdout.
_DRIVER = """
import contextlib, io, json, sys, traceback
import eant2_jax
eant2_jax.enable_compilation_cache()
codes, outs = json.loads(sys.stdin.read()), []
real = sys.stdout
for i, code in enumerate(codes):
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            exec(compile(code, f"<example {i}>", "exec"), {"__name__": "__main__"})
    except BaseException:
        outs.append({"error": traceback.format_exc(), "code": code})
        break
    outs.append({"out": buf.getvalue()})
real.write("\\n" + json.dumps(outs) + "\\n")
"""


def _run_python(found: list, cwd: Path) -> list[str]:
    """What each of these Python examples prints, run one after another in one process."""
    proc = subprocess.run([sys.executable, "-c", _DRIVER], cwd=cwd, env=example_env(), timeout=600,
                          input=json.dumps([e.code for e in found]), capture_output=True,
                          text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    outs = json.loads(proc.stdout.splitlines()[-1])
    failed = [o for o in outs if "error" in o]
    assert not failed, f"example failed:\n{failed[0]['code']}\n{failed[0]['error'][-3000:]}"
    assert len(outs) == len(found)
    return [o["out"] for o in outs]


def test_examples_are_found_and_masked():
    page = "```python\nprint(1)\n```\n\n```text\n1\n```\n\n```console\n$ echo 2\n2\n```\n"
    found = examples(page)
    assert [(e.kind, e.shown) for e in found] == [("python", "1\n"), ("console", "$ echo 2\n2\n")]
    assert mask("5,004 evals, 539/s | 9.3 s") == "5,004 evals, N/s | T s"
    assert mask('{"wall_s": 9.24, "best_cost": 0.5}') == '{"wall_s": T, "best_cost": 0.5}'


def test_loose_masks_numbers_and_compiling_lines_only():
    """Another CPU's outputs: other numbers and other compile points, the same lines."""
    a = "gen 1/3 | best 0 | 20,868 evals, 9/s | 1.3 s\nN0/3*1.65 I0*-0.83\n"
    b = "gen 1/3 | best 0.25 | 20,886 evals, 7/s | 2.1 s\nN0/3*1.7619 I0*7.7e-05\n"
    compiling = "gen 2/3: compiling the exploitation program (6 structures, 12 genes)...\n"
    assert loose(a) == loose(b) == loose(compiling + b)
    assert loose(a) != loose(a.replace("best", "worst"))  # words still count
    assert loose(a) != loose(a + "N1/2*0.5\n")  # and lines
    assert loose("N0/3*1.65 I0*-0.83") != loose("N0/3*1.65 B*-0.83")  # and gene kinds


@pytest.mark.slow
@pytest.mark.parametrize("page", ["quickstart.md"])
def test_printed_outputs_match_the_code(page, monkeypatch):
    # The page's examples run as `check` runs them (tests/docs_outputs.py: in page order, in
    # one scratch folder, each console command in its own process, compared by `same`), but
    # each run of consecutive Python examples shares ONE fresh process (`_run_python`): the
    # import and the programs an earlier example compiled are paid once. Each example still
    # runs alone, as its own script (its own globals, `__main__`), and prints what it prints.
    # That process runs with the settings the page's `eant2` commands use, as the page
    # advises ("Compile once, across processes": `eant2_jax.enable_compilation_cache()`,
    # EANT2_CACHE_DIR), so that its `eant2_jax.run` of the `eant2 run` above reads that
    # run's programs instead of compiling them again. What the examples print does not
    # depend on it.
    if os.environ.get("EANT2_CACHE_DIR"):
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", os.environ["EANT2_CACHE_DIR"])
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    found = examples((ROOT / "docs" / page).read_text())
    assert sum(e.kind == "python" for e in found) >= 2  # the shared process is exercised
    wrong = []
    with tempfile.TemporaryDirectory() as tmp:
        i = 0
        while i < len(found):
            j = i + 1
            if found[i].kind == "python":
                while j < len(found) and found[j].kind == "python":
                    j += 1
                got = _run_python(found[i:j], Path(tmp))
            else:
                got = [run(found[i], Path(tmp))]
                if found[i] == docs_outputs.quickstart_demo() and not docs_outputs.demo_printed:
                    docs_outputs.demo_printed.append(got[0])  # as `check` hands it over
            wrong += [(ex, out) for ex, out in zip(found[i:j], got, strict=True)
                      if not same(out, ex.shown)]  # fmt: skip
            i = j
    assert not wrong, (
        "\n\n".join(f"--- shown\n{ex.shown}--- printed now\n{got}" for ex, got in wrong)
        + "\n(regenerate: python tests/docs_outputs.py docs/"
        + page
        + ")"
    )
