# The benchmark (README "Regenerating the benchmark"): `snakemake benchmark` builds
# results/benchmark/<scale>/REPORT.md from ordinary runs of the rules above under
# results/benchmark/<scale>/runs/ (src/physgs_steps/benchmark/). Helpers: common.smk.

localrules: benchmark, benchmark_stages


rule benchmark:
    input:
        bench_report_path("REPORT.md"),


rule benchmark_stages:
    input:
        bench_report_path("stages.md"),


# One run of the stress-vs-E figure: forward simulation + one BGDO step from a given E.
rule bench_stress:
    input:
        particles=lambda w: bench_stress_plan(w).path("particles"),
        params=lambda w: bench_stress_plan(w).path("params0"),
    output:
        result="results/{scene}/stress/{stress_id}/run{index}.json",
    wildcard_constraints:
        scene=r"benchmark/(smoke|cpu|full)/runs/[A-Za-z0-9_\-]+",
        stress_id=r"E-[0-9a-f]+",
        index=r"[0-9]+",
    params:
        cfg=bench_stress_cfg,
        job=job_command("bench_stress", bench_stress_cfg),
    log:
        "results/{scene}/logs/bench_stress-{stress_id}-{index}.log",
    benchmark:
        "results/{scene}/benchmarks/bench_stress-{stress_id}-{index}.tsv"
    resources:
        mem_mb=mem_mb("bench_stress"),
        runtime=runtime_min("bench_stress"),
        gpu=gpu_count("bench_stress"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


rule benchmark_stage_table:
    input:
        unpack(lambda w: bench_spec(w.scale).stage_inputs()),
    output:
        md="results/benchmark/{scale}/stages.md",
        csv="results/benchmark/{scale}/tables/stages.csv",
        json="results/benchmark/{scale}/stages.json",
    wildcard_constraints:
        scale=BENCH_SCALES,
    params:
        cfg=bench_stage_cfg,
    log:
        "results/benchmark/{scale}/logs/benchmark_stage_table.log",
    benchmark:
        "results/benchmark/{scale}/benchmarks/benchmark_stage_table.tsv"
    resources:
        mem_mb=mem_mb("benchmark_report"),
        runtime=runtime_min("benchmark_report"),
    script:
        "../scripts/benchmark_stage_table.py"


rule benchmark_report:
    input:
        unpack(lambda w: bench_spec(w.scale).report_inputs()),
    output:
        report="results/benchmark/{scale}/REPORT.md",
        data="results/benchmark/{scale}/report.json",
        tables=expand("results/benchmark/{{scale}}/tables/{name}.csv", name=BENCH_TABLES),
        figures=directory("results/benchmark/{scale}/figures"),
    wildcard_constraints:
        scale=BENCH_SCALES,
    params:
        cfg=bench_report_cfg,
    log:
        "results/benchmark/{scale}/logs/benchmark_report.log",
    benchmark:
        "results/benchmark/{scale}/benchmarks/benchmark_report.tsv"
    resources:
        mem_mb=mem_mb("benchmark_report"),
        runtime=runtime_min("benchmark_report"),
    script:
        "../scripts/benchmark_report.py"
