"""Snakemake adapter for the cluster stage (logic in physgs_steps.cluster)."""
from physgs_steps.worker import dispatch

dispatch("cluster", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
