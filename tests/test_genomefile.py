"""Genome files (header + genes), load, and the exports, against the NumPy reference.

Tolerances: the loaded network runs the kernels in float32, so against the float64
reference (on float32-rounded weights and inputs) it is judged as in test_evaluate (1e-4 of
the output scale). The formula is float64 arithmetic like the reference, summed in another
order: 1e-12.
"""

from __future__ import annotations

import ast
import builtins
import json
import os
import re
import threading
from pathlib import Path
from unittest import mock

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import fewer_examples, genomes
from test_evaluate import assert_close, reference

import eant2_jax
from eant2_jax import export
from eant2_jax.compiler import networks
from eant2_jax.genome import Genome
from eant2_jax.genomefile import GenomeFile, GenomeFileError, read_text
from eant2_jax.kernels import activations
from eant2_jax.loaded import load
from eant2_jax.reference import interpret

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = "N0/3*1.0 F2*0.3 N1/2*0.5 I0*1 I1*-2 R0*0.7 N2/2*-1.2 B*0.1 I2*0.4"
XOR = np.array([[0.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 1.0]])
ACTS = st.sampled_from(sorted(activations.BUILTIN))


def _spec(text=EXAMPLE, hidden="sigmoid", output="tanh", n_inputs=4, **kw) -> GenomeFile:
    return GenomeFile(Genome.parse(text), hidden=hidden, output=output, n_inputs=n_inputs, **kw)


# ------------------------------------------------------------------------------ the format
@given(g=genomes(), hidden=ACTS, output=ACTS, extra=st.integers(0, 3), task=st.none() | st.text())
def test_header_round_trip(g, hidden, output, extra, task):
    spec = GenomeFile(g, hidden, output, g.n_inputs + extra, task, {"n": 3} if task else None)
    text = spec.to_text()
    assert text.startswith("# eant2-genome {") and text.count("\n") == 2
    assert GenomeFile.parse(text) == spec
    assert Genome.parse(text) == g  # any reader of the bare text form reads the file too


@pytest.mark.slow
def test_file_without_header_stays_readable(tmp_path):
    path = tmp_path / "best.genome"
    path.write_text(EXAMPLE + "\n")  # as run directories held it before the header
    spec = GenomeFile.read(path)
    assert spec.genome == Genome.parse(EXAMPLE) and not spec.has_header
    with pytest.raises(GenomeFileError, match="no header naming its activations"):
        load(path)
    net = load(path, hidden="tanh", output="identity")
    x = np.random.default_rng(0).normal(size=(3, 2, 3))
    np.testing.assert_array_equal(net(x), eant2_jax.evaluate(EXAMPLE, x)[0])


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("# eant2-genome {oops", "header is corrupt: Expecting property name"),
        ('# eant2-genome {"format": 2, "hidden": "tanh", "output": "tanh"}', "format 1"),
        ('# eant2-genome {"format": 1, "hidden": "tanh"}', "no activation name 'output'"),
        (
            '# eant2-genome {"format": 1, "hidden": "tanh", "output": "tanh", "n_outputs": 1}',
            "says 1 outputs, the genome has 2",
        ),
        (
            '# eant2-genome {"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": 2}',
            "n_inputs 2 is below the 3 inputs",
        ),
    ],
)
def test_bad_headers_are_named(tmp_path, header, message):
    path = tmp_path / "bad.genome"
    path.write_text(header + "\n" + EXAMPLE + "\n")
    with pytest.raises(GenomeFileError, match=message) as e:
        GenomeFile.read(path)
    assert str(path) in str(e.value)


def test_explicit_activations_must_agree_with_the_header(tmp_path):
    path = _spec().write(tmp_path / "a.genome")
    with pytest.raises(GenomeFileError, match="hidden activation is 'sigmoid', not 'tanh'"):
        load(path, hidden="tanh")
    assert load(path, hidden="sigmoid").spec == _spec()
    with pytest.raises(FileExistsError):
        _spec().write(path)  # nothing is overwritten unless asked


def test_write_never_follows_a_link(tmp_path):
    target = tmp_path / "bashrc"
    target.write_text("keep\n")
    (tmp_path / "a.genome").symlink_to(target)
    (tmp_path / "b.genome").symlink_to(tmp_path / "absent")
    for name in ("a.genome", "b.genome"):
        with pytest.raises(FileExistsError):
            _spec().write(tmp_path / name)
    _spec().write(tmp_path / "a.genome", overwrite=True)
    assert target.read_text() == "keep\n" and not (tmp_path / "a.genome").is_symlink()
    assert GenomeFile.read(tmp_path / "a.genome") == _spec()
    assert not (tmp_path / "absent").exists()


