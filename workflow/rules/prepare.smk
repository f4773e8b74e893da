rule prepare:
    input:
        unpack(prepare_inputs),
    output:
        scene="results/{scene}/scene.ply",
        transform="results/{scene}/transform.json",
    params:
        cfg=lambda w: target_plan(w.scene).cfgs["prepare"],
    log:
        "results/{scene}/logs/prepare.log",
    benchmark:
        "results/{scene}/benchmarks/prepare.tsv"
    resources:
        mem_mb=mem_mb("prepare"),
        runtime=runtime_min("prepare"),
    script:
        "../scripts/prepare.py"
