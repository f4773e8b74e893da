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

The benchmark (physgs_steps.benchmark) runs the same rules in its own namespace: its "scene"
is the key ``benchmark/{scale}/runs/{name}`` (so every artifact lies under
``results/benchmark/{scale}/runs/{name}/``, apart from a user's runs of the same scene, which
may have other sizes) and its variants are ``{key}/variants/{variant}``.
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


# Config keys that decide nothing a stage writes for a run that succeeds, left out of the ids:
# sim.on_unstable only says whether an unstable final run stops or keeps its stable frames.
_NOT_HASHED = {"sim": ("on_unstable",)}


def _hashed(section: str, cfg: dict) -> dict:
    return {k: v for k, v in cfg.items() if k not in _NOT_HASHED.get(section, ())}


def _public_scene(scene_cfg: dict) -> dict:
    return {k: v for k, v in scene_cfg.items() if not k.startswith("_")}


# The scene-file keys each stage reads. A stage gets only these (plus the file's path for
# messages), so that editing e.g. the camera re-runs render alone (Snakemake's params trigger).
SCENE_KEYS = {
    "prepare": ("source", "builtin", "transform", "region"),  # region reduced to its box below
    "cluster": ("instances", "region"),  # reduced to the geometry (name, at, box), static pins and choice below
    "fill": ("source", "builtin"),
    "params": ("prompt", "instances"),
    "sim": ("dynamics",),
    "bgdo": ("dynamics",),
    "render": ("camera",),
    "metrics": ("prompt",),
}


def scene_view(scene_cfg: dict, stage: str) -> dict:
    view = {k: copy.deepcopy(scene_cfg.get(k)) for k in SCENE_KEYS[stage] if k in scene_cfg}
    if stage == "prepare" and "region" in view:
        view["region"] = {"box": (view["region"] or {}).get("box")}
    if stage == "cluster":
        region = view.pop("region", None) or {}
        chosen = region.get("instances")
        refs = {r for r in chosen or [] if isinstance(r, str)}
        view["instances"] = [_cluster_entry(inst, refs) for inst in view.get("instances") or []]
        if chosen is not None:
            view["region"] = {"instances": chosen}
    view["_path"] = scene_cfg.get("_path")
    return view


def _cluster_entry(inst: dict, refs: set) -> dict:
    """What the cluster stage reads of a scene ``instances`` entry: its geometry, a static pin,
    and its hint only when ``region.instances`` refers to it by hint (so editing a hint the
    material stage reads does not re-run the clustering)."""
    out = {k: inst.get(k) for k in ("name", *_GEOMETRY_KEYS)}
    if inst.get("static"):
        out["static"] = True
    if inst.get("hint") is not None and inst.get("hint") in refs:
        out["hint"] = inst["hint"]
    return out


@dataclass
class Plan:
    scene: str          # the folder under results/: a scene name, or a benchmark key benchmark/<scale>/runs/<name>
    ablation: str | None
    cfgs: dict = field(default_factory=dict)  # stage -> cfg passed to the stage
    ids: dict = field(default_factory=dict)   # artifact kind -> id
    steps: list = field(default_factory=list)  # ["it0", "it1-<bgdo_id>", ...]
    pinned: bool = False  # every instance pinned: params come from the scene file alone
    variant_dir: str = "ablations"  # the path segment before a variant's name ("variants" in the benchmark)

    @property
    def name(self) -> str:
        """The scene file's name (``bear`` also for the benchmark key ``benchmark/cpu/runs/bear``)."""
        return self.scene.rsplit("/", 1)[-1]

    @property
    def target(self) -> str:
        return self.scene if not self.ablation else f"{self.scene}/{self.variant_dir}/{self.ablation}"

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
            "carrier": f"{s}/fill/{i.get('fill')}/carrier.h5",
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
        return self._job_file("benchmarks", "tsv", rule, step)

    def log_path(self, rule: str, step: str | None = None) -> str:
        """Where the ``log:`` file of a job of this plan lies (see workflow/rules)."""
        return self._job_file("logs", "log", rule, step)

    def _job_file(self, folder: str, ext: str, rule: str, step: str | None) -> str:
        s, i = f"{RESULTS}/{self.scene}/{folder}", self.ids
        names = {
            "prepare": f"{s}/prepare.{ext}",
            "cluster": f"{s}/cluster-{i['cluster']}.{ext}",
            "fill": f"{s}/fill-{i['fill']}.{ext}",
            "vlm_params": f"{s}/vlm_params-{i['params']}.{ext}",
            "pinned_params": f"{s}/pinned_params-{i['params']}.{ext}",
            "render": f"{RESULTS}/{self.target}/{folder}/render.{ext}",
            "metrics": f"{RESULTS}/{self.target}/{folder}/metrics.{ext}",
        }
        if rule in names:
            return names[rule]
        return f"{s}/{rule}-{i['sim']}-{step}.{ext}"


