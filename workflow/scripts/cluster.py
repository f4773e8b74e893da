"""Snakemake adapter for the cluster stage (logic in physgs_steps.cluster)."""
from physgs_steps.cluster import run as stage
from physgs_steps.runtime import run_stage, snakemake_io

run_stage("cluster", stage, *snakemake_io(snakemake))  # noqa: F821 (injected by Snakemake)
