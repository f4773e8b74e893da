"""Snakemake adapter for the bgdo_update stage (logic in physgs_steps.bgdo)."""
from physgs_steps.worker import dispatch

dispatch("bgdo_update", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
