"""ONNX export (eant2_jax.export_onnx) against the library, run by onnxruntime.

Every comparison is on fresh random inputs: the ONNX graph steps the streams with its
explicit state (h_prev -> h) and must give the library's outputs (`LoadedNetwork`, the
kernels' float32 evaluation). Tolerance: both are float32 with different summation orders and
activation implementations (XLA against onnxruntime's), so agreement is to float32 rounding
propagated through the network: |onnx - library| <= 1e-5 + 1e-5 |library|. The maxima
measured are in docs/export.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hypothesis.strategies as st
import jax
import numpy as np
import onnx
import onnxruntime as ort
import pytest
from hypothesis import given
from strategies import fewer_examples, genomes
from test_pole import DPNV_GENOME

import eant2_jax
from eant2_jax.app.cli import main
from eant2_jax.compiler import networks
from eant2_jax.export import dense
from eant2_jax.export_onnx import MIN_OPSET, ONNX_ACTIVATIONS, save, to_onnx
from eant2_jax.genome import GeneKind, Genome
from eant2_jax.genomefile import GenomeFile, GenomeFileError
from eant2_jax.kernels import activations
from eant2_jax.loaded import LoadedNetwork
from eant2_jax.tasks import pole
from eant2_jax.tasks.pole_physics import observe

ROOT = Path(__file__).resolve().parent.parent
SERVO = ROOT / "bench" / "inputs" / "servo-h100-none-s1-gen13.genome"
# XOR with tanh hidden neurons and an identity output (the xor task's activations):
# h1 ~ OR, h2 ~ AND, y = (h1 - h2) / 2.
XOR_GENOME = "N0/3*1.0 N1/3*0.5 I0*20 I1*20 B*-10 N2/3*-0.5 I0*20 I1*20 B*-30 B*0.0"
RTOL = ATOL = 1e-5


def session(model: onnx.ModelProto) -> ort.InferenceSession:
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])


def run_onnx(spec: GenomeFile, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``[T, M, n_in] -> [T, M, n_out]`` by the exported step, its state carried (zeros at
    first); also the last state ``[M, H]`` (None for a feed-forward network)."""
    model = to_onnx(spec)
    sess = session(model)
    names = [i.name for i in model.graph.input]
    h = (
        np.zeros((xs.shape[1], len(dense(spec)["neurons"])), np.float32)
        if "h_prev" in names
        else None
    )
    ys = []
    for x in xs:
        if h is None:
            (y,) = sess.run(["y"], {"x": x})
        else:
            y, h = sess.run(["y", "h"], {"x": x, "h_prev": h})
        ys.append(y)
    return np.stack(ys), h


def max_diff(spec: GenomeFile, xs: np.ndarray) -> float:
    """Compare the ONNX graph with the library over ``xs`` (asserting agreement, NaN where
    NaN); return the largest absolute difference."""
    want = np.asarray(LoadedNetwork(spec)(xs))
    got, _ = run_onnx(spec, xs.astype(np.float32))
    assert got.shape == want.shape and got.dtype == np.float32
    if spec.output == "exp":
        # exp multiplies its argument's rounding by the argument: at y = 2.4e16 (argument
        # 37.7) a few float32 ulps of the argument are 1.5e-5 of y. Compared on the
        # argument, as strictly as every other output (NaN where NaN, equal infinities).
        with np.errstate(divide="ignore", invalid="ignore"):
            np.testing.assert_allclose(np.log(got), np.log(want), rtol=RTOL, atol=ATOL)
    else:
        np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)
    both = np.isfinite(want)  # an infinity matched by an equal infinity differs by nothing
    return float(np.max(np.abs(got[both] - want[both]), initial=0.0))


@pytest.mark.slow
def test_xor_network_matches_and_solves():
    spec = GenomeFile.from_task(Genome.parse(XOR_GENOME), eant2_jax.tasks.make("xor"), name="xor")
    patterns = np.array([[[0, 0], [0, 1], [1, 0], [1, 1]]], np.float32)
    got, state = run_onnx(spec, patterns)
    assert state is None  # feed-forward: no state input
    assert ((got.ravel() > 0.5) == [False, True, True, False]).all()
    xs = np.random.default_rng(1).normal(size=(1, 256, 2))
    assert max_diff(spec, xs) <= 1e-5


