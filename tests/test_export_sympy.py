"""sympy export (eant2_jax.export_sympy) against the library.

The expressions, lambdified with NumPy (float64), must give the library's float32 outputs
(`LoadedNetwork`) on fresh random inputs, up to float32 rounding propagated through the
network: |sympy - library| <= 1e-5 + 1e-5 |library| (the maxima measured are in
docs/export.md). Each activation alone is checked against its float64 NumPy reference
(kernels/activations.py) to 1e-12.
"""

from __future__ import annotations

import contextlib
import signal
import sys

import hypothesis.strategies as st
import numpy as np
import pytest
import sympy
from docs_outputs import ROOT, check
from hypothesis import given
from strategies import fewer_examples, genomes
from test_export_onnx import XOR_GENOME
from test_pole import DPNV_GENOME

from eant2_jax.app.cli import main
from eant2_jax.exploration import initial_genome, mutate
from eant2_jax.export import dense
from eant2_jax.export_sympy import to_sympy
from eant2_jax.genome import Genome
from eant2_jax.genomefile import GenomeFile, GenomeFileError
from eant2_jax.kernels import activations
from eant2_jax.loaded import LoadedNetwork

RTOL = ATOL = 1e-5


def outputs(net, xs: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
    """The lambdified outputs ``[M, n_out]`` for inputs ``[M, n_in]`` (and state)."""
    cols = [xs[:, j].astype(np.float64) for j in range(xs.shape[1])]
    if state is not None:
        cols += [state[:, j].astype(np.float64) for j in range(state.shape[1])]
    ys = net.function()(*cols)
    return np.stack([np.broadcast_to(np.asarray(y, np.float64), xs.shape[:1]) for y in ys], -1)


def grown_network(seed: int, n_neurons: int = 20) -> Genome:
    """A feed-forward network grown from the minimal start (4 inputs, 2 outputs) by the
    library's own mutations, with random weights."""
    rng = np.random.default_rng(seed)
    g, next_id = initial_genome(rng, 4, 2), 2
    while g.n_neurons < n_neurons:
        op = str(rng.choice(["add_subnetwork", "add_bias"], p=[0.8, 0.2]))
        child = mutate(rng, g, op, n_inputs=4, next_id=next_id)
        if child is not None:
            g, next_id = child, next_id + 1
    return g.with_weights(rng.normal(0, 1, g.n_params))


@pytest.mark.slow
def test_twenty_neuron_network_grown_by_mutation():
    """The fast lane's 20-neuron network (depth > 2): outputs of the inputs alone,
    lambdified, against the library on 256 fresh random inputs."""
    genome = grown_network(20)
    assert genome.n_neurons == 20 and genome.depth() > 2
    spec = GenomeFile(genome, hidden="tanh", output="identity", n_inputs=4)
    net = to_sympy(spec)
    xs = np.random.default_rng(21).normal(size=(256, 4)).astype(np.float32)
    want = np.asarray(LoadedNetwork(spec)(xs))
    np.testing.assert_allclose(outputs(net, xs), want, rtol=RTOL, atol=ATOL)
    assert net.latex(substitute=True).count("\\tanh") == 18  # the hidden neurons, once each


@pytest.mark.slow
# Two random 20-neuron networks (each a compile and a deep sympy substitution; the test
# above checks a third, grown by mutation).
@fewer_examples(0.02, least=2)
@given(
    genome=genomes(
        n_inputs=4, n_outputs=2, min_neurons=20, max_neurons=20, recurrent=False, max_id=40
    ),
    hidden=st.sampled_from(["tanh", "sigmoid", "relu"]),
    seed=st.integers(0, 2**32 - 1),
)
def test_twenty_neuron_feed_forward_network(genome, hidden, seed):
    """A 20-neuron feed-forward network: its output expressions (inputs only, every neuron
    substituted), lambdified, equal the library's outputs; LaTeX comes from them."""
    assert genome.n_neurons == 20
    spec = GenomeFile(genome, hidden=hidden, output="identity", n_inputs=4)
    net = to_sympy(spec)
    assert net.state == () and len(net.equations) == 20 + 2
    assert all(e.free_symbols <= set(net.inputs) for e in net.outputs)
    xs = np.random.default_rng(seed).normal(size=(128, 4)).astype(np.float32)
    want = np.asarray(LoadedNetwork(spec)(xs))
    got = outputs(net, xs)
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)
    tex = net.latex()
    assert tex.startswith("\\begin{aligned}") and tex.count("&=") == 22
    assert net.latex(substitute=True).count("&=") == 2


