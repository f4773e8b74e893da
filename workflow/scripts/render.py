"""Snakemake adapter for the render stage (logic in physgs_steps.render.stage)."""
from physgs_steps.render.stage import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("render", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
