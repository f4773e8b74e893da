# Time and peak memory of every stage that made a target (from the benchmark: files).
rule stage_report:
    input:
        video="results/{target}/video.mp4",
        metrics="results/{target}/metrics.json",
    output:
        table="results/{target}/stage_report.tsv",
    params:
        cfg=lambda w: {"jobs": report_jobs(w)},
        job=job_command("stage_report", lambda w: {"jobs": report_jobs(w)}),
    log:
        "results/{target}/logs/stage_report.log",
    benchmark:
        "results/{target}/benchmarks/stage_report.tsv"
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
