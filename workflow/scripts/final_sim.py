"""Snakemake adapter for the final_sim stage (logic in physgs_steps.simulate)."""
from physgs_steps.simulate import run_final as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("final_sim", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
