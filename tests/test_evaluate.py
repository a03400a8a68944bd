"""The compiled, batched forward pass against the NumPy reference interpreter.

Tolerance. The compiled path stores weights and inputs in float32 and computes in float32; the
reference computes in float64. To compare arithmetic only, the reference is given the same
float32-rounded weights and inputs. What remains is float32 rounding (eps = 6e-8) in sums of at
most 8 products per neuron, through at most 6 neurons (depth) and 8 time steps, with weights in
[-2, 2] and 1-Lipschitz activations: some hundreds of ulps at the very worst, relative to the
size of the values being summed. Hence ``RTOL = 1e-4`` relative, plus the same fraction of the
genome's largest output (or 1, the natural size of an output here) as an absolute floor, so an
output that cancels to ~0 is judged against the size of what cancelled. Over 6,000 random
genomes (all 16 activation pairs, T = 8) the largest error seen was 2e-6 of that scale, 50
times below the tolerance.
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compiles import count_compiles
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from strategies import fewer_examples, genome_batches, genomes, weights

import eant2_jax
from eant2_jax.compiler import Bucket, bucket_for, compile_genomes
from eant2_jax.evaluate import rollout_batch
from eant2_jax.genome import Genome
from eant2_jax.kernels import network as kn
from eant2_jax.reference import interpret

RTOL = 1e-4
ACTIVATIONS = ("tanh", "sigmoid", "relu", "identity")
N_IN = 3
# Sizes of the genomes drawn here (strategies.genomes defaults): at most 6 neurons of at most
# 3 terminals each, so 24 genes and depth 6. One fixed bucket holds them all, so that the
# property tests below compile a handful of programs, not one per example.
MAX_NEURONS, MAX_GENES, MAX_DEPTH = 6, 24, 6
ROWS = 4  # genomes per compiled batch in the fixed-bucket tests (padded with copies)
# Inputs of the fixed-bucket tests: one shape for all of them (T time steps, M streams), so
# that they share their programs (one per number of outputs, sweeps and activation pair).
T, M = 4, 2
# Outputs of the genomes drawn by the fixed-bucket tests: one number for all of them, so that
# each of them compiles one program per sweep count and activation pair, the same programs.
# Two outputs exercise the root order (output k is root k); other numbers of outputs (1-3) go
# through the public entry point against the reference in test_evaluate_matches_reference.
OUTPUTS = 2


def _f32(a) -> np.ndarray:
    return np.asarray(a, np.float32).astype(np.float64)


def reference(batch: list[Genome], x, hidden: str = "tanh", output: str = "identity"):
    """``[G, T, M, n_out]`` from the interpreter, on float32-rounded weights and inputs."""
    run = functools.partial(interpret, inputs=_f32(x), hidden=hidden, output=output)
    return np.stack([run(g, weights=_f32(g.weights)) for g in batch])


def assert_close(got, want) -> None:
    """Per genome: ``|got - want| <= RTOL * (|want| + max(1, max |want|))`` (module docstring)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape
    assert np.all(np.isfinite(got))
    for k in range(want.shape[0]):
        scale = max(1.0, float(np.max(np.abs(want[k]), initial=0.0)))
        np.testing.assert_allclose(got[k], want[k], rtol=RTOL, atol=RTOL * scale)


def inputs(t: int, m: int, n_in: int = N_IN) -> st.SearchStrategy[np.ndarray]:
    """``float32[t, m, n_in]`` in [-2, 2]; shrinks towards zeros."""
    return hnp.arrays(np.float32, (t, m, n_in), elements=st.floats(-2, 2, width=32))


def run_fixed_bucket(batch, x, *, hidden="tanh", output="identity", sweeps=None):
    """The compiled path (``rollout_batch``, jitted) in the fixed bucket; first rows only."""
    sweeps = bucket_for(batch).sweeps if sweeps is None else sweeps
    rows = list(batch) + [batch[0]] * (ROWS - len(batch))
    compiled = compile_genomes(
        rows, N_IN, bucket=Bucket(neurons=MAX_NEURONS, genes=MAX_GENES, sweeps=sweeps)
    )
    ys = rollout_batch(
        compiled.layout, compiled.weights, jnp.asarray(x), hidden=hidden, output=output
    )
    return np.asarray(ys)[: len(batch)]