def make_plan(cfg: dict, scene: str, ablation: str | None = None, *, scene_cfg: dict | None = None,
              key: str | None = None, variant_dir: str = "ablations") -> Plan:
    """Compute the stage configs and artifact ids of one target.

    ``scene_cfg`` (a validated scene dict, e.g. with a benchmark scale's sizes) replaces the
    scene file ``scene``; ``key`` is the plan's folder under results/ (default ``scene``);
    ``ablation`` names an entry of ``cfg["ablations"]``.
    """
    sc = C.load_scene(cfg, scene) if scene_cfg is None else scene_cfg
    pub = _public_scene(sc)
    sec = {s: C.effective_section(cfg, sc, s, ablation) for s in C.SECTIONS}
    device = cfg.get("device", "auto")
    p = Plan(key or scene, ablation, variant_dir=variant_dir)

    p.cfgs["prepare"] = {"scene": scene_view(sc, "prepare"), "prepare": sec["prepare"]}

    instances = pub.get("instances") or []
    geometry = [{k: inst.get(k) for k in _GEOMETRY_KEYS} for inst in instances]
    p.cfgs["cluster"] = {"scene": scene_view(sc, "cluster"), "cluster": sec["cluster"]}
    view = p.cfgs["cluster"]["scene"]
    choice = [[e.get("static"), e.get("hint")] for e in view["instances"]] + [view.get("region")]
    # scenes without static pins or a region choice keep the ids they had before those keys existed
    p.ids["cluster"] = "dbscan-" + short_hash([sec["cluster"], geometry, p.cfgs["prepare"]]
                                              + ([choice] if any(c is not None and c != [None, None] for c in choice) else []))

    fill = copy.deepcopy(sec["fill"])
    if fill.get("n_grid") is None:
        fill["n_grid"] = sec["sim"]["n_grid"]
    if fill.get("particles") is None:
        fill["particles"] = sec["sim"]["particles"]
    p.cfgs["fill"] = {"scene": scene_view(sc, "fill"), "fill": fill}
    tag = fill["method"] if fill["method"] != "ipf" else f"ipf-{fill['occupancy']}-{'mcis' if fill['mcis'] else 'uniform'}"
    tag += "-gaussians" if fill["particles"] == "gaussians" else ""
    p.ids["fill"] = f"{tag}-" + short_hash([fill, p.ids["cluster"]])

    from .params.stage import fully_pinned

    material_view = {"prompt": pub.get("prompt"), "instances": instances}
    p.cfgs["params"] = {"scene": scene_view(sc, "params"), "materials": sec["materials"], "device": device}
    # a scene that pins every instance leaves the material backend (vlm_params) out
    p.pinned = fully_pinned(pub)
    tag = "pinned" if p.pinned else sec["materials"]["backend"]
    # materials.initial_E (a deliberate start E) counts only when set, so that ids made before it existed stay
    mat = {k: v for k, v in sec["materials"].items() if k != "initial_E"}
    start = [] if sec["materials"].get("initial_E") is None else [{"initial_E": sec["materials"]["initial_E"]}]
    p.ids["params"] = tag + "-" + short_hash([material_view, p.ids["cluster"]] + ([] if p.pinned else [mat]) + start)

    bgdo = sec["bgdo"]
    forward_keys = {k: bgdo[k] for k in ("key_frames", "forward_frames") if k in bgdo}
    sim_view = {"sim": _hashed("sim", sec["sim"]), "dynamics": pub.get("dynamics"), "forward": forward_keys}
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
    """``bear`` -> ("bear", None); ``bear/ablations/no_bgdo`` -> ("bear", "no_bgdo");
    ``benchmark/cpu/runs/bear/variants/baseline`` -> ("benchmark/cpu/runs/bear", "baseline")."""
    parts = target.split("/")
    head = 4 if len(parts) >= 4 and parts[0] == BENCHMARK and parts[2] == "runs" else 1
    key, rest = "/".join(parts[:head]), parts[head:]
    if not rest:
        return key, None
    segment = "variants" if head == 4 else "ablations"
    if len(rest) == 2 and rest[0] == segment and rest[1]:
        return key, rest[1]
    raise ConfigError("target", f"'{target}' is neither <scene> nor <scene>/ablations/<name> nor "
                      "benchmark/<scale>/runs/<scene>[/variants/<name>]")


BENCHMARK = "benchmark"


def step_index(step: str) -> int:
    return int(step.split("-")[0][2:])


def previous_step(step: str) -> str:
    i = step_index(step)
    if i <= 0:
        raise ValueError(f"step {step} has no predecessor")
    return "it0" if i == 1 else f"it{i - 1}-{step.split('-', 1)[1]}"


