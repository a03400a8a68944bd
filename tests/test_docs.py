"""The documentation site builds with warnings as errors (mkdocs --strict), API included."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_docs_build_strict(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").is_file()
    api = (tmp_path / "site" / "api" / "index.html").read_text()
    assert "compile_genomes" in api
    # Sphinx roles are not markdown: mkdocstrings would print them literally.
    roles = re.findall(r":(?:class|func|meth|mod|data|attr|exc|obj):", api)
    assert not roles, f"{len(roles)} raw Sphinx roles on the API page"
    for name in ("register_activation", "load", "GenomeFile", "to_jax_source", "formula"):
        assert name in api, name


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text()
    for link in re.findall(r"\]\(([^)#]+\.md)\)", text):
        assert (ROOT / link).is_file(), f"README links to missing {link}"


def test_readme_names_every_bench_suite():
    from bench.__main__ import SUITES

    readme = (ROOT / "README.md").read_text()
    (names,) = re.findall(r"^python -m bench \{([a-z_,]+)\}$", readme, re.M)
    assert names.split(",") == list(SUITES)
