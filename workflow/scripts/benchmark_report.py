"""Snakemake adapter for benchmark_report (logic in physgs_steps.benchmark.report): the params name
the manifest by its digest; the job rebuilds it from the workflow's config."""
from physgs_steps.benchmark.report import run_report as stage
from physgs_steps.benchmark.spec import job_manifest
from physgs_steps.runtime import run_stage, snakemake_io

inputs, outputs, params, log = snakemake_io(snakemake)  # noqa: F821 (injected by Snakemake)
run_stage("benchmark_report", lambda i, o, c, lg: stage(i, o, job_manifest(snakemake.config, c, "report"), lg),  # noqa: F821
          inputs, outputs, params, log)
