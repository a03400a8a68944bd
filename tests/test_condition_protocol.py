"""The condition protocol (docs/protocol.md, section 2): the float64 runner against the
engine, the controls, the positive control, the flat directions, the endpoints and the
verdicts, each against a plain computation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from eant2_jax import interpret
from eant2_jax.app.condition import recording_config
from eant2_jax.app.condition_controls import (
    flat_directions,
    leaf_removable,
    remove_like,
    shared_entries,
    with_duplicate,
)
from eant2_jax.app.condition_endpoints import (
    PLATEAU_SLOPE,
    endpoints,
    half_slope,
    paired_claim,
    paired_t_interval,
)
from eant2_jax.app.condition_protocol import (
    cast_task,
    flat_share,
    iterate,
    protocol_experiment,
    summarise,
)
from eant2_jax.app.report_stats import bootstrap_indices
from eant2_jax.exploitation import init as engine_init
from eant2_jax.exploitation import run as run_engine
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.tasks import regression
from eant2_jax.tuning import prepare

# The docs' worked example (docs/genome.md): two identity roots, a forward jumper reading
# root 2 and a recurrent jumper of root 0 into itself.
EXAMPLE = Genome.parse("N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4")


def _task(seed=0, n=128):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 2))
    return regression(x, 0.8 * x[:, :1] - 0.3 * x[:, 1:] + 0.2 * np.tanh(x[:, :1] * x[:, 1:]))


@pytest.mark.slow
def test_iterate_is_the_engine_iteration_in_float32():
    """With networks in float32 (the engine's evaluation), `iterate` records the engine's
    cond(C) to the bit: the same keys, ask/tell and cost call."""
    task = _task()
    genomes = [Genome.parse("N0/3*1 I0*0.7 I0*0.8 I1*0.5"), Genome.parse("N0/2*0.5 I0*1 I1*-1")]
    config = recording_config(0.5, 30, 1e7, "float32")
    key = jax.random.key(4)
    prep = prepare(genomes, task, key=key, config=config, pad_count=False)
    _, hist = run_engine(prep.state, prep.batch.layout, task, key=key, config=config)
    _, cond = iterate(
        prep.state, prep.batch.layout, task, key, iters=30, chunk=15, eval_dtype="float32"
    )
    np.testing.assert_array_equal(cond, np.asarray(hist.cond)[:30])


def test_cast_task_makes_the_cost_float64():
    task = _task()
    with jax.enable_x64(True):
        t64 = cast_task(task, jnp.float64)
        leaves = [a for a in jax.tree.leaves(t64) if jnp.issubdtype(a.dtype, jnp.floating)]
        assert leaves and all(a.dtype == jnp.float64 for a in leaves)
        assert all(a.dtype == jnp.float32 for a in jax.tree.leaves(task) if a.dtype.kind == "f")


def _grow(genome, w, iters=150):
    """log10 cond(C) after each of ``iters`` float64 iterations of one run (x64 mode) on a
    task a tanh neuron solves exactly (no scaling symmetry: tanh is not homogeneous)."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(128, 2))
    y = np.tanh(0.8 * x[:, :1] - 0.3 * x[:, 1:] + 0.1)
    task = cast_task(regression(x, y, output="tanh"), jnp.float64)
    config = recording_config(0.5, iters, 1e14, "float64")
    from eant2_jax.compiler import compile_genomes

    batch = compile_genomes([genome], 2, pad_count=False)
    mean = np.zeros(batch.weights.shape)
    mean[0, : len(genome)] = w
    st = engine_init(
        jax.random.key(1)[None], jnp.asarray(mean), batch.layout.gene_mask, config, popsize=8
    )
    _, cond = iterate(st, batch.layout, task, jax.random.key(0), iters=iters, chunk=iters)
    return np.log10(cond[:, 0])


@pytest.mark.slow
def test_an_exact_duplicate_makes_cond_grow_faster():
    """The positive control on a tiny network: with one connection duplicated (same source,
    same neuron, same weight) the sum is all the cost sees, an exactly flat direction, and
    cond(C) grows faster than without it from the same start."""
    genome = Genome.parse("N0/3*1 I0*0.5 I1*0.5 B*0.1")
    w = np.array([1.0, 0.3, -0.2, 0.05])
    dup = with_duplicate(genome, 1)
    assert str(dup) == "N0/4*1.0 I0*0.5 I0*0.5 I1*0.5 B*0.1"
    assert shared_entries(dup, 2) == [[1, 2]] and shared_entries(genome, 2) == []
    with jax.enable_x64(True):
        plain = _grow(genome, w)
        doubled = _grow(dup, np.insert(w, 2, w[1]))
    assert doubled[-1] > plain[-1] + 1.0, (doubled[-1], plain[-1])


def test_with_duplicate_refuses_a_neuron():
    with pytest.raises(ValueError, match="neuron"):
        with_duplicate(EXAMPLE, 2)


def _random_genome(rng):
    text = "N0/{k}*1.0 " + " ".join(f"I{rng.integers(3)}*{rng.normal():.3f}" for _ in range(6))
    inner = "N1/3*0.7 I0*0.2 I1*-0.4 B*0.3"
    return Genome.parse(text.format(k=7) + " " + inner)


@pytest.mark.parametrize("seed", range(4))
def test_controls_remove_exactly_the_count_asked(seed):
    rng = np.random.default_rng(seed)
    genome = _random_genome(rng)
    count = int(rng.integers(1, 5))
    for rule, key in (("random", jax.random.key(seed)), ("magnitude", None)):
        reduced, kept = remove_like(genome, count, rule=rule, key=key)
        assert len(reduced) == len(genome) - count == len(kept)
        for g, i in zip(reduced.genes, kept, strict=True):
            assert (g.kind, g.ref, g.weight) == (genome[i].kind, genome[i].ref, genome[i].weight)
        removed = sorted(set(range(len(genome))) - set(kept.tolist()))
        assert all(genome[i].kind != GeneKind.NEURON for i in removed)
    # The same key, the same removals; magnitude takes the smallest |w| first.
    a = remove_like(genome, count, rule="random", key=jax.random.key(seed))[1]
    np.testing.assert_array_equal(
        a, remove_like(genome, count, rule="random", key=jax.random.key(seed))[1]
    )
    one = remove_like(genome, 1, rule="magnitude")[1]
    gone = (set(range(len(genome))) - set(one.tolist())).pop()
    ok = np.flatnonzero(leaf_removable(genome))
    assert abs(genome.weights[gone]) == np.min(np.abs(genome.weights[ok]))


def test_controls_refuse_more_than_can_go():
    genome = Genome.parse("N0/2*1 I0*0.5 I1*0.5")
    with pytest.raises(ValueError, match="only 1 of 2"):
        remove_like(genome, 2, rule="magnitude")


@pytest.mark.parametrize("seed", range(3))
def test_flat_directions_are_exact_symmetries(seed):
    """Along each scaling orbit (incoming weights x a, uses of the output / a) and along a
    shared entry's difference, the reference interpreter's outputs do not change."""
    rng = np.random.default_rng(seed)
    genome = with_duplicate(EXAMPLE, 7)  # a second bias on neuron 2 as well
    w = rng.normal(size=len(genome))
    x = rng.normal(size=(4, 5, 3))
    base = interpret(genome, x, weights=w)
    v = flat_directions(genome, w, hidden="tanh", output="identity", n_inputs=3)
    assert v.shape == (3, len(genome))  # two identity roots, one shared entry
    a = np.exp(rng.normal())
    for d in v[:2]:
        orbit = np.where(np.isclose(d, w) & (d != 0), w * a, w)
        orbit = np.where(np.isclose(d, -w) & (d != 0), w / a, orbit)
        assert not np.allclose(orbit, w)
        np.testing.assert_allclose(
            interpret(genome, x, weights=orbit), base, rtol=1e-12, atol=1e-12
        )
    np.testing.assert_allclose(interpret(genome, x, weights=w + 0.7 * v[2]), base, atol=1e-12)
    # The self jumper R0 is both an input and a use of neuron 0: it does not move.
    assert v[0][5] == 0
    # tanh roots have no such symmetry; an output that is not homogeneous neither.
    assert len(flat_directions(EXAMPLE, w[:-1], hidden="tanh", output="tanh", n_inputs=3)) == 0


def test_flat_share_of_a_covariance_stretched_along_a_flat_direction():
    genome = with_duplicate(Genome.parse("N0/2*1 N1/2*0.5 I0*1 I1*1 I1*-1"), 4)
    w = np.array([1.0, 0.5, 1.0, 1.0, 1.0, -1.0])
    u = np.zeros(6)
    u[[4, 5]] = [1, -1]
    u /= np.linalg.norm(u)
    rng = np.random.default_rng(0)
    q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    C = q @ np.diag(rng.uniform(1, 2, 6)) @ q.T + 1e6 * np.outer(u, u)
    f = flat_share(genome, w, C, hidden="tanh", output="identity", n_inputs=2)
    assert f["directions"] == 2 and f["top_alignment"] > 0.999
    assert f["log10_cond"] > 5.5 and f["log10_cond_off_flat"] < 1 and f["share"] > 0.8


def test_endpoints_against_numpy():
    rng = np.random.default_rng(1)
    iters = 400
    t = np.arange(1, iters + 1)
    rising = 0.004 * t + rng.normal(0, 0.01, (3, iters))
    flat = 7.0 + rng.normal(0, 1e-4, (2, iters))
    y = np.concatenate([rising, flat])
    e = endpoints(y, at=(100, 300, 400, 900))
    assert set(e) == {"at_100", "at_300", "at_400", "slope", "plateau"}
    np.testing.assert_array_equal(e["at_300"], y[:, 299])
    half = slice(iters // 2, iters)
    want = [1000 * np.polyfit(t[half], row[half], 1)[0] for row in y]
    np.testing.assert_allclose(half_slope(y), want, rtol=1e-9, atol=1e-12)
    assert e["plateau"][:3] == [None] * 3
    np.testing.assert_allclose(e["plateau"][3:], y[3:, half].mean(axis=1))
    # The threshold is the protocol's: a slope just inside it plateaus, just outside not.
    edge = np.stack([(PLATEAU_SLOPE * s / 1000) * t for s in (0.99, 1.01)])
    assert endpoints(edge)["plateau"][0] is not None and endpoints(edge)["plateau"][1] is None


def test_paired_interval_against_scipy():
    rng = np.random.default_rng(2)
    d = rng.normal(0.3, 1.0, 25)
    m, lo, hi = paired_t_interval(d)
    ci = stats.ttest_1samp(d, 0).confidence_interval(0.95)
    np.testing.assert_allclose([lo, hi], [ci.low, ci.high], rtol=1e-12)
    assert m == pytest.approx(d.mean())
    assert paired_t_interval(np.full(4, 0.5)) == (0.5, 0.5, 0.5)
    with pytest.raises(ValueError):
        paired_t_interval([1.0])


@pytest.mark.slow
def test_paired_claim_verdicts_and_bootstrap():
    rng = np.random.default_rng(3)
    b = rng.normal(10, 2, 25)
    lower = paired_claim(b - 1 + rng.normal(0, 0.1, 25), b)
    higher = paired_claim(b + 1 + rng.normal(0, 0.1, 25), b)
    mixed = paired_claim(b + rng.normal(0, 1, 25), b)
    assert (lower["verdict"], higher["verdict"], mixed["verdict"]) == (
        "held",
        "not held",
        "undecided",
    )
    # The bootstrap: the protocol's key and resamples, the mean of each resample.
    d = (b - 1 + rng.normal(0, 0.1, 25)) - b
    c = paired_claim(d + b, b)
    idx = bootstrap_indices(jax.random.fold_in(jax.random.key(0), 0), 25, 10_000)
    means = np.array([d[i].mean() for i in idx])
    np.testing.assert_allclose(
        [c["bootstrap_low"], c["bootstrap_high"]], np.quantile(means, [0.025, 0.975]), rtol=1e-12
    )


@pytest.mark.slow
def test_protocol_experiment_end_to_end_and_resumed():
    """Two tiny networks: the controls remove as many genes as the pruner's rounds did,
    every row reports, and a run resumed from its first chunk's checkpoint (no pruning
    rounds again) ends with the uninterrupted run's records."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(64, 2))
    task = regression(x, np.tanh(1.5 * x[:, :1]) + 0.5 * x[:, 1:2])
    # Both two deep: the pruning rounds of the two share one compiled program (one bucket),
    # which a depth-1 network would not. The second reads its three connections through a
    # hidden neuron that cannot go (the output's only input): the pruner can remove at most
    # the two connections that the controls can remove.
    genomes = [
        Genome.parse("N0/3*1 N1/2*0.5 I0*0.7 I1*0.2 I0*0.8 I1*0.5"),
        Genome.parse("N0/1*1 N1/3*0.9 I0*0.7 B*0.3 I1*0.5"),
    ]
    points = []
    options = dict(
        network_keys=[jax.random.key(3000), jax.random.key(3001)],
        init_keys=[jax.random.key(3100), jax.random.key(3101)],
        iters=40,
        chunk=20,
        prune={"iters": 60, "window": 20},
    )
    with jax.enable_x64(True):
        res = protocol_experiment(
            genomes, task, on_chunk=lambda done, p: points.append(p["checkpoint"]), **options
        )
        s = summarise(res, at=(10, 40))
        again = protocol_experiment(genomes, task, resume=points[1], **options)
        fresh = protocol_experiment(genomes, task, resume=points[0], **options)
    assert len(res["rows"]) == 2 * 2 * 4 + 2 and [p["done"] for p in points] == [0, 20, 40]
    for net in res["networks"]:
        sizes = {len(Genome.parse(net[f"genome_{v}"])) for v in ("pruned", "random", "magnitude")}
        assert len(sizes) == 1 and sizes.pop() <= net["size"]
    assert any(net["removed"] for net in res["networks"])  # the pruner removed something
    assert all(np.shape(r["log10_cond"]) == (40,) for r in res["rows"])
    assert {c["iteration"] for c in s["claims"]} == {10, 40} and len(s["claims"]) == 13
    means = [c for c in s["claims"] if c["claim"].endswith("(network means)")]
    assert [c["pairs"] for c in means] == [2, 2, 2] and {c["iteration"] for c in means} == {40}
    assert set(s["positive_control"]) >= {"duplicate_reached_bound", "detects"}
    for a, b, c in zip(res["rows"], again["rows"], fresh["rows"], strict=True):
        np.testing.assert_array_equal(a["log10_cond"], b["log10_cond"])
        np.testing.assert_array_equal(a["log10_cond"], c["log10_cond"])
        assert a["best_cost"] == b["best_cost"] == c["best_cost"]


@pytest.mark.slow
def test_bench_protocol_quick_writes_and_resumes(tmp_path):
    """``python -m bench condition --protocol --quick``: the JSON and markdown, a checkpoint
    read back without pickle, and a resumed run from it with the same rows."""
    import json

    from bench import bench_condition

    out, point = tmp_path / "c.json", tmp_path / "c.npz"
    first = bench_condition.main(
        ["--protocol", "--quick", "--out", str(out), "--checkpoint", str(point)]
    )
    md = out.with_suffix(".md").read_text()
    assert "### Network 3000" in md and "Positive control" in md and "1.8e17" in md
    assert json.loads(out.read_text())["done"] == first["iters"] == 20  # --quick's
    again = bench_condition.main(
        [
            "--protocol",
            "--quick",
            "--out",
            str(out),
            "--force",
            "--checkpoint",
            str(point),
            "--resume",
        ]
    )
    assert again["resumed_at"] == 20
    assert [r["trace"] for r in again["rows"]] == [r["trace"] for r in first["rows"]]
    with pytest.raises(bench_condition.BenchInputError, match="other settings"):
        bench_condition.main(
            [
                "--protocol",
                "--quick",
                "--out",
                str(tmp_path / "d.json"),
                "--checkpoint",
                str(point),
                "--resume",
                "--seed",
                "5",
            ]
        )


def test_bench_protocol_defaults_are_the_protocols():
    """``python -m bench condition --protocol`` runs docs/protocol.md's numbers and writes
    ``bench/results/condition-protocol-<device>.json``; a genome file is refused with it."""
    from bench import bench_condition, harness
    from bench.common import device_tag

    args = harness.parse_args(bench_condition.SUITE, ["--protocol"])
    assert args.out.endswith(f"bench/results/condition-protocol-{device_tag()}.json")
    assert (args.iters, args.inits, args.networks, args.max_condition) == (10_000, 5, 5, 1e14)
    assert (args.prune_iters, args.chunk, args.checkpoint, args.resume) == (2000, 1000, None, False)
    assert len(bench_condition.PROTOCOL_FILES) == 5
    with pytest.raises(bench_condition.BenchInputError, match="genome-file"):
        harness.parse_args(bench_condition.SUITE, ["--protocol", "--genome-file", "x.genome"])
    with pytest.raises(bench_condition.BenchInputError, match="--resume needs"):
        harness.parse_args(bench_condition.SUITE, ["--protocol", "--resume"])
