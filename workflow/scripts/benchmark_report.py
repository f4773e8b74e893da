"""Snakemake adapter for benchmark_report (logic in physgs_steps.benchmark.report)."""
from physgs_steps.benchmark.report import run_report as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("benchmark_report", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