# ------------------------------------------------------------------------ reference anchors
# Everything is compared with the interpreter; these pin the interpreter (and the compiled
# path) to hand-computed values of the semantics in eant2_jax.genome.
ANCHORS = [
    # text, hidden, output, x[T, 1, n_in], y[T, 1, n_out]
    ("N0/1*0.5 I0*1", "tanh", "identity", [[[2.0]]], [[[1.0]]]),  # the root's weight scales
    ("N0/2*2 I0*0.5 R0*1", "tanh", "identity", [[[1.0]], [[2.0]], [[3.0]]], [[[1]], [[3]], [[6]]]),
    ("N0/1*1 I0*1 N1/1*1 I1*3", "tanh", "identity", [[[1.0, 2.0]]], [[[1.0, 6.0]]]),  # order
    ("N0/1*1 N1/1*1 I0*1", "relu", "identity", [[[-1.0]], [[2.0]]], [[[0.0]], [[2.0]]]),
    ("N0/1*1 N1/1*1 I0*1", "identity", "relu", [[[-1.0]]], [[[0.0]]]),
    ("N0/2*1 F1*3 N1/1*1 I0*1", "identity", "identity", [[[1.5]]], [[[6.0]]]),  # 3x + x
    ("N0/3*1 I0*1 I0*1 B*0.25", "tanh", "identity", [[[1.0]]], [[[2.25]]]),  # repeated input
    ("N0/1*1 R1*1 N1/1*1 B*1", "tanh", "identity", [[[0]], [[0]]], [[[0, 1]], [[1, 1]]]),
    ("N0/1*1 B*0", "tanh", "sigmoid", [[[9.0]]], [[[0.5]]]),
]


# The compiled path runs every anchor on inputs of one shape: its own steps, then zeros up to
# the most steps of any anchor, and zero columns up to the most inputs. A step reads no later
# step and no gene reads the added inputs, so the anchor's steps keep their values; anchors of
# one activation pair and number of outputs then share one program.
ANCHOR_T = max(len(a[3]) for a in ANCHORS)
ANCHOR_IN = max(len(a[3][0][0]) for a in ANCHORS)


@pytest.mark.parametrize(("text", "hidden", "output", "x", "y"), ANCHORS)
@pytest.mark.slow
def test_hand_computed_values(text, hidden, output, x, y):
    g = Genome.parse(text)
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    np.testing.assert_allclose(interpret(g, x, hidden=hidden, output=output), y)
    t, m, n_in = x.shape
    padded = np.zeros((ANCHOR_T, m, ANCHOR_IN))
    padded[:t, :, :n_in] = x
    got = eant2_jax.evaluate(g, padded, hidden=hidden, output=output)
    np.testing.assert_allclose(np.asarray(got)[0, :t], y, rtol=1e-6)


@pytest.mark.slow
def test_streams_are_independent():
    # Each of the M streams carries its own recurrent state: permuting the streams permutes
    # the outputs (the same program runs both calls).
    g = Genome.parse("N0/2*1 I0*1 R0*0.5")
    x = np.random.default_rng(0).normal(size=(6, 5, 1)).astype(np.float32)
    perm = np.array([3, 0, 4, 2, 1])
    y = np.asarray(eant2_jax.evaluate(g, x))[0]
    np.testing.assert_array_equal(np.asarray(eant2_jax.evaluate(g, x[:, perm]))[0], y[:, perm])
    assert_close(y[None], reference([g], x))


# ------------------------------------------------------------------------ property: compiled
@pytest.mark.slow
@given(batch=genome_batches(max_size=ROWS, n_outputs=OUTPUTS), x=inputs(T, M))
def test_compiled_matches_reference(batch, x):
    """Batches of 1-4 genomes of different sizes, exactly the sweeps their depth needs (the
    smallest the compiler would pick, so a sweep too few would show): at most 5 programs
    (sweeps 1, 2, 3, 4, 6), shared by the other fixed-bucket tests."""
    assert_close(run_fixed_bucket(batch, x), reference(batch, x))


# Each activation once as the hidden one and once as the output one (a cycle through
# ACTIVATIONS). The compiled path applies the two independently (a root's value is the output
# activation of its sum, every other neuron's the hidden one's), so no pair is a path of its
# own; (tanh, identity) is the program of the tests above.
ROLES = [("tanh", "identity"), ("identity", "relu"), ("relu", "sigmoid"), ("sigmoid", "tanh")]
assert sorted(h for h, _ in ROLES) == sorted(o for _, o in ROLES) == sorted(ACTIVATIONS)


