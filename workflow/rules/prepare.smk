rule prepare:
    input:
        unpack(prepare_inputs),
    output:
        scene="results/{scene}/scene.ply",
        transform="results/{scene}/transform.json",
    params:
        cfg=target_cfg("prepare", "scene"),
        job=job_command("prepare", target_cfg("prepare", "scene")),
    log:
        "results/{scene}/logs/prepare.log",
    benchmark:
        "results/{scene}/benchmarks/prepare.tsv"
    resources:
        mem_mb=mem_mb("prepare"),
        runtime=runtime_min("prepare"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
