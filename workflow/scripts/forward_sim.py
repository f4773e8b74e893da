"""Snakemake adapter for the forward_sim stage (logic in physgs_steps.simulate)."""
from physgs_steps.simulate import run_forward as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("forward_sim", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
