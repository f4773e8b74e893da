"""Snakemake adapter for the metrics stage (logic in physgs_steps.metrics.stage)."""
from physgs_steps.worker import dispatch

dispatch("metrics", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