@pytest.mark.slow
@pytest.mark.parametrize(("hidden", "output"), ROLES)
@fewer_examples(0.1)  # one program each
@given(batch=genome_batches(n_outputs=OUTPUTS, min_size=ROWS, max_size=ROWS), x=inputs(T, M))
def test_each_activation_as_hidden_and_as_output(hidden, output, batch, x):
    """Every activation of ACTIVATIONS, as the hidden one and as the output one, against the
    reference on random batches."""
    got = run_fixed_bucket(batch, x, hidden=hidden, output=output, sweeps=MAX_DEPTH)
    assert_close(got, reference(batch, x, hidden, output))


@pytest.mark.slow
@fewer_examples(0.05)  # each example may compile a program of its own: 5 (as in CI)
@given(
    batch=genome_batches(max_size=3),
    shape=st.sampled_from([(1, 1), (3, 4), (8, 2)]),
    acts=st.sampled_from([("tanh", "identity"), ("sigmoid", "tanh"), ("relu", "sigmoid")]),
    data=st.data(),
)
def test_evaluate_matches_reference(batch, shape, acts, data):
    """The public entry point, with the bucket it chooses itself, several T and M."""
    x = data.draw(inputs(*shape), label="x")
    got = eant2_jax.evaluate(batch, x, hidden=acts[0], output=acts[1])
    assert got.shape == (len(batch), *shape, batch[0].n_outputs)
    assert got.dtype == jnp.float32
    assert_close(got, reference(batch, x, *acts))


@pytest.mark.slow
def test_text_and_genomes_are_accepted():
    text = "N0/2*1 I1*0.5 B*-1"
    # The anchors' input shape: one genome is then the program of the first anchors.
    x = np.random.default_rng(1).normal(size=(ANCHOR_T, 1, ANCHOR_IN))
    a = eant2_jax.evaluate(text, x)
    b = eant2_jax.evaluate([Genome.parse(text)], x)
    c = eant2_jax.evaluate((text, Genome.parse(text)), jnp.asarray(x))
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.concatenate([a, a]), c)


# ------------------------------------------------------------------- property: vmap over params
@functools.cache
def _vmapped_rollout(hidden: str, output: str):
    """One structure, many parameter vectors (as CMA-ES asks): ``[K, P] -> [K, T, M, n_out]``."""

    def one(layout, params, xs):
        net = kn.network(layout, params)
        run = functools.partial(kn.rollout, net, hidden=hidden, output=output)
        return jax.vmap(run, in_axes=1, out_axes=1)(xs)  # M streams, each its own state

    return jax.jit(jax.vmap(one, in_axes=(None, 0, None)))


@pytest.mark.slow
@fewer_examples(0.1)
@given(
    g=genomes(n_outputs=OUTPUTS),  # one program (numbers of outputs: the tests above)
    w=hnp.arrays(np.float32, (5, MAX_GENES), elements=st.floats(-2, 2, width=32)),
    x=inputs(4, 2),
)
def test_vmap_over_params_matches_reference(g, w, x):
    """The kernels vmapped by hand over a batch of parameter vectors for one structure (as
    CMA-ES evaluates a population), and over streams, under jit."""
    compiled = compile_genomes(
        [g], N_IN, bucket=Bucket(neurons=MAX_NEURONS, genes=MAX_GENES, sweeps=MAX_DEPTH)
    )
    layout = jax.tree.map(lambda a: a[0], compiled.layout)
    got = _vmapped_rollout("tanh", "sigmoid")(layout, jnp.asarray(w), jnp.asarray(x))
    want = np.stack(
        [
            interpret(g, _f32(x), hidden="tanh", output="sigmoid", weights=_f32(wk[: len(g)]))
            for wk in w
        ]
    )
    assert_close(got, want)


