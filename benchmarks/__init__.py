"""Benchmarks and studies, run from the repository root as modules: ``python -m benchmarks.perf.NAME`` (timings,
benchmarks/perf/) and ``python -m benchmarks.studies.NAME`` (experiments on what a model learns, benchmarks/studies/);
``benchmarks/harness.py`` is what they share. Each module's docstring is its command and what it prints."""
