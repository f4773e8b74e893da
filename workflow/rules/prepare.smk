def prepare_inputs(w):
    sc = REG.plan(w.scene).cfgs["prepare"]["scene"]
    kind, path = C.resolve_source(sc)
    return {"source": str(path)} if kind == "file" else {}


rule prepare:
    input:
        unpack(prepare_inputs),
    output:
        scene="results/{scene}/scene.ply",
        transform="results/{scene}/transform.json",
    params:
        cfg=lambda w: REG.plan(w.scene).cfgs["prepare"],
    log:
        "results/{scene}/logs/prepare.log",
    benchmark:
        "results/{scene}/benchmarks/prepare.tsv"
    resources:
        mem_mb=res("prepare", "mem_mb"),
        runtime=runtime_min("prepare"),
    script:
        "../scripts/prepare.py"