# 20 neurons, depth 11: a spine of sigmoids, each over a sigmoid of one input, a bias and the
# next, every weight positive. In the substituted output every exponent is provably negative
# and sympy's LaTeX printer asked is_constant() of each: a simplify() of the whole nest below,
# for hours (the test above drew such networks).
SIGMOID_SPINE = (
    "N0/1*0.5 N2/3*0.3 N3/2*0.4 I2*0.5 B*0.25 B*0.5 N4/3*0.5 N5/2*0.6 I0*0.5 B*0.25 B*0.5 "
    "N6/3*0.7 N7/2*0.8 I2*0.5 B*0.25 B*0.5 N8/3*0.9 N9/2*0.1 I0*0.5 B*0.25 B*0.5 "
    "N10/3*0.2 N11/2*0.3 I2*0.5 B*0.25 B*0.5 N12/3*0.4 N13/2*0.5 I0*0.5 B*0.25 B*0.5 "
    "N14/3*0.6 N15/2*0.7 I2*0.5 B*0.25 B*0.5 N16/3*0.8 N17/2*0.9 I0*0.5 B*0.25 B*0.5 "
    "N18/2*0.1 N19/2*0.2 I2*0.5 B*0.25 B*0.5 N1/2*0.5 I1*0.5 B*0.25"
)


@contextlib.contextmanager
def time_limit(seconds: float):
    """TimeoutError in the main thread once ``seconds`` have passed (SIGALRM)."""

    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_latex_of_nested_positive_sigmoids_is_bounded(monkeypatch):
    """LaTeX of `SIGMOID_SPINE` in seconds, and the same as sympy's own printer gives once
    told the answer it would have spent hours on: none of the exponents is constant."""
    spec = GenomeFile(Genome.parse(SIGMOID_SPINE), hidden="sigmoid", output="identity")
    net = to_sympy(spec)
    assert len(net.neurons) == 20
    with time_limit(10):
        tex = {sub: net.latex(substitute=sub, digits=None) for sub in (False, True)}
        assert net.latex(substitute=True).count("e^{") == 18  # the sigmoids, once each
    monkeypatch.setattr(sympy.Expr, "is_constant", lambda e, *a, **k: not e.free_symbols)
    for sub, rows in (
        (False, [(eq.lhs, eq.rhs) for eq in net.equations]),
        (True, [(sympy.Symbol(f"y{k}"), e) for k, e in enumerate(net.outputs)]),
    ):
        lines = [f"{sympy.latex(lhs)} &= {sympy.latex(rhs)}" for lhs, rhs in rows]
        assert tex[sub] == "\\begin{aligned}\n" + " \\\\\n".join(lines) + "\n\\end{aligned}"