def test_unknown_activation_in_a_header(tmp_path):
    path = _spec(hidden="mine").write(tmp_path / "a.genome")
    with pytest.raises(ValueError, match="unknown activation 'mine'"):
        load(path)


# -------------------------------------------------------------------------- the loaded net
@pytest.mark.slow
def test_loaded_network_shapes_and_state(tmp_path):
    net = load(_spec().write(tmp_path / "a.genome"))
    rng = np.random.default_rng(1)
    xs = rng.normal(size=(5, 3, 4))
    ys = np.asarray(net(xs))
    want = eant2_jax.evaluate(EXAMPLE, xs, hidden="sigmoid", output="tanh")[0]
    np.testing.assert_array_equal(ys, want)  # the same kernels, the same program shapes
    np.testing.assert_array_equal(net(xs[0]), ys[0])  # [M, n_in]: one step each
    np.testing.assert_array_equal(net(xs[0, 1]), ys[0, 1])  # [n_in]: one step
    h = net.initial_state(3)
    for t in range(5):  # closed loop: the state carried by hand
        y, h = net.step(xs[t], h)
        np.testing.assert_allclose(y, ys[t], rtol=1e-6, atol=1e-6)
    y1, _ = net.step(xs[0, 2], net.initial_state())
    np.testing.assert_allclose(y1, ys[0, 2], rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match=r"n_in = 4, got shape \(5, 3, 3\)"):
        net(xs[..., :3])


@pytest.mark.slow
def test_reload_reproduces_the_task_outputs_exactly(tmp_path):
    """What a run's task computes (its predict, through the compiler's route) equals what the
    reloaded file computes, bit for bit, with non-default activations on both neuron kinds;
    the defaults would give other outputs (the bug headers fix)."""
    task = eant2_jax.tasks.make("xor", hidden="sigmoid", output="sigmoid")
    g = Genome.parse("N0/4*1.5 N1/2*-3 I0*2 I1*2 I0*1.2 I1*1.1 B*-0.4")
    spec = GenomeFile.from_task(g, task, name="xor", options={"hidden": "sigmoid"})
    net = load(spec.write(tmp_path / "best.genome"))
    run_outputs = task.predict(jax.tree.map(lambda a: a[0], networks([g], task.n_inputs)))
    np.testing.assert_array_equal(net(XOR), run_outputs[0])
    defaults = eant2_jax.evaluate(g, XOR[None])[0, 0]
    assert np.max(np.abs(defaults - run_outputs[0])) > 0.1


@pytest.mark.slow
def test_run_writes_a_header_and_reload_matches_the_run(tmp_path):
    """End to end: a sigmoid XOR run, its best.genome reloaded with no arguments gives the
    outputs whose cost the run recorded."""
    task = eant2_jax.tasks.make("xor", hidden="sigmoid", output="sigmoid")
    config = eant2_jax.EANT2Config(
        population=4, exploit=eant2_jax.ExploitConfig(max_iters=150, pruner="none")
    )
    meta = {"task": "xor", "task_options": {"hidden": "sigmoid", "output": "sigmoid"}}
    result = eant2_jax.run(
        task, key=jax.random.key(0), config=config, generations=0, out=tmp_path / "r", meta=meta
    )
    net = load(tmp_path / "r" / "best.genome")
    assert net.spec.task == "xor" and net.spec.task_options == meta["task_options"]
    assert net.genome == result.best
    y = np.asarray(net(XOR), np.float64).ravel()
    cost = np.mean(np.square(y - [0, 1, 1, 0]))
    np.testing.assert_allclose(cost, result.generations[-1].best_cost, rtol=1e-6)


# ------------------------------------------------------------------------------- exports
# Activations whose float32 error stays within test_evaluate's tolerance through a few layers
# (sin and gauss scale their input by 5, log is ill-conditioned near 0: each is compared
# with the reference on its own in test_activations).
TAME = st.sampled_from(["tanh", "sigmoid", "relu", "identity", "elu", "selu", "clamped", "hat"])


