"""Tests of the pure-JAX kernels (``kernels/``, installed as ``eant2_jax.kernels``).

Kernel level: the scatter of ``network()`` against a NumPy construction of the dense matrices
straight from the genome; ``step`` and ``rollout`` under jit and vmap, without retracing;
padding; gradients. Packaging: ``eant2_jax.kernels`` is this repository's ``kernels/`` folder
(never the unrelated ``kernels`` distribution on PyPI), in the editable install and in a
built wheel, and it imports nothing from the rest of eant2_jax.
"""

from __future__ import annotations

import ast
import functools
import os
import subprocess
import sys
import textwrap
import tomllib
import zipfile
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from strategies import fewer_examples, genomes

import eant2_jax
from eant2_jax.compiler import Bucket, compile_genomes
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.kernels import netdot, netfused
from eant2_jax.kernels import network as kn
from eant2_jax.reference import interpret

REPO = Path(__file__).resolve().parents[1]
KERNELS = REPO / "kernels"
N_IN, H, P, SWEEPS = 3, 6, 24, 6  # a bucket that holds every genome strategies.genomes draws
EXAMPLE = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"


def one_layout(g: Genome, *, neurons: int = H, genes: int = P, sweeps: int = SWEEPS):
    """The unbatched Layout of one genome and its float32 weights ``[genes]``."""
    compiled = compile_genomes(
        [g], N_IN, bucket=Bucket(neurons=neurons, genes=genes, sweeps=sweeps)
    )
    return jax.tree.map(lambda a: a[0], compiled.layout), compiled.weights[0]


def dense_numpy(g: Genome, h: int, n_in: int) -> dict[str, np.ndarray]:
    """The dense tensors of a genome, built directly from the gene table of the compiler's
    docstring (no flat buffer, no slots array): neuron slots by descending gene index."""
    order = sorted((i for i, x in enumerate(g) if x.kind == GeneKind.NEURON), reverse=True)
    slot = {g[i].ref: s for s, i in enumerate(order)}
    out = {
        "w_in": np.zeros((h, n_in)),
        "bias": np.zeros(h),
        "w_ff": np.zeros((h, h)),
        "w_rec": np.zeros((h, h)),
        "w_out": np.zeros((g.n_outputs, h)),
        "is_root": np.zeros(h, bool),
        "neuron_mask": np.zeros(h, bool),
    }
    out["neuron_mask"][: len(order)] = True
    w = g.weights.astype(np.float32)
    for i, gene in enumerate(g):
        p = g.parent[i]
        if p < 0:  # a root: its own weight selects its output
            out["w_out"][g.roots.index(i), slot[gene.ref]] += w[i]
            out["is_root"][slot[gene.ref]] = True
            continue
        row = slot[g[p].ref]
        if gene.kind == GeneKind.INPUT:
            out["w_in"][row, gene.ref] += w[i]
        elif gene.kind == GeneKind.BIAS:
            out["bias"][row] += w[i]
        elif gene.kind == GeneKind.RECURRENT:
            out["w_rec"][row, slot[gene.ref]] += w[i]
        else:  # a sub-neuron or a forward jumper: a current-step edge
            out["w_ff"][row, slot[gene.ref]] += w[i]
    return out


# ------------------------------------------------------------------------------- network()
_network = jax.jit(kn.network)


@pytest.mark.slow
@given(g=genomes(), junk=hnp.arrays(np.float32, P, elements=st.floats(-9, 9, width=32)))
# Found by hypothesis: three recurrent genes on one edge cancel to 0.0016.
@example(
    g=Genome.parse("N0/3*0.0 R0*1.3125 R0*0.37656726255360384 R0*-1.6875 N1/1*0.0 B*0.0"),
    junk=np.zeros(P, np.float32),
)
def test_network_scatter_matches_numpy(g, junk):
    layout, w = one_layout(g)
    # Padding gene slots carry junk: network() must ignore it (gene_mask).
    params = jnp.where(layout.gene_mask, w, jnp.asarray(junk))
    net = _network(layout, params)
    want = dense_numpy(g, H, N_IN)
    # The same entries summed in absolute value: repeated genes add in float32 here and in
    # float64 there, so an entry whose terms cancel (1.3125 + 0.3766 - 1.6875 = 0.0016) is
    # off by up to a few float32 roundings of the terms' magnitude, not of the result.
    magnitude = dense_numpy(g.with_weights(np.abs(g.weights)), H, N_IN)
    eps = np.finfo(np.float32).eps
    for name, value in want.items():
        # XLA on CPU flushes float32 subnormals to zero, hence the floor at the smallest
        # normal.
        got = np.asarray(getattr(net, name))
        if not np.issubdtype(np.asarray(value).dtype, np.floating):
            np.testing.assert_array_equal(got, value, err_msg=name)
            continue
        atol = 4 * eps * np.abs(magnitude[name]) + np.finfo(np.float32).tiny
        assert np.all(np.abs(got - value) <= atol + 1e-6 * np.abs(value)), name
    assert net.sweeps == SWEEPS
    # Slot order is topological: a neuron reads only earlier slots at the current step.
    assert not np.any(np.triu(np.asarray(net.w_ff)))


def test_buffer_size_and_activation_errors():
    assert kn.buffer_size(4, 3, 2) == 4 * 3 + 4 + 2 * 16 + 2 * 4 + 1
    with pytest.raises(ValueError, match="unknown activation 'gelu'; known: abs, clamped"):
        kn.activation("gelu")


# ------------------------------------------------------------------------ step and rollout
@functools.cache
def _example():
    layout, w = one_layout(Genome.parse(EXAMPLE), neurons=8, genes=12, sweeps=3)
    rng = np.random.default_rng(0)
    xs = jnp.asarray(rng.normal(size=(5, 4, N_IN)), jnp.float32)  # [T, B, n_in]
    return layout, w, xs


@pytest.mark.slow
def test_rollout_matches_reference_and_steps():
    layout, w, xs = _example()
    net = kn.network(layout, w)
    # Jitted: one program, not one eager program per operation (jit against eager is the
    # test below).
    ys = jax.jit(functools.partial(kn.rollout, hidden="sigmoid", output="tanh"))(net, xs[:, 0])
    want = interpret(
        Genome.parse(EXAMPLE), np.asarray(xs[:, :1], np.float64), hidden="sigmoid", output="tanh"
    )
    np.testing.assert_allclose(np.asarray(ys), want[:, 0], rtol=1e-5, atol=1e-6)
    step = jax.jit(functools.partial(kn.step, hidden="sigmoid", output="tanh"))
    h = jnp.zeros(8)
    for t in range(xs.shape[0]):
        y, h = step(net, xs[t, 0], h)
        np.testing.assert_allclose(np.asarray(y), np.asarray(ys[t]), rtol=1e-6, atol=1e-7)


