"""Snakemake adapter for benchmark_stage_table (logic in physgs_steps.benchmark.report): the params name
the manifest by its digest; the job rebuilds it from the workflow's config."""
from physgs_steps.benchmark.report import run_stages as stage
from physgs_steps.benchmark.spec import job_manifest
from physgs_steps.runtime import run_stage, snakemake_io

inputs, outputs, params, log = snakemake_io(snakemake)  # noqa: F821 (injected by Snakemake)
run_stage("benchmark_stage_table", lambda i, o, c, lg: stage(i, o, job_manifest(snakemake.config, c, "stages"), lg),  # noqa: F821
          inputs, outputs, params, log)