@pytest.mark.slow
@fewer_examples(0.05)
@given(g=genomes(n_inputs=3, max_neurons=4), hidden=TAME, seed=st.integers(0, 99))
def test_jax_export_matches_reference(g, hidden, seed):
    """The exported function against the NumPy reference; it imports nothing of eant2_jax.
    (Each example compiles its own jitted module: a few random structures suffice, the
    rule does not depend on their size.)"""
    spec = GenomeFile(g, hidden=hidden, output="tanh", n_inputs=3)
    x = np.random.default_rng(seed).uniform(-1, 1, size=(3, 2, 3)).astype(np.float32)
    real_import = builtins.__import__

    def guarded(name, globals=None, *args, **kw):
        package = (globals or {}).get("__package__") or ""
        assert not (name + package).startswith("eant2_jax"), f"the export imported {name}"
        return real_import(name, globals, *args, **kw)

    source = export.to_jax_source(spec)
    namespace: dict = {}
    with mock.patch.object(builtins, "__import__", guarded):
        exec(source, namespace)  # noqa: S102
        got = np.asarray(namespace["network"](x))
    modules = {
        getattr(v, "__module__", None) or getattr(v, "__name__", "") for v in namespace.values()
    }
    assert not any(str(m).startswith("eant2_jax") for m in modules), modules
    assert_close(got[None], reference([g], x, hidden, "tanh"))


def test_json_round_trip_and_dense_tensors():
    spec = _spec(task="xor", task_options={"hidden": "sigmoid"})
    doc = json.loads(json.dumps(export.to_json(spec)))
    assert export.from_json(doc) == spec
    assert doc["weights"] == spec.genome.weights.tolist() and len(doc["genes"]) == 9
    assert doc["genes"][0] == {"kind": "neuron", "ref": 0, "arity": 3, "weight": 1.0}
    dense = doc["dense"]
    assert dense["neurons"] == [2, 1, 0] and dense["sweeps"] == 2
    # genome.md's worked example, without its padding slot
    assert dense["w_in"] == [[0, 0, pytest.approx(0.4), 0], [1, -2, 0, 0], [0, 0, 0, 0]]
    assert dense["w_out"] == [[0, 0, 1.0], [pytest.approx(-1.2), 0, 0]]
    assert dense["is_root"] == [True, False, True]
    for bad in ({"genome": EXAMPLE}, {"format": True, "genome": EXAMPLE}, {"format": 1}, []):
        with pytest.raises(GenomeFileError, match="not an eant2 network document"):
            export.from_json(bad)
    with pytest.raises(GenomeFileError, match="not an eant2 network document"):
        export.from_json(doc | {"genome": 5})  # a TypeError from Genome.parse before
    with pytest.raises(GenomeFileError, match="task must be a string"):
        export.from_json(doc | {"task": 5})


@given(g=genomes(n_inputs=3, recurrent=False, max_neurons=5), hidden=ACTS, output=ACTS)
def test_formula_matches_reference(g, hidden, output):
    spec = GenomeFile(g, hidden=hidden, output=output, n_inputs=3)
    text = export.formula(spec)
    x = np.random.default_rng(0).uniform(-1, 1, size=(1, 4, 3))
    names = {f"x{j}": x[0, :, j] for j in range(3)}
    names |= {n: activations.get(n).numpy for n in activations.names()}
    with np.errstate(over="ignore", invalid="ignore"):  # cube of cube of ... may overflow
        exec(text, names)  # noqa: S102
        got = np.stack([names[f"y{k}"] * np.ones(4) for k in range(g.n_outputs)], -1)
        want = interpret(g, x, hidden=hidden, output=output)[0]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_formula_of_the_docs_example_and_its_refusals():
    """docs/genome.md's example file and the formula printed for it, as the code gives them."""
    blocks = re.findall(r"```[a-z]*\n(.*?)```", (ROOT / "docs" / "genome.md").read_text(), re.S)
    (file_text,) = [b for b in blocks if b.startswith("# eant2-genome")]
    spec = GenomeFile.parse(file_text)
    assert spec == _spec("N0/3*1.5 N1/2*-3 I0*2 I1*2 I0*1.2 B*-0.4", output="identity",
                         n_inputs=2, task="xor", task_options={"hidden": "sigmoid"})  # fmt: skip
    assert spec.to_text() == file_text  # the header is written exactly so
    text = export.formula(spec)
    assert text == (
        "# sigmoid(a) = 1 / (1 + exp(-a))\n"
        "h1 = sigmoid(2.0 * x0 + 2.0 * x1)\n"
        "h0 = -3.0 * h1 + 1.2 * x0 - 0.4\n"
        "y0 = 1.5 * h0\n"
    )
    assert text in blocks
    with pytest.raises(GenomeFileError, match="recurrent"):
        export.formula(_spec())
    with pytest.raises(GenomeFileError, match="3 neurons, more than max_neurons=2"):
        export.formula(_spec(EXAMPLE.replace("R0", "I0")), max_neurons=2)
    with pytest.raises(GenomeFileError, match="names no activations"):
        export.formula(GenomeFile(Genome.parse(EXAMPLE)))


