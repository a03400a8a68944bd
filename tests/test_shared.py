"""tests/shared.py: a session's result computed once, read by every later caller."""

import multiprocessing

import pytest
from shared import once


def _count(folder, name):
    import os

    os.environ["EANT2_TEST_SHARED_DIR"] = str(folder)
    with open(folder / "calls", "a") as f:
        return once(name, lambda: (f.write("x"), f.flush(), {"value": [1.5, None]})[2])


def test_computed_once_across_processes_and_failures_store_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("EANT2_TEST_SHARED_DIR", str(tmp_path))
    with pytest.raises(ZeroDivisionError):
        once("r", lambda: 1 / 0)
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        got = pool.starmap(_count, [(tmp_path, "r")] * 3)
    assert got == [{"value": [1.5, None]}] * 3
    assert (tmp_path / "calls").read_text() == "x"  # one computation for three callers
    assert once("r", lambda: pytest.fail("computed again")) == {"value": [1.5, None]}
    with pytest.raises(TypeError):  # a value JSON cannot hold is an error, not a stored value
        once("s", lambda: {1, 2})
    assert not (tmp_path / "s.json").exists()
