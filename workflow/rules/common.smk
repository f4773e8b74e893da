# Helpers shared by all rules: config validation, the artifact plan, resources.
#
# Problems stop Snakemake with one line on stderr ("physgs: <what is wrong, where, the valid
# choices>") and exit status 1, never a traceback. A broken scene file stops only the
# targets of that scene, when one is requested (plans are made on first use);
# `physgs check` lists every problem of every scene file at once.
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

from physgs_steps import config as C
from physgs_steps import plan as P
from physgs_steps.errors import ConfigError, PhysGSError

# worker.enabled auto serves a local one-core run's jobs in the warm worker (worker.py)
if workflow.is_main_process and workflow.local_exec:
    from physgs_steps.worker import note_run_cores

    note_run_cores(lambda: workflow.cores)


def fail(err):
    """Stop with a one-line message and exit status 1 (at parse time or in an input function)."""
    print(f"physgs: {err}", file=sys.stderr)
    sys.exit(1)


def config_layers():
    """[(name, dict)] in the order Snakemake applied them: config/config.yaml, each
    --configfile, then --config (for naming where a bad value came from)."""
    settings = getattr(workflow, "config_settings", None)
    layers = []
    for f in ["config/config.yaml", *[str(f) for f in (getattr(settings, "configfiles", None) or [])]]:
        try:
            layers.append((f, C.read_yaml(f)))
        except PhysGSError:
            pass
    layers.append(("--config", dict(getattr(settings, "config", None) or {})))
    return layers


try:
    C.validate_config(config)
except ConfigError as e:
    import re

    key = e.key if e.key != "<root>" else ""
    unknown = re.search(r"'([^']+)' (?:was|were) unexpected", e.problem)  # an unknown key: where was it set?
    if unknown:
        key = f"{key}.{unknown.group(1)}" if key else unknown.group(1)
    fail(ConfigError(e.key, e.problem, (C.origin_of(key, config_layers()) if key else None) or e.source))

SCENES, NO_SCENES = C.list_scenes(config)  # NO_SCENES: why there are none (a missing folder...)
REG = P.Registry(config, SCENES)
DEVICE = config["device"]


def scene_problem(e):
    """The message of a plan's problem; a scene file's own problem points at `physgs check`."""
    in_file = getattr(e, "source", None) or getattr(e, "path", None)
    return f"{e} (physgs check lists every problem of every scene file)" if in_file else str(e)


def target_plan(target):
    """The plan of a target (``bear``, ``bear/ablations/no_bgdo``), or stop with its problem."""
    try:
        return REG.plan(target)
    except PhysGSError as e:
        fail(scene_problem(e))


def main_scene():
    """`snakemake --cores 1` alone: the main job (bear), or the first scene of a custom scenes_dir."""
    if not SCENES:
        fail(NO_SCENES)
    return "bear" if "bear" in SCENES else SCENES[0]


# A scene folder is a scene name, or a benchmark run folder benchmark/<scale>/runs/<name>
# (physgs_steps.benchmark.spec); a target adds /ablations/<name> (benchmark: /variants/<name>).
wildcard_constraints:
    scene=r"(benchmark/(smoke|cpu|full)/runs/)?[A-Za-z0-9_\-]+",
    target=r"[A-Za-z0-9_\-]+(/ablations/[A-Za-z0-9_\-]+)?|benchmark/(smoke|cpu|full)/runs/[A-Za-z0-9_\-]+(/variants/[A-Za-z0-9_\-]+)?",
    cluster_id=r"[A-Za-z0-9_\-]+",
    fill_id=r"[A-Za-z0-9_\-]+",
    params_id=r"[A-Za-z0-9_\-]+",
    sim_id=r"[A-Za-z0-9_\-]+",
    step=r"it0|it[1-9][0-9]*-[0-9a-f]+",


def plan_path(target, kind, step=None):
    return target_plan(target).path(kind, step)


def plan_for(w, kind):
    """The plan that owns the artifact id in this job's output path."""
    ident = getattr(w, f"{kind}_id")
    try:
        return REG.for_id(w.scene, kind, ident)
    except PhysGSError as e:
        fail(scene_problem(e))


def stage_cfg(kind, stage):
    return lambda w: plan_for(w, kind).cfgs[stage]


def gpu_count(stage):
    """GPU stages ask for a GPU only when the configured device is CUDA."""
    return 1 if DEVICE == "cuda" and stage in config["resources"]["gpu_stages"] else 0


def job_request(stage, w):
    """mem_mb and runtime of a job: its rule, the configured material backend and the size of
    its scene (physgs_steps.resources; config section `resources`)."""
    from physgs_steps import resources

    target = getattr(w, "target", None) or getattr(w, "scene", None)
    if stage == "vlm_params":  # the plan of this params id (an ablation may change the backend)
        plan = plan_for(w, "params")
    else:  # None: a job over no scene (the benchmark's aggregations)
        plan = target_plan(target) if target else None
    n = resources.scene_gaussians(plan.cfgs["prepare"]["scene"]) if plan is not None else None
    backend = plan.cfgs["params"]["materials"]["backend"] if stage == "vlm_params" else None
    return resources.request(config["resources"], stage, n, backend)


def mem_mb(stage):
    return lambda wildcards: job_request(stage, wildcards)["mem_mb"]


def runtime_min(stage):
    return lambda wildcards, attempt: job_request(stage, wildcards)["runtime"] * attempt


