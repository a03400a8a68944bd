"""Benchmarks of eant2_jax: ``python -m bench SUITE [options]`` from the repository root.

Every suite runs under one harness (:mod:`bench.harness`: common options, the JSON and
markdown result files in ``bench/results/``, the no-overwrite rule); shared measuring helpers
(device tagging, timing, random genomes, tables) live in :mod:`bench.common`.
"""
