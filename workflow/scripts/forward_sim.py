"""Snakemake adapter for the forward_sim stage (logic in physgs_steps.simulate)."""
from physgs_steps.worker import dispatch

dispatch("forward_sim", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