def test_export_of_an_activation_without_source():
    activations.register("twice", lambda a: 2 * a, lambda a: 2 * a)
    try:
        with pytest.raises(GenomeFileError, match="'twice' has no source"):
            export.to_jax_source(_spec(hidden="twice"))
        assert "twice(" in export.formula(_spec(EXAMPLE.replace("R0", "I0"), hidden="twice"))
    finally:
        activations.ACTIVATIONS.pop("twice")


def test_top_level_names():
    assert eant2_jax.load is load and eant2_jax.GenomeFile is GenomeFile


# ------------------------------------------------------------------- trust boundaries
def _hostile_tasks(marker: Path) -> list[str]:
    """Task names that try to leave the generated module's docstring or its lines."""
    run = f'__import__("os").system("touch {marker}")'
    return [
        f'x""" + {run} + """',  # closes the docstring (what repr() let through)
        f"x''' + {run} + '''",
        f'x"""\n{run}\n"""',
        f'x\\\\""" + {run} + \\',  # backslashes
        f"x\u2028{run}\u2029\x85\r",  # line ends Python's tokenizer or a viewer may take
        f"__import__('os').system('touch {marker}')",
    ]


@pytest.mark.slow
def test_to_jax_of_a_hostile_header_runs_nothing(tmp_path):
    """A genome file's strings never reach generated code: for each hostile task name
    (written by an attacker into a real header), the exported source holds none of it, its
    only string is its docstring, exec runs nothing (no marker file), and the function
    computes what eant2_jax.evaluate computes."""
    marker = tmp_path / "ran"
    x = np.random.default_rng(3).uniform(-1, 1, size=(4, 2, 4)).astype(np.float32)
    want = eant2_jax.evaluate(EXAMPLE, x, hidden="sigmoid", output="tanh")
    for i, task in enumerate(_hostile_tasks(marker)):
        path = tmp_path / f"h{i}.genome"
        head = _spec(task=task, task_options={"k": task}).header()
        path.write_text("# eant2-genome " + json.dumps(head) + "\n" + EXAMPLE)
        net = load(path)
        assert net.spec.task == task
        source = net.to_jax_source()
        module = ast.parse(source)
        strings = [n.value for n in ast.walk(module) if isinstance(n, ast.Constant)]
        strings = [v for v in strings if isinstance(v, str)]
        assert strings == [ast.get_docstring(module, clean=False)], strings
        assert "import" not in strings[0] and "task" not in strings[0]
        assert [type(n).__name__ for n in module.body[:3]] == ["Expr", "Import", "Import"]
        got = np.asarray(net.to_jax()(x))
        assert not marker.exists(), f"to_jax ran the file's code (task {task!r})"
        assert_close(got[None], want)


def test_exported_names_pass_a_whitelist():
    spec = _spec(task="gymnax:CartPole-v1")
    assert "on task gymnax:CartPole-v1:" in export.to_jax_source(spec)
    assert "hidden activation sigmoid, output activation tanh." in export.to_jax_source(spec)
    assert " on task" not in export.to_jax_source(_spec(task="a b"))
    assert " on task" not in export.to_jax_source(_spec(task="x" * 65))


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "task": 5}', "task must be a str"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "task": ["x"]}', "task must be"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "task_options": [1]}', "an object"),
        ('{"format": true, "hidden": "tanh", "output": "tanh"}', "not of format 1"),
        ('{"format": 1.0, "hidden": "tanh", "output": "tanh"}', "not of format 1"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_outputs": 2.0}', "says 2.0 out"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": 4.0}', "n_inputs must"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": true}', "n_inputs must"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": 1e999}', "n_inputs must"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": 2147483648}', "up to"),
        ('{"format": 1, "hidden": "a b", "output": "tanh"}', "hidden activation 'a b' is not"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "x": ' + "[" * 100_000, "deeper"),
        ('{"format": 1, "hidden": "tanh", "output": "tanh", "n_inputs": 1' + "0" * 5000, "corr"),
    ],
)
def test_hostile_header_fields_end_in_one_line(tmp_path, header, message):
    """Header fields of the wrong type or size (a 100,000-deep header, a non-string task)
    are one GenomeFileError line naming the file, before anything uses them."""
    path = tmp_path / "bad.genome"
    path.write_text("# eant2-genome " + header + "\n" + EXAMPLE + "\n")
    with pytest.raises(GenomeFileError, match=re.escape(message)) as e:
        GenomeFile.read(path)
    assert str(path) in str(e.value) and len(str(e.value).splitlines()) == 1


