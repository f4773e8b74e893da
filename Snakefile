# physgs: FastPhysGS as a Snakemake workflow. Stages and artifacts: docs/ARCHITECTURE.md.
from snakemake.utils import min_version

min_version("8.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/prepare.smk"
include: "workflow/rules/fill.smk"
include: "workflow/rules/params.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/benchmark.smk"
include: "workflow/rules/validation.smk"


# `snakemake --cores 1` alone: the main job (bear), or the first scene of a custom scenes_dir.
rule all:
    default_target: True
    input:
        video=lambda w: plan_path(main_scene(), "video"),
        metrics=lambda w: plan_path(main_scene(), "metrics"),


# The warm stage worker (config `worker`, src/physgs_steps/worker.py) outlives a successful run
# by worker.idle_seconds (the next run starts warm) unless worker.stop_after_run; a failed run stops it.
onsuccess:
    stop_worker(after_success=True)


onerror:
    stop_worker()
