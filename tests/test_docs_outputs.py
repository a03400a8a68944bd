"""The printed outputs in the docs are what the code prints today (see tests/docs_outputs.py;
docs/genome.md and docs/tasks-custom.md are checked by their own tests)."""

import os

import pytest
from docs_outputs import ROOT, check, examples, loose, mask


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
    # a comma after a number is text, one inside it is not
    assert loose("best cost 0, size 6") == loose("best cost 8.88178e-16, size 6")
    assert loose("best cost 0, size 6") != loose("best cost 0 size 6")


@pytest.mark.slow
@pytest.mark.parametrize("page", ["quickstart.md"])
def test_printed_outputs_match_the_code(page, monkeypatch):
    # The page's examples run as `check` runs them (tests/docs_outputs.py: in page order, in
    # one scratch folder, each console command in its own process, compared by `same`), with
    # ``one_process``: each run of consecutive Python examples shares ONE fresh process
    # (`docs_outputs.run_python`): the import and the programs an earlier example compiled
    # are paid once. Each example still runs alone, as its own script (its own globals,
    # `__main__`), and prints what it prints. That process runs with the settings the page's
    # `eant2` commands use, as the page advises ("Compile once, across processes":
    # `eant2_jax.enable_compilation_cache()`, EANT2_CACHE_DIR), and with their XLA flags, so
    # that its `eant2_jax.run` of the `eant2 run` above reads that run's programs instead of
    # compiling them again (and its `optimize`, the programs of `eant2 demo`).
    # What the examples print does not depend on it.
    if os.environ.get("EANT2_CACHE_DIR"):
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", os.environ["EANT2_CACHE_DIR"])
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
        monkeypatch.setenv("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")
    found = examples((ROOT / "docs" / page).read_text())
    assert sum(e.kind == "python" for e in found) >= 2  # the shared process is exercised
    wrong = check(ROOT / "docs" / page, one_process=True)
    assert not wrong, (
        "\n\n".join(f"--- shown\n{ex.shown}--- printed now\n{got}" for ex, got in wrong)
        + "\n(regenerate: python tests/docs_outputs.py docs/"
        + page
        + ")"
    )
