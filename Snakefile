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


rule all:
    default_target: True
    input:
        video=plan_path("bear", "video"),
        metrics=plan_path("bear", "metrics"),
