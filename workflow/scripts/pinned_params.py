"""Snakemake adapter for pinned_params (logic in physgs_steps.params.stage.run_pinned)."""
from physgs_steps.params.stage import run_pinned as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("pinned_params", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
