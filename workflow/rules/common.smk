# Helpers shared by all rules: config validation, the artifact plan, resources.
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

from physgs_steps import config as C
from physgs_steps import plan as P

C.validate_config(config)

SCENES = sorted(p.stem for p in Path(config["scenes_dir"]).glob("*.yaml"))
REG = P.Registry(config, SCENES)
DEVICE = config["device"]


wildcard_constraints:
    scene=r"[A-Za-z0-9_\-]+",
    target=r"[A-Za-z0-9_\-]+(/ablations/[A-Za-z0-9_\-]+)?",
    cluster_id=r"[A-Za-z0-9_\-]+",
    fill_id=r"[A-Za-z0-9_\-]+",
    params_id=r"[A-Za-z0-9_\-]+",
    sim_id=r"[A-Za-z0-9_\-]+",
    step=r"it0|it[1-9][0-9]*-[0-9a-f]+",


def plan_path(target, kind, step=None):
    return REG.plan(target).path(kind, step)


def plan_for(w, kind):
    """The plan that owns the artifact id in this job's output path."""
    ident = getattr(w, f"{kind}_id")
    return REG.for_id(w.scene, kind, ident)


def stage_cfg(kind, stage):
    return lambda w: plan_for(w, kind).cfgs[stage]


def gpu_count(stage):
    """GPU stages ask for a GPU only when the configured device is CUDA."""
    return 1 if DEVICE == "cuda" and stage in config["resources"]["gpu_stages"] else 0


def res(stage, key):
    r = config["resources"]["stages"].get(stage, {})
    return r.get(key, config["resources"]["default"][key])


def runtime_min(stage):
    return lambda wildcards, attempt: int(res(stage, "runtime") * attempt)


# ---- input functions of the rules

def prepare_inputs(w):
    sc = REG.plan(w.scene).cfgs["prepare"]["scene"]
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
    plan = REG.plan(w.target)
    ins = {"frames": plan.path("final"), "scene": plan.path("scene"), "transform": plan.path("transform"),
           "carrier": plan.path("carrier")}
    cam = plan.cfgs["render"]["scene"].get("camera") or {}
    if cam.get("mode") == "cameras_json":  # an INRIA training run's cameras.json
        ins["cameras"] = str(C.resolve_path(cam["cameras_json"]))
    return ins


def report_jobs(w):
    plan = REG.plan(w.target)
    return [{"rule": r, "step": s, "benchmark": plan.benchmark_path(r, s)} for r, s in plan.jobs()]
