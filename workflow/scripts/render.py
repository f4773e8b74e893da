"""Snakemake adapter for the render stage (logic in physgs_steps.render.stage)."""
from physgs_steps.worker import dispatch

dispatch("render", snakemake)  # noqa: F821 (injected by Snakemake); runs in the warm worker where configured
