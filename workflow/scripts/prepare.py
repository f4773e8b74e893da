"""Snakemake adapter for the prepare stage (logic in physgs_steps.prepare)."""
from physgs_steps.worker import dispatch

dispatch("prepare", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