@pytest.mark.parametrize("name", sorted(activations.BUILTIN))
def test_every_builtin_activation_against_its_numpy_reference(name):
    spec = GenomeFile(Genome.parse("N0/1*1.0 I0*1.0"), hidden="tanh", output=name)
    a = np.concatenate([np.linspace(-8, 8, 321), [-100.0, 100.0, 0.0]])
    got = outputs(to_sympy(spec), a[:, None])[:, 0]
    want = activations.get(name).numpy(a)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_recurrent_step_with_its_state():
    """The dpnv controller of test_pole: one step from a random state, the state symbols
    ``hp<id>`` fed with the library's state slots (slot order of `export.dense`)."""
    spec = GenomeFile(Genome.parse(DPNV_GENOME), hidden="tanh", output="tanh", n_inputs=3)
    net = to_sympy(spec)
    slot = {n: i for i, n in enumerate(dense(spec)["neurons"])}
    assert sorted(str(s) for s in net.state) == ["hp1", "hp2", "hp3"]
    loaded = LoadedNetwork(spec)
    assert loaded.to_latex() == net.latex() and loaded.to_sympy().equations == net.equations
    rng = np.random.default_rng(5)
    xs = rng.normal(0, 0.3, size=(64, 3)).astype(np.float32)
    state = rng.normal(0, 0.3, size=(64, loaded.initial_state().shape[0])).astype(np.float32)
    want, _ = loaded.step(xs, state)
    cols = state[:, [slot[int(str(s)[2:])] for s in net.state]]
    np.testing.assert_allclose(outputs(net, xs, cols), want, rtol=RTOL, atol=ATOL)


def test_xor_latex_and_text():
    spec = GenomeFile(Genome.parse(XOR_GENOME), hidden="tanh", output="identity", n_inputs=2)
    net = to_sympy(spec)
    assert net.text().splitlines()[-1] == "y0 = 1.0*h0"
    assert "\\tanh" in net.latex() and "20.0 x_{0}" in net.latex()
    f = net.function()
    ys = [f(*p)[0] for p in ((0, 0), (0, 1), (1, 0), (1, 1))]
    assert [y > 0.5 for y in ys] == [False, True, True, False]


def test_registered_activation_is_an_undefined_function():
    name = "hd_export_twice"
    activations.register(name, lambda a: 2 * a, lambda a: 2 * a, overwrite=True)
    try:
        spec = GenomeFile(Genome.parse("N0/1*1.0 I0*0.5"), hidden=name, output=name)
        net = to_sympy(spec)
        assert net.outputs[0].atoms(sympy.core.function.AppliedUndef)
        f = net.function(modules=[{name: lambda a: 2 * a}, "numpy"])
        assert f(3.0)[0] == 3.0
    finally:
        # Nothing was compiled with it (no stale program to drop): popping it is enough,
        # and jax.clear_caches() would cost later tests their compiled programs.
        activations.ACTIVATIONS.pop(name)
    with pytest.raises(GenomeFileError, match="names no activations"):
        to_sympy(GenomeFile(Genome.parse("N0/1*1.0 I0*0.5")))


def test_missing_extra_is_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "sympy", None)
    spec = GenomeFile(Genome.parse("N0/1*1.0 I0*0.5"), hidden="tanh", output="tanh")
    with pytest.raises(ImportError, match=r"pip install 'eant2-jax\[export\]'"):
        to_sympy(spec)


def test_cli_export_sympy_and_latex(tmp_path, capsys):
    genome = tmp_path / "xor.genome"
    GenomeFile(Genome.parse(XOR_GENOME), hidden="tanh", output="identity", n_inputs=2).write(genome)
    assert main(["export", str(genome), "--format", "latex"]) == 0
    assert (tmp_path / "xor.genome.tex").read_text().startswith("\\begin{aligned}")
    assert main(["export", str(genome), "--format", "sympy", "--substitute"]) == 0
    text = (tmp_path / "xor.genome.sympy.txt").read_text()
    assert text.startswith("y0 = ") and text.count("\n") == 1
    capsys.readouterr()
    assert main(["export", str(genome), "--format", "latex", "--out", "-"]) == 0
    assert capsys.readouterr().out.startswith("\\begin{aligned}")
    assert main(["export", str(genome), "--format", "latex"]) == 2  # exists: refused
    assert "already exists" in capsys.readouterr().err


@pytest.mark.slow
def test_docs_export_page_prints_what_it_shows():
    """docs/export.md's agreement table and commands, run again (tests/docs_outputs.py)."""
    wrong = check(ROOT / "docs" / "export.md")
    assert not wrong, "\n\n".join(
        f"--- shown\n{ex.shown}--- printed now\n{got}" for ex, got in wrong
    )
