"""Snakemake adapter for bench_stress (logic in physgs_steps.benchmark.stress)."""
from physgs_steps.benchmark.stress import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("bench_stress", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
