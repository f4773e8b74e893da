"""Snakemake adapter for benchmark_stage_table (logic in physgs_steps.benchmark.report)."""
from physgs_steps.benchmark.report import run_stages as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("benchmark_stage_table", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
