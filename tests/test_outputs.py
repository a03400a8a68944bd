"""eant2_jax.app.outputs: whole files, renamed into place, never written through a link."""

import os
import signal
import subprocess
import sys
import textwrap

import pytest

from eant2_jax.app import outputs


def test_write_text_and_bytes_replace_whole_files(tmp_path):
    p = tmp_path / "a.md"
    outputs.write_text(p, "old\n")
    assert p.read_text() == "old\n"
    outputs.write_text(p, "new\n")
    assert p.read_text() == "new\n"
    outputs.write_bytes(tmp_path / "b.bin", b"\x00\x01")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.md", "b.bin"]  # no temp left


def test_mode_is_0o644_less_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        outputs.write_text(tmp_path / "m.txt", "x")
    finally:
        os.umask(old)
    assert (tmp_path / "m.txt").stat().st_mode & 0o777 == 0o640


@pytest.mark.parametrize("dangling", [False, True])
def test_a_planted_link_is_refused_and_its_target_untouched(tmp_path, dangling):
    outside = tmp_path / "outside"
    outside.mkdir()
    target = outside / "bashrc"
    if not dangling:
        target.write_text("precious\n")
    out = tmp_path / "report"
    out.mkdir()
    (out / "report.md").symlink_to(target)
    for write in (
        lambda: outputs.write_text(out / "report.md", "# injected\n"),
        lambda: outputs.write_bytes(out / "report.md", b"x"),
        lambda: outputs.write_text(out / "report.md", "x", overwrite=False),
    ):
        with pytest.raises(outputs.OutputError, match="report.md.*symbolic link"):
            write()
    if dangling:
        assert not target.exists()
    else:
        assert target.read_text() == "precious\n"
    assert (out / "report.md").is_symlink()
    assert [f.name for f in out.iterdir()] == ["report.md"]  # no temp file left


def test_a_figure_is_refused_at_a_link(tmp_path):
    plt = pytest.importorskip("matplotlib.pyplot")
    (tmp_path / "fig.png").symlink_to(tmp_path / "nowhere.png")
    fig = plt.figure()
    try:
        with pytest.raises(outputs.OutputError, match="fig.png"):
            outputs.save_figure(fig, tmp_path / "fig.png", dpi=50)
        outputs.save_figure(fig, tmp_path / "ok.png", dpi=50)
    finally:
        plt.close(fig)
    assert not (tmp_path / "nowhere.png").exists()
    assert (tmp_path / "ok.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_non_regular_destinations_are_refused(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dir").mkdir()
    for name in ("fifo", "dir"):
        with pytest.raises(outputs.OutputError, match="not a regular file"):
            outputs.write_text(tmp_path / name, "x")


def test_no_overwrite_refuses_an_existing_file(tmp_path):
    p = tmp_path / "x.png"
    p.write_text("old")
    with pytest.raises(outputs.OutputError, match="already exists"):
        outputs.write_bytes(p, b"new", overwrite=False)
    assert p.read_text() == "old"
    outputs.write_bytes(tmp_path / "y.png", b"new", overwrite=False)
    assert (tmp_path / "y.png").read_bytes() == b"new"


def test_make_folder_refuses_links(tmp_path):
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "report").symlink_to(tmp_path / "elsewhere")
    (tmp_path / "dangling").symlink_to(tmp_path / "gone")
    for name in ("report", "dangling"):
        with pytest.raises(outputs.OutputError, match="symbolic link"):
            outputs.make_folder(tmp_path / name)
    assert not (tmp_path / "gone").exists()
    made = outputs.make_folder(tmp_path / "a" / "b")
    assert made.is_dir()
    assert outputs.make_folder(made) == made
    with pytest.raises(outputs.OutputError, match="already exists"):
        outputs.make_folder(made, exist_ok=False)


