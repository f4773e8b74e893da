"""Snakemake adapter for the validation report (logic in physgs_steps.validation.stage)."""
from physgs_steps.runtime import run_stage, snakemake_io
from physgs_steps.validation.stage import report as stage

run_stage("validation_report", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
