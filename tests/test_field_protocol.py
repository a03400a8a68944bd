"""The field protocol (docs/protocol.md section 3; bench/field_*.py): TensorNEAT's networks
in the library's form against a plain NumPy reference of TensorNEAT's forward pass, the
champion rule and the interval and verdict rules against plain references on fresh random
inputs, the test episodes' initial states compared between the methods (a mismatch refused),
and ``python -m bench field --protocol`` end to end on CartPole with a stand-in second method
that writes TensorNEAT-format genomes (TensorNEAT is not installed in CI), resumed from its
checkpoint.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from bench import (
    bench_field,
    field_champions,
    field_protocol,
    field_stats,
    field_tnet,
    field_workers,
    harness,
)
from bench.common import BenchInputError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
HAS_GYMNAX = importlib.util.find_spec("gymnax") is not None


# ------------------------------------------------------------ TensorNEAT genomes, by hand
def random_tn_genome(rng, n_in, n_out, n_hidden, *, p=0.5, dead_output=False):
    """A random feed-forward TensorNEAT genome (``nodes [N, 4]``, ``conns [C, 3]``) with
    NaN padding rows, identity and tanh hidden nodes, some without inputs."""
    keys_h = list(range(n_in + n_out, n_in + n_out + n_hidden))
    rng.shuffle(keys_h)  # a topological order unlike the keys' order
    nodes = [[k, 0.0, 0, 0] for k in range(n_in)]
    nodes += [[k, rng.normal(), 0, 0] for k in range(n_in, n_in + n_out)]
    nodes += [[k, rng.normal(), 0, rng.choice([-1, 0])] for k in keys_h]
    conns = []
    sources = list(range(n_in))
    for k in keys_h:
        for s in sources:
            if rng.random() < p:
                conns.append([s, k, rng.normal()])
        sources.append(k)
    for o in range(n_in, n_in + n_out):
        if dead_output and o == n_in + n_out - 1:
            continue
        for s in sources:
            if rng.random() < p or s == 0:
                conns.append([s, o, rng.normal()])
    pad = np.full((3, 4), np.nan), np.full((4, 3), np.nan)
    return np.vstack([np.asarray(nodes, float), pad[0]]), np.vstack([np.asarray(conns), pad[1]])


def deepest_tn_genome():
    """The widest and deepest genome `random_tn_genome` makes with 4 inputs, 2 outputs and at
    most 3 hidden nodes (5 neurons, 4 sweeps). Among a run's candidates it sets the shapes of
    the judging programs (the batch is padded to its largest network), so that the runs of
    other seeds and tests are judged by the programs compiled once."""
    return random_tn_genome(np.random.default_rng(0), 4, 2, 3, p=1.0)


def tn_reference(nodes, conns, x, n_in, n_out, activations):
    """TensorNEAT's DefaultGenome forward in plain NumPy (float64): a node's value is
    act(bias + sum of weight * value) over sources with a value; outputs skip act; a node
    with no such source has no value (NaN)."""
    acts = {"tanh": np.tanh, "scaled_tanh": lambda z: 3.0 * np.tanh(z)}
    rows = {int(r[0]): r for r in nodes if not np.isnan(r[0])}
    edges = [(int(c[0]), int(c[1]), c[2]) for c in conns if not np.isnan(c[0])]
    vals, pending = {}, set(rows)
    while pending:
        for k in sorted(pending):
            if all(s in vals for s, t, _ in edges if t == k):
                break
        pending.remove(k)
        if k < n_in:
            vals[k] = x[k]
            continue
        ins = [w * vals[s] for s, t, w in edges if t == k and not np.isnan(vals[s])]
        if not ins:
            vals[k] = np.nan
            continue
        z = rows[k][1] + sum(ins)
        act = int(rows[k][3])
        out = n_in <= k < n_in + n_out
        vals[k] = z if out or act == -1 else acts[activations[act]](z)
    return np.array([vals.get(o, np.nan) for o in range(n_in, n_in + n_out)])


@pytest.mark.slow
@pytest.mark.parametrize("activation", ["tanh", "scaled_tanh"])
def test_tensorneat_network_matches_a_numpy_reference(activation):
    from eant2_jax.kernels import network as kn

    rng = np.random.default_rng()
    n_in, n_out = 4, 3
    genomes = [random_tn_genome(rng, n_in, n_out, int(rng.integers(0, 7)), dead_output=i == 0)
               for i in range(6)]  # fmt: skip
    lib_off, lib_scale = rng.normal(size=n_in), rng.uniform(0.5, 2.0, n_in)
    mean, std = rng.normal(size=n_in), rng.uniform(0.5, 2.0, n_in)
    off, scale = field_tnet.input_affine(lib_off, lib_scale, mean, std)
    nets = [field_tnet.tensorneat_net(n, c, n_inputs=n_in, n_outputs=n_out,
                                      activations=[activation], in_offset=off, in_scale=scale)
            for n, c in genomes]  # fmt: skip
    batch = field_tnet.stack(nets)
    obs = rng.normal(size=(5, n_in)) * 2
    u = (obs - lib_off) * lib_scale  # what the library's task feeds the network
    step = jax.jit(jax.vmap(jax.vmap(lambda net, x: kn.step(net, x, jax.numpy.zeros_like(
        net.bias))[0], in_axes=(None, 0)), in_axes=(0, None)))  # fmt: skip
    got = np.asarray(step(batch, jax.numpy.asarray(u, jax.numpy.float32)))
    tn_in = (obs - mean) / (std + 1e-6)  # what TensorNEAT's normalised problem feeds it
    want = np.array([[tn_reference(n, c, x, n_in, n_out, [activation]) for x in tn_in]
                     for n, c in genomes])  # fmt: skip
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(want[0, :, -1]).all()  # the dead output of genome 0
    # float32 evaluation of float64 weights: a few ulps of the largest term.
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=1e-4, atol=1e-4)


@pytest.mark.slow
def test_tensorneat_candidates_on_a_task_of_raw_observations():
    """A brax task keeps raw observations (``obs_offset`` None): TensorNEAT's candidates are
    judged on the same raw inputs (hopper's first judging failed on the None)."""
    from eant2_jax.kernels import network as kn

    rng = np.random.default_rng()
    n_in, n_out = 4, 3
    genomes = [random_tn_genome(rng, n_in, n_out, int(rng.integers(0, 7))) for _ in range(4)]
    run = {"kind": "tensorneat", "activations": ["tanh"],
           "candidates": {f"c{i}": {"nodes": n.tolist(), "conns": c.tolist()}
                          for i, (n, c) in enumerate(genomes)}}  # fmt: skip
    task = types.SimpleNamespace(n_inputs=n_in, n_outputs=n_out, obs_offset=None, obs_scale=None)
    ids, batch = field_workers.method_networks(task, run)
    assert ids == [f"c{i}" for i in range(4)]
    obs = rng.normal(size=(5, n_in)) * 2
    step = jax.jit(jax.vmap(jax.vmap(lambda net, x: kn.step(net, x, jax.numpy.zeros_like(
        net.bias))[0], in_axes=(None, 0)), in_axes=(0, None)))  # fmt: skip
    got = np.asarray(step(batch, jax.numpy.asarray(obs, jax.numpy.float32)))
    want = np.array([[tn_reference(n, c, x, n_in, n_out, ["tanh"]) for x in obs]
                     for n, c in genomes])  # fmt: skip
    assert np.array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------- the champion rule
def test_archive_and_choice_match_a_plain_reference():
    rng = np.random.default_rng()
    for _ in range(20):
        k = int(rng.integers(1, 6))
        archive = field_champions.Archive(k)
        offers = [(f"n{int(rng.integers(0, 12))}", float(rng.integers(-5, 5))) for _ in range(40)]
        for i, f in offers:
            archive.offer(i, f)
        best, first = {}, {}
        for n, (i, f) in enumerate(offers):
            best[i] = max(f, best.get(i, -math.inf))
            first.setdefault(i, n)
        ids = sorted(best, key=lambda i: (-best[i], first[i]))[:k]
        assert archive.entries() == [(i, best[i]) for i in ids]
        val = {i: float(rng.integers(0, 3)) for i in ids}
        scores = np.array([val[i] for i in ids])
        assert field_champions.choose(archive.entries(), val) == ids[int(np.argmax(scores))]
    with pytest.raises(ValueError, match="no candidates"):
        field_champions.choose([], {})


# ------------------------------------------------------------ intervals and verdicts
@pytest.mark.slow
def test_median_interval_matches_a_numpy_loop_and_scipy():
    import scipy.stats

    from eant2_jax.app.report_stats import bootstrap_indices

    rng = np.random.default_rng()
    # Ten values, as in `test_verdicts_need_the_interval_to_exclude_zero`: the resampling
    # program is compiled for the sample's size, so both tests run one program.
    x = rng.normal(loc=rng.normal(), size=10)
    est, low, high = field_stats.median_interval(list(x))
    idx = bootstrap_indices(jax.random.fold_in(jax.random.key(0), 0), x.size)
    meds = np.array([np.median(x[row]) for row in idx])  # the same resamples, one by one
    assert est == np.median(x)
    assert (low, high) == pytest.approx(tuple(np.quantile(meds, [0.025, 0.975])), abs=1e-12)
    ref = scipy.stats.bootstrap((x,), np.median, n_resamples=10_000, method="percentile",
                                rng=np.random.default_rng(0)).confidence_interval  # fmt: skip
    spread = x.max() - x.min()  # other resamples: agreement to a fraction of the spread
    assert abs(low - ref.low) < 0.15 * spread and abs(high - ref.high) < 0.15 * spread
    assert field_stats.median_interval([None, None]) is None


@pytest.mark.slow
def test_verdicts_need_the_interval_to_exclude_zero():
    rng = np.random.default_rng()
    up = rng.uniform(1, 2, 10)
    assert field_stats.verdict(field_stats.median_interval(up)) == "win"
    assert field_stats.verdict(field_stats.median_interval(-up)) == "loss"
    # Half of each sign, ten values as above: the same resamples of ten, drawn once.
    mixed = np.concatenate([up[:5], -up[5:]])
    assert field_stats.verdict(field_stats.median_interval(mixed)) == "tie"
    for low, high, want in ((0.0, 1.0, "tie"), (1e-9, 1.0, "win"), (-1.0, -1e-9, "loss")):
        assert field_stats.verdict((0.5, low, high)) == want
    assert field_stats.verdict(None) is None
    curve = [{"wall_s": 1.0, "test_return": 3.0}, {"wall_s": 2.0, "test_return": 9.0}]
    assert field_stats.wall_to_target(curve, 5.0) == 2.0
    assert field_stats.wall_to_target(curve, 10.0) == math.inf


def _judged(rng, n_points):
    """A method's judged run: budgets and a curve of champions at rising wall times."""
    walls = np.sort(rng.uniform(1, 100, n_points))
    curve = [{"wall_s": float(w), "test_return": float(rng.integers(0, 5))} for w in walls]
    return {"budgets": [{"test_return": float(rng.integers(0, 5))} for _ in range(3)],
            "curve": list(rng.permutation(curve))}  # fmt: skip


def test_seed_counts_match_a_plain_count_on_fresh_records():
    rng = np.random.default_rng()
    seeds = []
    for env in ("a", "b"):
        for seed in range(int(rng.integers(1, 8))):
            judged = {m: _judged(rng, int(rng.integers(1, 6))) for m in ("eant2", "tensorneat")}
            if rng.random() < 0.2:
                del judged["eant2"]  # a seed judged for one method only does not count
            seeds.append({"env": env, "seed": seed, "judged": judged})
    got = {r["env"]: r for r in field_stats.seed_counts(seeds)}
    for env in ("a", "b"):
        pairs = [s["judged"] for s in seeds if s["env"] == env and len(s["judged"]) == 2]
        if not pairs:
            assert env not in got
            continue
        evals = wall = 0
        for j in pairs:
            evals += (
                j["eant2"]["budgets"][2]["test_return"]
                >= j["tensorneat"]["budgets"][2]["test_return"]
            )
            tn = sorted(j["tensorneat"]["curve"], key=lambda p: p["wall_s"])[-1]
            mine = sorted((p for p in j["eant2"]["curve"] if p["wall_s"] <= tn["wall_s"]),
                          key=lambda p: p["wall_s"])  # fmt: skip
            wall += bool(mine) and mine[-1]["test_return"] >= tn["test_return"]
        n = len(pairs)
        want = {"env": env, "seeds": n, "evals": evals, "wall": wall,
                "most": {"evals": evals > n / 2, "wall": wall > n / 2}}  # fmt: skip
        assert got[env] == want


def test_seed_counts_by_hand():
    def run(budget, curve):
        return {"budgets": [{"test_return": budget}],
                "curve": [{"wall_s": w, "test_return": r} for w, r in curve]}  # fmt: skip

    seeds = [  # a tie counts; eant2_jax's later, better champion does not
        {"env": "e", "seed": 0, "judged": {"eant2": run(5.0, [(1.0, 1.0), (20.0, 9.0)]),
                                           "tensorneat": run(5.0, [(10.0, 4.0)])}},
        # no eant2_jax champion by TensorNEAT's wall time: -inf
        {"env": "e", "seed": 1, "judged": {"eant2": run(1.0, [(30.0, 9.0)]),
                                           "tensorneat": run(2.0, [(10.0, 4.0)])}},
    ]  # fmt: skip
    (row,) = field_stats.seed_counts(seeds)
    assert (row["evals"], row["wall"], row["seeds"]) == (1, 0, 2)
    assert row["most"] == {"evals": False, "wall": False}  # one of two is not most
    # TensorNEAT without a champion (no budget's return, no curve): eant2_jax's counts
    seeds.append({"env": "e", "seed": 2, "judged": {"eant2": run(1.0, [(30.0, 9.0)]),
                  "tensorneat": {"budgets": [{"test_return": None}], "curve": []}}})  # fmt: skip
    (row,) = field_stats.seed_counts(seeds)
    assert (row["evals"], row["wall"], row["seeds"]) == (2, 1, 3)
    assert row["most"] == {"evals": True, "wall": False}
    md = field_stats.render_summary([], [row])
    assert "| e | 2 of 3 (most) | 1 of 3 |" in md


# ------------------------------------------------------- the same test episodes, checked
# The stand-in imports numpy alone (this file, bench and JAX would cost each of its processes
# a second or more): the genome makers' source is put in, and its archive is the plain
# reference of `test_archive_and_choice_match_a_plain_reference` (the k best distinct
# networks, best first; ties to the one offered first).
FAKE_TN = """
import argparse, json
import numpy as np
{genome_source}
p = argparse.ArgumentParser()
for f in ("--out", "--seed", "--generations", "--pop", "--t0"):
    p.add_argument(f)
a = p.parse_args()
rng = np.random.default_rng(int(a.seed))
offered, cands, curve = [], {{}}, []
for g in range(int(a.generations)):
    for j in range(3):
        nodes, conns = random_tn_genome(rng, 4, 2, int(rng.integers(0, 4)))
        if g == j == 0:  # a candidate from the start: the judging programs' shapes fixed
            nodes, conns = deepest_tn_genome()
        d = f"g{{g}}-{{j}}"
        offered.append((d, float(rng.normal())))
        top = sorted(offered, key=lambda e: -e[1])[:5]  # stable: ties to the first offered
        if d in [i for i, _ in top]:
            cands[d] = {{"nodes": nodes[~np.isnan(nodes[:, 0])].tolist(),
                        "conns": conns[~np.isnan(conns[:, 0])].tolist()}}
    curve.append({{"evaluations": (g + 1) * int(a.pop), "wall_s": g + 1.0,
                  "train_return": top[0][1], "archive": [list(e) for e in top]}})
json.dump({{"method": "tensorneat", "kind": "tensorneat", "activations": ["tanh"],
           "curve": curve, "candidates": cands, "done": True}}, open(a.out, "w"))
"""


def fake_tensorneat(tmp_path: Path):
    """A stand-in for TensorNEAT's training process: random genomes in its format."""
    script = tmp_path / "fake_tn.py"
    source = inspect.getsource(random_tn_genome) + inspect.getsource(deepest_tn_genome)
    script.write_text(FAKE_TN.format(genome_source=source))
    calls = []

    def argv(method, args, env, seed, out):
        calls.append(seed)
        return [sys.executable, str(script), "--out", str(out), "--seed", str(seed),
                "--generations", "4", "--pop", str(args.tensorneat_pop or 100)]  # fmt: skip

    return argv, calls


# The protocol's CartPole as this file's runs train and judge it: its frozen settings but for
# episodes of at most SHORT steps and eant2_jax's smallest padding bucket that fits (no
# min_bucket), so that its programs compile and run small. Every test here that trains or
# judges on CartPole takes it, and so shares one set of programs.
SHORT = 50


@pytest.fixture
def short_cartpole(monkeypatch):
    from bench.field_settings import ENVS

    monkeypatch.setitem(ENVS["cartpole"], "max_steps", SHORT)
    monkeypatch.setitem(ENVS["cartpole"]["eant2"], "min_bucket", None)
    return ENVS["cartpole"]


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_both_methods_start_from_the_same_states_and_a_mismatch_is_refused(short_cartpole):
    from bench.field_workers import judge

    rng = np.random.default_rng()
    cands = {}
    # t2 (in no archive: never judged) is the stand-in's deepest network, as in its runs.
    for j in range(3):
        nodes, conns = random_tn_genome(rng, 4, 2, 2) if j < 2 else deepest_tn_genome()
        cands[f"t{j}"] = {"nodes": nodes[~np.isnan(nodes[:, 0])].tolist(),
                          "conns": conns[~np.isnan(conns[:, 0])].tolist()}  # fmt: skip
    curve = [{"evaluations": 100, "wall_s": 1.0, "archive": [["t0", 1.0], ["t1", 0.5]]}]
    tn = {"kind": "tensorneat", "activations": ["tanh"], "curve": curve, "candidates": cands}
    twin = dict(tn)  # a second method with the same networks: the same scores
    out = judge("cartpole", {"eant2": twin, "tensorneat": tn}, [100])
    assert out["eant2"]["starts_sha256"] == out["tensorneat"]["starts_sha256"]
    assert out["eant2"]["budgets"] == out["tensorneat"]["budgets"]
    (b,) = out["tensorneat"]["budgets"]
    assert b["champion"] in ("t0", "t1") and 1 <= b["test_return"] <= SHORT
    with pytest.raises(BenchInputError, match="start from different states"):
        judge("cartpole", {"eant2": twin, "tensorneat": tn}, [100],
              test_keys={"tensorneat": jax.random.key(9001)})  # fmt: skip


def workers_in_process(monkeypatch, what=("train", "judge")):
    """The protocol's ``python -m bench.field_workers`` processes of the kinds ``what`` run in
    this process, through the same argv and the workers' ``main`` (sharing this process's
    compiled programs); other children (the stand-in's script, the rest) stay processes."""
    child = field_protocol._call

    def call(argv, timeout):
        if argv[1:3] == ["-m", "bench.field_workers"] and argv[3] in what:
            assert field_workers.main(argv[3:]) == 0
            return ""
        return child(argv, timeout)

    monkeypatch.setattr(field_protocol, "_call", call)


def _protocol(tmp_path, *extra):
    return bench_field.main(["--protocol", "--envs", "cartpole", "--first-seed", "0",
                             "--budget", "400", "--tensorneat-pop", "100",
                             "--tensorneat", str(tmp_path / "tn"),
                             "--out", str(tmp_path / "f.json"), *extra])  # fmt: skip


def _fake_src(tmp_path):
    (tmp_path / "tn" / "tensorneat").mkdir(parents=True, exist_ok=True)
    (tmp_path / "tn" / "tensorneat" / "pipeline.py").write_text("")


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_protocol_end_to_end_on_cartpole(tmp_path, monkeypatch, capsys, short_cartpole):
    """eant2_jax's real run and the stand-in, judged on one task; files and labels. The
    stand-in trains in its own process, as the protocol runs it; eant2_jax's training and the
    judging run here, through the same argv and the workers' ``main`` (sharing their compiled
    programs with `test_eant2_training_goes_on_from_its_run_directory` and
    `test_both_methods_start_from_the_same_states_and_a_mismatch_is_refused`); that the
    workers' module runs as the protocol's fresh child process is
    `test_the_workers_run_as_a_child_process_of_the_protocol`."""
    argv, _ = fake_tensorneat(tmp_path)
    monkeypatch.setitem(field_protocol.METHODS, "tensorneat", argv)
    _fake_src(tmp_path)
    workers_in_process(monkeypatch)
    # A budget that ends eant2_jax's run with its second generation (78 and 234
    # evaluations), both judged; TensorNEAT's stand-in: 4 generations of 39.
    small = ("--budget", "234", "--tensorneat-pop", "39")
    payload = _protocol(tmp_path, "--seeds", "1", "--population", "2", "--max-iters", "3", *small)
    (rec,) = payload["seeds"]
    assert payload["trial"] and rec["env"] == "cartpole" and rec["seed"] == 0
    for m in ("eant2", "tensorneat"):
        judged = rec["judged"][m]
        assert [b["budget"] for b in judged["budgets"]] == [58, 117, 234]
        assert judged["budgets"][-1]["champion"] is not None, m
        for b in judged["budgets"]:
            if b["champion"] is not None:
                # CartPole's returns are episode lengths, at most the task's max_steps.
                assert b["evaluations"] <= b["budget"] and 1 <= b["test_return"] <= SHORT
                assert b["champion"] in [c["id"] for c in b["candidates"]]
                assert b["champion"] in rec["runs"][m]["champions"]
    assert rec["judged"]["eant2"]["starts_sha256"] == rec["judged"]["tensorneat"]["starts_sha256"]
    md = (tmp_path / "f.md").read_text()
    assert "A trial, not the protocol's result" in md and '"max_iters": 100' in md
    assert [r["budget"] for r in payload["summary"]] == [58, 117, 234]
    capsys.readouterr()


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_the_workers_run_as_a_child_process_of_the_protocol(tmp_path):
    """``python -m bench.field_workers judge``, started as the protocol starts its children
    (``protocol_child_env``: this checkout on ``PYTHONPATH``, no compilation cache), runs in
    a fresh process and writes its judged file; a failing child says what failed on its last
    stderr line. A run without a curve is not judged: the child's imports, task and file are
    the point here, the judging itself runs in-process in the tests above."""
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"method": "eant2", "kind": "eant2", "curve": []}))
    out = tmp_path / "judged.json"
    argv = [sys.executable, "-m", "bench.field_workers", "judge", "--env", "cartpole",
            "--out", str(out), "--budgets", "100", "--runs", str(run)]  # fmt: skip

    def child(argv):
        return subprocess.run(argv, capture_output=True, text=True, timeout=600,
                              env=field_protocol.protocol_child_env())  # fmt: skip

    proc = child(argv)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(out.read_text()) == {}
    proc = child([*argv[:-1], str(tmp_path / "missing.json")])
    assert proc.returncode != 0
    assert "missing.json" in proc.stderr.strip().splitlines()[-1]


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_protocol_resumes_from_its_checkpoint(tmp_path, monkeypatch, capsys, short_cartpole):
    """A run cut after its first seed goes on from the checkpoint: the finished seed is not
    run again, and the file is the uninterrupted run's (timings aside)."""
    argv, calls = fake_tensorneat(tmp_path)
    monkeypatch.setitem(field_protocol.METHODS, "tensorneat", argv)
    _fake_src(tmp_path)
    workers_in_process(monkeypatch)
    args = ("--seeds", "2", "--methods", "tensorneat")
    whole = _protocol(tmp_path, *args)
    assert calls == [0, 1]
    ckpt = tmp_path / "f.checkpoint.jsonl"
    lines = ckpt.read_text().splitlines()
    assert len(lines) == 3  # the settings, then one line per seed
    ckpt.write_text("\n".join(lines[:2]) + "\n")  # as if stopped after seed 0
    with pytest.raises(BenchInputError, match="exists"):
        _protocol(tmp_path, *args, "--force")
    resumed = _protocol(tmp_path, *args, "--resume", "--force")
    assert calls == [0, 1, 1]
    assert resumed["seeds"][0] == whole["seeds"][0]
    assert resumed["seeds"][1]["judged"] == whole["seeds"][1]["judged"]
    assert resumed["summary"] == whole["summary"]
    with pytest.raises(BenchInputError, match="another call's settings"):
        _protocol(tmp_path, "--seeds", "3", "--methods", "tensorneat", "--resume", "--force")
    capsys.readouterr()


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_width_candidates_share_tensorneats_runs_through_peer_runs(
    tmp_path, monkeypatch, capsys, short_cartpole
):
    """docs/protocol.md section 6: a second call with another --width and the same
    ``--peer-runs`` judges TensorNEAT's run of the first (not trained again), with the same
    results, and its payload names the reuse; the shared file outlives the judging."""
    argv, calls = fake_tensorneat(tmp_path)
    monkeypatch.setitem(field_protocol.METHODS, "tensorneat", argv)
    _fake_src(tmp_path)
    workers_in_process(monkeypatch)
    peers = tmp_path / "peers"
    shared = ("--seeds", "1", "--methods", "tensorneat", "--peer-runs", str(peers))
    first = _protocol(tmp_path, *shared)
    assert calls == [0] and first["reused_peer_runs"] == []
    file = peers / "cartpole-s0-tensorneat.json"
    assert json.loads(file.read_text())["peer_settings"]["generations"] == 4
    second = _protocol(tmp_path, *shared, "--width", "1024", "--out", str(tmp_path / "w.json"))
    assert calls == [0]  # not trained again
    (a,), (b,) = first["seeds"], second["seeds"]
    assert b["runs"]["tensorneat"].pop("reused_from") == str(file)
    assert b["runs"] == a["runs"] and b["judged"] == a["judged"]  # wall times included
    want = [{"env": "cartpole", "seed": 0, "method": "tensorneat", "file": str(file)}]
    assert second["reused_peer_runs"] == want
    assert "--peer-runs" in (tmp_path / "w.md").read_text()
    assert file.is_file()  # judged, and still shared
    assert not (tmp_path / "w.checkpoint.jsonl.runs" / file.name).exists()  # its own copy
    capsys.readouterr()


