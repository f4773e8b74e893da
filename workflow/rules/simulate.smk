rule forward_sim:
    input:
        unpack(sim_inputs),
    output:
        keyframes="results/{scene}/sim/{sim_id}/{step}/forward.h5",
    params:
        cfg=stage_cfg("sim", "sim"),
        job=job_command("forward_sim", stage_cfg("sim", "sim")),
    log:
        "results/{scene}/logs/forward_sim-{sim_id}-{step}.log",
    benchmark:
        "results/{scene}/benchmarks/forward_sim-{sim_id}-{step}.tsv"
    resources:
        mem_mb=mem_mb("forward_sim"),
        runtime=runtime_min("forward_sim"),
        gpu=gpu_count("forward_sim"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


rule bgdo_update:
    input:
        unpack(bgdo_inputs),
    output:
        params="results/{scene}/sim/{sim_id}/{step}/params.json",
    wildcard_constraints:
        step=r"it[1-9][0-9]*-[0-9a-f]+",
    params:
        cfg=stage_cfg("sim", "bgdo"),
        job=job_command("bgdo_update", stage_cfg("sim", "bgdo")),
    log:
        "results/{scene}/logs/bgdo_update-{sim_id}-{step}.log",
    benchmark:
        "results/{scene}/benchmarks/bgdo_update-{sim_id}-{step}.tsv"
    resources:
        mem_mb=mem_mb("bgdo_update"),
        runtime=runtime_min("bgdo_update"),
        gpu=gpu_count("bgdo_update"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)


rule final_sim:
    input:
        unpack(final_inputs),
    output:
        frames="results/{scene}/sim/{sim_id}/{step}/final.h5",
    params:
        cfg=stage_cfg("sim", "sim"),
        job=job_command("final_sim", stage_cfg("sim", "sim")),
    log:
        "results/{scene}/logs/final_sim-{sim_id}-{step}.log",
    benchmark:
        "results/{scene}/benchmarks/final_sim-{sim_id}-{step}.tsv"
    resources:
        mem_mb=mem_mb("final_sim"),
        runtime=runtime_min("final_sim"),
        gpu=gpu_count("final_sim"),
    run:
        stage_job(rule, input, output, params, log) or shell(STAGE_JOB)
