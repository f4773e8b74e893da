"""Snakemake adapter for bench_stress (logic in physgs_steps.benchmark.stress)."""
from physgs_steps.worker import dispatch

dispatch("bench_stress", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
