"""The configuration types: what a run is asked to do, as frozen values.

* `ExploitConfig` — the exploitation engine's (CMA-ES and pruning). A
  ``flax.struct`` pytree passed INTO the compiled program: fields that shape the program are
  static (part of the pytree's structure), every number is a traced leaf, so changing a
  number never compiles again and no hand-kept list says which is which.
* `EANT2Config` — the EANT2 loop's (host side only), holding an ``ExploitConfig``.

Both validate on construction and name the field and the reason in one line.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
from pathlib import Path

import numpy as np
from flax import struct

from .exploration import OPERATORS
from .kernels.pruning import PRUNERS

__all__ = ["EANT2Config", "ExploitConfig", "enable_x64"]


def enable_x64() -> None:
    """Turn on JAX's 64-bit mode, which ``ExploitConfig(dtype="float64")`` needs. Call it
    before any array is made: arrays made earlier keep their 32-bit types."""
    import jax

    jax.config.update("jax_enable_x64", True)


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_secs: float = 0.0
) -> Path | None:
    """Keep compiled XLA programs on disk between processes (JAX's persistent compilation
    cache, with XLA's GPU autotuning results): a second run of the same programs loads
    them instead of compiling (on a GPU, a servo run's first generation went from 22.9 s
    to 12.4 s: docs/benchmarks.md). With it, the engine's traced programs are kept too
    (`eant2_jax.programstore`, in the folder's ``eant2-programs``), so that a later process
    neither traces nor compiles them. The ``eant2`` command line calls it; the library
    itself never changes global JAX settings, so Python users call it once, first.

    Args:
      path: the cache folder; default ``$EANT2_CACHE_DIR``, else
        ``~/.cache/eant2_jax/xla``. An empty ``EANT2_CACHE_DIR`` (or ``path=""``) turns the
        cache off.
      min_compile_secs: keep only programs that took at least this long to compile (0:
        every program, so that a warm start compiles nothing).

    Returns:
      The folder used, or None when the cache is off.
    """
    import jax

    if path is None:
        path = os.environ.get("EANT2_CACHE_DIR", str(Path.home() / ".cache" / "eant2_jax" / "xla"))
    if not str(path):
        return None
    path = Path(path).expanduser()
    if not (min_compile_secs >= 0 and math.isfinite(min_compile_secs)):
        raise ValueError(f"min_compile_secs must be >= 0 and finite, got {min_compile_secs!r}")
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_secs))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def _static(default):
    """A field that shapes the compiled program: part of the pytree's structure (a new value
    compiles a new program)."""
    return struct.field(pytree_node=False, default=default)


_INTS = ("max_iters", "patience", "prune_window", "bound_patience")
# The static fields' types (they shape the program, so a wrong type is a wrong program).
_STATIC_TYPES = {
    "popsize": int,
    "chunk": int,
    "pruner": str,
    "prune_candidates": int,
    "dtype": str,
    "prune_refit": int,
    "prune_reference": str,
    "prune_at_stop": bool,
    "lazy_eigen": float,
    "recommend": str,
    "rescore": int,
}
RECOMMEND = ("best", "mean", "both")
DTYPES = ("float32", "float64")
# The default bound on cond(C) by the dtype of the CMA-ES state: float32 resolves an
# eigenvalue to about 1e-7 of the largest, so a larger bound lets rounding noise through
# (sigma then explodes along an exactly flat direction); float64 honours the paper's 1e14.
DEFAULT_MAX_CONDITION = {"float32": 1e7, "float64": 1e14}


@struct.dataclass
class ExploitConfig:
    """Hyper-parameters of the exploitation engine: a frozen pytree passed into the program.

    The type says what is static and what is traced. Fields marked *static* shape the
    compiled program (array sizes, branches) and are part of the pytree's structure: a new
    value compiles a new program. Every other field is a pytree leaf, a plain number traced
    into the program: changing it never compiles again. (``smoothing``'s None selects the
    per-structure rule, another branch of the start-up program; any number after that is
    traced.)

    Attributes:
      popsize: *static*. Candidates per CMA-ES iteration, shared by the batch; None takes
        `default_popsize` of the batch's padded gene count (the handover's one rule,
        `eant2_jax.tuning.popsize_for`).
      sigma0: initial step size.
      max_iters: iteration budget per structure.
      chunk: *static*. Iterations per compiled call (the host checks for early exit between
        chunks).
      sigma_tol: stop when ``sigma * max(D) < sigma_tol`` (the search has collapsed).
      tolfun: stop ("flat cost") when every candidate's cost has stayed within ``tolfun`` of
        the best cost so far for ``10 + ceil(30 n / popsize)`` iterations in a row (CMA-ES's
        TolFun, Hansen's tutorial B.3: nothing is left to learn, e.g. a perfect fit at cost
        0 or a plateau); None never stops for it. Run directories written before this rule
        existed resume with None, as they ran.
      patience: stop after this many iterations without improving the best cost.
      improve_rtol, improve_atol: an improvement must beat the best cost by
        ``improve_rtol * |best| + improve_atol`` (the absolute part ends runs whose cost
        approaches an exact 0).
      max_condition: bound on cond(C); eigenvalues are clipped to keep it, and the history
        reports each iteration where the bound bit. None: 1e7 for a float32 state (what
        float32 can resolve), 1e14 for float64.
      dtype: *static*. ``"float32"`` (default) or ``"float64"``, the dtype of the CMA-ES
        state (networks are still evaluated in float32). float64 needs JAX's x64 mode
        (`eant2_jax.enable_x64`), for experiments with large condition numbers.
      sigma_up: stop when ``sigma * max(D)`` exceeds ``sigma_up * sigma0`` ("sigma
        growth": the search is diverging, as it does along an exactly flat direction once
        the cost reaches the float resolution); the result is the best point seen before.
      bound_patience: stop when cond(C) has sat at ``max_condition`` for this many
        consecutive iterations ("condition bound").
      smoothing: g of sigma_bar (eq. 5); None uses `smoothing_for` of each structure.
      target_cost: stop a structure once its best cost is at or below this (pycma's
        ``ftarget``); None never stops for it (held as ``-inf``, which no cost is below).
      pruner: *static*. ``covariance`` (the paper's), ``magnitude``, ``obd``, ``obs``,
        ``snr`` (signal-to-noise) or ``none``.
      prune_window: W, a pruning attempt starts when sigma_bar has decreased for at least W
        iterations and then increases (paper IV.B.1).
      prune_tolerance: accept a removal iff the cost rises by less than this fraction
        (0.001: the paper's ``e~ < 1.001 e``).
      prune_candidates: *static*. k, the best k candidates are evaluated in one batch (1 =
        the paper); see `eant2_jax.pruning.attempt`.
      prune_refit: *static*. CMA-ES iterations of the reduced structure after the shift,
        before the acceptance test (0: none, the paper's literal rule); at most what is left
        of ``max_iters``, which they count against (at least 1).
      prune_refit_scale: the re-fit's initial step size, as a fraction of the shift's RMS
        length per kept coordinate (see `eant2_jax.pruning.attempt`).
      prune_reference: *static*. What the shifted (and re-fitted) cost is compared with:
        ``"best"``, the best cost seen before the attempt (default), or ``"mean"``, the cost
        of the current mean (the paper's literal rule).
      prune_at_stop: *static*. Also attempt when a structure stops (no improvement, sigma
        collapse, condition bound or the iteration budget): its CMA-ES has converged there,
        which is the paper's condition for trusting C. An accepted removal lets a structure
        stopped for any reason but the budget run on.

      lazy_eigen: *static*. A factor f > 0 decomposes a structure's C only every ``f / (n
        (c_1 + c_mu))`` iterations (`kernels.cmaes.eigen_interval`; Hansen's tutorial uses
        f = 0.1, pycma 0.5), rounded down to a power of two and aligned with the engine's
        iterations so that a batch's due structures share one batched ``eigh``
        (`kernels.cmaes.eigen_period`). Default 0.5, pycma's: with the default population
        size, every 2nd iteration up to about n = 40, every 4th up to 125. 0 decomposes C
        every iteration (run directories written before this field resume with 0). A
        pruning attempt always starts from a fresh decomposition.
      recommend: *static*. On a noisy task (``task.noisy``), which point of each search
        becomes the tuned network: ``"best"``, the best candidate the search saw (on its
        iterations' episodes, so the luckiest draw as much as the best weights);
        ``"mean"``, the final distribution mean (pycma's ``xfavorite``, the usual
        recommendation under noise); or ``"both"`` (default), whichever of the two scores
        the lower cost on the fresh episodes of ``rescore``. A task that is not noisy
        always takes the best candidate. Static only because it rides in this config: the
        engine program does not read it.
      rescore: *static*. On a noisy task, the tuned networks are scored on this many
        fresh draws of the task's cost (each its own ``episodes``), averaged: a lower-noise
        cost for selection and reports. Each draw counts one evaluation per scored
        network. Run directories written before these two fields existed resume with
        ``recommend="best"``, ``rescore=1``, as they ran.

    The defaults prune tentatively (re-fit, acceptance against the best cost, an attempt at
    every stop); `literal` gives the paper's rule as written. docs/pruning.md says why.
    """

    popsize: int | None = _static(None)
    sigma0: float = 0.5
    max_iters: int = 1000
    chunk: int = _static(50)
    sigma_tol: float = 1e-8
    tolfun: float | None = 1e-12
    patience: int = 300
    improve_rtol: float = 1e-7
    improve_atol: float = 1e-12
    max_condition: float | None = None
    smoothing: float | None = None
    target_cost: float | None = None
    pruner: str = _static("none")
    prune_window: int = 100
    prune_tolerance: float = 1e-3
    prune_candidates: int = _static(1)
    dtype: str = _static("float32")
    sigma_up: float = 1e4
    bound_patience: int = 100
    prune_refit: int = _static(100)
    prune_refit_scale: float = 0.3
    prune_reference: str = _static("best")
    prune_at_stop: bool = _static(True)
    lazy_eigen: float = _static(0.5)
    recommend: str = _static("both")
    rescore: int = _static(4)

    def __post_init__(self):
        # JAX rebuilds this pytree with tracers (or other placeholders) as leaves when it
        # traces or maps over it; only a config built from plain numbers is normalised and
        # validated.
        leaves = [getattr(self, f.name) for f in dataclasses.fields(self)]
        if not all(v is None or isinstance(v, (int, float, str, np.number)) for v in leaves):
            return
        for name, kind in _STATIC_TYPES.items():
            v = getattr(self, name)
            if kind is float and isinstance(v, int) and not isinstance(v, bool):
                v = float(v)  # a static float given as an int: the same program
                object.__setattr__(self, name, v)
            if not (isinstance(v, kind) and (kind is bool or not isinstance(v, bool))):
                if not (name == "popsize" and v is None):
                    raise ValueError(
                        f"ExploitConfig.{name} must be of type {kind.__name__}, got {v!r}"
                    )
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.metadata.get("pytree_node", True) and v is not None:
                # One Python type per field, so that every config traces to the same program
                # (a NumPy or int scalar would be a differently typed argument).
                if isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
                    raise ValueError(f"ExploitConfig.{f.name} must be a number, got {v!r}")
                if f.name in _INTS:
                    if float(v) != int(v):
                        raise ValueError(f"ExploitConfig.{f.name} must be an integer, got {v!r}")
                    v = int(v)
                else:
                    v = float(v)
                object.__setattr__(self, f.name, v)
        if self.target_cost is None:
            object.__setattr__(self, "target_cost", -math.inf)
        if self.tolfun is None:
            object.__setattr__(self, "tolfun", -math.inf)
        if self.dtype not in DTYPES:
            raise ValueError(
                f"ExploitConfig.dtype must be one of {', '.join(DTYPES)}, got {self.dtype!r}"
            )
        if self.max_condition is None:
            object.__setattr__(self, "max_condition", DEFAULT_MAX_CONDITION[self.dtype])
        checks = [
            ("popsize", self.popsize is None or self.popsize >= 2, ">= 2 (or None)"),
            ("sigma0", self.sigma0 > 0 and math.isfinite(self.sigma0), "> 0 and finite"),
            ("max_iters", self.max_iters >= 1, ">= 1"),
            ("chunk", self.chunk >= 1, ">= 1"),
            ("sigma_tol", self.sigma_tol >= 0, ">= 0"),
            (
                "tolfun",
                self.tolfun == -math.inf or (self.tolfun >= 0 and math.isfinite(self.tolfun)),
                ">= 0 and finite (or None)",
            ),
            ("patience", self.patience >= 1, ">= 1"),
            ("improve_rtol", self.improve_rtol >= 0, ">= 0"),
            ("improve_atol", self.improve_atol >= 0, ">= 0"),
            ("max_condition", self.max_condition > 1, "> 1"),
            ("smoothing", self.smoothing is None or 0 < self.smoothing <= 1, "in (0, 1]"),
            (
                "target_cost",
                self.target_cost == -math.inf or math.isfinite(self.target_cost),
                "finite (or None)",
            ),
            ("pruner", self.pruner in PRUNERS, f"one of {', '.join(PRUNERS)}"),
            ("prune_window", self.prune_window >= 1, ">= 1"),
            ("prune_tolerance", self.prune_tolerance >= 0, ">= 0"),
            ("prune_candidates", self.prune_candidates >= 1, ">= 1"),
            ("sigma_up", self.sigma_up > 1, "> 1"),
            ("prune_refit_scale", self.prune_refit_scale >= 0, ">= 0"),
            (
                "lazy_eigen",
                self.lazy_eigen >= 0 and math.isfinite(self.lazy_eigen),
                ">= 0 and finite",
            ),
            ("bound_patience", self.bound_patience >= 1, ">= 1"),
            (
                "prune_refit",
                isinstance(self.prune_refit, int) and self.prune_refit >= 0,
                "an integer >= 0",
            ),
            ("prune_reference", self.prune_reference in ("mean", "best"), "'mean' or 'best'"),
            ("prune_at_stop", isinstance(self.prune_at_stop, bool), "True or False"),
            ("recommend", self.recommend in RECOMMEND, f"one of {', '.join(RECOMMEND)}"),
            ("rescore", self.rescore >= 1, ">= 1"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(
                    f"ExploitConfig.{name} must be {want}, got {getattr(self, name)!r}"
                )
        # The numbers are used in the state's dtype: each must survive the cast there (a
        # float32 sigma0 of 1e-45 is 0, and the search turns NaN).
        info = np.finfo(self.dtype)
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in _INTS or not isinstance(v, float) or not math.isfinite(v) or v == 0:
                continue
            if not float(info.tiny) <= abs(v) <= float(info.max):
                raise ValueError(
                    f"ExploitConfig.{f.name} = {v!r} is outside the range of a {self.dtype} "
                    f"state (normal numbers {float(info.tiny):.3g} to {float(info.max):.3g})"
                )
        if not math.isfinite(np.array(self.sigma0 * self.sigma_up, dtype=self.dtype)):
            raise ValueError(
                f"ExploitConfig.sigma0 * sigma_up = {self.sigma0 * self.sigma_up:.3g} "
                f"overflows {self.dtype}"
            )

    @classmethod
    def literal(cls, **options) -> ExploitConfig:
        """The paper's pruning as written (IV.B): no re-fit, acceptance against the cost of
        the current mean, attempts only when sigma_bar turns (no attempt at a stop)."""
        return cls(
            **{"prune_refit": 0, "prune_reference": "mean", "prune_at_stop": False, **options}
        )

    def to_dict(self) -> dict:
        """JSON-ready fields (a target or tolfun of ``-inf`` is written as None, its
        meaning)."""
        d = dataclasses.asdict(self)
        for name in ("target_cost", "tolfun"):
            if d[name] == -math.inf:
                d[name] = None
        return d

    @classmethod
    def from_options(cls, options: dict) -> ExploitConfig:
        """``ExploitConfig(**options)``, with a ValueError naming any unknown option."""
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = [name for name in options if name not in known]
        if unknown:
            hints = []
            for name in unknown:
                close = difflib.get_close_matches(name, known, n=1)
                hints.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
            raise ValueError(
                f"unknown option {', '.join(hints)}; the options are the fields of "
                f"ExploitConfig: {', '.join(known)}"
            )
        return cls(**options)


# A documented size limit (docs/reliability.md): far above any useful EANT2 population, far
# below the sizes that would only exhaust memory before saying anything.
MAX_POPULATION = 1_000_000
_EANT2_TYPES = {
    "population": ("int",),
    "offspring": ("int", "None"),
    "init_connectivity": ("float",),
    "init_weight_scale": ("float",),
    "init_recurrent": ("bool",),
    "init_mutations": ("int",),
    "input_fraction": ("float",),
    "new_weight_scale": ("float",),
    "reexploit": ("bool",),
    "inherit_search": ("bool",),
    "similar_limit": ("int",),
    "prefer_smaller": ("bool",),
    "size_tolerance": ("float",),
    "size_atol": ("float",),
    "target_cost": ("float", "None"),
    "max_evaluations": ("int", "None"),
    "devices": ("int", "str", "None"),
}


# EANT2Config.min_bucket's bound on each entry: far beyond any network a generation compiles
# (the flat parameter buffer's int32 index allows 24,576 neuron slots: compiler.MAX_BUFFER).
_MAX_BUCKET = 16384

# Fields added after the run-directory format 2 was fixed: a file written before them lacks
# them, so ``complete`` does not require them and fills in the value that reproduces what
# that version did (not necessarily today's default).
_ADDED_LATER = {
    "init_recurrent": False,
    "init_mutations": 0,
    "max_evaluations": None,
    "inherit_search": False,
    "min_bucket": None,
}
_EXPLOIT_ADDED_LATER = {"lazy_eigen": 0.0, "tolfun": None, "recommend": "best", "rescore": 1}


@dataclasses.dataclass(frozen=True)
class EANT2Config:
    """Configuration of an EANT2 run (JSON round-trips through ``to_dict``/``from_dict``).

    Attributes:
      population: number of individuals kept by selection.
      offspring: new structures made per generation (None: ``population``).
      init_connectivity: probability that an initial output neuron reads each input.
      init_weight_scale: std of the initial weights.
      init_recurrent: recurrent-ready start: each initial output neuron also reads its own
        previous output through a recurrent jumper of weight 0 (same function as the plain
        minimal start; `exploration.initial_genome`). Default False (the paper's start).
      init_mutations: a diverse generation 0: each initial genome also gets this many
        structural mutations (operators drawn with ``operator_weights``, new genes joining
        at weight 0, so every start still computes a minimal network's function), and
        structures already drawn are drawn again. Default 0: the paper's minimal starts
        (with full connectivity, one structure).
      input_fraction: probability that a new hidden neuron reads each input (paper: ~50%).
      new_weight_scale: std of a new hidden neuron's inner weights.
      operator_weights: relative frequency of each operator in ``exploration.OPERATORS``.
      reexploit: also run CMA-ES again on surviving parents each generation, continuing from
        their tuned weights (default False: a parent was already tuned to convergence when it
        was new; its structure has not changed since).
      inherit_search: every individual keeps the CMA-ES search its tuning ended with (step
        size and covariance, in the run directory too); a child's search then starts from
        its parent's covariance on the genes it kept (scaled to a mean eigenvalue of 1) and
        the identity on its new genes, with step size ``exploit.sigma0``
        (`eant2_jax.tuning.inherited`), and a re-exploited parent (``reexploit``) continues
        from its own step size and covariance. Default False: every search starts at
        ``sigma0`` and ``C = I`` (the paper).
      similar_limit: at most this many similar structures survive (paper: 2).
      prefer_smaller: of two costs within ``size_tolerance`` the smaller network ranks first.
      size_tolerance, size_atol: relative and absolute cost tolerance of that rule.
      exploit: the CMA-ES / pruning configuration (its ``pruner`` turns pruning on).
      target_cost: stop the run once the best cost is at or below this (None: run all
        generations). A stopped run's directory holds fewer generations than asked.
      max_evaluations: stop the run once it has spent at least this many cost evaluations
        (None: no limit). Checked between generations, like ``target_cost``: the generation
        that reaches it is completed, so the run may overshoot by part of one generation
        (its records say by how much). For comparisons at an equal evaluation budget.
      devices: where exploitation runs: None (the default device), ``"all"`` or a count N —
        the structures are split over a 1-D mesh of those devices (every process's, in a
        multi-process run). Placement only: the results are identical.
      min_bucket: the smallest padding bucket ``(neurons, genes, sweeps)`` a generation
        compiles into (each rounded up to the bucket series; `loop.grow_bucket`), or None
        (the default: the smallest that fits, with one of each to spare). Every new bucket
        is a new program to compile: a second or so on a CPU for small tasks, 10 s on a GPU
        for servo, 30-40 s for a brax episode, while a generation is latency-bound and
        padding costs it little. A floor sized for the networks a run will reach compiles
        once. The default CMA-ES population follows the gene bucket
        (`eant2_jax.tuning.popsize_for`), so a floor also raises it (fix it with
        ``exploit.popsize``); the same key and config give the same run either way.
    """

    population: int = 20
    offspring: int | None = None
    init_connectivity: float = 1.0
    init_weight_scale: float = 0.1
    init_recurrent: bool = False
    init_mutations: int = 0
    input_fraction: float = 0.5
    new_weight_scale: float = 0.5
    operator_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0)
    reexploit: bool = False
    inherit_search: bool = False
    similar_limit: int = 2
    prefer_smaller: bool = True
    size_tolerance: float = 1e-3
    size_atol: float = 1e-9
    target_cost: float | None = None
    max_evaluations: int | None = None
    devices: int | str | None = None
    min_bucket: tuple[int, int, int] | None = None
    exploit: ExploitConfig = dataclasses.field(
        default_factory=lambda: ExploitConfig(pruner="covariance")
    )

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            kinds = _EANT2_TYPES.get(f.name)
            if kinds is None:
                continue
            ok = v is None if "None" in kinds else False
            ok = ok or ("bool" in kinds and isinstance(v, bool))
            ok = ok or ("int" in kinds and isinstance(v, int) and not isinstance(v, bool))
            ok = ok or (
                "float" in kinds
                and isinstance(v, int | float)
                and not isinstance(v, bool)
                and math.isfinite(v)
            )
            ok = ok or ("str" in kinds and isinstance(v, str))
            if not ok:
                raise ValueError(
                    f"EANT2Config.{f.name} must be {' or '.join(kinds)} (finite), got {v!r:.60}"
                )
        if not isinstance(self.operator_weights, list | tuple) or not all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
            for x in self.operator_weights
        ):
            raise ValueError(
                f"EANT2Config.operator_weights must be finite numbers, got "
                f"{self.operator_weights!r:.60}"
            )
        w = tuple(float(x) for x in self.operator_weights)
        object.__setattr__(self, "operator_weights", w)
        if self.min_bucket is not None:
            b = self.min_bucket
            if not (
                isinstance(b, list | tuple)
                and len(b) == 3
                and all(isinstance(x, int) and not isinstance(x, bool) for x in b)
                and all(1 <= x <= _MAX_BUCKET for x in b)
            ):
                raise ValueError(
                    "EANT2Config.min_bucket must be None or three integers (neurons, genes, "
                    f"sweeps) in [1, {_MAX_BUCKET}], got {b!r:.60}"
                )
            object.__setattr__(self, "min_bucket", tuple(b))
        checks = [
            ("population", 1 <= self.population <= MAX_POPULATION, f"in [1, {MAX_POPULATION}]"),
            (
                "offspring",
                self.offspring is None or 1 <= self.offspring <= MAX_POPULATION,
                f"in [1, {MAX_POPULATION}] (or None)",
            ),
            ("init_connectivity", 0 < self.init_connectivity <= 1, "in (0, 1]"),
            ("init_weight_scale", self.init_weight_scale >= 0, ">= 0"),
            ("init_mutations", 0 <= self.init_mutations <= 1000, "in [0, 1000]"),
            ("input_fraction", 0 < self.input_fraction <= 1, "in (0, 1]"),
            ("new_weight_scale", self.new_weight_scale >= 0, ">= 0"),
            (
                "operator_weights",
                len(w) == len(OPERATORS) and min(w) >= 0 and sum(w) > 0,
                f"{len(OPERATORS)} non-negative numbers, not all 0 (order: {', '.join(OPERATORS)})",
            ),
            ("similar_limit", self.similar_limit >= 1, ">= 1"),
            (
                "max_evaluations",
                self.max_evaluations is None or self.max_evaluations >= 1,
                ">= 1 (or None)",
            ),
            ("size_tolerance", self.size_tolerance >= 0, ">= 0"),
            ("size_atol", self.size_atol >= 0, ">= 0"),
            (
                "devices",
                self.devices is None
                or self.devices == "all"
                or (isinstance(self.devices, int) and self.devices >= 1),
                "None, 'all' or a count >= 1",
            ),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"EANT2Config.{name} must be {want}, got {getattr(self, name)!r}")
        if not isinstance(self.exploit, ExploitConfig):
            raise ValueError("EANT2Config.exploit must be an ExploitConfig")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["operator_weights"] = list(self.operator_weights)
        d["min_bucket"] = None if self.min_bucket is None else list(self.min_bucket)
        d["exploit"] = self.exploit.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict, *, complete: bool = False) -> EANT2Config:
        """Inverse of `to_dict`; unknown keys are a ValueError naming them.

        Args:
          d: the dict (an ``exploit`` dict is required: without it pruning would silently
            be off).
          complete: also require every field (as `to_dict` writes them), so that no
            missing key silently takes its default.
        """
        if not isinstance(d, dict):
            raise ValueError(f"an EANT2 configuration must be an object, got {d!r:.40}")
        d = dict(d)
        if not isinstance(d.get("exploit"), dict):
            raise ValueError("the configuration has no 'exploit' object")
        exploit = dict(d.pop("exploit"))
        _check_keys(cls, d, "EANT2Config")
        _check_keys(ExploitConfig, exploit, "ExploitConfig")
        for name, v in exploit.items():  # the pytree skips validation of non-number leaves
            if v is not None and not isinstance(v, bool | int | float | str):
                raise ValueError(f"ExploitConfig.{name} must be a number or name, got {v!r:.40}")
        if complete:
            for kind, given, name, later in (
                (cls, d, "EANT2Config", _ADDED_LATER),
                (ExploitConfig, exploit, "ExploitConfig", _EXPLOIT_ADDED_LATER),
            ):
                missing = sorted(
                    {f.name for f in dataclasses.fields(kind)} - set(given) - {"exploit", *later}
                )
                if missing:
                    raise ValueError(f"{name} option(s) missing: {', '.join(missing)}")
                for field, old in later.items():
                    given.setdefault(field, old)
        if isinstance(d.get("operator_weights"), list):
            d["operator_weights"] = tuple(d["operator_weights"])
        return cls(**d, exploit=ExploitConfig(**exploit))


def _check_keys(cls, d: dict, name: str) -> None:
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(
            f"unknown {name} option(s): {', '.join(unknown)}; known: {', '.join(sorted(known))}"
        )
