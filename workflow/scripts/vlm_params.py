"""Snakemake adapter for the vlm_params stage (logic in physgs_steps.params.stage)."""
from physgs_steps.params.stage import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("vlm_params", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