@pytest.mark.slow
def test_recurrent_pole_controller_state_in_and_out():
    """The dpnv controller of test_pole (it balances 100,000 steps with recurrent jumpers):
    outputs over 40 steps of 16 streams, and the state the graph hands back equals the
    library's neuron outputs (slot order: the model's ``neurons`` metadata)."""
    task = eant2_jax.tasks.make("dpnv")
    spec = GenomeFile.from_task(Genome.parse(DPNV_GENOME), task, name="dpnv")
    assert any(g.kind == GeneKind.RECURRENT for g in spec.genome)
    xs = np.random.default_rng(2).normal(0, 0.3, size=(40, 16, 3)).astype(np.float32)
    assert max_diff(spec, xs) <= 1e-5
    net = LoadedNetwork(spec)
    state = net.initial_state(16)
    for x in xs:
        _, state = net.step(x, state)
    _, h = run_onnx(spec, xs)
    n = h.shape[1]
    np.testing.assert_allclose(h, np.asarray(state)[:, :n], rtol=RTOL, atol=ATOL)
    model = to_onnx(spec)
    props = {p.key: p.value for p in model.metadata_props}
    assert props["neurons"] == str(dense(spec)["neurons"]) and props["task"] == "dpnv"
    assert [i.name for i in model.graph.input] == ["x", "h_prev"]
    assert [o.name for o in model.graph.output] == ["y", "h"]


@pytest.mark.slow
def test_pole_controller_on_its_own_trajectory():
    """The dpnv controller balancing the double pole (the library's closed loop,
    `pole.trajectory`, 500 steps): the ONNX graph, fed the observations of that trajectory
    and its own state, gives the actions the library took."""
    task = eant2_jax.tasks.make("dpnv")
    spec = GenomeFile.from_task(Genome.parse(DPNV_GENOME), task, name="dpnv")
    net = jax.tree.map(lambda a: a[0], networks([spec.genome], 3))
    states, actions = jax.jit(pole.trajectory, static_argnames="steps")(
        task, net, task.start, steps=500
    )
    before = np.concatenate([np.asarray(task.start)[None], np.asarray(states)[:-1]])
    obs = np.asarray(jax.vmap(lambda s: observe(s, velocities=task.velocities))(before), np.float32)
    assert np.all(np.abs(np.asarray(states)[:, 2]) < 0.2)  # the first pole stays up
    got, _ = run_onnx(spec, obs[:, None, :])
    np.testing.assert_allclose(got[:, 0, 0], np.asarray(actions), rtol=RTOL, atol=ATOL)


@pytest.mark.slow
def test_servo_network_from_a_run():
    """A servo network evolved by a run (10 inputs, 3 outputs, forward and recurrent
    jumpers), 30 steps of 32 streams."""
    spec = GenomeFile.read(SERVO)
    assert (spec.n_inputs, spec.n_outputs) == (10, 3)
    xs = np.random.default_rng(3).normal(size=(30, 32, 10))
    assert max_diff(spec, xs) <= 1e-4


@pytest.mark.slow
# Each example compiles its network: a few random structures (each activation alone is
# checked by test_every_builtin_activation_against_its_reference).
@fewer_examples(0.03, least=3)
@given(
    genome=genomes(n_inputs=3, max_outputs=2, max_neurons=5),
    hidden=st.sampled_from(sorted(ONNX_ACTIVATIONS)),
    output=st.sampled_from(sorted(ONNX_ACTIVATIONS)),
    seed=st.integers(0, 2**32 - 1),
)
def test_random_networks_every_activation_and_nonfinite_inputs(genome, hidden, output, seed):
    """Random structures (recurrent and forward jumpers), every activation, inputs with NaN
    and infinities in them: the graph keeps the kernels' rule (a non-finite value reaches
    only the neurons that read it), so NaN lands where the library's does."""
    spec = GenomeFile(genome, hidden=hidden, output=output, n_inputs=3)
    rng = np.random.default_rng(seed)
    xs = rng.normal(size=(4, 8, 3)).astype(np.float32)
    xs[rng.random(xs.shape) < 0.05] = rng.choice([np.nan, np.inf, -np.inf])
    max_diff(spec, xs)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(activations.BUILTIN))
def test_every_builtin_activation_against_its_reference(name):
    """A one-neuron network ``y = act(x0)``: the graph's activation against the registry's
    JAX function (what the kernels apply) on a grid through the clipping points, large
    values and NaN."""
    assert name in ONNX_ACTIVATIONS
    spec = GenomeFile(Genome.parse("N0/1*1.0 I0*1.0"), hidden="tanh", output=name)
    a = np.concatenate([np.linspace(-8, 8, 321), [-100.0, 100.0, 0.0, np.nan]])
    a = a.astype(np.float32)
    (y,) = session(to_onnx(spec)).run(["y"], {"x": a[:, None]})
    want = np.asarray(activations.get(name).jax(jax.numpy.asarray(a)))
    np.testing.assert_allclose(y[:, 0], want, rtol=RTOL, atol=ATOL)


