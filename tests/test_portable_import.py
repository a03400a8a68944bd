"""The package imports without flax (a test-only dependency) and without fcntl (as on
Windows): a fresh interpreter in which both cannot be imported imports eant2_jax, its
command line and its tasks, builds and evaluates a network, and refuses to create a run
directory unlocked (one line)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest


@pytest.mark.slow
def test_the_package_imports_without_flax_or_fcntl(tmp_path):
    code = f"""
    import sys
    sys.modules["fcntl"] = None  # import fcntl raises ImportError, as on Windows
    sys.modules["flax"] = None
    import numpy as np
    import eant2_jax
    import eant2_jax.app.cli
    from eant2_jax import tasks
    from eant2_jax.rundir import RunDir

    task = tasks.make("xor")
    genome = eant2_jax.Genome.parse("N0/3*1 N1/2*1 I0*1 I1*1 I0*0.5 I1*-0.5")
    out = eant2_jax.evaluate(genome, np.ones((1, 4, task.n_inputs), np.float32))
    assert out.shape == (1, 1, 4, 1) and np.all(np.isfinite(np.asarray(out)))
    config = {{"generations": 0, "key": [0, 0], "task": "xor", "config": {{}}}}
    try:
        RunDir.create({str(tmp_path / "run")!r}, config)
    except Exception as e:  # RunDirError or OSError, naming what is missing
        print(str(e).replace(chr(10), " "))
    heavy = {{"flax", "orbax", "tensorstore", "fcntl"}}
    print(sorted(m for m in sys.modules if m.split(".")[0] in heavy and sys.modules[m]))
    """
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["JAX_PLATFORMS"] = "cpu"
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    refusal, loaded = done.stdout.splitlines()
    assert "run directories need flock (POSIX), which this platform lacks" in refusal
    assert loaded == "[]", loaded
    assert not (tmp_path / "run").exists()
