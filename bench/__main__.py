"""One entry point for the benchmark suites: ``python -m bench SUITE [options]``.

Suites: forward (the evaluator kernel), cmaes (batched CMA-ES), servo (the MJX task),
generation (whole EANT2 generations, pruning overhead, scaling), peers (CMA-ES, pycma,
NEAT and EANT2 on the servo task at one evaluation budget), pole (evaluations to solve
double pole balancing), profile (where a run's time goes: compilation, a profiler
trace), scaling (over several devices), pycma (the batched engine against pycma + NumPy),
redundancy (pruning on networks of known redundancy), condition (the paper's V.A, float64),
coldstart (wall time of ``eant2 run`` from process start, empty and warm compilation cache).
fuzz_rundir (corrupted run directories and genome texts, issue 16).
brax (``eant2 run brax:ENV`` and ``eant2 resume`` from process start, the best network's
return on new episodes).
field (eant2_jax against TensorNEAT on gymnax and brax environments, issue 18).
runs (many runs of one configuration on one device: lock-step, threads, one at a time).
determinism (what XLA's deterministic GPU mode costs; whether runs repeat without it).
throughput (network-episodes and env steps per second against batch width, brax, issue 41).
width (the batch-width choice of docs/protocol.md section 6 from the field's choice runs).
normalize (the observation-normalisation choice of docs/protocol.md section 8, likewise).
spare (the spare-rows choice of docs/protocol.md section 9, likewise).
rows (whether a row's result depends on how many rows its program holds, stage by stage).
variants (CMA-ES variants for larger networks: evaluations to a target, protocol section 10).
Each writes JSON (device, versions, config, compile time apart from steady state) and a
markdown table, and never over an existing result file unless ``--force`` is given;
``--help`` after the suite name lists its options.
"""

from __future__ import annotations

import importlib
import sys

SUITES = {
    "forward": "bench.bench_forward",
    "cmaes": "bench.bench_cmaes",
    "servo": "bench.bench_servo",
    "generation": "bench.bench_generation",
    "scaling": "bench.bench_scaling",
    "pycma": "bench.bench_pycma",
    "peers": "bench.bench_peers",
    "pole": "bench.bench_pole",
    "profile": "bench.bench_profile",
    "redundancy": "bench.bench_redundancy",
    "condition": "bench.bench_condition",
    "coldstart": "bench.bench_coldstart",
    "fuzz_rundir": "bench.bench_fuzz_rundir",
    "brax": "bench.bench_brax",
    "field": "bench.bench_field",
    "runs": "bench.bench_runs",
    "determinism": "bench.bench_determinism",
    "finetune": "bench.bench_finetune",
    "throughput": "bench.bench_throughput",
    "width": "bench.field_width",
    "normalize": "bench.field_normalize",
    "spare": "bench.field_spare",
    "rows": "bench.bench_rows",
    "variants": "bench.bench_variants",
}


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in SUITES:
        print(__doc__)
        print("usage: python -m bench {" + ",".join(SUITES) + "} [options]")
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    from bench.common import BenchInputError

    try:
        importlib.import_module(SUITES[argv[0]]).main(argv[1:])
    except BenchInputError as e:
        print(f"python -m bench {argv[0]}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
