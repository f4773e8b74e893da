# Physical validation (issue #14): every case x variant x setting and every sweep pair is one
# cached job, so an interrupted run resumes and a cluster profile runs them in parallel.
# `snakemake --cores all validation` (scale from config `validation.scale`).
from physgs_steps import validation as V

VAL = config["validation"]
VAL_RUNS = V.runs(VAL)
VAL_PAIRS = V.sweep_pairs(VAL)
VAL_CASES = sorted({c for c, _, _ in VAL_RUNS})


wildcard_constraints:
    vcase=r"[a-z_]+",
    vvariant=r"[A-Za-z0-9.]+",
    vsetting=r"g[0-9]+-p[0-9]+-c[0-9.]+",
    vpair=r"[a-z_]+__[a-z_]+",


rule validation:
    input:
        "results/validation/REPORT.md",


rule validation_run:
    output:
        record="results/validation/runs/{vcase}/{vvariant}/{vsetting}.json",
    params:
        cfg=val_cfg(("backend", "timeout_s"), case="vcase", variant="vvariant", setting="vsetting"),
    log:
        "results/validation/logs/run-{vcase}-{vvariant}-{vsetting}.log",
    benchmark:
        "results/validation/benchmarks/run-{vcase}-{vvariant}-{vsetting}.tsv"
    resources:
        mem_mb=val_request("validation_run")["mem_mb"],
        runtime=lambda wildcards, attempt: val_request("validation_run")["runtime"] * attempt,
        gpu=gpu_count("validation_run"),
    script:
        "../scripts/validation_run.py"


rule validation_sweep:
    output:
        result="results/validation/sweep/{vpair}.json",
    params:
        cfg=val_cfg(("backend", "scale", "sweep_timeout_s"), pair="vpair"),
    log:
        "results/validation/logs/sweep-{vpair}.log",
    benchmark:
        "results/validation/benchmarks/sweep-{vpair}.tsv"
    resources:
        mem_mb=val_request("validation_sweep")["mem_mb"],
        runtime=lambda wildcards, attempt: val_request("validation_sweep")["runtime"] * attempt,
        gpu=gpu_count("validation_sweep"),
    script:
        "../scripts/validation_sweep.py"


rule validation_report:
    input:
        unpack(val_before),
        runs=[f"results/validation/runs/{c}/{v}/{s}.json" for c, v, s in VAL_RUNS],
        sweeps=[f"results/validation/sweep/{p}.json" for p in VAL_PAIRS],
    output:
        report="results/validation/REPORT.md",
        snapshot="results/validation/records.json",
        summary="results/validation/summary.csv",
        table="results/validation/error_vs_time.csv",
        figures=[f"results/validation/figures/{c}.png" for c in VAL_CASES],
        physics=[f"results/validation/figures/{c}_physics.png" for c in VAL_CASES if V.CASES[c].has_physics_plot],
    params:
        cfg=lambda w: {"validation": VAL, "device": DEVICE},
    log:
        "results/validation/logs/report.log",
    benchmark:
        "results/validation/benchmarks/report.tsv"
    script:
        "../scripts/validation_report.py"
