"""bench/bench_rows.py: its comparison against functions of known row dependence, and a
--quick run end to end."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from bench import bench_rows
from bench.common import BenchInputError


def test_compare_finds_a_row_count_dependence_and_only_that():
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(8, 5)), jnp.float32)
    rowwise = bench_rows.compare(lambda a: {"y": jnp.tanh(a).sum(-1), "i": a.argmax(-1)},
                                 (x,), [1, 3, 8])  # fmt: skip
    assert [(r["k"], r["same"], r["max_abs"]) for r in rowwise] == [(1, True, 0.0), (3, True, 0.0),
                                                                     (8, True, 0.0)]  # fmt: skip
    # Each row shifted by the number of rows its program holds: row-count dependent by
    # exactly 8 - k, an integer leaf too.
    shifted = bench_rows.compare(lambda a, n: (a + a.shape[0], n * a.shape[0]),
                                 (x, jnp.arange(8)), [2, 8])  # fmt: skip
    assert [(r["k"], r["same"]) for r in shifted] == [(2, False), (8, True)]
    assert shifted[0]["max_abs"] == np.inf  # the integer leaf differs: no float distance
    floats = bench_rows.compare(lambda a: a + a.shape[0], (x,), [2, 5])
    np.testing.assert_allclose([r["max_abs"] for r in floats], [6.0, 3.0], rtol=1e-6)


@pytest.mark.slow
def test_quick_run_writes_every_stage_and_k(tmp_path, capsys):
    out = tmp_path / "rows.json"
    bench_rows.main(["--quick", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["stage"], r["k"]) for r in rows] == [
        (s, k) for s in bench_rows.STAGES for k in (1, 3)
    ]
    assert all(r["rows"] == 6 and (r["max_abs"] == 0) == r["same"] for r in rows)
    md = out.with_suffix(".md").read_text()
    assert len([line for line in md.splitlines() if line.startswith("| ")]) == len(rows) + 2
    with pytest.raises(BenchInputError, match=r"--ks must lie in \[1, --rows = 6\]"):
        bench_rows.main(["--rows", "6", "--ks", "7", "--out", str(tmp_path / "bad.json")])
    assert not (tmp_path / "bad.json").exists()
    with pytest.raises(BenchInputError, match="--task xor: .*max_steps"):
        bench_rows.main(["--quick", "--task-option", "max_steps=9", "--out", str(tmp_path / "t")])
    capsys.readouterr()
