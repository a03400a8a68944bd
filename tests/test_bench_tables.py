"""The pole and servo suites' tables (bench/pole_tables.py, bench/servo_tables.py) render the
committed results as their markdown files show them: the tables a rerun of ``--render``
writes, from data files that run no code (plain JSON)."""

import json
from pathlib import Path

import pytest

from bench import pole_tables, servo_tables

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"


@pytest.mark.parametrize(
    ("render", "name"),
    [
        (servo_tables.render, "servo-gpu"),
        (pole_tables.render, "pole-gpu-h100"),
        (pole_tables.render, "pole-cpu"),
        (pole_tables.render, "pole-protocol-gpu-h200"),
    ],
)
def test_committed_results_render_as_their_markdown(render, name):
    payload = json.loads((RESULTS / f"{name}.json").read_text())
    tables = render(payload)
    assert "| --- |" in tables
    assert tables in (RESULTS / f"{name}.md").read_text()
