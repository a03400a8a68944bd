"""The code passes ``ruff check`` (CI runs README's test command only, so lint runs here)."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_check():
    # No importorskip: ruff is in the test extras, and a lint test that skips when ruff is
    # missing would pass CI without linting anything.
    folders = [str(REPO / d) for d in ("eant2_jax", "kernels", "tests", "bench")]
    done = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", *folders],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-2000:]
