"""Benchmarks of eant2_jax. Run each as a module from the repository root, e.g.
``python -m bench.bench_forward --help``; results go to ``bench/results/`` as JSON plus a
markdown table. Shared helpers (device tagging, timing, output) live in :mod:`bench.common`.
"""
