rule cluster:
    input:
        scene="results/{scene}/scene.ply",
    output:
        labels="results/{scene}/cluster/{cluster_id}/labels.npz",
        clusters="results/{scene}/cluster/{cluster_id}/clusters.json",
    params:
        cfg=stage_cfg("cluster", "cluster"),
        job=job_command("cluster", stage_cfg("cluster", "cluster")),
    log:
        "results/{scene}/logs/cluster-{cluster_id}.log",
    benchmark:
        "results/{scene}/benchmarks/cluster-{cluster_id}.tsv"
    resources:
        mem_mb=mem_mb("cluster"),
        runtime=runtime_min("cluster"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


rule fill:
    input:
        scene="results/{scene}/scene.ply",
        transform="results/{scene}/transform.json",
        labels=lambda w: plan_for(w, "fill").path("labels"),
    output:
        particles="results/{scene}/fill/{fill_id}/particles.h5",
        carrier="results/{scene}/fill/{fill_id}/carrier.h5",
        report="results/{scene}/fill/{fill_id}/fill_report.json",
    params:
        cfg=stage_cfg("fill", "fill"),
        job=job_command("fill", stage_cfg("fill", "fill")),
    log:
        "results/{scene}/logs/fill-{fill_id}.log",
    benchmark:
        "results/{scene}/benchmarks/fill-{fill_id}.tsv"
    resources:
        mem_mb=mem_mb("fill"),
        runtime=runtime_min("fill"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
