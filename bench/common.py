"""Helpers shared by the benchmarks: device tagging, timing, random genomes, markdown tables.

Nothing here is specific to one benchmark. A suite builds row dicts into a payload that
carries :func:`environment` and shows them with :func:`markdown_table`; :mod:`bench.harness`
runs it (arguments, files, printing).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from eant2_jax.genome import Gene, GeneKind, Genome
from eant2_jax.programs import stats as compilestats

__all__ = [
    "RESULTS_DIR",
    "BenchInputError",
    "CompileClock",
    "Column",
    "Timing",
    "child_env",
    "default_out",
    "device_tag",
    "eant2_argv",
    "environment",
    "evosax_start",
    "library_digest",
    "git_commit",
    "hash_sources",
    "markdown_table",
    "minimal_genome",
    "random_genome",
    "random_population",
    "time_call",
]

RESULTS_DIR = Path(__file__).resolve().parent / "results"


class BenchInputError(ValueError):
    """Bad input to a suite (a file, an option); ``python -m bench`` prints it as one line."""


# ------------------------------------------------------------------------------ environment
def environment() -> dict[str, Any]:
    """Where the numbers were taken: device, platform, library versions, date (UTC)."""
    dev = jax.devices()[0]
    try:
        import jaxlib

        jaxlib_version = jaxlib.__version__
    except (ImportError, AttributeError):  # pragma: no cover - jaxlib always ships with jax
        jaxlib_version = None
    return {
        "device_kind": dev.device_kind,
        "platform": dev.platform,
        "device_count": jax.device_count(),
        "jax_version": jax.__version__,
        "jaxlib_version": jaxlib_version,
        "numpy_version": np.__version__,
        "python_version": platform.python_version(),
        "machine": platform.machine(),
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "library_sha256": library_digest(),
    }


def library_digest() -> str:
    """SHA-256 of the code that made a result: the ``.py`` files of the imported packages
    ``eant2_jax``, ``eant2_jax.kernels`` (the repository's ``kernels/``) and ``bench``, each by
    its path inside its package, so that a copy without git (a device's) can be matched to a
    commit: check the commit out and compare ``python -c "from bench.common import
    library_digest; print(library_digest())"``."""
    import importlib

    h = hashlib.sha256()
    for name, label in (("eant2_jax", "eant2_jax"), ("eant2_jax.kernels", "kernels"),
                        ("bench", "bench")):  # fmt: skip
        root = Path(importlib.import_module(name).__file__).parent
        # The kernels installed inside the package are hashed as kernels.
        skip = "kernels/" if name == "eant2_jax" else None
        hash_sources(h, root, prefix=f"{label}/", skip=skip)
    return h.hexdigest()


def hash_sources(h, root: Path, *, prefix: str = "", skip: str | None = None) -> None:
    """Feed ``h`` every ``.py`` file under ``root``, in path order, as its path relative to
    ``root`` (after ``prefix``), a NUL, its bytes and a NUL; paths starting with ``skip``
    are left out."""
    for path in sorted(Path(root).rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if skip is None or not rel.startswith(skip):
            h.update(f"{prefix}{rel}".encode() + b"\0" + path.read_bytes() + b"\0")


def evosax_start(es, key: jax.Array, x0: jax.Array, params) -> Any:
    """``es.init(key, x0, params)`` with every leaf strongly typed: evosax's init leaves weakly
    typed floats that its ask/tell return strongly typed, so a step compiled on the start
    state would compile a second time on the state it returns (inside a timed loop)."""
    # evosax broadcasts [n] against [popsize, n]; allow it whatever the global config.
    with jax.numpy_rank_promotion("allow"):
        state = es.init(key, x0, params)
    return jax.tree.map(lambda a: jnp.asarray(a, a.dtype), state)


def unseen_key(seed: int) -> jax.Array:
    """A key for checking a run's result on episodes it never saw: ``fold_in(key(seed),
    2**31 - 1)``, a stream no run split from ``key(seed)`` ever draws."""
    return jax.random.fold_in(jax.random.key(seed), 2**31 - 1)


# Words of a device kind that name its maker or family, not the model (left out of tags).
_MAKERS = {"nvidia", "amd", "intel", "geforce", "tesla", "google", "instinct"}


def device_tag(platform: str | None = None, kind: str | None = None) -> str:
    """The tag of result file names, one per kind of device: the platform, then the model's
    first word on accelerators (``cpu``; ``gpu-h100`` for "NVIDIA H100 80GB HBM3", ``gpu-h200``
    for "NVIDIA H200"), so that each suite keeps one result file per device.

    Args:
      platform: a device's ``platform``; kind: its ``device_kind`` (default: the first
        device's).
    """
    if platform is None or kind is None:
        dev = jax.devices()[0]
        platform, kind = dev.platform, dev.device_kind
    if platform == "cpu":
        return "cpu"
    model = ""
    for word in [w for w in re.findall("[a-z0-9]+", kind.lower()) if w not in _MAKERS][:3]:
        if word != platform:
            model += word
        if any(c.isdigit() for c in word):  # "h100"; "rtx", "4090" -> "rtx4090"
            break
    return f"{platform}-{model}" if model else platform


def default_out(name: str) -> Path:
    """``bench/results/<name>-<device tag>.json``."""
    return RESULTS_DIR / f"{name}-{device_tag()}.json"


def eant2_pruner(quick: bool) -> str:
    """eant2's pruner in a bench run: covariance, the paper's method; none in a ``--quick``
    run, a smoke test of the bench's bookkeeping, whose engine then compiles in about half the
    time on a CPU (the pruner itself is tested by the test suite's own tests)."""
    return "none" if quick else "covariance"


# ------------------------------------------------------------------------ child processes
def eant2_argv(*args: str) -> list[str]:
    """The argv of ``eant2 ARGS`` run by this interpreter (no console script needed)."""
    main = "import sys; from eant2_jax.app.cli import main; sys.exit(main(sys.argv[1:]))"
    return [sys.executable, "-c", main, *args]


def child_env(pythonpath: str | None = None, **extra: str) -> dict[str, str]:
    """This process's environment for a child, with ``extra`` set and ``pythonpath`` (another
    install of eant2_jax, timed side by side) put first on ``PYTHONPATH``."""
    env = dict(os.environ, **extra)
    if pythonpath:
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [pythonpath, env.get("PYTHONPATH")]))
    return env


# ------------------------------------------------------------------------------ compiling
class CompileClock:
    """Counts XLA compilations and sums the seconds JAX spends tracing, lowering and compiling
    them (all programs, any caller) since it was made (the library's `eant2_jax.programs.stats`
    counters, read relative to that moment)."""

    def __init__(self):
        self._start = compilestats.snapshot()

    @property
    def compiles(self) -> int:
        return (compilestats.snapshot() - self._start).programs

    def snapshot(self) -> dict[str, float]:
        d = compilestats.snapshot() - self._start
        return {"compiles": d.programs, "trace_s": d.trace_s, "lower_s": d.lower_s,
                "compile_s": d.compile_s}  # fmt: skip


# ----------------------------------------------------------------------------------- timing
class Timing(NamedTuple):
    """Seconds of one benchmarked call.

    Attributes:
      first_call_s: the first call, tracing and XLA compilation included.
      median_s: median of the timed repeats (steady state, after warm-up).
      min_s: fastest timed repeat.
      times_s: every timed repeat.
    """

    first_call_s: float
    median_s: float
    min_s: float
    times_s: tuple[float, ...]

    @property
    def compile_s(self) -> float:
        """First call minus one steady-state call: tracing + compilation, approximately."""
        return max(self.first_call_s - self.median_s, 0.0)


def time_call(fn: Callable[[], Any], *, warmup: int = 2, repeats: int = 7) -> Timing:
    """Time a call that returns JAX arrays; every measurement waits for the device.

    Args:
      fn: zero-argument callable (typically a jitted function with its arguments bound).
        The caller makes sure its program is not in the compilation cache yet
        (``jax.clear_caches()``) if ``first_call_s`` is to include compilation.
      warmup: untimed calls between the first call and the timed ones.
      repeats: timed calls (>= 1); the median is reported.

    Returns:
      The :class:`Timing`.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return Timing(first, statistics.median(times), min(times), tuple(times))


# --------------------------------------------------------------------------- random genomes
def minimal_genome(rng: np.random.Generator, n_inputs: int, n_outputs: int) -> list[Gene]:
    """EANT2's minimal start network: every output neuron reads every input (paper III.B)."""
    genes: list[Gene] = []
    for r in range(n_outputs):
        genes.append(Gene(GeneKind.NEURON, r, float(rng.normal()), n_inputs))
        genes.extend(Gene(GeneKind.INPUT, j, float(rng.normal(scale=0.5))) for j in range(n_inputs))
    return genes


def random_genome(
    rng: np.random.Generator,
    n_genes: int,
    *,
    n_inputs: int = 10,
    n_outputs: int = 3,
    p_neuron: float = 0.6,
    p_forward: float = 0.25,
) -> Genome:
    """A random valid genome grown from the minimal network to at least ``n_genes`` genes.

    Growth repeats, until the genome is long enough, one of three structural mutations (the
    same kinds EANT2's exploration uses): with probability ``p_neuron`` a new hidden neuron
    reading 1-3 random inputs (at most all of them; and a bias half the time) becomes the
    first input of a random neuron; with ``p_forward`` a forward jumper from a neuron to the
    right is added to a random neuron; otherwise a recurrent jumper from any neuron. The
    result may overshoot ``n_genes`` by at most the size of one new neuron (5 genes).

    Args:
      rng: the NumPy generator (the result depends only on its state).
      n_genes: target length; a genome is never shorter than the minimal network,
        ``n_outputs * (n_inputs + 1)`` genes.
      n_inputs, n_outputs: network interface.
      p_neuron, p_forward: mutation probabilities (the rest are recurrent jumpers).

    Returns:
      A validated :class:`~eant2_jax.genome.Genome`.
    """
    genes = minimal_genome(rng, n_inputs, n_outputs)
    next_id = n_outputs
    # Gene indices of the neurons, kept sorted; updated on each insertion instead of
    # rescanning the genome (the scan made populations of 2048 x 300 genes slow to build).
    neurons = [r * (n_inputs + 1) for r in range(n_outputs)]
    while len(genes) < n_genes:
        i = neurons[rng.integers(len(neurons))]
        u = rng.random()
        if u < p_neuron:
            k = int(rng.integers(1, min(3, n_inputs) + 1))  # the same draws where n_inputs >= 3
            new = [
                Gene(GeneKind.INPUT, int(j), float(rng.normal(scale=0.5)))
                for j in rng.choice(n_inputs, size=k, replace=False)
            ]
            if rng.random() < 0.5:
                new.append(Gene(GeneKind.BIAS, -1, float(rng.normal(scale=0.5))))
            new.insert(0, Gene(GeneKind.NEURON, next_id, float(rng.normal()), len(new)))
            next_id += 1
        elif u < p_neuron + p_forward:
            # Only neurons to the right of the reader: they are evaluated before it.
            right = [n for n in neurons if n > i]
            if not right:
                continue
            src = genes[right[rng.integers(len(right))]].ref
            new = [Gene(GeneKind.FORWARD, src, float(rng.normal(scale=0.5)))]
        else:
            src = genes[neurons[rng.integers(len(neurons))]].ref
            new = [Gene(GeneKind.RECURRENT, src, float(rng.normal(scale=0.5)))]
        genes[i] = dataclasses.replace(genes[i], arity=genes[i].arity + 1)
        genes[i + 1 : i + 1] = new
        shift = len(new)
        neurons = [n + shift if n > i else n for n in neurons]
        if new[0].kind == GeneKind.NEURON:
            neurons.append(i + 1)
            neurons.sort()
    return Genome(genes)


def random_population(seed: int, count: int, n_genes: int, **kwargs: Any) -> list[Genome]:
    """``count`` random genomes of about ``n_genes`` genes, deterministic in ``seed``.

    Keyword arguments go to :func:`random_genome`.
    """
    rng = np.random.default_rng(seed)
    return [random_genome(rng, n_genes, **kwargs) for _ in range(count)]


# ---------------------------------------------------------------------------------- output
class Column(NamedTuple):
    """One column of a markdown table: row key (or callable on the row), header, format."""

    key: str | Callable[[dict], Any]
    header: str
    fmt: str = "{}"


def markdown_table(rows: Sequence[dict], columns: Sequence[Column]) -> str:
    """A GitHub markdown table of ``rows``; missing or None values print as an em dash."""
    lines = [
        "| " + " | ".join(c.header for c in columns) + " |",
        "| " + " | ".join("---" for _ in columns) + " |",
    ]
    for row in rows:
        cells = []
        for c in columns:
            value = c.key(row) if callable(c.key) else row.get(c.key)
            cells.append("—" if value is None else c.fmt.format(value))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def git_commit() -> str:
    """git's short HEAD of this checkout, ``+dirty`` when tracked files differ from it;
    ``unknown`` outside a git checkout."""
    root = Path(__file__).resolve().parent.parent

    def git(*args: str) -> str:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True)
        return out.stdout.strip()

    try:
        head, dirty = git("rev-parse", "--short", "HEAD"), git("status", "--porcelain", "-uno")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")
