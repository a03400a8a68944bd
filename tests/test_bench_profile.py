"""The profile suite: its trace analysis on a hand-made trace, and a tiny real run."""

import gzip
import json

import pytest

from bench import bench_profile


def _trace(tmp_path, events):
    path = tmp_path / "perfetto_trace.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": events}, f)
    return path


def test_analyse_trace_on_a_hand_made_trace(tmp_path):
    meta = [
        {"ph": "M", "pid": 1, "name": "process_name", "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "pid": 7, "name": "process_name", "args": {"name": "/host:CPU"}},
    ]

    def x(pid, name, ts, dur, tid=0):
        return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}

    events = meta + [
        # Window 0: [0, 100) us. Kernels overlap on two streams: busy = [0, 30) + [50, 60).
        x(1, "fusion_a", 0, 20, tid=1),
        x(1, "fusion_b", 10, 20, tid=2),
        x(1, "MemcpyD2H", 50, 10, tid=1),
        x(7, "$loop.py:10 run", 0, 95),
        x(7, "$loop.py:10 run", 5, 10),  # a nested call of the same function counts once
        x(7, "$other.py:3 helper", 0, 50),  # not ours: not reported
        {"ph": "i", "pid": 7, "tid": 0, "name": bench_profile._MARK, "ts": 100},
        # Window 1: [100, 300) us.
        x(1, "fusion_a", 120, 40, tid=1),
        x(1, "MemcpyH2D", 200, 5, tid=1),
        x(7, "$exploitation.py:5 run", 110, 150),
        {"ph": "i", "pid": 7, "tid": 0, "name": bench_profile._MARK, "ts": 300},
    ]
    out = bench_profile.analyse_trace(_trace(tmp_path, events), ["loop.py", "exploitation.py"])
    w0, w1 = out["windows"]
    assert w0["wall_s"] == pytest.approx(100e-6)
    assert w0["device_busy_s"] == pytest.approx(40e-6)
    assert (w0["device_ops"], w0["copies"], w0["d2h"], w0["h2d"]) == (3, 1, 1, 0)
    assert w0["copy_s"] == pytest.approx(10e-6)
    assert w1["wall_s"] == pytest.approx(200e-6)
    assert w1["device_busy_s"] == pytest.approx(45e-6)
    assert (w1["copies"], w1["h2d"]) == (1, 1)
    ops = {r["op"]: (r["count"], r["seconds"]) for r in out["device_ops"]}
    assert ops["fusion_a"] == (2, pytest.approx(60e-6))
    assert out["device_ops"][0]["op"] == "fusion_a"  # sorted by time
    py = {r["function"]: (r["calls"], r["seconds"]) for r in out["python"]}
    assert py == {
        "loop.py:run": (2, pytest.approx(95e-6)),
        "exploitation.py:run": (1, pytest.approx(150e-6)),
    }
    assert out["devices"] == ["/device:GPU:0"]
    (dev,) = out["per_device"]
    assert dev["device"] == "/device:GPU:0" and dev["ops"] == 5
    assert dev["busy_s"] == pytest.approx(85e-6) and dev["span_s"] == pytest.approx(205e-6)


def test_each_device_of_a_trace_gets_its_own_busy_time_and_span(tmp_path):
    meta = [
        {"ph": "M", "pid": p, "name": "process_name", "args": {"name": f"/device:GPU:{p}"}}
        for p in (0, 1)
    ]
    events = meta + [
        {"ph": "X", "pid": 0, "tid": 0, "name": "k", "ts": 0, "dur": 10},
        {"ph": "X", "pid": 0, "tid": 0, "name": "k", "ts": 5, "dur": 10},  # overlaps: once
        {"ph": "X", "pid": 1, "tid": 0, "name": "k", "ts": 40, "dur": 10},
        {"ph": "X", "pid": 1, "tid": 0, "name": "k", "ts": 90, "dur": 10},
    ]
    out = bench_profile.analyse_trace(_trace(tmp_path, events), [])
    d0, d1 = out["per_device"]
    assert (d0["device"], d0["ops"]) == ("/device:GPU:0", 2)
    assert (d1["device"], d1["ops"]) == ("/device:GPU:1", 2)
    assert d0["busy_s"] == pytest.approx(15e-6) and d0["span_s"] == pytest.approx(15e-6)
    assert d1["busy_s"] == pytest.approx(20e-6) and d1["span_s"] == pytest.approx(60e-6)


@pytest.mark.slow
def test_profile_quick_trace_run(tmp_path):
    # A real (tiny) servo run under jax.profiler: one window per generation, host functions
    # of the loop found; on a CPU there is no device process, so no device time. Without a
    # pruner: what is profiled is not the point here, and the engine compiles sooner.
    out = tmp_path / "profile.json"
    payload = bench_profile.main(
        [
            "--quick",
            "--parts",
            "cold,trace",
            "--generations",
            "2",
            "--pruner",
            "none",
            "--trace-dir",
            str(tmp_path / "trace"),
            "--out",
            str(out),
        ]
    )
    cold, trace = payload["cold"], payload["trace"]
    assert [r["generation"] for r in cold] == [0, 1, 2]
    assert cold[0]["compiles"] > 0 and cold[0]["compile_s"] > 0
    assert all(r["wall_s"] >= r["compile_s"] for r in cold)
    assert len(trace["windows"]) == 3
    functions = {r["function"] for r in trace["python"]}
    assert "loop.py:run" in functions
    assert json.loads(out.read_text())["trace"]["windows"][0]["wall_s"] > 0
    assert out.with_suffix(".md").read_text().count("|") > 20
