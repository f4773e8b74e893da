"""The artifact plan: which files a target needs and the config each stage gets.

Each cached artifact lives under a folder named by an id: a readable tag plus a short hash
of exactly the config that decides it *and* the ids of its inputs. Two variants (e.g. the
default pipeline and the "without BGDO" ablation) that agree on a stage's config and inputs
get the same id and so share that artifact; changing only the render settings changes no
upstream id, so only ``render`` re-runs.

    results/{scene}/scene.ply, transform.json                 prepare
    results/{scene}/cluster/{cluster_id}/labels.npz            cluster
    results/{scene}/fill/{fill_id}/particles.h5                fill
    results/{scene}/params/{params_id}/params.json             vlm_params (or pinned_params)
    results/{scene}/sim/{sim_id}/it0/forward.h5                forward_sim with params_0
    results/{scene}/sim/{sim_id}/it{i}-{bgdo_id}/params.json   bgdo_update (params_i)
    results/{scene}/sim/{sim_id}/it{i}-{bgdo_id}/forward.h5    forward_sim with params_i
    results/{scene}/sim/{sim_id}/{step_N}/final.h5             final_sim with params_N
    results/{target}/video.mp4, metrics.json                   render, metrics
where target is ``{scene}`` (default pipeline) or ``{scene}/ablations/{name}``.
"""
from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass, field

from . import config as C
from .errors import ConfigError, PhysGSError

RESULTS = "results"

# Scene-file keys that each stage reads (besides its own config sections).
_GEOMETRY_KEYS = ("at", "box")


def _strip_private(obj):
    if isinstance(obj, dict):
        return {k: _strip_private(v) for k, v in obj.items() if not str(k).startswith("_")}
    if isinstance(obj, (list, tuple)):
        return [_strip_private(v) for v in obj]
    return obj


def short_hash(obj) -> str:
    """8 hex digits of a SHA-1 of ``obj`` (keys starting with '_', e.g. file paths, left out)."""
    blob = json.dumps(_strip_private(obj), sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:8]


def _public_scene(scene_cfg: dict) -> dict:
    return {k: v for k, v in scene_cfg.items() if not k.startswith("_")}


# The scene-file keys each stage reads. A stage gets only these (plus the file's path for
# messages), so that editing e.g. the camera re-runs render alone (Snakemake's params trigger).
SCENE_KEYS = {
    "prepare": ("source", "builtin", "transform"),
    "cluster": ("instances",),  # reduced to the geometry (name, at, box) below
    "fill": ("source", "builtin"),
    "params": ("prompt", "instances"),
    "sim": ("dynamics",),
    "bgdo": ("dynamics",),
    "render": ("camera",),
    "metrics": ("prompt",),
}


def scene_view(scene_cfg: dict, stage: str) -> dict:
    view = {k: copy.deepcopy(scene_cfg.get(k)) for k in SCENE_KEYS[stage] if k in scene_cfg}
    if stage == "cluster":
        view["instances"] = [{k: inst.get(k) for k in ("name", *_GEOMETRY_KEYS)} for inst in view.get("instances") or []]
    view["_path"] = scene_cfg.get("_path")
    return view


