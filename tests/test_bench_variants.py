"""bench/lmmaes.py against the formulas of its paper, and bench/bench_variants.py end to end
(docs/protocol.md section 10)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench import bench_variants, lmmaes
from bench.common import BenchInputError


def test_params_are_the_papers_defaults():
    n = 128
    p = lmmaes.lmmaes_params(n)
    lam = 4 + int(np.floor(3 * np.log(n)))
    assert (p.popsize, p.mu, len(p.c_d)) == (lam, lam // 2, lam)  # m = 4 + floor(3 ln n)
    w = np.log(lam // 2 + 0.5) - np.log(np.arange(1, lam // 2 + 1))
    np.testing.assert_allclose(p.weights, w / w.sum())
    np.testing.assert_allclose(p.mu_w, w.sum() ** 2 / (w**2).sum())
    np.testing.assert_allclose(p.c_sigma, 2 * lam / n)
    np.testing.assert_allclose(p.c_d, [1 / (1.5**j * n) for j in range(lam)])
    np.testing.assert_allclose(p.c_c, [lam / (4.0**j * n) for j in range(lam)])
    with pytest.raises(ValueError, match="n >= 2"):
        lmmaes.lmmaes_params(16)  # lambda 12: c_sigma = 1.5


def _state(rng, n, params, t):
    st = lmmaes.lmmaes_init(rng.normal(size=n), 0.7, params)
    return st._replace(M=rng.normal(size=st.M.shape), p_sigma=rng.normal(size=n), t=t)


@pytest.mark.parametrize("t", [0, 3, 100])
def test_ask_applies_the_first_min_t_m_vectors_in_order(t):
    rng = np.random.default_rng(t)
    n = 40
    params = lmmaes.lmmaes_params(n)
    st = _state(rng, n, params, t)
    z, d, x = lmmaes.lmmaes_ask(np.random.default_rng(1), st, params)
    np.testing.assert_array_equal(z, np.random.default_rng(1).standard_normal(z.shape))
    want = z.copy()
    for j in range(min(t, len(params.c_d))):  # d <- d (I (1 - c_d,j) + c_d,j m_j m_j^T)
        mj = st.M[j]
        want = want @ ((1 - params.c_d[j]) * np.eye(n) + params.c_d[j] * np.outer(mj, mj))
    np.testing.assert_allclose(d, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x, st.mean + st.sigma * d)


def test_tell_is_the_papers_update_and_ignores_the_population_order():
    rng = np.random.default_rng(3)
    n = 50
    params = lmmaes.lmmaes_params(n)
    st = _state(rng, n, params, 5)
    z, d, _ = lmmaes.lmmaes_ask(rng, st, params)
    cost = rng.normal(size=params.popsize)
    new = lmmaes.lmmaes_tell(st, z, d, cost, params)
    best = np.argsort(cost)[: params.mu]
    zw, dw = params.weights @ z[best], params.weights @ d[best]
    cs, mw = params.c_sigma, params.mu_w
    p_sigma = (1 - cs) * st.p_sigma + np.sqrt(mw * cs * (2 - cs)) * zw
    np.testing.assert_allclose(new.p_sigma, p_sigma)
    for j, cc in enumerate(params.c_c):
        np.testing.assert_allclose(new.M[j], (1 - cc) * st.M[j] + np.sqrt(mw * cc * (2 - cc)) * zw)
    np.testing.assert_allclose(new.mean, st.mean + st.sigma * dw)
    np.testing.assert_allclose(new.sigma, st.sigma * np.exp(cs / 2 * (p_sigma @ p_sigma / n - 1)))
    assert new.t == st.t + 1
    perm = rng.permutation(params.popsize)  # rank-based: the order of the candidates is moot
    again = lmmaes.lmmaes_tell(st, z[perm], d[perm], cost[perm], params)
    for a, b in zip(new, again, strict=True):
        np.testing.assert_allclose(a, b)


def test_lmmaes_solves_a_sphere():
    n = 64
    opt = np.random.default_rng(0).uniform(-1, 1, n)
    evals = lmmaes.lmmaes_evals_to_target(lambda x: ((x - opt) ** 2).sum(1), n, 1.0, 1e-8,
                                          60_000, seed=0)  # fmt: skip
    assert 0 < evals < 60_000
    # A budget too small to reach: -1, never a count beyond the budget.
    assert lmmaes.lmmaes_evals_to_target(lambda x: ((x - opt) ** 2).sum(1), n, 1.0, 1e-8,
                                         300, seed=0) == -1  # fmt: skip


def test_functions_are_fresh_per_seed_and_separable_has_no_rotation():
    rot = bench_variants.functions("rotated", 8, 1e2, [1, 2])
    sep = bench_variants.functions("separable", 8, 1e2, [1, 2])
    assert not np.allclose(rot["rot"][0], rot["rot"][1])
    np.testing.assert_allclose(rot["rot"][0] @ rot["rot"][0].T, np.eye(8), atol=1e-5)
    np.testing.assert_array_equal(sep["rot"][0], np.eye(8))
    np.testing.assert_array_equal(sep["opt"], rot["opt"])
    x = sep["opt"][0][None, :]
    assert bench_variants.cost(sep["rot"][0], sep["scale"][0], sep["opt"][0], x)[0] == 0


def test_bad_arguments_get_one_error(tmp_path):
    with pytest.raises(BenchInputError, match="full, where given, must come first"):
        bench_variants.main(["--methods", "diagonal", "full", "--out", str(tmp_path / "a.json")])
    with pytest.raises(BenchInputError, match="--dims 10"):
        bench_variants.main(["--dims", "10", "--out", str(tmp_path / "b.json")])


@pytest.mark.slow
def test_quick_run_measures_each_method_and_the_separable_control(tmp_path):
    out = tmp_path / "variants.json"
    bench_variants.main(["--quick", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [(r["function"], r["method"]) for r in rows] == [
        (f, m) for f in bench_variants.FUNCTIONS for m in bench_variants.METHODS
    ]
    by = {(r["function"], r["method"]): r for r in rows}
    for f in bench_variants.FUNCTIONS:  # the full kernel reaches the quick target
        assert by[f, "full"]["reached"] == 2 and "ratio" not in by[f, "full"]
    # The control: the diagonal kernel needs fewer evaluations on a separable ellipsoid.
    assert by["separable", "diagonal"]["ratio"] < 1
    for r in rows:  # a count is a multiple of the method's population, or -1
        assert all(e == -1 or e % 14 == 0 for e in r["evaluations"]), r
    assert "| separable | 32 | diagonal | 2/2 |" in out.with_suffix(".md").read_text()
