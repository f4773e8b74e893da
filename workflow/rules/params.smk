rule vlm_params:
    input:
        scene="results/{scene}/scene.ply",
        labels=lambda w: plan_for(w, "params").path("labels"),
        clusters=lambda w: plan_for(w, "params").path("clusters"),
    output:
        params="results/{scene}/params/{params_id}/params.json",
    wildcard_constraints:
        params_id=r"(prior|qwen3vl|openai)-[0-9a-f]+",
    params:
        cfg=stage_cfg("params", "params"),
        job=job_command("vlm_params", stage_cfg("params", "params")),
    log:
        "results/{scene}/logs/vlm_params-{params_id}.log",
    benchmark:
        "results/{scene}/benchmarks/vlm_params-{params_id}.tsv"
    resources:
        mem_mb=mem_mb("vlm_params"),
        runtime=runtime_min("vlm_params"),
        gpu=gpu_count("vlm_params"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


# A scene whose instances are all fully pinned leaves vlm_params out: params come from the file.
rule pinned_params:
    input:
        clusters=lambda w: plan_for(w, "params").path("clusters"),
    output:
        params="results/{scene}/params/{params_id}/params.json",
    wildcard_constraints:
        params_id=r"pinned-[0-9a-f]+",
    params:
        cfg=stage_cfg("params", "params"),
        job=job_command("pinned_params", stage_cfg("params", "params")),
    log:
        "results/{scene}/logs/pinned_params-{params_id}.log",
    benchmark:
        "results/{scene}/benchmarks/pinned_params-{params_id}.tsv"
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
