"""The field protocol's champion rule, the same for both methods (docs/protocol.md section 3).

* **Candidates**: a method's `TOP` best distinct networks by training fitness seen so far
  (`Archive`; after each of its generations, the networks it scored then: TensorNEAT's
  population, eant2_jax's population after selection).
* **Champion**: at a reporting budget, the candidates of the method's last generation within
  the budget are scored on `VALIDATION_EPISODES` episodes from ``jax.random.key(8000)`` (not
  counted as evaluations); the best mean validation return is the champion (a tie goes to
  the better training fitness), `choose`.
* **Test**: the champion's mean return over `TEST_EPISODES` episodes from
  ``jax.random.key(9000)``. Every network of both methods runs through ONE task object and
  the library's episode code (`eant2_jax.tasks.episodic.returns`); the episodes' initial
  states of each method are drawn (`starts`) and compared (`check_same_starts`), and a
  judgement whose methods' test episodes start differently is refused.
"""

from __future__ import annotations

import hashlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bench.common import BenchInputError
from bench.field_settings import (
    CURVE_POINTS,
    TEST_EPISODES,
    TEST_KEY,
    TOP,
    VALIDATION_EPISODES,
    VALIDATION_KEY,
)

__all__ = ["Archive", "Judge", "check_same_starts", "choose", "curve_points", "judge_run"]
__all__ += ["starts", "starts_digest"]


class Archive:
    """The ``k`` best distinct networks by training fitness (higher is better) seen so far:
    ``(id, fitness)`` pairs, best first; a network offered again keeps its best fitness; of
    equal fitness the one offered first ranks first."""

    def __init__(self, k: int = TOP):
        self.k, self._seen, self._order = k, {}, {}

    def offer(self, ident: str, fitness: float) -> bool:
        """Offer a network; True if it is among the ``k`` best afterwards."""
        if ident not in self._order:
            self._order[ident] = len(self._order)
        self._seen[ident] = max(fitness, self._seen.get(ident, -np.inf))
        return any(i == ident for i, _ in self.entries())

    def entries(self) -> list[tuple[str, float]]:
        ranked = sorted(self._seen.items(), key=lambda kv: (-kv[1], self._order[kv[0]]))
        return [(i, float(f)) for i, f in ranked[: self.k]]

    def best(self) -> float:
        return self.entries()[0][1] if self._seen else -np.inf


def choose(candidates: list[tuple[str, float]], validation: dict[str, float]) -> str:
    """The champion: the candidate of the best validation return, ties to the earlier
    candidate (``candidates`` are best training fitness first)."""
    if not candidates:
        raise ValueError("no candidates to choose a champion from")
    best = max(range(len(candidates)), key=lambda i: (validation[candidates[i][0]], -i))
    return candidates[best][0]


def _finite(r: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(r), r, -np.inf)


class _StartOnly:
    """A task whose ``play`` returns the episode's initial ``(obs, state)``: the task's own
    ``episode`` code draws it, exactly as `eant2_jax.tasks.episodic.rollout` does."""

    def __init__(self, task):
        self._task = task

    def __getattr__(self, name):
        return getattr(self._task, name)

    def play(self, net, key, reset, step):
        return reset(jax.random.split(key)[0])


def starts(task, key: jax.Array, episodes: int) -> list[np.ndarray]:
    """The initial ``(obs, state)`` leaves of ``episodes`` episodes from ``key``, as
    `eant2_jax.tasks.episodic.returns` splits it (``[episodes, ...]`` each)."""
    keys = jax.random.split(key, episodes)
    drawn = jax.vmap(lambda k: type(task).episode(_StartOnly(task), None, k))(keys)
    return [np.asarray(leaf) for leaf in jax.tree.leaves(drawn)]