def plans_of(cfg: dict, key: str) -> list[Plan]:
    """Every plan of one scene key: the scene with each ablation, or a benchmark key's variants."""
    if key.startswith(BENCHMARK + "/"):
        from .benchmark.spec import spec_for_key

        spec, name = spec_for_key(cfg, key)
        return spec.plans(name)
    return [make_plan(cfg, key, abl) for abl in [None, *sorted(cfg.get("ablations") or {})]]


def plan_for_target(cfg: dict, target: str) -> Plan:
    """The plan of one target (a scene, an ablation or a benchmark run)."""
    key, variant = parse_target(target)
    if key.startswith(BENCHMARK + "/"):
        for plan in plans_of(cfg, key):
            if plan.ablation == variant:
                return plan
        raise ConfigError("target", f"'{target}': the benchmark has no variant '{variant}'")
    return make_plan(cfg, key, variant)


class Registry:
    """The plans the workflow knows (every scene x every ablation, and the benchmark's runs x
    their variants), indexed by artifact id, so that a rule can find the config belonging to an
    id in its output path.

    Plans are made on first use: a scene's own plan first, its ablations only when one is
    asked for or an artifact id is not the scene's own (a run of the main job makes one plan,
    not one per ablation: 7 with the default config, 0.2 s of every Snakemake start on the
    2-core machine); a benchmark key's runs all at once.  So a dry run of one scene builds only
    that scene's plans, and a scene file with a problem
    blocks only its own targets: the problem is recorded and raised when one of them is asked
    for (``snakemake`` for other scenes, ``-n`` included, is unaffected).
    """

    def __init__(self, cfg: dict, scenes: list[str]):
        self.cfg = cfg
        self.scenes = list(scenes)
        self.plans: dict[str, Plan] = {}
        self.problems: dict[str, PhysGSError] = {}  # target (or benchmark key) -> why it has no plan
        self.by_id: dict[tuple[str, str, str], Plan] = {}
        self._loaded: set[str] = set()

    def ablations(self) -> list[str]:
        return sorted(self.cfg.get("ablations") or {})

    def _add(self, key: str, plan: Plan) -> None:
        self.plans[plan.target] = plan
        for kind, ident in plan.ids.items():
            self.by_id.setdefault((key, kind, ident), plan)

    def _load(self, key: str, ablations: bool = False) -> None:
        """Make the plans of ``key``: a scene's own plan, and with ``ablations`` its ablations'
        too (each at most once); a benchmark key's runs and variants."""
        if key.startswith(BENCHMARK + "/"):
            if key in self._loaded:
                return
            self._loaded.add(key)
            try:
                plans = plans_of(self.cfg, key)
            except PhysGSError as e:
                self.problems[key] = e
                return
            for plan in plans:
                self._add(key, plan)
            return
        todo = []
        if key not in self._loaded:
            self._loaded.add(key)
            todo.append(None)
        if ablations and f"{key}/ablations" not in self._loaded:
            self._loaded.add(f"{key}/ablations")
            todo += self.ablations()
        for abl in todo:
            target = key if abl is None else f"{key}/ablations/{abl}"
            try:
                plan = make_plan(self.cfg, key, abl)
            except PhysGSError as e:
                self.problems[target] = e
                continue
            self._add(key, plan)

    def _check_scene(self, key: str) -> None:
        if key.startswith(BENCHMARK + "/"):
            return  # the benchmark spec names its unknown runs itself
        if key not in self.scenes:
            raise ConfigError("scene", f"unknown scene '{key}': no scene file {C.scene_path(self.cfg, key)}; "
                                       f"known scenes: {', '.join(self.scenes) or '(none)'}")

    def plan(self, target: str) -> Plan:
        key, variant = parse_target(target)
        self._check_scene(key)
        bench = key.startswith(BENCHMARK + "/")
        if not bench and variant is not None and variant not in self.ablations():
            raise ConfigError("ablations", f"unknown ablation '{variant}' in target '{target}'; ablations: "
                                           f"{', '.join(self.ablations()) or '(none configured)'}")
        self._load(key, ablations=variant is not None and not bench)
        if target in self.problems:
            raise self.problems[target]
        if bench and key in self.problems:  # the benchmark run's spec itself is broken
            raise self.problems[key]
        if target not in self.plans:
            known = sorted(t for t in self.plans if t == key or t.startswith(key + "/"))
            raise ConfigError("target", f"unknown target '{target}'; known for {key}: {', '.join(known)}")
        return self.plans[target]

    def for_id(self, scene: str, kind: str, ident: str) -> Plan:
        self._check_scene(scene)
        self._load(scene)
        if (scene, kind, ident) not in self.by_id:  # not the scene's own id: an ablation's?
            self._load(scene, ablations=True)
        try:
            return self.by_id[(scene, kind, ident)]
        except KeyError:
            if scene in self.problems:  # the scene file itself is broken
                raise self.problems[scene] from None
            raise ConfigError(kind, f"no current config of scene '{scene}' gives {kind} id '{ident}' "
                              "(the path is stale: the config changed since it was requested)") from None
