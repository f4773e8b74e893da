"""Snakemake adapter for the fill stage (logic in physgs_steps.fill)."""
from physgs_steps.fill import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("fill", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