@dataclass
class Plan:
    scene: str
    ablation: str | None
    cfgs: dict = field(default_factory=dict)  # stage -> cfg passed to the stage
    ids: dict = field(default_factory=dict)   # artifact kind -> id
    steps: list = field(default_factory=list)  # ["it0", "it1-<bgdo_id>", ...]
    pinned: bool = False  # every instance pinned: params come from the scene file alone

    @property
    def target(self) -> str:
        return self.scene if not self.ablation else f"{self.scene}/ablations/{self.ablation}"

    # ---------------------------------------------------------------- paths
    def path(self, kind: str, step: str | None = None) -> str:
        s = f"{RESULTS}/{self.scene}"
        i = self.ids
        table = {
            "scene": f"{s}/scene.ply",
            "transform": f"{s}/transform.json",
            "labels": f"{s}/cluster/{i.get('cluster')}/labels.npz",
            "clusters": f"{s}/cluster/{i.get('cluster')}/clusters.json",
            "particles": f"{s}/fill/{i.get('fill')}/particles.h5",
            "fill_report": f"{s}/fill/{i.get('fill')}/fill_report.json",
            "params0": f"{s}/params/{i.get('params')}/params.json",
            "video": f"{RESULTS}/{self.target}/video.mp4",
            "contact_sheet": f"{RESULTS}/{self.target}/contact_sheet.png",
            "render_report": f"{RESULTS}/{self.target}/render.json",
            "metrics": f"{RESULTS}/{self.target}/metrics.json",
        }
        if kind in table:
            return table[kind]
        sim = f"{s}/sim/{i.get('sim')}"
        step = step or self.steps[-1]
        if kind == "forward":
            return f"{sim}/{step}/forward.h5"
        if kind == "final":
            return f"{sim}/{self.steps[-1]}/final.h5"
        if kind == "params":
            return self.path("params0") if step == "it0" else f"{sim}/{step}/params.json"
        raise KeyError(kind)


    def jobs(self) -> list[tuple[str, str | None]]:
        """The (rule, step) jobs that produce this target's video, in execution order."""
        jobs = [("prepare", None), ("cluster", None), ("fill", None),
                ("pinned_params" if self.pinned else "vlm_params", None)]
        for i, step in enumerate(self.steps[:-1]):
            jobs += [("forward_sim", step), ("bgdo_update", self.steps[i + 1])]
        return jobs + [("final_sim", self.steps[-1]), ("render", None), ("metrics", None)]

    def benchmark_path(self, rule: str, step: str | None = None) -> str:
        """Where Snakemake's ``benchmark:`` file of a job of this plan lies (see workflow/rules)."""
        s, i = f"{RESULTS}/{self.scene}/benchmarks", self.ids
        names = {
            "prepare": f"{s}/prepare.tsv",
            "cluster": f"{s}/cluster-{i['cluster']}.tsv",
            "fill": f"{s}/fill-{i['fill']}.tsv",
            "vlm_params": f"{s}/vlm_params-{i['params']}.tsv",
            "pinned_params": f"{s}/pinned_params-{i['params']}.tsv",
            "render": f"{RESULTS}/{self.target}/benchmarks/render.tsv",
            "metrics": f"{RESULTS}/{self.target}/benchmarks/metrics.tsv",
        }
        if rule in names:
            return names[rule]
        return f"{s}/{rule}-{i['sim']}-{step}.tsv"


def make_plan(cfg: dict, scene: str, ablation: str | None = None) -> Plan:
    """Compute the stage configs and artifact ids of one target."""
    sc = C.load_scene(cfg, scene)
    pub = _public_scene(sc)
    sec = {s: C.effective_section(cfg, sc, s, ablation) for s in C.SECTIONS}
    device = cfg.get("device", "auto")
    p = Plan(scene, ablation)

    p.cfgs["prepare"] = {"scene": scene_view(sc, "prepare"), "prepare": sec["prepare"]}

    instances = pub.get("instances") or []
    geometry = [{k: inst.get(k) for k in _GEOMETRY_KEYS} for inst in instances]
    p.cfgs["cluster"] = {"scene": scene_view(sc, "cluster"), "cluster": sec["cluster"]}
    p.ids["cluster"] = "dbscan-" + short_hash([sec["cluster"], geometry, p.cfgs["prepare"]])

    fill = copy.deepcopy(sec["fill"])
    if fill.get("n_grid") is None:
        fill["n_grid"] = sec["sim"]["n_grid"]
    p.cfgs["fill"] = {"scene": scene_view(sc, "fill"), "fill": fill}
    tag = fill["method"] if fill["method"] != "ipf" else f"ipf-{fill['occupancy']}-{'mcis' if fill['mcis'] else 'uniform'}"
    p.ids["fill"] = f"{tag}-" + short_hash([fill, p.ids["cluster"]])

    from .params.stage import fully_pinned

    material_view = {"prompt": pub.get("prompt"), "instances": instances}
    p.cfgs["params"] = {"scene": scene_view(sc, "params"), "materials": sec["materials"], "device": device}
    # a scene that pins every instance leaves the material backend (vlm_params) out
    p.pinned = fully_pinned(pub)
    tag = "pinned" if p.pinned else sec["materials"]["backend"]
    p.ids["params"] = tag + "-" + short_hash([material_view, p.ids["cluster"]] + ([] if p.pinned else [sec["materials"]]))

    bgdo = sec["bgdo"]
    forward_keys = {k: bgdo[k] for k in ("key_frames", "forward_frames") if k in bgdo}
    sim_view = {"sim": sec["sim"], "dynamics": pub.get("dynamics"), "forward": forward_keys}
    # the simulation reads only the key-frame settings of bgdo: other BGDO keys must not re-run it
    p.cfgs["sim"] = {"scene": scene_view(sc, "sim"), "sim": sec["sim"], "bgdo": forward_keys, "device": device}
    p.ids["sim"] = "mpm-" + short_hash([sim_view, p.ids["fill"], p.ids["params"]])

    bgdo_view = {k: v for k, v in bgdo.items() if k not in ("iterations",) and k not in forward_keys}
    p.ids["bgdo"] = short_hash(bgdo_view)
    p.cfgs["bgdo"] = {"scene": scene_view(sc, "bgdo"), "sim": sec["sim"], "bgdo": bgdo, "device": device}
    p.steps = ["it0"] + [f"it{i}-{p.ids['bgdo']}" for i in range(1, int(bgdo["iterations"]) + 1)]

    p.cfgs["render"] = {"scene": scene_view(sc, "render"), "render": sec["render"], "device": device}
    p.cfgs["metrics"] = {"scene": scene_view(sc, "metrics"), "metrics": sec["metrics"], "device": device}
    return p