# ------------------------------------------------------------------------- compiled only once
@pytest.mark.slow
def test_same_bucket_does_not_compile_again():
    # Shapes no other test uses (T=7, M=5, 4 inputs), so the counts below are this test's.
    x = np.random.default_rng(2).normal(size=(7, 5, 4)).astype(np.float32)
    first = [
        "N0/2*0.5 N1/2*0.5 N2/2*0.5 N3/2*0.5 N4/1*0.5 I0*1 I1*1 R0*1 B*1 I3*1",
        "N0/2*1 I0*1 R0*0.5",
    ]
    # Other structures, ids and weights; exact sizes that differ from the first batch's and
    # lie above the bucket floors (so that the test fails if evaluate stops bucketing), in the
    # same bucket: 6 neurons, 12 genes, 6 sweeps, 2 rows, 1 output.
    second = [
        "N9/2*1 F4*0.3 N8/3*1 N7/1*1 N6/1*1 N5/1*-1 N4/2*1 I2*1 B*0.1 R9*1 I0*2",
        "N5/2*0.3 B*1 I3*2",
    ]
    third = [*second, "N0/1*1 I0*1"]  # three genomes: a bigger bucket (3 rows)
    g1, g2 = [Genome.parse(t) for t in first], [Genome.parse(t) for t in second]
    assert bucket_for(g1) == bucket_for(g2) == Bucket(neurons=6, genes=12, sweeps=6)
    sizes = [(max(g.n_neurons for g in b), max(len(g) for g in b), max(g.depth() for g in b))
             for b in (g1, g2)]  # fmt: skip
    assert sizes == [(5, 10, 5), (6, 11, 6)]

    with count_compiles() as c:
        y1 = eant2_jax.evaluate(first, x)
    assert c.of("rollout_batch") == 1, c.names
    with count_compiles() as c:
        y2 = eant2_jax.evaluate(second, x)
    assert c.count == 0, "a same-bucket batch compiled again"
    with count_compiles() as c:
        eant2_jax.evaluate(second, 2 * x)  # new input values: no new program either
    assert c.count == 0
    # The check can fail: a bigger bucket does compile, once.
    with count_compiles() as c:
        y3 = eant2_jax.evaluate(third, x)
    assert c.of("rollout_batch") == 1, c.names
    with count_compiles() as c:
        eant2_jax.evaluate(third, x)
    assert c.count == 0
    # And the reused program computed the second batch, not the first.
    assert_close(y1, reference(g1, x))
    assert_close(y2, reference(g2, x))
    np.testing.assert_array_equal(y3[:2], y2)


# ---------------------------------------------------------------------------- deep networks
# The first sweep bucket past `kn.SWEEPS_UNROLLED`: a step's sweeps run as one loop.
LOOPED_SWEEPS = 96


@pytest.mark.slow
@fewer_examples(0.1)  # two programs: 96 sweeps, and the 6 of the tests above
@given(batch=genome_batches(max_size=ROWS, n_outputs=OUTPUTS), x=inputs(T, M))
def test_sweeps_as_a_loop_match_reference_and_the_written_out_program(batch, x):
    """Genomes run in a bucket of 96 sweeps, past `kn.SWEEPS_UNROLLED`, where the sweeps
    are one loop: the reference's values; and on a CPU the bits of the program that writes
    out the sweeps of the smaller bucket (sweeps past a network's depth leave it as it is)."""
    assert kn.SWEEPS_UNROLLED < LOOPED_SWEEPS
    looped = run_fixed_bucket(batch, x, sweeps=LOOPED_SWEEPS)
    assert_close(looped, reference(batch, x))
    if jax.default_backend() == "cpu":
        np.testing.assert_array_equal(looped, run_fixed_bucket(batch, x, sweeps=MAX_DEPTH))


def _chain(depth: int, seed: int) -> Genome:
    """``depth`` neurons, each reading the next one, the last reading input 0; weights of
    +-1 with random signs (so the output's sign is the product of theirs)."""
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=depth + 1)
    text = " ".join(f"N{i}/1*{s:g}" for i, s in enumerate(signs[:-1]))
    return Genome.parse(f"{text} I0*{signs[-1]:g}")


@pytest.mark.slow
def test_a_chain_of_3000_neurons_evaluates_in_seconds():
    """Issue 40: a 3,000-deep chain (3,072 neurons and sweeps) took over 300 s and 7.3 GB
    to compile with every sweep written out; as a loop, `evaluate` (compile and run) took
    5.5 s for one stream on the 2-core CPU machine. For these 4 streams it took 12-14 s of
    CPU time, and 35-72 s of wall time while other processes loaded the machine six times
    over. Waiting for a core is not the program's cost, so the test bounds the CPU time by
    half of the issue's minute. The values are the reference's: with
    ``tanh`` and weights of +-1 the chain's value decays as the depth grows (so a missing
    sweep would leave the output at 0) and each neuron adds at most a few float32 roundings
    to its input's relative error without amplifying it (``|tanh'| <= 1``), hence a relative
    tolerance of 4 roundings (2^-24 each) per neuron."""
    depth = 3000
    g = _chain(depth, seed=3)
    assert g.depth() == depth and bucket_for([g]).sweeps > kn.SWEEPS_UNROLLED
    x = np.array([[[-2.0], [-0.5], [0.25], [1.0]]], np.float32)  # [T=1, M=4, 1]
    wall, cpu = time.perf_counter(), time.process_time()
    got = np.asarray(eant2_jax.evaluate(g, x))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    want = interpret(g, x.astype(np.float64))
    assert np.all(np.abs(want) > 1e-3)  # the input reached the root
    np.testing.assert_allclose(got[0], want, rtol=4 * depth * 2.0**-24, atol=0)
    assert cpu < 30, f"a {depth}-deep chain: {cpu:.1f} s of CPU time ({wall:.1f} s of wall time)"