@pytest.mark.slow
def test_refusals_are_one_line(tmp_path):
    g = Genome.parse("N0/2*1.0 I0*0.5 I1*-0.5")
    with pytest.raises(GenomeFileError, match="names no activations"):
        to_onnx(GenomeFile(g))
    with pytest.raises(ValueError, match="opset"):
        to_onnx(GenomeFile(g, hidden="tanh", output="tanh"), opset=13)
    name = "hd_export_square2"
    activations.register(name, lambda a: 2 * a * a, lambda a: 2 * a * a, overwrite=True)
    try:
        with pytest.raises(GenomeFileError, match="no ONNX form"):
            to_onnx(GenomeFile(g, hidden=name, output="identity"))
    finally:
        # Nothing was compiled with it (no stale program to drop): popping it is enough,
        # and jax.clear_caches() would cost later tests their compiled programs.
        activations.ACTIVATIONS.pop(name)


def test_opset_and_save_never_overwrite(tmp_path):
    spec = GenomeFile(Genome.parse("N0/2*1.0 I0*0.5 I1*-0.5"), hidden="tanh", output="tanh")
    model = to_onnx(spec, opset=18)
    assert model.opset_import[0].version == 18 and MIN_OPSET == 17
    path = save(model, tmp_path / "net.onnx")
    assert onnx.load(str(path)).graph.node  # reads back
    with pytest.raises(FileExistsError, match="already exists"):
        save(model, path)
    (tmp_path / "link.onnx").symlink_to(tmp_path / "target")
    with pytest.raises(FileExistsError):
        LoadedNetwork(spec).to_onnx(tmp_path / "link.onnx")
    assert not (tmp_path / "target").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.onnx", "net.onnx"]


@pytest.mark.slow
def test_cli_export_onnx(tmp_path, capsys):
    genome = tmp_path / "servo.genome"
    genome.write_text(SERVO.read_text())
    assert main(["export", str(genome), "--format", "onnx"]) == 0
    out = tmp_path / "servo.genome.onnx"
    spec = GenomeFile.read(SERVO)
    xs = np.random.default_rng(4).normal(size=(1, 8, 10)).astype(np.float32)
    sess = session(onnx.load(str(out)))
    n_h = len(dense(spec)["neurons"])
    (y,) = sess.run(["y"], {"x": xs[0], "h_prev": np.zeros((8, n_h), np.float32)})
    np.testing.assert_allclose(y, np.asarray(LoadedNetwork(spec)(xs))[0], rtol=RTOL, atol=ATOL)
    assert main(["export", str(genome), "--format", "onnx"]) == 2  # exists: refused
    assert capsys.readouterr().err.strip().count("\n") == 0
    assert main(["export", str(genome), "--format", "onnx", "--force"]) == 0


def test_missing_extra_is_one_line(monkeypatch, tmp_path, capsys):
    """Without onnx installed (made unimportable here) the export names the extra, and the
    command says so in one line (exit 2)."""
    monkeypatch.setitem(sys.modules, "onnx", None)
    spec = GenomeFile(Genome.parse("N0/2*1.0 I0*0.5 I1*-0.5"), hidden="tanh", output="tanh")
    with pytest.raises(ImportError, match=r"pip install 'eant2-jax\[export\]'"):
        to_onnx(spec)
    spec.write(tmp_path / "net.genome")
    assert main(["export", str(tmp_path / "net.genome"), "--format", "onnx"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "eant2-jax[export]" in err
    assert not (tmp_path / "net.genome.onnx").exists()


@pytest.mark.slow
def test_cli_file_without_header_takes_activations(tmp_path, capsys):
    """bench/inputs/servo-none-s1-best.genome has no header: eant2 export asks for
    --activations in one line, and with them exports the network the library loads so."""
    genome = tmp_path / "old.genome"
    genome.write_text((SERVO.parent / "servo-none-s1-best.genome").read_text())
    assert main(["export", str(genome), "--format", "onnx"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--activations HIDDEN,OUTPUT" in err
    assert main(["export", str(genome), "--format", "onnx", "--activations", "tanh"]) == 2
    args = ["export", str(genome), "--format", "onnx", "--activations", "tanh,identity"]
    assert main(args) == 0
    spec = GenomeFile.read(genome).with_activations("tanh", "identity")
    model = onnx.load(str(tmp_path / "old.genome.onnx"))
    xs = np.random.default_rng(6).normal(size=(1, 8, 10)).astype(np.float32)
    n_h = len(dense(spec)["neurons"])
    (y,) = session(model).run(["y"], {"x": xs[0], "h_prev": np.zeros((8, n_h), np.float32)})
    np.testing.assert_allclose(y, np.asarray(LoadedNetwork(spec)(xs))[0], rtol=RTOL, atol=ATOL)
