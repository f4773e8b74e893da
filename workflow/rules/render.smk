rule render:
    input:
        unpack(render_inputs),
    output:
        video="results/{target}/video.mp4",
        contact_sheet="results/{target}/contact_sheet.png",
        report="results/{target}/render.json",
    params:
        cfg=target_cfg("render"),
        job=job_command("render", target_cfg("render")),
    log:
        "results/{target}/logs/render.log",
    benchmark:
        "results/{target}/benchmarks/render.tsv"
    resources:
        mem_mb=mem_mb("render"),
        runtime=runtime_min("render"),
        gpu=gpu_count("render"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


rule metrics:
    input:
        video="results/{target}/video.mp4",
        frames=lambda w: target_plan(w.target).path("final"),
        params=lambda w: target_plan(w.target).path("params"),
    output:
        metrics="results/{target}/metrics.json",
    params:
        cfg=target_cfg("metrics"),
        job=job_command("metrics", target_cfg("metrics")),
    log:
        "results/{target}/logs/metrics.log",
    benchmark:
        "results/{target}/benchmarks/metrics.tsv"
    resources:
        mem_mb=mem_mb("metrics"),
        runtime=runtime_min("metrics"),
        gpu=gpu_count("metrics"),   # 0 unless "metrics" is in resources.gpu_stages (a VideoPhy2 rater on a GPU)
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
