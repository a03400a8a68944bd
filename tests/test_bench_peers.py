"""Smoke tests of the peers and pole benchmarks (``--quick``), and of the NEAT scoring path."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("cma")
pytest.importorskip("neat")

# Each runs a peer or the pole benchmark end to end (10 to 30 s on a 2-core CPU).
pytestmark = pytest.mark.slow


def test_outputs_cost_matches_network_cost():
    # The NEAT path scores raw outputs; for a network it must equal task.cost exactly
    # (same moves, same cost): float32, same ops, so a tight tolerance.
    from bench import peer_methods
    from eant2_jax import tasks
    from eant2_jax.compiler import networks
    from eant2_jax.kernels import network as kn

    task = tasks.make("servo", n_starts=17)
    genome = peer_methods.fixed_genome(np.random.default_rng(1), 2, scale=0.5)
    nets = networks([genome], task.n_inputs)
    want = np.asarray(task.cost(None, nets))
    net = jax.tree.map(lambda a: a[0], nets)
    h0 = jnp.zeros_like(net.bias)
    y = jax.vmap(lambda x: kn.step(net, x, h0, hidden=task.hidden, output=task.output)[0])(
        task.x_start
    )
    got = np.asarray(peer_methods.outputs_cost(task, y[None]))
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_peers_quick(tmp_path):
    # Every method once (hidden size 2 for the CMA-ES baselines, as --quick sets).
    from bench import bench_peers

    out = tmp_path / "peers.json"
    payload = bench_peers.main(["--quick", "--out", str(out)])
    saved = json.loads(out.read_text())
    assert [r["method"] for r in saved["rows"]] == ["cmaes-h2", "pycma-h2", "neat", "eant2"]
    assert saved["config"]["budget"] == 100  # --quick's budget, spent by every method
    for r in payload["rows"]:
        assert r["evaluations_used"] >= 100
        assert np.isfinite(r["best_cost_at_budget"])
        costs = [p["best_cost"] for p in r["curve"]]
        assert costs == sorted(costs, reverse=True)  # best so far never rises
    assert out.with_suffix(".md").exists()


def test_pole_seeds_split_then_merged(tmp_path):
    from bench import bench_pole
    from bench.common import BenchInputError

    a, b, merged = tmp_path / "a.json", tmp_path / "b.json", tmp_path / "merged.json"
    (row,) = bench_pole.main(["--quick", "--out", str(a)])["rows"]  # a whole quick run
    assert row["task"] == "dpv" and row["seeds"] == 1
    assert row["published_CMA-ES"] == 895
    assert json.loads(a.read_text())["runs"]["dpv"][0]["evaluations"] > 0
    bench_pole.main(["--quick", "--first-seed", "1", "--out", str(b)])
    payload = bench_pole.main(["--merge", str(b), str(a), "--out", str(merged)])
    runs = payload["runs"]["dpv"]
    assert [r["seed"] for r in runs] == [0, 1]
    assert payload["rows"][0]["seeds"] == 2
    single = json.loads(a.read_text())
    assert runs[0] == single["runs"]["dpv"][0]
    assert payload["device_kind"] == single["device_kind"]
    # One experiment only: a seed twice, other settings, or writing over an input refused.
    with pytest.raises(BenchInputError, match="repeats dpv seed"):
        bench_pole.main(["--merge", str(a), str(a), "--out", str(tmp_path / "x.json")])
    other = json.loads(b.read_text())
    other["config"]["budget"] = 7
    (tmp_path / "c.json").write_text(json.dumps(other))
    with pytest.raises(BenchInputError, match="budget"):
        bench_pole.main(
            ["--merge", str(a), str(tmp_path / "c.json"), "--out", str(tmp_path / "y.json")]
        )
    with pytest.raises(BenchInputError, match="exists; pass --force"):
        bench_pole.main(["--merge", str(a), str(b), "--out", str(merged)])
    with pytest.raises(BenchInputError, match="is one of the merged files"):
        bench_pole.main(["--merge", str(a), str(b), "--out", str(a)])
    assert json.loads(a.read_text()) == single
