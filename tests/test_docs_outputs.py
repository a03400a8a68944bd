"""The printed outputs in the docs are what the code prints today (see tests/docs_outputs.py;
docs/genome.md and docs/tasks-custom.md are checked by their own tests)."""

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


@pytest.mark.slow
@pytest.mark.parametrize("page", ["quickstart.md"])
def test_printed_outputs_match_the_code(page):
    wrong = check(ROOT / "docs" / page)
    assert not wrong, (
        "\n\n".join(f"--- shown\n{ex.shown}--- printed now\n{got}" for ex, got in wrong)
        + "\n(regenerate: python tests/docs_outputs.py docs/"
        + page
        + ")"
    )
