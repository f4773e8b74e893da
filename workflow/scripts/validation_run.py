"""Snakemake adapter for one validation run (logic in physgs_steps.validation.stage)."""
from physgs_steps.runtime import run_stage, snakemake_io
from physgs_steps.validation.stage import run_case as stage

run_stage("validation_run", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