# -------------------------------------------------------------------------------- bad input
def test_different_numbers_of_outputs():
    with pytest.raises(ValueError, match="different numbers of outputs"):
        eant2_jax.evaluate(["N0/1*1 I0*1", "N0/1*1 I0*1 N1/1*1 I0*1"], np.ones((2, 1, 1)))


@pytest.mark.parametrize("shape", [(4,), (4, 2), (1, 4, 2, 1)])
def test_inputs_of_wrong_rank(shape):
    with pytest.raises(ValueError, match=r"shape \[T, M, n_in\]"):
        eant2_jax.evaluate("N0/1*1 I0*1", np.ones(shape))


@pytest.mark.parametrize(("hidden", "output"), [("softmax", "tanh"), ("tanh", "Tanh")])
def test_unknown_activation(hidden, output):
    with pytest.raises(ValueError, match="unknown activation .* known: abs, clamped, cube"):
        eant2_jax.evaluate("N0/1*1 I0*1", np.ones((2, 1, 1)), hidden=hidden, output=output)


def test_genome_reads_more_inputs_than_given():
    with pytest.raises(ValueError, match="genome 1 reads input 2 but the data has 2 inputs"):
        eant2_jax.evaluate(["N0/1*1 I1*1", "N0/1*1 I2*1"], np.ones((2, 1, 2)))


def test_other_bad_arguments():
    with pytest.raises(ValueError, match="no genomes"):
        eant2_jax.evaluate([], np.ones((2, 1, 1)))
    with pytest.raises(TypeError, match="numeric"):
        eant2_jax.evaluate("N0/1*1 I0*1", np.ones((2, 1, 1), bool))
    with pytest.raises(TypeError, match="expected a Genome"):
        eant2_jax.evaluate([1], np.ones((2, 1, 1)))
    with pytest.raises(eant2_jax.GenomeError, match="stack underflow"):
        eant2_jax.evaluate("N0/2*1 I0*1", np.ones((2, 1, 1)))


# ------------------------------------------------------------------------ non-finite inputs
@pytest.mark.slow
def test_unread_nan_input_does_not_poison_outputs():
    """Issue 16: one NaN in an input no gene reads made every output NaN (0 * nan in the
    dense product); the reference leaves the outputs alone."""
    g = Genome.parse("N0/1*1 I0*1 N1/2*1 N2/1*1 I1*1 B*0.5")  # input 2 is never read
    x = np.array([[[0.5, -1.0, np.nan]], [[1.0, 2.0, np.inf]]], np.float32)
    got = np.asarray(eant2_jax.evaluate(g, x))[0]
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, interpret(g, x), rtol=1e-6)


@pytest.mark.slow
@given(
    batch=genome_batches(max_size=ROWS, n_outputs=OUTPUTS, weight=weights(subnormal=False)),
    x=inputs(T, M),
    where=hnp.arrays(np.int8, (T, M, N_IN), elements=st.integers(0, 3)),
)
def test_non_finite_inputs_match_reference(batch, x, where):
    """NaN and +-inf inputs: the same NaN / inf / finite pattern as the reference (a value
    reaches exactly the neurons that read it), finite outputs within the usual tolerance."""
    # A subnormal float32 weight is 0 to XLA's CPU arithmetic (flush to zero) but not to the
    # float64 reference: 0 * inf is NaN in one and not the other. Not the semantics tested, so
    # the strategy draws none (a filter here failed hypothesis's filter_too_much health check).
    x = np.where(where == 1, np.nan, np.where(where == 2, np.inf, x)).astype(np.float32)
    x = np.where(where == 3, -np.inf, x).astype(np.float32)
    got = np.asarray(run_fixed_bucket(batch, x), np.float64)
    with np.errstate(all="ignore"):
        want = reference(batch, x)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_array_equal(np.isposinf(got), np.isposinf(want))
    np.testing.assert_array_equal(np.isneginf(got), np.isneginf(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=RTOL, atol=RTOL * 10)