@pytest.mark.slow
# Activations not the default ones (tanh, identity), for both: jit and eager resolve the names
# alike. (tanh-identity was a second case: it compiled a third of this file's eager programs
# again for the same claim.)
@pytest.mark.parametrize(("hidden", "output"), [("relu", "sigmoid")])
def test_step_and_rollout_jit_equal_eager(hidden, output):
    layout, w, xs = _example()
    net = kn.network(layout, w)
    h0 = jnp.asarray(np.random.default_rng(1).normal(size=8), jnp.float32)
    h0 = jnp.where(layout.neuron_mask, h0, 0.0)
    step = functools.partial(kn.step, hidden=hidden, output=output)
    rollout = functools.partial(kn.rollout, hidden=hidden, output=output)
    for a, b in zip(step(net, xs[0, 0], h0), jax.jit(step)(net, xs[0, 0], h0), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(
        np.asarray(rollout(net, xs[:, 0], h0=h0)),
        np.asarray(jax.jit(rollout)(net, xs[:, 0], h0=h0)),
        rtol=1e-6,
        atol=1e-7,
    )


@pytest.mark.slow
def test_step_and_rollout_under_vmap():
    layout, w, xs = _example()
    net = kn.network(layout, w)
    hs = jnp.asarray(np.random.default_rng(2).normal(size=(4, 8)), jnp.float32)
    # Over examples (and states): vmap equals a Python loop.
    ys, h_next = jax.jit(jax.vmap(kn.step, in_axes=(None, 0, 0)))(net, xs[0], hs)
    step = jax.jit(kn.step)
    for b in range(4):
        y, h = step(net, xs[0, b], hs[b])
        np.testing.assert_allclose(np.asarray(ys[b]), np.asarray(y), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(np.asarray(h_next[b]), np.asarray(h), rtol=1e-6, atol=1e-7)
    # Over networks: a batched Layout and parameters, one stream each.
    g2 = Genome.parse("N0/2*0.5 I2*1 R0*-1 N5/1*2 B*0.3")
    layout2, w2 = one_layout(g2, neurons=8, genes=12, sweeps=3)
    layouts = jax.tree.map(lambda a, b: jnp.stack([a, b]), layout, layout2)
    run = jax.jit(jax.vmap(lambda lay, p, x: kn.rollout(kn.network(lay, p), x)))
    ys = run(layouts, jnp.stack([w, w2]), jnp.stack([xs[:, 0], xs[:, 1]]))
    # Each network by itself, jitted (one program for both: one bucket).
    alone_fn = jax.jit(lambda lay, p, x: kn.rollout(kn.network(lay, p), x))
    for k, (lay, p, x) in enumerate([(layout, w, xs[:, 0]), (layout2, w2, xs[:, 1])]):
        alone = alone_fn(lay, p, x)
        np.testing.assert_allclose(np.asarray(ys[k]), np.asarray(alone), rtol=1e-6, atol=1e-7)


@pytest.mark.slow
def test_no_retrace_for_new_values():
    chex.clear_trace_counter()

    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(layout, params, xs):
        return kn.rollout(kn.network(layout, params), xs)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def one_step(layout, params, x, h):
        return kn.step(kn.network(layout, params), x, h)

    layout, w, xs = _example()
    # Another structure in the same bucket: new values, same shapes and static fields.
    other = Genome.parse("N4/2*1 I1*1 F9*2 N9/1*1 R4*1")
    layout2, w2 = one_layout(other, neurons=8, genes=12, sweeps=3)
    for lay, p in [(layout, w), (layout2, w2), (layout, 2 * w)]:
        run(lay, p, xs[:, 0]).block_until_ready()
        jax.block_until_ready(one_step(lay, p, xs[0, 0], jnp.ones(8)))
    # The check can fail: a new sequence length is a new trace.
    with pytest.raises(AssertionError, match="traced > 1 times"):
        run(layout, w, xs[:3, 0])


# ---------------------------------------------------------------------------------- padding
@pytest.mark.slow
@given(
    g=genomes(max_neurons=3, n_outputs=2),  # one program (one per number of outputs)
    h_prev=hnp.arrays(np.float32, H, elements=st.floats(-3, 3, width=32)),
)
def test_padding_neurons_stay_zero(g, h_prev):
    # sigmoid(0) = 0.5: without the mask, the padding slots would light up.
    layout, w = one_layout(g)
    real = np.asarray(layout.neuron_mask)
    assert real.sum() == g.n_neurons < H
    y, h = _sigmoid_step(layout, w, jnp.ones(N_IN), jnp.asarray(h_prev))
    assert np.all(np.asarray(h)[~real] == 0.0)
    assert np.all(np.asarray(h)[real] > 0.0)
    assert np.all(np.isfinite(np.asarray(y)))


@jax.jit
def _sigmoid_step(layout, params, x, h_prev):
    return kn.step(kn.network(layout, params), x, h_prev, hidden="sigmoid", output="sigmoid")


@pytest.mark.slow
def test_empty_padding_rows_output_zero():
    from eant2_jax.evaluate import rollout_batch

    batch = [Genome.parse("N0/1*1 I0*1")] * 5  # five genomes: padded to six rows
    compiled = compile_genomes(batch, N_IN)
    assert compiled.layout.slot.shape[0] == 6 and compiled.count == 5
    xs = jnp.ones((3, 2, N_IN))
    ys = rollout_batch(compiled.layout, compiled.weights, xs, hidden="sigmoid", output="sigmoid")
    assert np.all(np.asarray(ys[5]) == 0.0)
    np.testing.assert_allclose(np.asarray(ys[0]), 1 / (1 + np.exp(-1.0)), rtol=1e-6)


# ------------------------------------------------------------ sweeps: written out or a loop
@functools.cache
def _step_fn(form: str, unroll: bool):
    """`kn.step_inline` vmapped over networks ``[N]``, then over their examples ``[E]``
    (inputs ``[E, n_in]`` shared by the networks, states ``[N, E, H]``), jitted. ``form``:
    "rule" (the non-finite rule in every product), "plain" (plain products and the
    finiteness check) or "compact" (every product a dot)."""

    def one(layout, params, x, h):
        net = kn.network(layout, params)
        if form == "plain":
            net = net.replace(reads=None)
        check, compact = form == "plain", form == "compact"
        return kn.step_inline(
            net, x, h, hidden="tanh", output="sigmoid", check=check, compact=compact,
            unroll=unroll,
        )  # fmt: skip

    per_net = jax.vmap(one, in_axes=(None, None, 0, 0))
    return jax.jit(jax.vmap(per_net, in_axes=(0, 0, None, 0)))


def _assert_loop_equals_written_out(layout, params, x, h):
    for form in ("rule", "plain", "compact"):
        written = _step_fn(form, True)(layout, params, x, h)
        looped = _step_fn(form, False)(layout, params, x, h)
        for a, b in zip(written, looped, strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=form)


@pytest.mark.slow
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the exact claim is the CPU's")
@fewer_examples(0.1)  # six programs, compiled once
@given(
    # One number of outputs (each number is six programs more): the outputs are read after
    # the sweeps, by the same product in both forms.
    g=genomes(n_outputs=2),
    x=hnp.arrays(np.float32, (4, N_IN), elements=st.floats(-3, 3, width=32)),
    h=hnp.arrays(np.float32, (4, H), elements=st.floats(-3, 3, width=32)),
    bad=st.sampled_from([None, np.nan, np.inf, -np.inf]),
)
def test_sweeps_as_a_loop_equal_the_sweeps_written_out(g, x, h, bad):
    """A step whose sweeps run as one loop (past `kn.SWEEPS_UNROLLED`) gives the bits of the
    same sweeps written out one after another, in each form of the step: with the
    non-finite rule (and a NaN or inf input of one example), plain with the finiteness
    check, and compact; on fresh random genomes (unrolled products), inputs and states."""
    layout, w = one_layout(g)
    if bad is not None:
        x = np.array(x)
        x[1, 0] = bad
    batch = jax.tree.map(lambda a: a[None], (layout, w, jnp.asarray(h)))
    _assert_loop_equals_written_out(batch[0], batch[1], jnp.asarray(x), batch[2])


@pytest.mark.slow
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the exact claim is the CPU's")
@pytest.mark.parametrize("seed", [0, 1])
def test_sweeps_as_a_loop_equal_the_sweeps_written_out_with_dots(seed):
    """The same on eight random networks of 16 neuron slots (products over neurons are
    dots, `netdot.UNROLL_MAX`), with finite inputs and with a NaN input."""
    layout, params, x, h = _batch_of_networks(seed, neurons=16)
    _assert_loop_equals_written_out(layout, params, x, h)
    _assert_loop_equals_written_out(layout, params, x.at[2, 1].set(np.nan), h)


@pytest.mark.slow
def test_deep_step_is_one_loop_whose_program_does_not_grow():
    """Up to `kn.SWEEPS_UNROLLED` sweeps a step writes each sweep out (the programs every
    run so far compiled); past it the sweeps are one loop, so a step of 3,072 sweeps lowers
    to a program as long as one of 96 (the next bucket past 64)."""
    g = Genome.parse(EXAMPLE)

    def lowered(sweeps: int) -> str:
        layout, w = one_layout(g, neurons=4, genes=12, sweeps=sweeps)
        per_example = jax.vmap(lambda lay, p, x, h: kn.step(kn.network(lay, p), x, h),
                               in_axes=(None, None, 0, 0))  # fmt: skip
        return (
            jax.jit(per_example).lower(layout, w, jnp.ones((4, N_IN)), jnp.zeros((4, 4))).as_text()
        )

    written, looped = lowered(kn.SWEEPS_UNROLLED), lowered(96)
    assert kn.SWEEPS_UNROLLED < 96
    assert written.count("stablehlo.while") == 0 < looped.count("stablehlo.while")
    assert len(written.splitlines()) > len(lowered(kn.SWEEPS_UNROLLED // 2).splitlines())
    assert len(lowered(3072).splitlines()) == len(looped.splitlines())


# -------------------------------------------------------------------------------- gradients
@pytest.mark.slow
@fewer_examples(0.1)
@given(
    # One compilation of the gradient per number of outputs: two (a cotangent per output,
    # summed over the outputs), so one program; in a bucket of 4 neuron slots and sweeps (the
    # gradient of a rollout is compiled in a fraction of the time of 6's).
    g=genomes(n_outputs=2, max_neurons=4),
    x=hnp.arrays(np.float32, (4, N_IN), elements=st.floats(-2, 2, width=32)),
    seed=st.integers(0, 2**32 - 1),
)
def test_grad_through_network_and_rollout(g, x, seed):
    """Finite, zero on padding genes, and equal to central differences of the reference.

    Smooth activations only (relu has a kink). The float64 central difference with step 1e-6
    is exact to ~1e-9; the float32 gradient to ~1e-5 relative, hence rtol 1e-3 on the
    directional derivative, with the size of the summed terms as absolute floor.
    """
    rng = np.random.default_rng(seed)
    layout, w = one_layout(g, neurons=4, sweeps=4)
    cot = rng.normal(size=(4, g.n_outputs))
    grad = np.asarray(_grad(layout, w, jnp.asarray(x), jnp.asarray(cot, jnp.float32)))
    assert np.all(np.isfinite(grad))
    assert np.all(grad[len(g) :] == 0.0)
    v = rng.normal(size=len(g))

    def ref_loss(wts):
        xs = x[:, None].astype(np.float64)
        y = interpret(g, xs, hidden="tanh", output="sigmoid", weights=wts)
        return float(np.sum(y[:, 0] * cot))

    w64 = np.asarray(w[: len(g)], np.float64)
    eps = 1e-6
    fd = (ref_loss(w64 + eps * v) - ref_loss(w64 - eps * v)) / (2 * eps)
    scale = float(np.sum(np.abs(v))) * float(np.sum(np.abs(cot)))
    np.testing.assert_allclose(grad[: len(g)] @ v, fd, rtol=1e-3, atol=1e-4 * scale)


@jax.jit
def _grad(layout, w, x, cot):
    """d/dp of sum(rollout(network(layout, p), x) * cot) at p = w."""

    def loss(p):
        ys = kn.rollout(kn.network(layout, p), x, hidden="tanh", output="sigmoid")
        return jnp.sum(ys * cot)

    return jax.grad(loss)(w)


# ------------------------------------------------------------- the product, short and long
def _stack_product(w, read, w_nf, v):
    """NumPy, entry by entry, what `netdot.dot` computes: the finite values through ``w``; a
    non-finite ``v[j]`` only into the rows that read it, times ``w_nf`` (float64 sums)."""
    out = np.zeros(w.shape[0])
    with np.errstate(all="ignore"):
        for i in range(w.shape[0]):
            for j in range(v.shape[0]):
                if np.isfinite(v[j]):
                    out[i] += float(w[i, j]) * float(v[j])
                elif read[i, j]:
                    out[i] += float(w_nf[i, j]) * float(v[j])
    return out


def _summed_product(w, v, reads):
    return jnp.sum(netdot.dot(w, reads, v))


# Jitted, as the engine runs them: a program per number of terms (and per form), where eager
# calls compiled one per operation.
_dot = jax.jit(netdot.dot)
_product_grad = jax.jit(jax.grad(_summed_product, argnums=(0, 1)))


@pytest.mark.slow
# One term, the most terms written out, the fewest as a dot, and a long dot (3 and 6 terms,
# two more unrolled sums between 1 and UNROLL_MAX, were cases here too).
@pytest.mark.parametrize("k", [1, kn.UNROLL_MAX, kn.UNROLL_MAX + 1, 40])
def test_product_short_unrolled_and_long_dot_match_numpy(k):
    """Both ways `netdot.dot` is written (an unrolled sum up to `netdot.UNROLL_MAX` terms, XLA's dot
    past it) against NumPy on fresh random inputs: finite ones, and ones with NaN and +-inf
    entries read by some rows and not others; with finite inputs the gradient is finite
    although ``w_nf`` holds NaNs."""
    rng = np.random.default_rng(1000 + k)
    rows = 5
    for trial in range(20):
        w = rng.normal(size=(rows, k)).astype(np.float32)
        read = rng.random((rows, k)) < 0.6
        w = np.where(read, w, 0).astype(np.float32)
        w_nf = np.where(read, np.where(rng.random((rows, k)) < 0.2, np.nan, w), 0)
        w_nf = w_nf.astype(np.float32)
        v = rng.normal(size=k).astype(np.float32)
        if trial % 2:
            special = rng.choice([np.nan, np.inf, -np.inf], size=k)
            v = np.where(rng.random(k) < 0.3, special, v).astype(np.float32)
        got = np.asarray(_dot(jnp.asarray(w), (jnp.asarray(read), jnp.asarray(w_nf)), v))
        want = _stack_product(w, read, w_nf, v)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_array_equal(np.isposinf(got), np.isposinf(want))
        np.testing.assert_array_equal(np.isneginf(got), np.isneginf(want))
        fin = np.isfinite(want)
        np.testing.assert_allclose(got[fin], want[fin], rtol=1e-5, atol=1e-5)
        v_fin = np.where(np.isfinite(v), v, 0).astype(np.float32)
        plain = np.asarray(_dot(jnp.asarray(w), None, jnp.asarray(v_fin)))
        want_plain = np.asarray(w, np.float64) @ v_fin.astype(np.float64)
        np.testing.assert_allclose(plain, want_plain, rtol=1e-5, atol=1e-5)
        if not trial % 2:  # finite v: the NaN entries of w_nf must not reach the gradient
            reads = (jnp.asarray(read), jnp.asarray(w_nf))
            grad = _product_grad(jnp.asarray(w), jnp.asarray(v), reads)
            assert all(np.all(np.isfinite(np.asarray(g))) for g in grad)


@pytest.mark.slow
@pytest.mark.parametrize("branch_min", [0, 10**12])
@pytest.mark.parametrize("nonfinite", [False, True])
def test_long_product_batched_matches_numpy(monkeypatch, branch_min, nonfinite):
    """A long product (a dot and the pass over its non-finite terms), vmapped over examples
    and networks and jitted, as the engine runs it, with the batch-level branch
    (``branch_min`` 0) and without it (a bound no batch reaches): NumPy's values, and with
    finite inputs the gradient of a plain product (differentiation takes the plain pass)."""
    monkeypatch.setattr(netdot, "BRANCH_MIN", branch_min)
    rng = np.random.default_rng(7 + 2 * nonfinite)
    nets, examples, rows, k = 3, 4, 5, kn.UNROLL_MAX + 3
    read = rng.random((nets, rows, k)) < 0.6
    w = np.where(read, rng.normal(size=(nets, rows, k)), 0).astype(np.float32)
    w_nf = np.where(read, np.where(rng.random((nets, rows, k)) < 0.2, np.nan, w), 0)
    w_nf = w_nf.astype(np.float32)
    v = rng.normal(size=(nets, examples, k)).astype(np.float32)
    if nonfinite:  # one example of one network only
        v[1, 2, [0, 5]] = [np.inf, np.nan]

    def product(w, read, w_nf, v):
        return netdot.dot(w, (read, w_nf), v)

    batched = jax.jit(jax.vmap(jax.vmap(product, in_axes=(None, None, None, 0))))
    got = np.asarray(batched(w, read, w_nf, v))
    for n in range(nets):
        for e in range(examples):
            want = _stack_product(w[n], read[n], w_nf[n], v[n, e])
            np.testing.assert_array_equal(np.isnan(got[n, e]), np.isnan(want))
            np.testing.assert_array_equal(np.isinf(got[n, e]), np.isinf(want))
            fin = np.isfinite(want)
            np.testing.assert_allclose(got[n, e][fin], want[fin], rtol=1e-5, atol=1e-5)
    if not nonfinite:
        loss = jax.jit(
            jax.grad(
                lambda w, v: jnp.sum(
                    jax.vmap(jax.vmap(product, in_axes=(None, None, None, 0)))(w, read, w_nf, v)
                ),
                argnums=(0, 1),
            )
        )
        grads = loss(w, v)
        want = jax.grad(lambda w, v: jnp.sum(jnp.einsum("nrk,nek->ner", w, v)), argnums=(0, 1))(
            w, v
        )
        for g, h in zip(grads, want, strict=True):
            np.testing.assert_allclose(np.asarray(g), np.asarray(h), rtol=1e-5, atol=1e-5)


# ------------------------------------------------- a CPU step: plain products, then the rule
def _batch_of_networks(seed: int, scale: float = 1.0, neurons: int = 8, sweeps: int = 4):
    """Eight random networks of one bucket (``neurons`` slots, ``sweeps`` sweeps), random
    states, and inputs ``[4 examples, N_IN]`` shared by every network, as a task batches
    them."""
    from bench.common import random_population

    genomes = random_population(seed, 8, 14, n_inputs=N_IN, n_outputs=2)
    bucket = Bucket(neurons=neurons, genes=24, sweeps=sweeps)
    compiled = compile_genomes(genomes, N_IN, bucket=bucket)
    rng = np.random.default_rng(seed)
    params = jnp.asarray(compiled.weights * scale, jnp.float32)
    x = jnp.asarray(rng.normal(size=(4, N_IN)), jnp.float32)
    h = jnp.asarray(rng.normal(size=(8, 4, neurons)), jnp.float32)
    return compiled.layout, params, x, h


def _assert_same_values(got, want):
    """The same NaN and +-inf entries, the finite ones equal to float32 rounding (the rule's
    branch may sum in another order, `netdot.dot`'s compact form)."""
    for a, b in zip(got, want, strict=True):
        a, b = np.asarray(a), np.asarray(b)
        for kind in (np.isnan, np.isposinf, np.isneginf):
            np.testing.assert_array_equal(kind(a), kind(b))
        fin = np.isfinite(b)
        np.testing.assert_allclose(a[fin], b[fin], rtol=1e-5, atol=1e-6)


def _batched_step(layout, params, x, h, *, rule: bool, hidden="tanh", output="identity"):
    """``[nets, examples]`` outputs and states: vmapped over networks, then over examples
    sharing each network (the network's arrays unbatched there, the inputs unbatched over
    networks); ``rule`` runs `kn.step_inline` with the non-finite rule, inline."""
    return _batched_step_fn(rule, hidden, output)(layout, params, x, h)


@functools.cache
def _batched_step_fn(rule: bool, hidden: str, output: str):
    def one(lay, p, x, h):
        net = kn.network(lay, p)
        if rule:
            return kn.step_inline(net, x, h, hidden=hidden, output=output)
        return kn.step(net, x, h, hidden=hidden, output=output)

    per_net = jax.vmap(one, in_axes=(None, None, 0, 0))
    return jax.jit(jax.vmap(per_net, in_axes=(0, 0, None, 0)))


@pytest.mark.slow
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the branch is taken on CPUs only")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cpu_step_equals_the_rule_with_finite_and_non_finite_values(seed):
    """On a CPU `kn.step` runs plain products over the whole batch and the non-finite rule
    only when some value entering a product was not finite. Against `kn.step_inline` with the
    rule inline, on fresh random networks, states and inputs: finite values agree to float32
    rounding (plain products may contract into fused multiply-adds); a NaN or inf input of
    one example, and an overflow to inf inside a network with finite inputs, take the rule:
    the same NaN and inf entries. The plain products alone would differ there (checked), so
    a branch that never took the rule fails this test."""
    layout, params, x, h = _batch_of_networks(seed)
    fast = _batched_step(layout, params, x, h, rule=False)
    ruled = _batched_step(layout, params, x, h, rule=True)
    for a, b in zip(fast, ruled, strict=True):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)

    bad = x.at[seed % 4, seed % N_IN].set([np.nan, np.inf, -np.inf][seed])
    _assert_same_values(
        _batched_step(layout, params, bad, h, rule=False),
        _batched_step(layout, params, bad, h, rule=True),
    )

    # Finite inputs, weights of 1e20 and identity neurons: sums overflow to inf mid-network.
    big, params_big, x_big, _ = _batch_of_networks(seed, scale=1e20)
    x_big = x_big * 1e20
    args = (big, params_big, x_big, h, "identity", "identity")
    got = _batched_step(*args[:4], rule=False, hidden="identity", output="identity")
    want = _batched_step(*args[:4], rule=True, hidden="identity", output="identity")
    _assert_same_values(got, want)

    ys = _plain_identity_step(*args[:4])[0]
    assert not np.array_equal(np.isnan(np.asarray(ys)), np.isnan(np.asarray(want[0])))


@jax.jit
def _plain_identity_step(layout, params, x, h):
    """`kn.step_inline` with plain products only (no rule), identity neurons, batched as
    `_batched_step` (one program for every seed of the test above and the fused one's)."""

    def plain(lay, p, x, h):
        net = kn.network(lay, p).replace(reads=None)
        return kn.step_inline(net, x, h, hidden="identity", output="identity")

    per_net = jax.vmap(plain, in_axes=(None, None, 0, 0))
    return jax.vmap(per_net, in_axes=(0, 0, None, 0))(layout, params, x, h)


def _cuda_text(args, hidden="tanh", output="identity") -> str:
    """The CUDA lowering of `_batched_step` (traced as a GPU backend would, on any machine;
    the caller sets ``jax.default_backend``)."""
    # A function of its own: jit's trace cache would hand back the CPU's traces.
    fn = _batched_step_fn.__wrapped__(False, hidden, output)
    return fn.trace(*args).lower(lowering_platforms=("cuda",)).as_text()


def _conditionals(text: str) -> int:
    return text.count("stablehlo.case") + text.count("stablehlo.if")


_TRITON = "xla.gpu.triton"


@pytest.mark.slow
@pytest.mark.parametrize("neurons", [8, 16])
def test_gpu_step_branches_only_large_batches_of_dot_networks(monkeypatch, neurons):
    """Off the CPU (traced as a GPU backend would) a network of at most `kn.UNROLL_MAX`
    neurons runs as one fused kernel (`netfused`), whatever the batch; without that kernel
    (``kn.FUSED`` off) the rule stays inline with no conditional. Larger networks keep the
    rule inline below `kn.GPU_BRANCH_MIN` product terms; above it they branch once,
    passthrough first, and the values (run here on the CPU, in the GPU's branch order) are
    the rule's: finite ones to rounding, NaN and inf entries exactly, with a non-finite
    input and without."""
    layout, params, x, h = _batch_of_networks(5, neurons=neurons)
    args = (layout, params, x, h)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")

    small = neurons <= kn.UNROLL_MAX
    assert _cuda_text(args).count(_TRITON) == small
    monkeypatch.setattr(kn, "FUSED", False)
    assert _conditionals(_cuda_text(args)) == 0  # 8 x 4 examples: a small batch
    monkeypatch.setattr(kn, "GPU_BRANCH_MIN", 0)
    assert _conditionals(_cuda_text(args)) == (not small)
    bad = x.at[1, 2].set(np.nan)
    fast = _batched_step_fn.__wrapped__(False, "tanh", "identity")  # traced under the above
    # The rule inline (`kn.step_inline`) reads no setting above: the CPU test's program,
    # compiled once for both tests where the bucket is theirs (8 slots).
    ruled = _batched_step_fn(True, "tanh", "identity")
    for inputs in (x, bad):
        args = (layout, params, inputs, h)
        _assert_same_values(fast(*args), ruled(*args))


# ----------------------------------------------- a GPU step: the batch as one fused kernel
_build_networks = jax.jit(jax.vmap(kn.network))  # one program, not one per eager operation


def _fused_args(seed: int, neurons: int, *, scale: float = 1.0, shared: bool = True):
    """`netfused.step_batch`'s network arguments of `_batch_of_networks`'s eight networks,
    with their inputs ``[1 or 8, 4, N_IN]`` and states ``[8, 4, neurons]``."""
    layout, params, x, h = _batch_of_networks(seed, scale=scale, neurons=neurons)
    if scale != 1.0:
        x = x * scale
    nets = _build_networks(layout, params)
    xs = x[None] if shared else jnp.broadcast_to(x, (8, *x.shape)) + jnp.arange(8.0)[:, None, None]
    return (layout, params, x if shared else xs, h), nets, xs


@functools.partial(jax.jit, static_argnames=("hidden", "output", "block"))
def _fused(nets, xs, h, hidden="tanh", output="identity", block=None):
    """`netfused.step_batch` in Pallas' interpreter (jitted: interpreting is slow to trace)."""
    return netfused.step_batch(
        nets.w_in, nets.bias, nets.w_ff, nets.w_rec, nets.w_out, nets.reads, nets.is_root,
        nets.neuron_mask, xs, h, sweeps=nets.sweeps, hidden=hidden, output=output,
        block=block, interpret=True,
    )  # fmt: skip


@functools.partial(jax.jit, static_argnames=("hidden", "output", "shared"))
def _ruled(layout, params, x, h, hidden="tanh", output="identity", shared=True):
    """`kn.step_inline` with the rule inline, vmapped over networks and their examples."""

    def one(lay, p, xs, hs):
        net = kn.network(lay, p)
        return jax.vmap(lambda a, b: kn.step_inline(net, a, b, hidden=hidden, output=output))(
            xs, hs
        )

    return jax.vmap(one, in_axes=(0, 0, None if shared else 0, 0))(layout, params, x, h)


@pytest.mark.slow
# 6 slots pad to Triton's 8, UNROLL_MAX = 12 to 16 (7 was a third case: padded to 8 as 6 is).
@pytest.mark.parametrize(("neurons", "shared"), [(6, False), (kn.UNROLL_MAX, True)])
def test_fused_step_equals_the_rule(neurons, shared):
    """`netfused.step_batch` (run in Pallas' interpreter) against `kn.step_inline` with the
    non-finite rule inline, on fresh random networks, states and inputs: finite values to
    float32 rounding (its sums may be ordered otherwise); a NaN or +-inf input of one
    example takes the kernel's rule: the same NaN and inf entries. Inputs shared by every
    network and inputs of each network's own; blocks smaller than the examples."""
    seed = neurons + 10 * shared
    (layout, params, x, h), nets, xs = _fused_args(seed, neurons, shared=shared)
    want = _ruled(layout, params, x, h, shared=shared)
    # Blocks of every example of a network (None), and smaller ones, in one case: a program
    # each.
    for block in (None, 2) if not shared else (None,):
        got = _fused(nets, xs, h, block=block)
        for a, b in zip(got, want, strict=True):
            assert np.all(np.isfinite(np.asarray(a)))
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    for value in (np.nan, np.inf, -np.inf):
        bad_x = x.at[..., seed % 4, seed % N_IN].set(value)
        bad_xs = xs.at[..., seed % 4, seed % N_IN].set(value)
        _assert_same_values(
            _fused(nets, bad_xs, h), _ruled(layout, params, bad_x, h, shared=shared)
        )
    bad_h = h.at[1, 2, neurons - 1].set(np.nan)
    _assert_same_values(_fused(nets, xs, bad_h), _ruled(layout, params, x, bad_h, shared=shared))


@pytest.mark.slow
def test_fused_step_takes_the_rule_when_a_value_inside_overflows():
    """Finite inputs, weights of 1e20 and identity neurons: sums overflow to inf inside
    the networks, where the kernel's plain products alone would give NaN (checked); the
    kernel finds it from the final states and takes the rule: the same NaN and inf
    entries as `kn.step_inline` with the rule."""
    (layout, params, x, h), nets, xs = _fused_args(3, 8, scale=1e20)
    # The rule inline, batched as the CPU test batches it: that test's program.
    want = _batched_step(layout, params, x, h, rule=True, hidden="identity", output="identity")
    assert not np.all(np.isfinite(np.asarray(want[1])))
    _assert_same_values(_fused(nets, xs, h, "identity", "identity"), want)
    plain = _plain_identity_step(layout, params, x, h)  # the networks of `nets`, built again
    assert not np.array_equal(np.isnan(np.asarray(plain[0])), np.isnan(np.asarray(want[0])))


@pytest.mark.slow
def test_fused_step_lowers_for_cuda_with_each_activation():
    """Every activation of `netfused.ACTIVATIONS` lowers to one Triton kernel (the CUDA
    lowering, on any machine), as the hidden and as the output activation: the names listed
    there are the ones Triton lowers. The kernel is lowered by itself (a tenth of the time of
    the whole step's lowering); that `kn.step` hands a batch of such networks to this kernel
    is test_gpu_step_branches_only_large_batches_of_dot_networks's and
    test_fused_step_applies_only_where_it_can's."""
    _, nets, xs = _fused_args(7, 8)
    h = jnp.zeros((8, 4, 8))

    def lowered(activation: str) -> str:
        def kernel(nets, xs, h):
            return netfused.step_batch(
                nets.w_in, nets.bias, nets.w_ff, nets.w_rec, nets.w_out, nets.reads,
                nets.is_root, nets.neuron_mask, xs, h, sweeps=nets.sweeps, hidden=activation,
                output=activation,
            )  # fmt: skip

        return jax.jit(kernel).trace(nets, xs, h).lower(lowering_platforms=("cuda",)).as_text()

    for activation in sorted(netfused.ACTIVATIONS):
        assert lowered(activation).count(_TRITON) == 1, activation


@pytest.mark.slow
def test_fused_step_applies_only_where_it_can(monkeypatch):
    """The kernel is left out (the rule stays inline) for buckets of fewer than 8 neuron
    slots (`kn.FUSED_NEURONS`), for a registered activation Triton is not known to lower,
    and for a batch whose networks vary at an inner level (examples outside, networks
    inside); a network's own arrays may be shared at an outer level."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert _cuda_text(_fused_args(2, 6)[0]).count(_TRITON) == 0
    (layout, params, x, h), _, _ = _fused_args(2, 8)
    eant2_jax.register_activation(
        "test_fused_softsign", lambda a: a / (1 + jnp.abs(a)), lambda a: a / (1 + np.abs(a))
    )
    try:
        text = _cuda_text((layout, params, x, h), "test_fused_softsign")
    finally:
        eant2_jax.kernels.activations.ACTIVATIONS.pop("test_fused_softsign")
    assert text.count(_TRITON) == 0

    def examples_outside(lay, p, xs, hs):
        def per_example(a, b):
            return jax.vmap(
                lambda lay_, p_, b_: kn.step(kn.network(lay_, p_), a, b_), in_axes=(0, 0, 0)
            )(lay, p, b)

        return jax.vmap(per_example, in_axes=(0, 1))(xs, hs)

    args = (layout, params, x, h)
    text = jax.jit(examples_outside).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count(_TRITON) == 0
    # One layout shared by the eight weight vectors (a structure's candidates).
    one = jax.tree.map(lambda a: a[0], layout)
    shared_layout = jax.jit(jax.vmap(lambda p, hs: jax.vmap(
        lambda a, b: kn.step(kn.network(one, p), a, b))(x, hs)))  # fmt: skip
    text = shared_layout.trace(params, h).lower(lowering_platforms=("cuda",)).as_text()
    assert text.count(_TRITON) == 1


@pytest.mark.slow
def test_step_gradient_is_the_rules():
    """Differentiation of `kn.step` takes the rule's own path: the gradient of a batched loss
    in the parameters equals the one through `kn.step_inline` with the rule. (Second order works
    the same way; its compile of a minute on 2 cores is left to `jax.hessian`'s users.)
    Networks of 4 neuron slots and 3 sweeps (seed 3's networks have at most 4 neurons and
    depth 3): the gradients' programs compile in under half the time of 8 slots and 4
    sweeps', on the same path."""
    layout, params, x, h = _batch_of_networks(3, neurons=4, sweeps=3)
    layout, params, h = jax.tree.map(lambda a: a[:2], (layout, params, h))

    def loss(p, rule):
        ys, hs = _batched_step(layout, p, x, h, rule=rule)
        return jnp.sum(jnp.sin(ys)) + jnp.sum(hs**2)

    got, want = (jax.jit(jax.grad(lambda p, r=rule: loss(p, r)))(params) for rule in (False, True))
    assert np.all(np.isfinite(np.asarray(got)))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-4, atol=1e-5)


# --------------------------------------------------------------------- threefry written out
@pytest.mark.slow
def test_threefry_draws_equal_jax_random():
    """`kernels.threefry`'s ``fold_in`` and scalar ``normal`` give `jax.random`'s bits on
    fresh keys and data (the full uint32 range), jitted and vmapped, with partitionable
    threefry (JAX's default) and without; on a CPU the program has no loop left (JAX's
    own lowering there is a loop over the rounds)."""
    from eant2_jax.kernels import threefry

    rng = np.random.default_rng()
    keys = jax.random.split(jax.random.key(int(rng.integers(2**31))), 2048)
    data = jnp.asarray(rng.integers(0, 2**32, size=2048, dtype=np.uint64).astype(np.uint32))
    for partitionable in (True, False):
        with jax.threefry_partitionable(partitionable):
            got = jax.jit(jax.vmap(threefry.fold_in))(keys, data)
            want = jax.jit(jax.vmap(jax.random.fold_in))(keys, data)
            np.testing.assert_array_equal(jax.random.key_data(got), jax.random.key_data(want))
            z = jax.jit(jax.vmap(threefry.normal))(keys)
            want_z = jax.jit(jax.vmap(lambda k: jax.random.normal(k, ())))(keys)
            np.testing.assert_array_equal(np.asarray(z), np.asarray(want_z))
    if jax.default_backend() == "cpu":
        text = jax.jit(jax.vmap(lambda k, d: threefry.normal(threefry.fold_in(k, d))))
        assert "while" not in text.lower(keys, data).as_text()
    # Another implementation's keys are jax.random's business.
    rbg = jax.random.split(jax.random.key(1, impl="rbg"), 4)
    np.testing.assert_array_equal(
        jax.random.key_data(jax.vmap(threefry.fold_in)(rbg, data[:4])),
        jax.random.key_data(jax.vmap(jax.random.fold_in)(rbg, data[:4])),
    )


# ---------------------------------------------------------------------- packaging: imports
def _run_python(code: str, *, python: str = sys.executable, cwd: Path) -> str:
    """Run ``code`` in a fresh interpreter from ``cwd`` (not the repository, whose own
    ``kernels/`` folder would otherwise be importable as a top-level ``kernels``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["JAX_PLATFORMS"] = "cpu"
    done = subprocess.run(
        [python, "-c", textwrap.dedent(code)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, f"stdout:\n{done.stdout}\nstderr:\n{done.stderr}"
    return done.stdout


def test_kernels_resolve_to_this_repository():
    assert Path(kn.__file__).resolve() == KERNELS / "network.py"
    assert Path(eant2_jax.kernels.__file__).resolve() == KERNELS / "__init__.py"


@pytest.fixture(scope="module")
def fresh_interpreter(tmp_path_factory) -> dict[str, str]:
    """What one fresh interpreter, started outside the repository, reports for the two tests
    below (one interpreter start and JAX import for both): first ``kernels/`` loaded as a
    standalone package, before anything imported eant2_jax, and the eant2_jax or top-level
    ``kernels`` modules that this loaded; then eant2_jax imported, and where its kernels
    came from."""
    out = _run_python(
        f"""
        import importlib, importlib.util, pathlib, sys
        folder = pathlib.Path({str(KERNELS)!r})
        spec = importlib.util.spec_from_file_location(
            "standalone_kernels", folder / "__init__.py", submodule_search_locations=[str(folder)]
        )
        package = importlib.util.module_from_spec(spec)
        sys.modules["standalone_kernels"] = package
        spec.loader.exec_module(package)
        for path in sorted(folder.glob("*.py")):
            if path.stem != "__init__":
                importlib.import_module("standalone_kernels." + path.stem)
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in ("eant2_jax", "kernels"))
        print("leaked:", leaked)
        # Then the package, as a user imports it (the standalone copy has other names).
        import eant2_jax, eant2_jax.kernels.network as n
        print("package:", eant2_jax.__file__)
        print("network:", n.__file__)
        # Nothing in eant2_jax imports a top-level `kernels` (ours, or PyPI's).
        print("imported:", "kernels" in sys.modules)
        spec = importlib.util.find_spec("kernels")
        print("top_level:", spec.origin if spec else None)
        """,
        cwd=tmp_path_factory.mktemp("fresh"),
    )
    return dict(line.split(": ", 1) for line in out.split("\n") if ": " in line)


@pytest.mark.slow
def test_kernels_resolve_in_a_fresh_interpreter(fresh_interpreter):
    report = fresh_interpreter
    package, network = report["package"], report["network"]
    imported, top_level = report["imported"], report["top_level"]
    package_dir = Path(package).resolve().parent
    if package_dir == REPO / "eant2_jax":  # the editable install: the repository's folder
        assert Path(network).resolve() == KERNELS / "network.py"
    else:  # a regular install: the copy next to the package
        assert Path(network).resolve() == package_dir / "kernels" / "network.py"
    assert imported == "False"
    assert top_level == "None" or not Path(top_level).resolve().is_relative_to(REPO)


@pytest.mark.slow
def test_kernels_import_nothing_from_the_package(fresh_interpreter):
    # Statically: no import names eant2_jax, and no relative import leaves kernels/.
    for path in sorted(KERNELS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level <= 1, f"{path.name}: relative import out of kernels/"
                names = [node.module or ""]
            else:
                continue
            assert not any(n.split(".")[0] == "eant2_jax" for n in names), path.name
    # Dynamically: kernels/ loaded as a standalone package (every module of it) in a fresh
    # interpreter; eant2_jax never got imported, nor a top-level kernels.
    assert fresh_interpreter["leaked"] == "[]", fresh_interpreter["leaked"]


# ----------------------------------------------------------------------- packaging: a wheel
def _copy_sources(dest: Path) -> None:
    """The files a wheel is built from: pyproject.toml, its readme/license, its packages."""
    import shutil

    meta = tomllib.loads((REPO / "pyproject.toml").read_text())
    project, tool = meta["project"], meta["tool"]["setuptools"]
    files = ["pyproject.toml"]
    readme = project.get("readme")
    files += [readme] if isinstance(readme, str) else [readme["file"]] if readme else []
    license_ = project.get("license", {})
    files += [license_["file"]] if isinstance(license_, dict) and "file" in license_ else []
    files += project.get("license-files", [])
    for f in files:
        shutil.copy2(REPO / f, dest / f)
    package_dir = tool.get("package-dir", {})
    folders = {package_dir.get(p, p.replace(".", "/")) for p in tool["packages"]}
    for folder in sorted(folders):
        if not (dest / folder).exists():
            shutil.copytree(
                REPO / folder, dest / folder, ignore=shutil.ignore_patterns("__pycache__")
            )


def _expected_in_wheel() -> set[str]:
    """Every module and data file the wheel must hold, read off pyproject.toml's packages,
    package-dir and package-data (so a new module or task file is covered automatically)."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    package_dir, package_data = tool.get("package-dir", {}), tool.get("package-data", {})
    expected = set()
    for package in tool["packages"]:
        folder = REPO / package_dir.get(package, package.replace(".", "/"))
        patterns = ["*.py", *package_data.get(package, [])]
        files = {f for pattern in patterns for f in folder.glob(pattern) if f.is_file()}
        expected |= {f"{package.replace('.', '/')}/{f.name}" for f in files}
    return expected


@pytest.mark.slow
def test_wheel_installs_kernels_inside_the_package(tmp_path):
    """Build a wheel, install it in a fresh venv, import from outside the repository."""
    src, dist, venv, elsewhere = (tmp_path / d for d in ("src", "dist", "venv", "elsewhere"))
    for d in (src, dist, elsewhere):
        d.mkdir()
    # Build from a copy, so the build leaves no build/ or *.egg-info in the working tree.
    _copy_sources(src)
    build = subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--outdir", str(dist), str(src)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    (wheel,) = dist.glob("eant2_jax-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert "eant2_jax/kernels/network.py" in names
    # Every stage and application module, and the servo task's model, ship in the wheel.
    for module in ("tuning", "exploitation", "pruning", "config", "multirun", "app/cli"):
        assert f"eant2_jax/{module}.py" in names, module
    assert "eant2_jax/tasks/arm.xml" in names
    missing = _expected_in_wheel() - set(names)
    assert not missing, f"not in the wheel: {sorted(missing)}"
    assert not any(n.startswith("kernels/") for n in names), "a top-level kernels/ was packaged"
    # Metadata a public index shows: the one version, classifiers, extras, the readme.
    (meta_name,) = [n for n in names if n.endswith(".dist-info/METADATA")]
    meta = zipfile.ZipFile(wheel).read(meta_name).decode()
    for field in (
        f"Version: {eant2_jax.__version__}\n",
        "Requires-Python: >=3.11\n",
        "License-Expression: Apache-2.0\n",
        "License-File: LICENSE\n",
        "Classifier: Programming Language :: Python :: 3.12\n",
        "Classifier: Typing :: Typed\n",
        "Provides-Extra: test\n",
        "Description-Content-Type: text/markdown\n",
        "Keywords: ",
    ):
        assert field in meta, field
    assert "# eant2_jax" in meta  # the readme is the long description
    top_level = [n for n in names if n.endswith(".dist-info/top_level.txt")]
    if top_level:
        assert zipfile.ZipFile(wheel).read(top_level[0]).decode().split() == ["eant2_jax"]

    # A fresh venv that sees this interpreter's packages (jax and the other dependencies: no
    # network) through a path file. ``--system-site-packages`` would see the BASE
    # interpreter's packages instead, which inside a venv have no jax. Site directories
    # listed in a path file are plain path entries: their own .pth files (this checkout's
    # editable install among them) are not run, so eant2_jax can only come from the wheel.
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120
    )
    python = str(venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python"))
    purelib = _run_python(
        "import sysconfig; print(sysconfig.get_paths()['purelib'])", python=python, cwd=elsewhere
    ).strip()
    import site

    outer = [d for d in site.getsitepackages() if Path(d).is_dir()]
    (Path(purelib) / "outer-site.pth").write_text("\n".join(outer) + "\n")
    install = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q",
         "--target", purelib, str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )  # fmt: skip
    assert install.returncode == 0, install.stdout[-3000:] + install.stderr[-3000:]
    out = _run_python(
        """
        import sys
        import numpy as np
        import eant2_jax
        import eant2_jax.kernels.network as n
        print(sys.prefix)
        print(eant2_jax.__file__)
        print(n.__file__)
        y = eant2_jax.evaluate("N0/2*2 I0*0.5 R0*1", np.array([[[1.0]], [[2.0]], [[3.0]]]))
        print(np.asarray(y).ravel().tolist())
        print("kernels" in sys.modules)
        import eant2_jax.tasks.servo  # (MJX may print a line of its own on import)
        print("arm:", eant2_jax.tasks.servo.ARM_XML)
        for name, module in sorted(sys.modules.items()):
            if name.split(".")[0] == "eant2_jax":
                print("module:", module.__file__)
        """,
        python=python,
        cwd=elsewhere,
    )
    prefix, package, network, y, imported = out.split("\n")[:5]
    tagged = [line.split(": ", 1) for line in out.split("\n") if ": " in line]
    (arm,) = [f for tag, f in tagged if tag == "arm"]
    modules = [f for tag, f in tagged if tag == "module"]
    assert Path(prefix).resolve() == venv.resolve()
    # Every eant2_jax module imported (evaluate's and the servo task's dependencies) is the
    # installed copy; none came from this checkout.
    assert len(modules) > 10, modules
    for f in (package, network, arm, *modules):
        assert Path(f).resolve().is_relative_to(venv.resolve()), f
    assert Path(arm).is_file()
    assert Path(network).resolve().parent == Path(package).resolve().parent / "kernels"
    assert y == "[1.0, 3.0, 6.0]"
    assert imported == "False"


@pytest.mark.slow
def test_network_build_is_deterministic_by_construction():
    """No float scatter with repeated indices in the build, batched as the engine batches it
    (structures x candidates): a GPU would add such entries in any order, and XLA's
    deterministic mode would sort them, 3.6x slower on the servo task (docs/benchmarks.md).
    A genome with genes on one entry (R0 three times) exercises the repeated slots."""
    from compiles import nondeterministic_scatters

    g = Genome.parse("N0/3*0.0 R0*1.3125 R0*0.37656726255360384 R0*-1.6875 N1/1*0.0 B*0.0")
    layout, w = one_layout(g)
    layouts = jax.tree.map(lambda a: jnp.stack([a, a]), layout)
    params = jnp.stack([jnp.stack([w, 2 * w, -w])] * 2)  # [2 structures, 3 candidates, P]
    build = jax.vmap(jax.vmap(kn.network, in_axes=(None, 0)))
    assert nondeterministic_scatters(jax.make_jaxpr(build)(layouts, params)) == []
    # The repeated entry is the sum of its genes (as a float32 add, to the rounding).
    net = jax.jit(build)(layouts, params)  # one program, not one per eager operation
    want = dense_numpy(g, H, N_IN)["w_rec"]
    np.testing.assert_allclose(np.asarray(net.w_rec[1, 1]), 2 * want, rtol=1e-6, atol=1e-6)
