"""Strings from data files reach the user escaped (issue 40 item 3): ``eant2 show`` prints a
genome header's task name and options on their lines, a newline, a terminal escape
sequence or a line separator in them written as an escape (the report's: tests/test_report.py)."""

from __future__ import annotations

from rundirs import run_main

from eant2_jax import Genome
from eant2_jax.genomefile import GenomeFile

HOSTILE = "xor\x1b[2J\nfake: line\u2028\r\x07"


def test_show_prints_header_strings_escaped_on_their_lines(tmp_path, capsys, monkeypatch):
    spec = GenomeFile(Genome.parse("N0/2*1 I0*0.5 I1*-0.5"), hidden="tanh", output="tanh",
                      task=HOSTILE, task_options={"a\nb": "\x1b]0;title\x07"})  # fmt: skip
    path = spec.write(tmp_path / "h.genome")
    rc, out, err = run_main(["show", path, "--out", tmp_path / "h.png"], capsys, monkeypatch)
    assert rc == 0, err
    assert all(ch.isprintable() for ch in out.replace("\n", "")), repr(out)
    (line,) = [x for x in out.splitlines() if x.strip().startswith("task:")]
    assert "xor\\u001b[2J\\nfake: line\\u2028\\r\\u0007" in line, line
    assert '{"a\\nb": "\\u001b]0;title\\u0007"}' in line, line
    assert "fake: line" not in out.replace(line, "")  # no line of the file's own