def test_one_line_rule_for_genome_files(tmp_path):
    """Genes after a line end other than \\n (U+2028 inside the header, a lone \\r, NEL)
    would load as a network other than the file shows: such a file is refused, whatever
    reads it; \\r\\n (a file saved on Windows) reads as \\n."""
    head = _spec(n_inputs=3, task="x<SEP>N9/1*5 B*1 #").header()
    del head["n_outputs"]  # so that an extra root would not be noticed
    line = "# eant2-genome " + json.dumps(head) + "\n" + EXAMPLE + "\n"
    for sep in ("\u2028", "\u2029", "\r", "\x85", "\x0b", "\x0c", "\x1c"):
        text = line.replace("<SEP>", sep)  # a viewer shows it inside the header line
        with pytest.raises(GenomeFileError, match=f"U\\+{ord(sep):04X}"):
            GenomeFile.parse(text)
        path = tmp_path / "sep.genome"
        path.write_text(text, newline="")
        with pytest.raises(GenomeFileError, match="line 1: character"):
            load(path)
        with pytest.raises(eant2_jax.GenomeError, match="line 1: character"):
            Genome.parse(text)
    plain = _spec(task="xor").to_text()
    assert GenomeFile.parse(plain.replace("\n", "\r\n")) == GenomeFile.parse(plain)


def test_reads_are_bounded_by_bytes_read(tmp_path):
    """Reading trusts no size the file system reports: /proc files claim 0 bytes, and a
    limit is met by counting what was read."""
    proc = Path("/proc/self/status")
    if proc.exists():
        assert proc.stat().st_size == 0
        with pytest.raises(GenomeFileError, match="more than 100 bytes"):
            read_text(proc, limit=100)
        assert "Name:" in read_text(proc)
    path = tmp_path / "a.genome"
    path.write_bytes(b"N0/1*1 B*1\n")
    assert read_text(path, limit=11) == "N0/1*1 B*1\n"
    with pytest.raises(GenomeFileError, match="more than 10 bytes"):
        read_text(path, limit=10)
    path.write_bytes(b"N0/1*1 B*\xff1\n")
    with pytest.raises(GenomeFileError, match="not UTF-8 text"):
        GenomeFile.read(path)


def _in_thread(fn, timeout=20.0):
    """``fn()``'s exception (None if it returned), failing the test if it blocks."""
    out: dict = {}

    def target():
        try:
            fn()
        except BaseException as e:  # noqa: BLE001 - handed back to the test
            out["error"] = e

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), "the read blocked"
    return out.get("error")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_special_files_end_in_one_line(tmp_path):
    """A best.genome linked to /dev/zero, a FIFO nobody writes, a directory: one line each,
    without blocking or reading; a link to a regular file is read."""
    (tmp_path / "zero.genome").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "fifo.genome")
    (tmp_path / "dir.genome").mkdir()
    for name in ("zero.genome", "fifo.genome", "dir.genome"):
        for read in (GenomeFile.read, load):
            err = _in_thread(lambda read=read, name=name: read(tmp_path / name))
            assert isinstance(err, GenomeFileError), err
            assert "not a regular file" in str(err) and len(str(err).splitlines()) == 1
    err = _in_thread(lambda: GenomeFile.read(tmp_path / "missing.genome"))
    assert isinstance(err, GenomeFileError) and "No such file" in str(err)
    _spec().write(tmp_path / "real.genome")
    (tmp_path / "link.genome").symlink_to(tmp_path / "real.genome")
    assert GenomeFile.read(tmp_path / "link.genome") == _spec()


def _package_imports(module: str) -> set[str]:
    """The eant2_jax modules a module's source imports, at any depth of its code."""
    tree = ast.parse((ROOT / "eant2_jax" / f"{module}.py").read_text())
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            found |= {node.module} if node.module else {a.name for a in node.names}
    return found


def test_genome_file_modules_import_one_way():
    """genome <- genomefile <- export <- loaded: the file format imports neither its
    exports nor the loader (they imported each other), nor JAX."""
    assert _package_imports("genomefile") <= {"genome", "jsonio"}
    assert "loaded" not in _package_imports("export")
    assert {"genomefile", "export"} <= _package_imports("loaded")
    tree = ast.parse((ROOT / "eant2_jax" / "genomefile.py").read_text())
    absolute = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    absolute |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level}
    assert not any(m.split(".")[0] in {"jax", "numpy"} for m in absolute), absolute