# ---- the stage rules' job (src/physgs_steps/job.py)
# Each stage rule's `run:` block is `stage_job(rule, input, output, params, log) or
# shell(STAGE_JOB)`. Snakemake runs a local job's `run:` block in a thread of its own process
# (profiles/default sets force-use-threads; a job Snakemake spawns itself, e.g. on a SLURM node,
# gets --force-use-threads from it): where the warm stage worker serves the stage (worker.py),
# stage_job hands the job to it over its socket from there, with no process started per job.
# Otherwise (no worker wanted or none could start) it returns False and the job runs
# `{params.job} {log:q}`: the job client (no Snakemake, no numpy) running the stage in its own
# process. params.job is derived from the job's input and output, so Snakemake's params rerun
# trigger compares params.cfg alone.
STAGE_JOB = "{params.job} {log:q}"


def stage_job(stage, input, output, params, log):
    """True when the warm stage worker ran this job of ``stage`` (a failed stage raises)."""
    from physgs_steps.job import run_in_worker

    who = "Snakemake's main process" if workflow.is_main_process else "a Snakemake process of this job"
    return run_in_worker(stage, dict(input.items()), dict(output.items()), params.cfg, log[0] if log else None,
                         config.get("worker"), who)


def job_command(stage, cfg):
    """params.job of a stage rule whose params.cfg is ``cfg`` (a function of the wildcards)."""
    from physgs_steps.job import command

    return lambda wildcards, input, output: command(stage, dict(input.items()), dict(output.items()),
                                                    cfg(wildcards), config.get("worker"))


def target_cfg(stage, wildcard="target"):
    """The config subset of ``stage`` in the plan of the job's target (or scene) wildcard."""
    return lambda w: target_plan(getattr(w, wildcard)).cfgs[stage]


# ---- input functions of the rules

def prepare_inputs(w):
    sc = target_plan(w.scene).cfgs["prepare"]["scene"]
    kind, path = C.resolve_source(sc)
    return {"source": str(path)} if kind == "file" else {}


def sim_inputs(w):
    plan = plan_for(w, "sim")
    return {"particles": plan.path("particles"), "params": plan.path("params", w.step)}


def final_inputs(w):
    return dict(sim_inputs(w), transform=plan_for(w, "sim").path("transform"))


def bgdo_inputs(w):
    plan = plan_for(w, "sim")
    prev = P.previous_step(w.step)
    return {"keyframes": plan.path("forward", prev), "params": plan.path("params", prev)}


def render_inputs(w):
    plan = target_plan(w.target)
    ins = {"frames": plan.path("final"), "scene": plan.path("scene"), "transform": plan.path("transform"),
           "carrier": plan.path("carrier")}
    cam = plan.cfgs["render"]["scene"].get("camera") or {}
    if cam.get("mode") == "cameras_json":  # an INRIA training run's cameras.json
        ins["cameras"] = str(C.resolve_path(cam["cameras_json"]))
    return ins


def report_jobs(w):
    plan = target_plan(w.target)
    return [{"rule": r, "step": s, "benchmark": plan.benchmark_path(r, s)} for r, s in plan.jobs()]


# ---- the benchmark (workflow/rules/benchmark.smk)

from physgs_steps.benchmark import spec as BS

BENCH_SCALE = config["benchmark"]["scale"]
BENCH_SCALES = "|".join(BS.SCALES)
BENCH_TABLES = ("comparison", "comparison_scenes", "ablations", "robustness", "fill", "bgdo_change", "stress_vs_E")


def bench_spec(scale):
    return BS.spec_for(config, scale)


def bench_report_path(name, scale=BENCH_SCALE):
    return f"{BS.report_dir(scale)}/{name}"


def bench_stress_plan(w):
    spec, name = BS.spec_for_key(config, w.scene)
    if name != spec.stress["scene"]:
        raise C.ConfigError("benchmark.stress.scene", f"stress runs are made for '{spec.stress['scene']}', not '{name}'")
    return spec.plan(name)


def bench_stress_cfg(w):
    spec, _ = BS.spec_for_key(config, w.scene)
    return spec.stress_cfg(w.stress_id, int(w.index))


def bench_stage_cfg(w):
    return bench_spec(w.scale).stage_cfg()


def bench_report_cfg(w):
    return bench_spec(w.scale).report_cfg()


def stop_worker(after_success=False):
    """End the warm stage worker of this run's code (worker.py) at the end of a run; after a
    successful one it stays for worker.idle_seconds unless worker.stop_after_run."""
    from physgs_steps import worker as W

    wcfg = config.get("worker") or {}
    if after_success and not wcfg.get("stop_after_run", False):
        # no ping: the worker answers only after collecting the last job's garbage (0.1 s and
        # more of every run's end); `python -m physgs_steps.worker status` tells its size
        pid = W.serving_pid()
        if pid is not None:
            print(f"physgs: the warm stage worker (pid {pid}) stays for "
                  f"{wcfg.get('idle_seconds', W.DEFAULT_IDLE_SECONDS):g} s without a job (worker.stop_after_run "
                  "stops it now; `python -m physgs_steps.worker status` shows its memory, `... stop` stops it)",
                  file=sys.stderr)
        return
    if W.shutdown():
        print("physgs: stopped the warm stage worker", file=sys.stderr)


# ---------------------------------------------------------------- validation (validation.smk)
# VAL (config["validation"]) is defined at the top of validation.smk.

def val_request(stage):
    """mem_mb and runtime (minutes) of a validation job (config section `resources`)."""
    from physgs_steps import resources

    return resources.request(config["resources"], stage)


def val_cfg(keys, **extra):
    """The config a job reads (only these keys: a change elsewhere in `validation` re-runs nothing)."""
    sub = {k: VAL[k] for k in keys}
    return lambda w: {"validation": sub, "device": DEVICE, **{k: getattr(w, v) for k, v in extra.items()}}


def val_before(w):
    """The optional `validation.before` snapshot as a named input (absent when null)."""
    b = VAL.get("before")  # --config gives null as a string
    return {"before": str(C.resolve_path(b))} if b and str(b).lower() not in ("null", "none") else {}
