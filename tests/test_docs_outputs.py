"""The printed outputs in the docs are what the code prints today (see tests/docs_outputs.py;
docs/genome.md and docs/tasks-custom.md are checked by their own tests)."""

import pytest
from docs_outputs import ROOT, check, examples, mask


def test_examples_are_found_and_masked():
    page = "```python\nprint(1)\n```\n\n```text\n1\n```\n\n```console\n$ echo 2\n2\n```\n"
    found = examples(page)
    assert [(e.kind, e.shown) for e in found] == [("python", "1\n"), ("console", "$ echo 2\n2\n")]
    assert mask("5,004 evals, 539/s | 9.3 s") == "5,004 evals, N/s | T s"
    assert mask('{"wall_s": 9.24, "best_cost": 0.5}') == '{"wall_s": T, "best_cost": 0.5}'


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
