"""Snakemake adapter for one pair of the stiff/extreme sweep (logic in physgs_steps.validation.stage)."""
from physgs_steps.runtime import run_stage, snakemake_io
from physgs_steps.validation.stage import run_sweep as stage

run_stage("validation_sweep", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
