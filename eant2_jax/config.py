"""The configuration types: what a run is asked to do, as frozen values.

* `ExploitConfig` — the exploitation engine's (CMA-ES and pruning). A
  ``eant2_jax.pytree`` pytree passed INTO the compiled program: fields that shape the program are
  static (part of the pytree's structure), every number is a traced leaf, so changing a
  number never compiles again.
* `EANT2Config` — the EANT2 loop's (host side only), holding an ``ExploitConfig``.

Each field is declared once, with its spec (`eant2_jax.configspec.option`): default, type,
check, static or traced, the version that added it and its old default, help. Validation
(one line naming the field), the JSON round trip with older run directories' defaults, the
attribute lists below and the command line's help are generated from the specs.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import pytree
from .configspec import Check, Configured, above, at_least, between, document, one_of, option
from .configvalues import (
    DEFAULT_MAX_CONDITION,
    DTYPES,
    FINITE,
    FRACTION,
    NON_NEGATIVE,
    RECOMMEND,
    SPARE_ROWS,
    TOLERANCE,
    bucket_value,
    plain_numbers,
    weights_value,
)
from .configvalues import MAX_BUCKET as MAX_BUCKET  # importable here, as before
from .configvalues import MAX_POPULATION as MAX_POPULATION
from .exploration import OPERATORS

# Process-wide JAX settings live in their own module; their names stay importable here.
from .jaxsetup import enable_compilation_cache as enable_compilation_cache
from .jaxsetup import enable_x64 as enable_x64
from .kernels.pruning import PRUNERS

__all__ = ["EANT2Config", "ExploitConfig", "enable_x64"]


@document
@pytree.dataclass
class ExploitConfig(Configured):
    """Hyper-parameters of the exploitation engine: a frozen pytree passed into the program.

    The spec says what is static and what is traced. Fields marked *static* shape the
    compiled program (array sizes, branches) and are part of the pytree's structure: a new
    value compiles a new program. Every other field is a pytree leaf, a plain number traced
    into the program: changing it never compiles again. (``smoothing``'s None selects the
    per-structure rule, another branch of the start-up program; any number after that is
    traced.) Numbers are normalised to one Python type per field, so that every config
    traces to the same program.

    The defaults prune with the covariance method (``pruner="none"`` is plain CMA-ES),
    tentatively (re-fit, acceptance against the best cost, an attempt at every stop);
    `literal` gives the paper's rule as written. docs/pruning.md says why.

    Fields: one spec each (`eant2_jax.configspec.option`), listed from the specs by
    ``help(ExploitConfig)``, ``eant2 config`` and docs/quickstart.md.
    """

    popsize: int | None = option(
        None,
        "Candidates per CMA-ES iteration, shared by the batch; None takes `default_popsize` "
        "of the batch's padded gene count, or more with ``width`` (the handover's one rule, "
        "`eant2_jax.tuning.popsize_for`).",
        check=at_least(2),
        static=True,
    )
    width: int | None = option(
        None,
        "Networks per engine batch (all rows, padding included, on every device): with no "
        "``popsize``, each row gets ``max(default_popsize, width // rows)`` candidates "
        "(`eant2_jax.tuning.popsize_for`; docs/algorithm.md, Batch width). None: the task's "
        "``default_width`` for the device class (episodic tasks: 1,024 on a GPU), else the "
        "default popsize alone (as ``width=1``).",
        check=at_least(1),
        static=True,
        added="0.1.0 (issue 41)",
        old=None,
    )
    spare_rows: str = option(
        "idle",
        "What a batch's padding rows (beyond its structures, up to ``min_rows`` and the "
        "bucket series) do: ``idle``, nothing; ``restarts``, each runs another independent "
        "search of a structure (row j: structure j % count, from the row's own key): each "
        "structure keeps its search of the lowest cost and counts every search's "
        "evaluations (`eant2_jax.spare`; docs/algorithm.md, Spare rows).",
        check=one_of(*SPARE_ROWS),
        static=True,
        added="0.1.0 (issue 41)",
        old="idle",
    )
    sigma0: float = option(0.5, "Initial step size.", check=above(0))
    max_iters: int = option(1000, "Iteration budget per structure.", check=at_least(1))
    chunk: int = option(
        50,
        "Iterations per compiled call (the host checks for early exit between chunks).",
        check=at_least(1),
        static=True,
    )
    sigma_tol: float = option(
        1e-8,
        "Stop when ``sigma * max(D) < sigma_tol`` (the search has collapsed).",
        check=at_least(0),
    )
    tolfun: float | None = option(
        1e-12,
        'Stop ("flat cost") when every candidate\'s cost has stayed within ``tolfun`` of the '
        "best cost so far for ``10 + ceil(30 n / popsize)`` iterations in a row (CMA-ES's "
        "TolFun, Hansen's tutorial B.3: nothing is left to learn, e.g. a perfect fit at cost "
        "0 or a plateau); None never stops for it.",
        check=TOLERANCE,
        none=-math.inf,
        added="0.1.0 (7d7ae39)",
        old=None,
    )
    patience: int = option(
        300, "Stop after this many iterations without improving the best cost.", check=at_least(1)
    )
    improve_rtol: float = option(
        1e-7,
        "An improvement must beat the best cost by ``improve_rtol * |best| + improve_atol``.",
        check=at_least(0),
    )
    improve_atol: float = option(
        1e-12,
        "The absolute part of that margin (it ends runs whose cost approaches an exact 0).",
        check=at_least(0),
    )
    max_condition: float | None = option(
        None,
        "Bound on cond(C); eigenvalues are clipped to keep it, and the history reports each "
        "iteration where the bound bit. None: 1e7 for a float32 state (what float32 can "
        "resolve), 1e14 for float64.",
        check=Check(lambda v: v > 1, "> 1"),
        none=lambda config: DEFAULT_MAX_CONDITION[config.dtype],
    )
    smoothing: float | None = option(
        None,
        "g of sigma_bar (eq. 5); None uses `smoothing_for` of each structure.",
        check=between(0, 1, open_low=True),
    )
    target_cost: float | None = option(
        None,
        "Stop a structure once its best cost is at or below this (pycma's ``ftarget``); None "
        "never stops for it.",
        check=FINITE,
        none=-math.inf,
    )
    pruner: str = option(
        "covariance",
        "``covariance`` (the paper's, the default wherever a config is built), "
        "``magnitude``, ``obd``, ``obs``, ``snr`` (signal-to-noise), ``random`` (a control: "
        "the connection tried is drawn at random) or ``none`` (no pruning: plain CMA-ES).",
        check=one_of(*PRUNERS),
        static=True,
        # Before pruning existed nothing pruned; every run directory since writes the field.
        added="0.1.0 (6e2a709)",
        old="none",
    )
    prune_window: int = option(
        100,
        "W: a pruning attempt starts when sigma_bar has decreased for at least W iterations "
        "and then increases (paper IV.B.1).",
        check=at_least(1),
    )
    prune_tolerance: float = option(
        1e-3,
        "Accept a removal iff the cost rises by less than this fraction (0.001: the paper's "
        "``e~ < 1.001 e``), plus ``improve_atol`` (docs/pruning.md, section 4).",
        check=at_least(0),
    )
    prune_candidates: int = option(
        1,
        "k: the best k candidates are evaluated in one batch (1 = the paper); see "
        "`eant2_jax.pruning.attempt`.",
        check=at_least(1),
        static=True,
    )
    dtype: str = option(
        "float32",
        "The dtype of the CMA-ES state, ``float32`` or ``float64`` (networks are still "
        "evaluated in float32). float64 needs JAX's x64 mode (`eant2_jax.enable_x64`), for "
        "experiments with large condition numbers.",
        check=one_of(*DTYPES),
        static=True,
    )
    sigma_up: float = option(
        1e4,
        'Stop when ``sigma * max(D)`` exceeds ``sigma_up * sigma0`` ("sigma growth": the '
        "search is diverging, as it does along an exactly flat direction once the cost "
        "reaches the float resolution); the result is the best point seen before.",
        check=Check(lambda v: v > 1, "> 1"),
    )
    bound_patience: int = option(
        100,
        "Stop when cond(C) has sat at ``max_condition`` for this many consecutive iterations "
        '("condition bound").',
        check=at_least(1),
    )
    prune_refit: int = option(
        100,
        "CMA-ES iterations of the reduced structure after the shift, before the acceptance "
        "test (0: none, the paper's literal rule); another stretch as long follows while the "
        "re-fit still closes in on the acceptance limit (docs/pruning.md, section 4); at most "
        "what is left of ``max_iters``, which they count against (at least 1).",
        check=at_least(0),
        static=True,
    )
    prune_refit_scale: float = option(
        0.3,
        "The re-fit's initial step size, as a fraction of the shift's RMS length per kept "
        "coordinate (see `eant2_jax.pruning.attempt`).",
        check=at_least(0),
    )
    prune_reference: str = option(
        "best",
        "What the shifted (and re-fitted) cost is compared with: ``best``, the best cost "
        "seen before the attempt, or ``mean``, the cost of the current mean (the paper's "
        "literal rule).",
        check=one_of("mean", "best"),
        static=True,
    )
    prune_at_stop: bool = option(
        True,
        "Also attempt when a structure stops (no improvement, sigma collapse, condition "
        "bound or the iteration budget): its CMA-ES has converged there, which is the "
        "paper's condition for trusting C. An accepted removal lets a structure stopped for "
        "any reason but the budget run on.",
        static=True,
    )
    lazy_eigen: float = option(
        0.5,
        "A factor f > 0 decomposes a structure's C only every ``f / (n (c_1 + c_mu))`` "
        "iterations (`kernels.cmaes.eigen_interval`; Hansen's tutorial uses f = 0.1, pycma "
        "0.5), rounded down to a power of two and aligned with the engine's iterations so "
        "that a batch's due structures share one batched ``eigh`` "
        "(`kernels.cmaes.eigen_period`). With the default population size, every 2nd "
        "iteration up to about n = 40, every 4th up to 125. 0 decomposes C every iteration. "
        "A pruning attempt always starts from a fresh decomposition.",
        check=Check(lambda v: v >= 0 and math.isfinite(v), ">= 0 and finite"),
        static=True,
        added="0.1.0 (d81513d)",
        old=0.0,
    )
    covariance: str = option(
        "full",
        "``full`` (CMA-ES, the paper's) or ``diagonal``: separable CMA-ES (Ros & Hansen 2008, "
        "`kernels.sepcmaes`), which adapts only the diagonal of C, with its learning rates "
        "times (n + 2) / 3, and never decomposes C: sampling costs O(n) per candidate, not "
        "O(n^2), and ``lazy_eigen`` has nothing to do. For large networks whose weights "
        "matter nearly independently; it learns no correlations. The covariance pruner then "
        "shifts along coordinate axes only: it sets the candidate weight i to 0 and moves no "
        "other (docs/algorithm.md, Separable CMA-ES). No size switches to it by default: at "
        "n = 128 it needs more evaluations than ``full`` where weights interact "
        "(docs/protocol.md section 10).",
        check=one_of("full", "diagonal"),
        static=True,
        added="0.1.0 (issue 41)",
        old="full",
    )
    recommend: str = option(
        "both",
        "On a noisy task (``task.noisy``), which point of each search becomes the tuned "
        "network: ``best``, the best candidate the search saw (on its iterations' episodes, "
        "so the luckiest draw as much as the best weights); ``mean``, the final "
        "distribution mean (pycma's ``xfavorite``, the usual recommendation under noise); "
        "or ``both``, whichever of the two scores the lower cost on the fresh episodes of "
        "``rescore``. A task that is not noisy always takes the best candidate. Static only "
        "because it rides in this config: the engine program does not read it.",
        check=one_of(*RECOMMEND),
        static=True,
        added="0.1.0 (72196e9)",
        old="best",
    )
    rescore: int = option(
        4,
        "On a noisy task, the tuned networks are scored on this many fresh draws of the "
        "task's cost (each its own ``episodes``), averaged: a lower-noise cost for selection "
        "and reports. Each draw counts one evaluation per scored network.",
        check=at_least(1),
        static=True,
        added="0.1.0 (72196e9)",
        old=1,
    )

    def __post_init__(self):
        if plain_numbers(self):
            super().__post_init__()

    def check_across(self) -> None:
        """``popsize`` and ``width`` exclude each other (either sets the candidates per
        row). The numbers are used in the state's dtype: each must survive the cast there (a
        float32 sigma0 of 1e-45 is 0, and the search turns NaN)."""
        if self.popsize is not None and self.width is not None:
            raise ValueError(
                f"ExploitConfig.popsize = {self.popsize} and ExploitConfig.width = "
                f"{self.width} are both set: set one (popsize fixes the candidates per row)"
            )
        info = np.finfo(self.dtype)
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, float) or not math.isfinite(v) or v == 0:
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


def _exploit(v) -> ExploitConfig:
    if not isinstance(v, ExploitConfig):
        raise TypeError(v)
    return v


@document
@dataclasses.dataclass(frozen=True)
class EANT2Config(Configured):
    """Configuration of an EANT2 run (JSON round-trips through ``to_dict``/``from_dict``).

    Fields: one spec each (`eant2_jax.configspec.option`), listed from the specs by
    ``help(EANT2Config)``, ``eant2 config`` and docs/quickstart.md.
    """

    population: int = option(
        20, "Number of individuals kept by selection.", check=between(1, MAX_POPULATION)
    )
    offspring: int | None = option(
        None,
        "New structures made per generation (None: ``population``).",
        check=between(1, MAX_POPULATION),
    )
    init_connectivity: float = option(
        1.0, "Probability that an initial output neuron reads each input.", check=FRACTION
    )
    init_weight_scale: float = option(0.1, "Std of the initial weights.", check=NON_NEGATIVE)
    init_recurrent: bool = option(
        False,
        "Recurrent-ready start: each initial output neuron also reads its own previous output "
        "through a recurrent jumper of weight 0 (same function as the plain minimal start; "
        "`exploration.initial_genome`). Default False (the paper's start).",
        added="0.1.0 (53979e0)",
        old=False,
    )
    init_mutations: int = option(
        0,
        "A diverse generation 0: each initial genome also gets this many structural "
        "mutations (operators drawn with ``operator_weights``, new genes joining at weight 0, "
        "so every start still computes a minimal network's function), and structures already "
        "drawn are drawn again. Default 0: the paper's minimal starts (with full "
        "connectivity, one structure).",
        check=between(0, 1000),
        added="0.1.0 (7d7ae39)",
        old=0,
    )
    input_fraction: float = option(
        0.5,
        "Probability that a new hidden neuron reads each input (paper: ~50%).",
        check=FRACTION,
    )
    new_weight_scale: float = option(
        0.5, "Std of a new hidden neuron's inner weights.", check=NON_NEGATIVE
    )
    operator_weights: tuple[float, ...] = option(
        (1.0, 1.0, 1.0, 1.0, 1.0),
        "Relative frequency of each operator in ``exploration.OPERATORS``.",
        convert=weights_value,
        want="finite numbers",
        check=Check(
            lambda w: len(w) == len(OPERATORS) and min(w) >= 0 and sum(w) > 0,
            f"{len(OPERATORS)} non-negative numbers, not all 0 (order: {', '.join(OPERATORS)})",
        ),
    )
    reexploit: bool = option(
        False,
        "Also run CMA-ES again on surviving parents each generation, continuing from their "
        "tuned weights (default False: a parent was already tuned to convergence when it was "
        "new; its structure has not changed since).",
    )
    inherit_search: bool = option(
        False,
        "Every individual keeps the CMA-ES search its tuning ended with (step size and "
        "covariance, in the run directory too); a child's search then starts from its "
        "parent's covariance on the genes it kept (scaled to a mean eigenvalue of 1) and the "
        "identity on its new genes, with step size ``exploit.sigma0`` "
        "(`eant2_jax.tuning.inherited`), and a re-exploited parent (``reexploit``) continues "
        "from its own step size and covariance. Default False: every search starts at "
        "``sigma0`` and ``C = I`` (the paper).",
        added="0.1.0 (f6e6947)",
        old=False,
    )
    similar_limit: int = option(
        2, "At most this many similar structures survive (paper: 2).", check=at_least(1)
    )
    prefer_smaller: bool = option(
        True, "Of two costs within ``size_tolerance`` the smaller network ranks first."
    )
    size_tolerance: float = option(
        1e-3, "Relative cost tolerance of that rule.", check=NON_NEGATIVE
    )
    size_atol: float = option(1e-9, "Absolute cost tolerance of that rule.", check=NON_NEGATIVE)
    target_cost: float | None = option(
        None,
        "Stop the run once the best cost is at or below this. None: the task's solved level "
        "(its ``solved_cost``) while ``stop_when_solved``, else no target (run all "
        "generations). A run starts by resolving it (`eant2_jax.strategy.resolved`), and "
        "its run directory's config.json records the target it used; a stopped run's "
        "directory holds fewer generations than asked.",
        check=Check(math.isfinite, "finite"),
    )
    stop_when_solved: bool = option(
        True,
        "With no ``target_cost`` given, stop once the best cost reaches the task's solved "
        "level, where the task defines one (XOR, dpv, gymnax and brax environments with a "
        "solved return: docs/tasks.md); a run with a ``solution_test`` is solved by its test "
        "instead. False runs every generation (``--no-solved-stop``).",
        added="0.1.0 (issue 43)",
        old=False,
    )
    max_evaluations: int | None = option(
        None,
        "Stop the run once it has spent at least this many cost evaluations (None: no "
        "limit). Checked between generations, like ``target_cost``: the generation that "
        "reaches it is completed, so the run may overshoot by part of one generation (its "
        "records say by how much). For comparisons at an equal evaluation budget.",
        check=at_least(1),
        limit=2**63 - 1,  # counted on the host
        added="0.1.0 (cce5ad3)",
        old=None,
    )
    solution_rule: str = option(
        "structure",
        "Which networks a run's ``solution_test`` (`eant2_jax.run`) tests: ``structure``, the "
        "best network of every structure being tuned whenever it improves (after each "
        "``exploit.chunk`` CMA-ES iterations; the first that passes halts the tuning), or "
        "``champion``, the generation's champion alone, once per generation after selection "
        "(the published protocol of ESP, NEAT and CoSyNE; docs/pole.md).",
        check=one_of("structure", "champion"),
        added="0.1.0 (issue 42)",
        old="structure",
    )
    devices: int | str | None = option(
        None,
        "Where exploitation runs: None (the default device), ``all`` or a count N: the "
        "structures are split over a 1-D mesh of those devices (every process's, in a "
        "multi-process run). Placement only: the results are identical.",
        check=Check(
            lambda v: v == "all" or (isinstance(v, int) and v >= 1), "'all' or a count >= 1"
        ),
    )
    min_bucket: tuple[int, int, int] | None = option(
        None,
        "The smallest padding bucket ``(neurons, genes, sweeps)`` a generation compiles into "
        "(each rounded up to the bucket series; `loop.grow_bucket`), or None (the default: "
        "the smallest that fits, with one of each to spare). Every new bucket is a new "
        "program to compile, while a generation is latency-bound and padding costs it "
        "little: a floor sized for the networks a run will reach compiles once. The default "
        "CMA-ES population follows the gene bucket (`eant2_jax.tuning.popsize_for`), so a "
        "floor also raises it (fix it with ``exploit.popsize``). A run with a floor is as "
        "deterministic as one without, but not the same run to the bit: padded structures "
        "follow their unpadded search up to float rounding (`eant2_jax.kernels.cmaes`), "
        "which a long search or a chaotic task can amplify.",
        convert=bucket_value,
        want=f"None or three integers (neurons, genes, sweeps) in [1, {MAX_BUCKET}]",
        added="0.1.0 (8993ec2)",
        old=None,
    )
    exploit: ExploitConfig = option(
        help="The CMA-ES / pruning configuration (its ``pruner``, covariance by default, "
        "chooses the pruning; ``none`` turns it off).",
        factory=ExploitConfig,
        convert=_exploit,
        want="an ExploitConfig",
    )
