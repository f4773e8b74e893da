"""Snakemake adapter for the vlm_params stage (logic in physgs_steps.params.stage)."""
from physgs_steps.worker import dispatch

dispatch("vlm_params", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