def starts_digest(leaves: list[np.ndarray]) -> str:
    h = hashlib.sha256()
    for a in leaves:
        h.update(str((a.dtype, a.shape)).encode() + np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def check_same_starts(drawn: dict[str, list[np.ndarray]]) -> None:
    """Refuse (one line) when the methods' test episodes do not start from the same states."""
    names = sorted(drawn)
    for m in names[1:]:
        a, b = drawn[names[0]], drawn[m]
        same = len(a) == len(b) and all(
            x.shape == y.shape and np.array_equal(x, y, equal_nan=x.dtype.kind == "f")
            for x, y in zip(a, b, strict=False)
        )
        if not same:
            raise BenchInputError(
                f"field protocol: the test episodes of {names[0]} and {m} start from "
                "different states; refused (both must play the same 100 episodes)"
            )


class Judge:
    """One method's networks through the shared task: candidates' validation returns and
    champions' test returns, each network scored once (cached by id).

    Args:
      task: the task object both methods' networks run through.
      nets: ``[n]`` the method's candidate networks, one batch (one compiled program).
      ids: the candidates' ids in ``nets`` order.
      test_key, validation_key: the episodes' keys (default the protocol's).
    """

    def __init__(self, task, nets, ids: list[str], *, test_key=None, validation_key=None):
        from eant2_jax.tasks.episodic import returns

        self.task, self.nets, self._returns = task, nets, returns
        self.row = {i: n for n, i in enumerate(ids)}
        self.test_key = jax.random.key(TEST_KEY) if test_key is None else test_key
        self.val_key = jax.random.key(VALIDATION_KEY) if validation_key is None else validation_key
        self.validation: dict[str, float] = {}
        self.test: dict[str, float] = {}

    def _score(self, ids: list[str], key, episodes: int) -> np.ndarray:
        rows = [self.row[i] for i in ids]
        rows += [rows[0]] * (TOP - len(rows)) if len(rows) < TOP else []  # one batch shape
        nets = jax.tree.map(lambda a: a[jnp.asarray(rows)], self.nets)
        r = self._returns(self.task, nets, key=key, episodes=episodes)
        return _finite(np.asarray(r, np.float64)).mean(axis=-1)[: len(ids)]

    def champion(self, candidates: list[tuple[str, float]]) -> tuple[str, dict[str, float]]:
        """The champion of ``candidates`` and their validation returns."""
        new = [i for i, _ in candidates if i not in self.validation]
        if new:
            for i, r in zip(new, self._score(new, self.val_key, VALIDATION_EPISODES), strict=True):
                self.validation[i] = float(r)
        return choose(candidates, self.validation), {i: self.validation[i] for i, _ in candidates}

    def tested(self, ident: str) -> float:
        """The mean test return of one network."""
        if ident not in self.test:
            self.test[ident] = float(self._score([ident], self.test_key, TEST_EPISODES)[0])
        return self.test[ident]

    def starts(self) -> list[np.ndarray]:
        return starts(self.task, self.test_key, TEST_EPISODES)


def curve_points(curve: list[dict], total: int, points: int = CURVE_POINTS) -> list[dict]:
    """The generations of ``curve`` judged along the run: for each ``i / points`` of the
    ``total`` budget (i = 1 .. points) the last generation within it, each once."""
    picked: list[dict] = []
    for i in range(1, points + 1):
        within = [p for p in curve if p["evaluations"] <= total * i / points]
        if within and (not picked or within[-1] is not picked[-1]):
            picked.append(within[-1])
    return picked


def judge_run(judge: Judge, curve: list[dict], budgets: list[int]) -> dict[str, Any]:
    """A method's run under the rule: at each budget the candidates of its last generation
    within it, their validation returns, the champion and its test return; and along the
    run (`curve_points` of the largest budget) the champion and its test return, for the
    wall time to a target."""
    out: dict[str, Any] = {"budgets": [], "curve": []}
    for p in curve_points(curve, max(budgets)):
        champ, _ = judge.champion([tuple(c) for c in p["archive"]])
        out["curve"].append({"evaluations": p["evaluations"], "wall_s": p["wall_s"],
                             "champion": champ, "test_return": judge.tested(champ)})  # fmt: skip
    for b in budgets:
        within = [p for p in curve if p["evaluations"] <= b]
        if not within:
            out["budgets"].append({"budget": b, "champion": None, "test_return": None})
            continue
        p = within[-1]
        cands = [tuple(c) for c in p["archive"]]
        champ, val = judge.champion(cands)
        out["budgets"].append({
            "budget": b, "evaluations": p["evaluations"], "wall_s": p["wall_s"],
            "candidates": [{"id": i, "train": f, "validation": val[i]} for i, f in cands],
            "champion": champ, "test_return": judge.tested(champ),
        })  # fmt: skip
    return out
