"""Snakemake adapter for pinned_params (logic in physgs_steps.params.stage.run_pinned)."""
from physgs_steps.worker import dispatch

dispatch("pinned_params", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
