"""The fuzz of what eant2 reads (``python -m bench fuzz_rundir --quick``): every target
(run directories with hostile tasks, genome texts, reproduction manifests, genome headers,
program-store entries, gymnax/brax/Playground task options) ends every case in a one-line
error or an exact acceptance: no traceback, no silent wrong result, nothing lost, no code
named by the data executed."""

from __future__ import annotations

import json

import pytest

BUGS = ("traceback", "silent_wrong", "lost", "executed")


def test_a_payload_that_runs_is_classed_executed(tmp_path):
    """The detector itself: building a hostile task directly (what no data may cause) runs
    it, and the case is classed ``executed`` whatever it raised afterwards."""
    from bench.fuzz.common import Marker, classify, hostile_tasks
    from eant2_jax import tasks

    marker = Marker(tmp_path)
    hostile = dict(hostile_tasks(marker, tmp_path))
    for spec in ("os:system", f"{tmp_path}/task.py:make_task"):
        verdict, _ = classify(lambda: tasks.make(spec, **hostile[spec]), marker)  # noqa: B023
        assert verdict == "executed", spec
        assert not marker.fired()  # cleared for the next case
    assert classify(lambda: tasks.make("xor", bogus=1), marker)[0] == "error"


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> dict:
    """One ``--quick`` run of every target (the program store included), read by the tests
    below: its JSON file holds the rows it returned."""
    from bench import bench_fuzz_rundir

    out = tmp_path_factory.mktemp("fuzz") / "fuzz.json"
    payload = bench_fuzz_rundir.main(["--quick", "--out", str(out)])
    assert json.loads(out.read_text())["rows"] == payload["rows"]
    return payload


@pytest.mark.slow
def test_quick_fuzz_finds_no_bug(quick):
    """Every target read some cases, each hostile task was refused, and no case of any
    target (the program store's too) is a bug."""
    rows = {r["what"]: r for r in quick["rows"]}
    for target in ("run directories", "reproduce.json", "genome headers", "task options"):
        assert rows[f"{target} (all)"]["error"] + rows[f"{target} (all)"]["accepted"] > 0
    assert rows["run directories (hostile)"]["error"] >= 9  # each hostile task refused
    assert rows["genome texts"]["error"] > 0
    for family in ("gymnax", "brax", "playground"):  # each family's options drawn
        row = rows[f"task options ({family})"]
        assert row["error"] + row["accepted"] > 0, family
    found = {c: rows["all targets"][c] for c in BUGS}
    assert found == dict.fromkeys(BUGS, 0), quick["bugs"][:5]
    assert sum(rows["all targets"][c] for c in ("error", "accepted")) >= 500


@pytest.mark.slow
def test_quick_store_fuzz_finds_no_bug(quick):
    """Program-store entries, each read by a fresh process (a crash or hang is a bug)."""
    rows = {r["what"]: r for r in quick["rows"]}
    assert rows["program store (all)"]["accepted"] > 0
    found = {c: rows["program store (all)"][c] for c in BUGS}
    assert found == dict.fromkeys(BUGS, 0), quick["bugs"][:5]
