"""Timings: each script measures what something costs on this machine (seconds, rates, memory) and prints every
figure with the load average and the float32 matmul rate (``benchmarks/harness.py``). Run as
``python -m benchmarks.perf.NAME --help``."""