def parse_target(target: str) -> tuple[str, str | None]:
    """``bear`` -> ("bear", None); ``bear/ablations/no_bgdo`` -> ("bear", "no_bgdo")."""
    parts = target.split("/")
    if len(parts) == 1:
        return parts[0], None
    if len(parts) == 3 and parts[1] == "ablations":
        return parts[0], parts[2]
    raise ConfigError("target", f"'{target}' is neither <scene> nor <scene>/ablations/<name>")


def step_index(step: str) -> int:
    return int(step.split("-")[0][2:])


def previous_step(step: str) -> str:
    i = step_index(step)
    if i <= 0:
        raise ValueError(f"step {step} has no predecessor")
    return "it0" if i == 1 else f"it{i - 1}-{step.split('-', 1)[1]}"


class Registry:
    """The plans the workflow knows (every scene x every ablation), indexed by artifact id,
    so that a rule can find the config belonging to an id in its output path.

    Plans are made on first use, one scene (with all its ablations) at a time, so a scene
    file with a problem blocks only its own targets: the problem is recorded and raised when
    one of them is asked for (``snakemake`` for other scenes, ``-n`` included, is unaffected).
    """

    def __init__(self, cfg: dict, scenes: list[str]):
        self.cfg = cfg
        self.scenes = list(scenes)
        self.plans: dict[str, Plan] = {}
        self.problems: dict[str, PhysGSError] = {}  # target -> why it has no plan
        self.by_id: dict[tuple[str, str, str], Plan] = {}
        self._loaded: set[str] = set()

    def ablations(self) -> list[str]:
        return sorted(self.cfg.get("ablations") or {})

    def _load(self, scene: str) -> None:
        if scene in self._loaded:
            return
        self._loaded.add(scene)
        for abl in [None, *self.ablations()]:
            target = scene if abl is None else f"{scene}/ablations/{abl}"
            try:
                plan = make_plan(self.cfg, scene, abl)
            except PhysGSError as e:
                self.problems[target] = e
                continue
            self.plans[target] = plan
            for kind, ident in plan.ids.items():
                self.by_id.setdefault((scene, kind, ident), plan)

    def _check_scene(self, scene: str) -> None:
        if scene not in self.scenes:
            raise ConfigError("scene", f"unknown scene '{scene}': no scene file {C.scene_path(self.cfg, scene)}; "
                                       f"known scenes: {', '.join(self.scenes) or '(none)'}")

    def plan(self, target: str) -> Plan:
        scene, abl = parse_target(target)
        self._check_scene(scene)
        if abl is not None and abl not in self.ablations():
            raise ConfigError("ablations", f"unknown ablation '{abl}' in target '{target}'; ablations: "
                                           f"{', '.join(self.ablations()) or '(none configured)'}")
        self._load(scene)
        if target in self.problems:
            raise self.problems[target]
        return self.plans[target]

    def for_id(self, scene: str, kind: str, ident: str) -> Plan:
        self._check_scene(scene)
        self._load(scene)
        try:
            return self.by_id[(scene, kind, ident)]
        except KeyError:
            if scene in self.problems:  # the scene file itself is broken
                raise self.problems[scene] from None
            raise ConfigError(kind, f"no current config of scene '{scene}' gives {kind} id '{ident}' "
                              "(the path is stale: the config changed since it was requested)") from None
