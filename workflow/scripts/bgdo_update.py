"""Snakemake adapter for the bgdo_update stage (logic in physgs_steps.bgdo)."""
from physgs_steps.bgdo import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("bgdo_update", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
