"""Snakemake adapter for the prepare stage (logic in physgs_steps.prepare)."""
from physgs_steps.prepare import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("prepare", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
