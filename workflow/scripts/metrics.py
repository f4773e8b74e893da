"""Snakemake adapter for the metrics stage (logic in physgs_steps.metrics.stage)."""
from physgs_steps.metrics.stage import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("metrics", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