@pytest.mark.slow
def test_a_kill_mid_write_leaves_the_old_file_whole(tmp_path):
    """SIGKILL while the new contents are half written: the old file is still there, whole."""
    p = tmp_path / "report.md"
    p.write_text("old report\n")
    script = textwrap.dedent(
        f"""
        import sys, time
        from eant2_jax.app import outputs

        def write(f):
            f.write(b"new half")
            f.flush()
            print("half", flush=True)
            time.sleep(60)
            f.write(b" and the rest")

        outputs.write_with({str(p)!r}, write)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline() == b"half\n"
        temps = [f for f in tmp_path.iterdir() if f.name != "report.md"]
        assert len(temps) == 1 and temps[0].name.startswith(".report.md.")
        assert temps[0].read_bytes() == b"new half"  # only the temp name is being written
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert p.read_text() == "old report\n"


def test_an_error_while_writing_leaves_no_temp_and_the_old_file(tmp_path):
    p = tmp_path / "s.json"
    p.write_text("{}")

    def write(f):
        f.write(b"partial")
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        outputs.write_with(p, write)
    assert p.read_text() == "{}"
    assert [f.name for f in tmp_path.iterdir()] == ["s.json"]


# Calls that create or write files, whatever their receiver (`Path.write_text`, `savefig`,
# `shutil.copy`, `tempfile.mkstemp`, `os.rename`...).
WRITERS = {
    *("write_text", "write_bytes", "savefig", "save", "dump", "copyfile", "copy2", "copytree"),
    *("mkstemp", "mkdtemp", "touch", "mkdir", "makedirs", "symlink_to", "hardlink_to"),
    *("rename", "link", "symlink", "write_atomic", "saving", "tofile"),
}
# The one exception, and why: the animation writer needs a file name (ffmpeg, Pillow), so
# it writes into a private `tempfile.TemporaryDirectory`; the result reaches its
# destination through `outputs.write_bytes`.
ALLOWED = {("draw.py", "writer.saving")}


def _file_writes(path):
    """``(module, line, call)`` for each call in ``path`` that writes a file other than
    through `eant2_jax.app.outputs` (or a name imported from it)."""
    import ast

    tree = ast.parse(path.read_text())
    from_outputs = {
        a.asname or a.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == "outputs"
        for a in node.names
    }
    hits = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f, text, call = node.func, ast.unparse(node.func), ast.unparse(node)
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)
        receiver = ast.unparse(f.value) if isinstance(f, ast.Attribute) else None
        if receiver == "outputs" or (receiver is None and name in from_outputs):
            continue
        if (path.name, text) in ALLOWED or "os.devnull" in call:  # no file of the user's
            continue
        if (
            name in WRITERS
            or (text == "open" and any(m in call for m in ("'w", "'a", "'x", "+'")))
            or (text == "os.open" and any(m in call for m in ("O_WRONLY", "O_RDWR", "O_CREAT")))
        ):
            hits.append((path.name, node.lineno, call[:80]))
    return hits


def test_the_command_line_writes_files_only_through_outputs(tmp_path):
    """Every file an ``eant2`` command writes outside a run directory (which `RunDir`
    writes, docs/reliability.md) goes through `outputs`: whole, renamed into place, never
    through a link. The scan itself finds each way of writing a file it looks for."""
    from pathlib import Path

    probe = tmp_path / "probe.py"
    probe.write_text(
        "from .outputs import write_text\nwrite_text(p, 'ok')\noutputs.write_bytes(p, b'')\n"
        "p.write_text('x')\nfig.savefig(p)\nopen(p, 'w')\nopen(p, 'rb')\n"
        "os.open(p, os.O_WRONLY | os.O_CREAT)\nos.open(p, os.O_RDONLY)\nshutil.copyfile(a, b)\n"
    )
    assert [line for _, line, _ in _file_writes(probe)] == [4, 5, 6, 8, 10]
    app = Path(outputs.__file__).parent
    hits = [h for p in sorted(app.glob("*.py")) if p.name != "outputs.py" for h in _file_writes(p)]
    assert hits == []
