"""Fuzz of genome files as data (issue 40): hostile headers and texts through the paths a
user's file takes (`GenomeFile.read`/`parse`, which `load` and `eant2 show` use, and
`export.to_jax_source`).

Every case ends in one of two classes: a one-line `GenomeFileError` naming the file, or a
file accepted whose genes are exactly those a viewer shows (lines broken at ``\\n`` only,
``#`` comments skipped), whose fields have their types, and which writes back to itself.
Anything else fails: another exception, a message of several lines, a network other than
the one shown. Generated source must hold no string but its docstring.

The fast lane runs the hypothesis profile's number of examples per property; the slow test
runs `FUZZ_CASES` more file texts (docs/reliability.md, "Genome files").
"""

from __future__ import annotations

import ast

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from strategies import LINE_BREAKS, genome_file_texts, genomes, hostile_strings

from eant2_jax import export
from eant2_jax.genome import Genome, GenomeError, parse_gene
from eant2_jax.genomefile import GenomeFile, GenomeFileError

FUZZ_CASES = 2000


def _shown_genome(text: str) -> Genome:
    """The genes a viewer shows: lines broken at \\n (a \\r before it is part of the end)."""
    lines = [line.removesuffix("\r") for line in text.split("\n")]
    tokens = [t for line in lines for t in line.split("#", 1)[0].split()]
    return Genome(parse_gene(t, i) for i, t in enumerate(tokens))


def check_file(text: str, data: bytes, tmp) -> str:
    """One fuzz case through parse and read; returns its class ("error" or "accepted")."""
    path = tmp / "case.genome"
    path.write_bytes(data)
    try:
        read = GenomeFile.read(path)
    except GenomeFileError as e:
        assert str(e).startswith(f"{path}") or f" {path}" in str(e), str(e)
        assert not any(c in str(e) for c in LINE_BREAKS), repr(str(e))
        read = None
    try:
        spec = GenomeFile.parse(text, source="f.genome")
    except GenomeFileError as e:
        assert str(e).startswith("f.genome: "), str(e)
        assert not any(c in str(e) for c in LINE_BREAKS), repr(str(e))
        assert read is None or data != text.encode()
        return "error"
    if data == text.encode():
        assert read == spec
    ends = text.replace("\r\n", "\n")
    assert not any(c in ends for c in LINE_BREAKS if c != "\n"), repr(text)
    assert spec.genome == _shown_genome(text) == Genome.parse(text)
    if spec.has_header:
        assert all(isinstance(a, str) and a.isidentifier() for a in (spec.hidden, spec.output))
        assert spec.task is None or isinstance(spec.task, str)
        assert spec.task_options is None or isinstance(spec.task_options, dict)
        n = spec.n_inputs
        assert n is None or (type(n) is int and n >= spec.genome.n_inputs)
    assert GenomeFile.parse(spec.to_text()) == spec
    return "accepted"


def _damaged(data: bytes, edit: tuple[int, int]) -> bytes:
    """The file's bytes with one byte replaced (position modulo the length), or as written."""
    at, byte = edit
    if byte < 0 or not data:
        return data
    at %= len(data)
    return data[:at] + bytes([byte]) + data[at + 1 :]


_EDITS = st.tuples(st.integers(0, 2**16), st.integers(-256, 255))


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@settings(suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(text=genome_file_texts(), edit=_EDITS)
@pytest.mark.slow
def test_genome_file_texts(tmp, text, edit):
    check_file(text, _damaged(text.encode(), edit), tmp)


@pytest.mark.slow
def test_genome_file_fuzz(tmp):
    """FUZZ_CASES file texts; both classes must occur."""
    seen = {"error": 0, "accepted": 0}

    @settings(
        max_examples=FUZZ_CASES,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        database=None,
    )
    @given(text=genome_file_texts(), edit=_EDITS)
    def case(text, edit):
        seen[check_file(text, _damaged(text.encode(), edit), tmp)] += 1

    case()
    print(f"genome file fuzz: {seen}")
    assert sum(seen.values()) >= FUZZ_CASES and min(seen.values()) > FUZZ_CASES // 20, seen


@pytest.mark.slow
@settings(suppress_health_check=[HealthCheck.too_slow])
@given(
    g=genomes(n_inputs=2, max_neurons=3),
    task=st.none() | hostile_strings(),
    hidden=st.sampled_from(["tanh", "sigmoid", "identity"]),
)
def test_exported_source_carries_no_file_text(g, task, hidden):
    """Whatever the task string, the generated module's only string is its docstring and
    names a task only if it passes the whitelist; the module compiles."""
    spec = GenomeFile(g, hidden, "identity", 2, task, {"t": task})
    source = export.to_jax_source(spec)
    module = ast.parse(source)
    strings = [n.value for n in ast.walk(module) if isinstance(n, ast.Constant)]
    doc = ast.get_docstring(module, clean=False)
    assert [s for s in strings if isinstance(s, str)] == [doc]
    named = task is not None and _whitelisted(task)
    assert (f" on task {task}:" in doc) if named else (" on task" not in doc)
    compile(source, "<fuzz>", "exec")


def _whitelisted(task: str) -> bool:
    return 1 <= len(task) <= 64 and all(c.isascii() and (c.isalnum() or c in "_.:-") for c in task)


@given(st.lists(st.text(min_size=1, max_size=6), max_size=5).map(" ".join))
def test_genome_text_parse_is_one_line_or_a_genome(text):
    """Any text: a genome equal to the one shown, or one GenomeError line."""
    try:
        g = Genome.parse(text)
    except GenomeError as e:
        assert not any(c in str(e) for c in LINE_BREAKS), repr(str(e))
    else:
        assert g == _shown_genome(text)
