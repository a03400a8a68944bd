"""The sdist holds what its tests read: every tracked file under docs/, bench/ and tests/,
the license and the docs' mkdocs.yml, and no build or cache litter."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _tracked() -> list[str]:
    """The repository's files as git sees them (tracked, or new and not ignored)."""
    out = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.decode()
    return [f for f in out.split("\0") if f and (REPO / f).is_file()]


@pytest.mark.slow
def test_sdist_holds_docs_bench_tests_and_license(tmp_path):
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout (an unpacked sdist): nothing to compare against")
    src, dist = tmp_path / "src", tmp_path / "dist"
    files = _tracked()
    for f in files:  # build from a copy: no build/ or *.egg-info in the working tree
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, src / f)
    build = subprocess.run(
        [sys.executable, "-m", "build", "--sdist", "--outdir", str(dist), str(src)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    (sdist,) = dist.glob("eant2_jax-*.tar.gz")
    with tarfile.open(sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    wanted = {
        f for f in files if f.split("/")[0] in ("docs", "bench", "tests") and "MUJOCO_LOG" not in f
    }
    wanted |= {"LICENSE", "README.md", "mkdocs.yml", "pyproject.toml", "kernels/network.py"}
    assert not wanted - names, f"not in the sdist: {sorted(wanted - names)[:20]}"
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    assert "PKG-INFO" in names
