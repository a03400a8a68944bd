"""The command line's information commands: --version and tasks; MJX's import is quiet."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest

import eant2_jax
from eant2_jax import tasks
from eant2_jax.app.cli import main
from eant2_jax.kernels import activations


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"eant2 {eant2_jax.__version__} (jax ") and out.count("\n") == 1


def test_tasks_lists_every_task_and_its_options(capsys, monkeypatch):
    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    assert main(["tasks"]) == 0
    out = capsys.readouterr().out
    for name in tasks.names():
        assert f"\n{name}: " in "\n" + out, name
    assert '    options: hidden="tanh", output="identity"' in out  # xor's
    assert 'mode="kinematic"' in out and "n_starts=1023" in out  # servo's, imported lazily
    assert ", ".join(activations.names()) in out
    assert tasks.namespaces() == ["brax", "gymnax", "playground"]
    assert "docs/tasks-custom.md): brax, gymnax, playground.\n" in out


def test_task_options_read_the_real_factory():
    assert tasks.options("xor") == {"hidden": "tanh", "output": "identity"}
    assert tasks.factory("dpv").__name__ == "dpv"
    assert tasks.options("dpv")["max_steps"] == 100_000
    assert all(v is not inspect.Parameter.empty for v in tasks.options("servo").values())
    with pytest.raises(ValueError, match="unknown task 'nope'; known tasks: dpnv"):
        tasks.options("nope")


@pytest.mark.slow
def test_mjx_import_prints_nothing_when_warp_is_absent():
    # warp made absent in the child whether or not it is installed (the test extra installs
    # it with playground): MJX's import would print "Failed to import warp" to stdout.
    code = "import sys; sys.modules['warp'] = None; import eant2_jax.tasks.servo; print('imported')"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "imported\n"
    assert "warp" not in proc.stderr


def test_show_prints_the_header(tmp_path, capsys, monkeypatch):
    from eant2_jax.genome import Genome
    from eant2_jax.genomefile import GenomeFile

    monkeypatch.setenv("EANT2_CACHE_DIR", "")
    genome = Genome.parse("N0/3*1.5 N1/2*-3 I0*2 I1*2 I0*1.2 B*-0.4")
    with_header = GenomeFile(genome, "sigmoid", "identity", 3, "xor", {"hidden": "sigmoid"})
    path = with_header.write(tmp_path / "best.genome")
    assert main(["show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "   activations: hidden sigmoid, output identity\n" in out
    assert '          task: xor {"hidden": "sigmoid"} (3 inputs, 1 outputs)\n' in out
    assert (tmp_path / "best.genome.png").read_bytes()[:4] == b"\x89PNG"
    old = tmp_path / "old.genome"
    old.write_text(str(genome) + "\n")
    assert main(["show", str(old)]) == 0
    assert "activations: not recorded (a file without a header)" in capsys.readouterr().out
