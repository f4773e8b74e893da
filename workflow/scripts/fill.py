"""Snakemake adapter for the fill stage (logic in physgs_steps.fill)."""
from physgs_steps.worker import dispatch

dispatch("fill", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