def _planted(tmp_path: Path, monkeypatch) -> Path:
    """A module that, if imported, would leave a file behind (found by name, by anyone)."""
    plant = tmp_path / "plant"
    plant.mkdir()
    sentinel = tmp_path / "imported"
    (plant / "planted_peer.py").write_text(f"open({str(sentinel)!r}, 'w').close()\n")
    monkeypatch.syspath_prepend(str(plant))
    monkeypatch.setenv("PYTHONPATH", str(plant), prepend=os.pathsep)  # and for any child
    return sentinel


class _Unpickled:
    """Unpickling it touches ``path``."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return Path.touch, (self.path,)


def test_a_peer_file_is_data_and_a_mismatch_is_refused(tmp_path, monkeypatch):
    """A shared TensorNEAT run naming a module is read as JSON and nothing else (the module
    never imported, pickle bytes refused unread); a file made with other settings is refused
    with the settings that differ named, before any training; only finished runs are shared."""
    import pickle

    from bench import field_peers
    from bench.common import environment

    _fake_src(tmp_path)
    sentinel = _planted(tmp_path, monkeypatch)
    peers = tmp_path / "peers"
    kw = {"pop": 100, "generations": 4, "src": tmp_path / "tn", "device": environment()}
    want = field_peers.settings("cartpole", 0, **kw)
    run = {"method": "tensorneat", "kind": "planted_peer", "module": "planted_peer",
           "done": True, "curve": [], "candidates": {}, "process_s": 2.5}  # fmt: skip
    path = field_peers.publish(peers, run, want)
    assert path == peers / "cartpole-s0-tensorneat.json"
    assert field_peers.publish(peers, {**run, "process_s": 9.0}, want) is None  # kept as it is
    found = field_peers.find(peers, "cartpole", 0, want)
    assert found == {**run, "reused_from": str(path)}
    assert not sentinel.exists() and "planted_peer" not in sys.modules

    # Made with other settings: refused by the protocol's command, nothing trained.
    path.write_text(json.dumps({**run, "peer_settings": field_peers.settings(
        "cartpole", 0, **{**kw, "generations": 8})}))  # fmt: skip
    argv, calls = fake_tensorneat(tmp_path)
    monkeypatch.setitem(field_protocol.METHODS, "tensorneat", argv)
    with pytest.raises(BenchInputError, match="generations 8 in the file, 4 asked"):
        _protocol(tmp_path, "--seeds", "1", "--methods", "tensorneat", "--peer-runs", str(peers))
    assert calls == []
    (tmp_path / "tn" / "tensorneat" / "pipeline.py").write_text("# another TensorNEAT\n")
    with pytest.raises(BenchInputError, match="source_sha256"):
        field_peers.find(peers, "cartpole", 0, field_peers.settings("cartpole", 0, **kw))

    # Not JSON (here a pickle that would touch a file): refused, never unpickled.
    touched = tmp_path / "unpickled"
    path.write_bytes(pickle.dumps(_Unpickled(touched)))
    with pytest.raises(BenchInputError, match="not a JSON run file"):
        field_peers.find(peers, "cartpole", 0, want)
    assert not touched.exists()
    pickle.loads(path.read_bytes())
    assert touched.exists()  # the plant was armed

    # Only finished runs: not a stopped or failed one, nor one never finished.
    for bad in ({"deadline": "killed after 3600 s"}, {"error": "exit 1"}, {"done": False}):
        assert field_peers.publish(tmp_path / "other", {**run, **bad}, want) is None
    path.write_text(json.dumps({**run, "done": False, "peer_settings": want}))
    with pytest.raises(BenchInputError, match="not a finished run"):
        field_peers.find(peers, "cartpole", 0, want)
    with pytest.raises(BenchInputError, match="--peer-runs belong to --protocol"):
        bench_field.main(["--peer-runs", str(peers), "--quick", "--out", str(tmp_path / "g.json")])


@pytest.mark.parametrize(
    "argv,phrase",
    [
        (["--envs", "servo", "--methods", "eant2"], "--protocol runs"),
        (["--quick", "--methods", "eant2"], "--quick"),
        (["--budget", "0", "--methods", "eant2"], "--budget"),
        (["--methods", "tensorneat"], "--tensorneat"),
    ],
)
def test_protocol_options_are_checked(argv, phrase, tmp_path):
    with pytest.raises(BenchInputError, match=phrase):
        bench_field.main(["--protocol", *argv, "--out", str(tmp_path / "f.json")])
    assert not (tmp_path / "f.json").exists()


def test_frozen_settings_are_the_protocols():
    from bench import field_settings as fs

    assert fs.SEEDS == {"gymnax": tuple(range(4000, 4010)), "brax": tuple(range(4000, 4005))}
    assert (fs.VALIDATION_KEY, fs.VALIDATION_EPISODES, fs.TEST_KEY, fs.TEST_EPISODES) == (
        8000, 10, 9000, 100)  # fmt: skip
    for env in fs.ENVS.values():
        assert fs.budgets(env) == [25_000, 50_000, 100_000]
    assert json.loads(json.dumps(fs.table()))["budgets"]["hopper"] == [25_000, 50_000, 100_000]


def test_brax_settings_take_the_chosen_width_by_section_6s_rule(tmp_path):
    """docs/protocol.md section 6: the chosen width replaces brax's frozen popsize, and each
    environment's iterations keep its frozen evaluations per structure and generation,
    ``max(2, ceil(popsize x max_iters / (width // 12)))`` (hopper 24 x 10, halfcheetah
    48 x 100); walker2d takes halfcheetah's settings on its own three seeds."""
    from bench import field_settings as fs

    frozen = {"hopper": (24, 10), "halfcheetah": (48, 100), "walker2d": (48, 100)}
    for name, (popsize, iters) in frozen.items():
        s = fs.ENVS[name]["eant2"]
        assert (s["width"], s["popsize"]) == (fs.WIDTH, None)
        assert s["max_iters"] == max(2, math.ceil(popsize * iters / (fs.WIDTH // 12)))
    assert fs.ENVS["walker2d"]["eant2"] == fs.ENVS["halfcheetah"]["eant2"]
    assert fs.env_seeds("walker2d") == [4000, 4001, 4002]
    assert fs.env_seeds("hopper") == list(range(4000, 4005))
    with pytest.raises(BenchInputError, match="walker2d: only with --protocol"):
        bench_field.main(["--envs", "walker2d", "--out", str(tmp_path / "f.json")])


def test_a_width_trial_reaches_eant2_alone_and_older_checkpoints_still_match(tmp_path):
    """``--width W`` (issue 41): a --protocol trial whose eant2_jax run takes
    ``ExploitConfig.width = W`` in place of its frozen popsize; TensorNEAT's argv is
    untouched, and a call without it has the settings a checkpoint written before the
    option existed holds."""
    from bench.field_settings import ENVS

    env = ENVS["cartpole"]
    frozen = field_workers.eant2_config(env, budget=1000)
    assert (frozen.exploit.popsize, frozen.exploit.width) == (None, 1)  # the default popsize
    chosen = field_workers.eant2_config(ENVS["hopper"], budget=1000)
    assert (chosen.exploit.popsize, chosen.exploit.width) == (None, 1024)
    wide = field_workers.eant2_config(env, budget=1000, width=4096)
    assert (wide.exploit.popsize, wide.exploit.width) == (None, 4096)
    assert dataclasses.replace(wide, exploit=frozen.exploit) == frozen  # nothing else moves

    (tmp_path / "tensorneat").mkdir()
    (tmp_path / "tensorneat" / "pipeline.py").write_text("")  # found, never imported here
    argv = ["--protocol", "--envs", "hopper", "--width", "4096", "--tensorneat", str(tmp_path),
            "--out", str(tmp_path / "f.json")]  # fmt: skip
    args = harness.parse_args(bench_field.SUITE, argv)
    assert args.trial and "--width" in field_protocol.trial_overrides(args)
    out = tmp_path / "run.json"
    eant2 = field_protocol.METHODS["eant2"]("eant2", args, "hopper", 4000, out)
    tn = field_protocol.METHODS["tensorneat"]("tensorneat", args, "hopper", 4000, out)
    assert eant2[eant2.index("--width") + 1] == "4096" and "--width" not in tn
    assert field_protocol.call_settings(args)["args"]["width"] == 4096
    args.width = None
    assert "width" not in field_protocol.call_settings(args)["args"]
    with pytest.raises(BenchInputError, match="--width belongs to --protocol"):
        bench_field.main(["--width", "64", "--quick", "--out", str(tmp_path / "g.json")])


class _Killed(Exception):
    pass


@pytest.mark.slow
@pytest.mark.skipif(not HAS_GYMNAX, reason="gymnax not installed")
def test_eant2_training_goes_on_from_its_run_directory(tmp_path, short_cartpole):
    """A training run killed after a generation goes on from its run directory: the same
    generations, archives and candidates as the run never stopped, its wall times going on."""
    from bench.field_workers import Log, resume_log, train_eant2

    # Two generations (78 and 234 evaluations): cut after the first, one to go on.
    sizes = {"seed": 3, "budget": 100, "population": 2, "max_iters": 3}
    whole = Log(tmp_path / "whole.json", 0.0, {})
    train_eant2(short_cartpole, log=whole, rundir=tmp_path / "whole.rundir", **sizes)

    class Dies(Log):
        def point(self, **point):
            super().point(**point)
            if len(self.data["curve"]) == 1:
                raise _Killed

    path = tmp_path / "cut.json"
    with pytest.raises(_Killed):
        train_eant2(short_cartpole, log=Dies(path, 0.0, {}), rundir=tmp_path / "cut.rundir",
                    **sizes)  # fmt: skip
    cut_at = json.loads(path.read_text())["curve"][-1]["wall_s"]
    log = resume_log(path, __import__("time").time(), {})
    assert log.wall() == pytest.approx(cut_at, abs=5.0)
    train_eant2(short_cartpole, log=log, rundir=tmp_path / "cut.rundir", **sizes)

    def strip(curve):  # as the files hold them (tuples become lists), wall times aside
        return [
            {k: v for k, v in p.items() if k != "wall_s"} for p in json.loads(json.dumps(curve))
        ]

    assert len(whole.data["curve"]) > 1
    assert strip(log.data["curve"]) == strip(whole.data["curve"])
    assert log.data["candidates"] == whole.data["candidates"]
    assert log.data["resumed_at_s"] == [cut_at]


@pytest.mark.parametrize("callers", [None, "true"])
def test_the_orchestrator_holds_no_device_memory(monkeypatch, callers):
    """The protocol's own process does not preallocate device memory (its children would run
    out); the children get the caller's setting back."""
    monkeypatch.setattr(field_protocol, "CHILD_PREALLOCATE", [])
    if callers is None:
        monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    else:
        monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", callers)
    field_protocol.hold_no_device_memory()
    field_protocol.hold_no_device_memory()  # twice: the caller's setting is kept, not "false"
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    assert field_protocol.protocol_child_env().get("XLA_PYTHON_CLIENT_PREALLOCATE") == callers
