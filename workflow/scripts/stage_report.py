"""Snakemake adapter for stage_report (logic in physgs_steps.stage_report)."""
from physgs_steps.runtime import run_stage, snakemake_io
from physgs_steps.stage_report import run as stage

run_stage("stage_report", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
