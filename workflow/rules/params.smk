rule vlm_params:
    input:
        scene="results/{scene}/scene.ply",
        labels=lambda w: plan_for(w, "params").path("labels"),
        clusters=lambda w: plan_for(w, "params").path("clusters"),
    output:
        params="results/{scene}/params/{params_id}/params.json",
    params:
        cfg=stage_cfg("params", "params"),
    log:
        "results/{scene}/logs/vlm_params-{params_id}.log",
    benchmark:
        "results/{scene}/benchmarks/vlm_params-{params_id}.tsv"
    resources:
        mem_mb=res("vlm_params", "mem_mb"),
        runtime=runtime_min("vlm_params"),
        gpu=gpu_count("vlm_params"),
    script:
        "../scripts/vlm_params.py"
