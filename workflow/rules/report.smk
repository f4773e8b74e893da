rule stage_report:
    input:
        video="results/{target}/video.mp4",
        metrics="results/{target}/metrics.json",
    output:
        table="results/{target}/stage_report.tsv",
    params:
        cfg=lambda w: {"plan": REG.plan(w.target).__dict__ | {"paths": {
            k: REG.plan(w.target).path(k) for k in ("scene", "labels", "particles", "params0", "final", "video")}}},
    log:
        "results/{target}/logs/stage_report.log",
    benchmark:
        "results/{target}/benchmarks/stage_report.tsv"
    script:
        "../scripts/stage_report.py"
