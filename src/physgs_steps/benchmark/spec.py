"""What the benchmark runs: scale, scenes, variants, plans and stress runs.

A benchmark run is a plan of the ordinary workflow (physgs_steps.plan) whose folder is the
key ``benchmark/<scale>/runs/<scene>``: its artifacts never mix with a user's runs of the same
scene, which may have other sizes (prepare's scene.ply carries no id). Its config is the
user's config with three layers on each scene (physgs_steps.config.effective_section order):
the scene file's own ``config:``, then the scale's ``config`` (``benchmark.<scale>.config``,
plus ``sim.on_unstable: keep`` so that a failing final run becomes a reported row), then the
variant's overlay (the benchmark's variants play the role of ``ablations``).

Variants (``Variant.role``):

=====================  =============================================================
``physgs``             the configured pipeline (IPF + MCIS, the configured params
                       backend, BGDO); its knowledge-base start is the robustness
                       experiment's "KB" row
``baseline``           PhysGaussian-style (``benchmark.baseline``: global fill, KB
                       parameters, no BGDO)
``ablation``           each of ``benchmark.ablations`` (the top-level ``ablations``)
``robustness``         ``e0_<E0>``: materials.initial_E = E0, with BGDO
``robustness_no_bgdo`` ``e0_<E0>_no_bgdo``: the same start without BGDO
=====================  =============================================================

``no_bgdo`` (bgdo.iterations 0) is always present: "Does BGDO change the result?" compares it
with physgs.
"""
from __future__ import annotations

import copy
import functools
import json
from dataclasses import dataclass, field

import numpy as np

from .. import config as C
from ..errors import ConfigError
from ..plan import BENCHMARK, Plan, make_plan, short_hash

SCALES = ("smoke", "cpu", "full")
RUNS = "runs"
ROOT = f"results/{BENCHMARK}"

# display names of the ablations the paper and the peers define (others show their key)
ABLATION_LABELS = {
    "no_ipf": "w/o IPF", "no_mcis": "w/o MCIS", "no_bgdo": "w/o BGDO", "global_fill": "global fill",
    "surface_fill": "surface fill", "no_rigid": "w/o rigid instances",
}


def scene_key(scale: str, name: str) -> str:
    """The plan folder (the rules' ``{scene}`` wildcard) of a benchmark scene."""
    return f"{BENCHMARK}/{scale}/{RUNS}/{name}"


def split_key(key: str) -> tuple[str, str]:
    """``benchmark/<scale>/runs/<name>`` -> (scale, name)."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != BENCHMARK or parts[2] != RUNS or parts[1] not in SCALES:
        raise ConfigError("target", f"'{key}' is not a benchmark run folder benchmark/<{'|'.join(SCALES)}>/runs/<scene>")
    return parts[1], parts[3]


def report_dir(scale: str) -> str:
    return f"{ROOT}/{scale}"


def e0_tag(E0: float) -> str:
    """A variant-name-safe spelling of an initial E: 3e10 -> '3e10', 3e8 -> '3e08', 30 -> '30'."""
    return f"{float(E0):g}".replace("+", "").replace(".", "p")


@dataclass(frozen=True)
class Variant:
    name: str | None            # None = physgs (the plan without an overlay)
    role: str                   # physgs | baseline | ablation | robustness | robustness_no_bgdo
    label: str
    overlay: dict = field(default_factory=dict, hash=False, compare=False)
    E0: float | None = None
    render: bool = True         # video + metrics wanted (robustness runs need final.h5 and params only)


def _json_key(cfg: dict) -> str:
    return json.dumps(cfg, sort_keys=True, default=str)


@functools.lru_cache(maxsize=8)
def _spec_cached(cfg_json: str, scale: str) -> "BenchmarkSpec":
    return BenchmarkSpec(json.loads(cfg_json), scale)


def spec_for(cfg: dict, scale: str) -> "BenchmarkSpec":
    """The (cached) spec of ``scale`` for a validated config."""
    return _spec_cached(_json_key(cfg), scale)


def spec_for_key(cfg: dict, key: str) -> tuple["BenchmarkSpec", str]:
    scale, name = split_key(key)
    return spec_for(cfg, scale), name


class BenchmarkSpec:
    """The benchmark at one scale for a validated global config."""

    def __init__(self, cfg: dict, scale: str):
        if scale not in SCALES:
            raise ConfigError("benchmark.scale", f"unknown scale '{scale}'; scales: {', '.join(SCALES)}")
        self.cfg = cfg
        self.scale = scale
        b = cfg.get("benchmark") or C.section_defaults("benchmark")
        self.settings = b
        s = b[scale]
        self.scale_settings = s
        self.scenes: list[str] = list(s["scenes"])
        self.n_gaussians = s.get("n_gaussians")
        self.overlay = C.deep_merge(s.get("config") or {}, {"sim": {"on_unstable": "keep"}})
        self.E0 = [float(e) for e in (s.get("robustness_E0") if s.get("robustness_E0") is not None
                                      else b["robustness"]["E0"])]
        self.stress_runs = int(s["stress_runs"])
        self.stress = dict(b["stress"])
        if not self.stress["E_max"] > self.stress["E_min"]:
            raise ConfigError("benchmark.stress.E_max", f"must exceed E_min ({self.stress['E_min']:g}), "
                                                        f"got {self.stress['E_max']:g}")
        self.variants = self._variants()
        self.bench_cfg = copy.deepcopy(cfg)
        self.bench_cfg["ablations"] = {v.name: v.overlay for v in self.variants if v.name is not None}
        self._scene_cfgs: dict[str, dict] = {}
        self._plans: dict[tuple, Plan] = {}
        self._manifest: dict | None = None

    # ------------------------------------------------------------------ variants
    def _variants(self) -> list[Variant]:
        b = self.settings
        backend = (self.cfg.get("materials") or {}).get("backend", "prior")
        out = [Variant(None, "physgs", f"physgs (IPF+MCIS, {backend} params, BGDO)"),
               Variant("baseline", "baseline", "PhysGaussian-style (global fill, KB params, no BGDO)",
                       copy.deepcopy(b["baseline"]))]
        ablations = self.cfg.get("ablations") or {}
        chosen, key = self.scale_settings.get("ablations"), f"benchmark.{self.scale}.ablations"
        if chosen is None:
            chosen, key = b.get("ablations"), "benchmark.ablations"
        names = list(ablations) if chosen is None else list(chosen)
        unknown = [n for n in names if n not in ablations]
        if unknown:
            raise ConfigError(key, f"unknown ablation(s) {unknown}; `ablations` defines: "
                                                     f"{', '.join(sorted(ablations)) or 'none'}")
        reserved = {"baseline"} | {f"e0_{e0_tag(e)}" for e in self.E0} | {f"e0_{e0_tag(e)}_no_bgdo" for e in self.E0}
        for n in names:
            if n in reserved:
                raise ConfigError(f"ablations.{n}", "the name is taken by a benchmark variant; rename the ablation")
            out.append(Variant(n, "ablation", ABLATION_LABELS.get(n, n), copy.deepcopy(ablations[n])))
        if "no_bgdo" not in names:  # needed by "Does BGDO change the result?" and the KB robustness row
            out.append(Variant("no_bgdo", "ablation_extra", "w/o BGDO", {"bgdo": {"iterations": 0}}))
        for e in self.E0:
            out.append(Variant(f"e0_{e0_tag(e)}", "robustness", f"E0 = {e:g} Pa, BGDO",
                               {"materials": {"initial_E": e}}, E0=e, render=False))
            if b["robustness"]["without_bgdo"]:
                out.append(Variant(f"e0_{e0_tag(e)}_no_bgdo", "robustness_no_bgdo", f"E0 = {e:g} Pa, no BGDO",
                                   {"materials": {"initial_E": e}, "bgdo": {"iterations": 0}}, E0=e, render=False))
        return out

    def variant(self, name: str | None) -> Variant:
        for v in self.variants:
            if v.name == name:
                return v
        raise ConfigError("target", f"the benchmark has no variant '{name}'; variants: "
                                    f"{', '.join(str(v.name) for v in self.variants if v.name)}")

    def table_variants(self) -> list[Variant]:
        """Variants with a video and metrics (comparison and ablation rows)."""
        return [v for v in self.variants if v.render]

    def robustness_variants(self) -> list[Variant]:
        return [v for v in self.variants if v.role in ("robustness", "robustness_no_bgdo")]

    # ------------------------------------------------------------------ scenes and plans
    def key(self, name: str) -> str:
        return scene_key(self.scale, name)

    def scene_cfg(self, name: str) -> dict:
        """The scene file with the scale's gaussian count and config overlay."""
        if name not in self._scene_cfgs:
            sc = C.load_scene(self.cfg, name)
            if self.n_gaussians is not None and str(sc.get("source", "")).startswith("builtin:"):
                sc["builtin"] = dict(sc.get("builtin") or {}, n_gaussians=int(self.n_gaussians))
            over = C.deep_merge(sc.get("config") or {}, self.overlay)
            for section in over:
                if section not in C.SECTIONS:
                    raise ConfigError(f"benchmark.{self.scale}.config.{section}",
                                      f"unknown section; allowed: {', '.join(C.SECTIONS)}")
            sc["config"] = over
            self._scene_cfgs[name] = sc
        return self._scene_cfgs[name]

    def is_builtin(self, name: str) -> bool:
        return str(self.scene_cfg(name).get("source", "")).startswith("builtin:")

    def robustness_scenes(self) -> list[str]:
        return [s for s in self.scenes if self.is_builtin(s)]

    def variants_of(self, name: str) -> list[Variant]:
        """The variants that run on a scene (robustness starts only on its built-in scenes)."""
        robust = name in self.robustness_scenes()
        return [v for v in self.variants if robust or v.role not in ("robustness", "robustness_no_bgdo")]

    def plan(self, name: str, variant: str | None = None) -> Plan:
        if (name, variant) not in self._plans:
            self._plans[(name, variant)] = make_plan(self.bench_cfg, name, variant, scene_cfg=self.scene_cfg(name),
                                                     key=self.key(name), variant_dir="variants")
        return self._plans[(name, variant)]

    def plans(self, name: str) -> list[Plan]:
        return [self.plan(name, v.name) for v in self.variants_of(name)]

    # ------------------------------------------------------------------ stress vs E
    def stress_E(self) -> list[float]:
        return [float(e) for e in np.geomspace(self.stress["E_min"], self.stress["E_max"], self.stress_runs)]

    def stress_id(self, plan: Plan) -> str:
        return "E-" + short_hash([plan.ids["sim"], plan.ids["bgdo"], self.stress["E_min"], self.stress["E_max"],
                                  self.stress_runs])

    def stress_paths(self) -> list[str]:
        plan = self.plan(self.stress["scene"])
        sid = self.stress_id(plan)
        return [f"results/{plan.scene}/stress/{sid}/run{i:03d}.json" for i in range(self.stress_runs)]

    def stress_cfg(self, stress_id: str, index: int) -> dict:
        plan = self.plan(self.stress["scene"])
        if stress_id != self.stress_id(plan):
            raise ConfigError("benchmark.stress", f"stress id '{stress_id}' is stale (the config now gives "
                                                  f"'{self.stress_id(plan)}')")
        if not 0 <= index < self.stress_runs:
            raise ConfigError("benchmark.stress", f"run {index} outside 0..{self.stress_runs - 1}")
        bgdo = copy.deepcopy(plan.cfgs["bgdo"])
        bgdo["bgdo"]["iterations"] = 1
        return {"E": self.stress_E()[index], "index": index, "runs": self.stress_runs, "sim": plan.cfgs["sim"],
                "bgdo": bgdo}

    # ------------------------------------------------------------------ what the report reads
    def run_record(self, name: str, variant: str | None) -> dict:
        """Paths and facts of one run (scene x variant) for the report (plain JSON data)."""
        v = self.variant(variant)
        plan = self.plan(name, variant)
        fill = plan.cfgs["fill"]["fill"]
        dyn = (plan.cfgs["sim"].get("scene") or {}).get("dynamics") or {}
        ground = dyn.get("ground") if isinstance(dyn.get("ground"), dict) else None
        jobs = [(r, s) for r, s in plan.jobs() if v.render or r not in ("render", "metrics")]
        rec = {
            "scene": name, "variant": v.name or "physgs", "role": v.role, "label": v.label, "E0": v.E0,
            "render": v.render, "target": plan.target,
            "final": plan.path("final"), "params": plan.path("params", plan.steps[-1]), "params0": plan.path("params0"),
            "forward": [plan.path("forward", s) for s in plan.steps[:-1]],
            "labels": plan.path("labels"), "particles": plan.path("particles"), "fill_report": plan.path("fill_report"), "fill_id": plan.ids["fill"],
            "fill_label": fill_label(fill), "bgdo_iterations": len(plan.steps) - 1,
            "ground_height": None if ground is None else float(ground.get("height", 0.0)),
            "domain_size": float(plan.cfgs["sim"]["sim"].get("domain_size", 1.0)),
            "jobs": [{"rule": r, "step": s, "benchmark": plan.benchmark_path(r, s), "log": plan.log_path(r, s)}
                     for r, s in jobs],
        }
        if v.render:
            rec.update(video=plan.path("video"), metrics=plan.path("metrics"), render_report=plan.path("render_report"),
                       contact_sheet=plan.path("contact_sheet"))
        return rec

    def manifest(self) -> dict:
        """Everything the report stage needs to know (its Snakemake params)."""
        if self._manifest is None:
            self._manifest = self._make_manifest()
        return copy.deepcopy(self._manifest)

    def _make_manifest(self) -> dict:
        runs = [self.run_record(s, v.name) for s in self.scenes for v in self.variants_of(s)]
        sim = self.plan(self.scenes[0]).cfgs["sim"]["sim"]
        render = self.plan(self.scenes[0]).cfgs["render"]["render"]
        stress_plan = self.plan(self.stress["scene"])
        return {
            "scale": self.scale, "scenes": self.scenes, "robustness_scenes": self.robustness_scenes(),
            "variants": [{"name": v.name or "physgs", "role": v.role, "label": v.label, "E0": v.E0, "render": v.render}
                         for v in self.variants],
            "runs": runs, "E0": self.E0, "published": bool(self.settings["published"]),
            "thumbnails": dict(self.settings["thumbnails"]), "device": self.cfg.get("device", "auto"),
            "sizes": {"n_gaussians": self.n_gaussians, "n_grid": sim["n_grid"], "n_frames": sim["n_frames"],
                      "bgdo_iterations": int(self.plan(self.scenes[0]).cfgs["bgdo"]["bgdo"]["iterations"]),
                      "render": [render["width"], render["height"]]},
            "stress": {"scene": self.stress["scene"], "E_min": self.stress["E_min"], "E_max": self.stress["E_max"],
                       "runs": self.stress_runs, "paths": self.stress_paths(),
                       "params0": stress_plan.path("params0")},
        }

    def report_cfg(self) -> dict:
        """The report job's Snakemake params: small, and changing whenever the manifest does
        (the job rebuilds the manifest from the config: :func:`report_manifest`)."""
        return {"scale": self.scale, "manifest": short_hash(self.manifest())}

    def stage_manifest(self) -> dict:
        man = self.manifest()
        return {"scale": self.scale, "device": man["device"], "published": man["published"], "sizes": man["sizes"],
                "runs": self.stage_runs()}

    def stage_cfg(self) -> dict:
        return {"scale": self.scale, "manifest": short_hash(self.stage_manifest())}

    def stage_runs(self) -> list[dict]:
        """The physgs run of every scene (the stage table's input)."""
        return [self.run_record(s, None) for s in self.scenes]

    def report_inputs(self) -> dict:
        """The files the report reads, grouped (Snakemake ``unpack``)."""
        man = self.manifest()
        groups: dict[str, list] = {"finals": [], "params": [], "fill_reports": [], "videos": [], "metrics": []}
        for r in man["runs"]:
            groups["finals"].append(r["final"])
            groups["params"].append(r["params"])
            groups["fill_reports"].append(r["fill_report"])
            if r["render"]:
                groups["videos"].append(r["video"])
                groups["metrics"].append(r["metrics"])
        out = {k: list(dict.fromkeys(v)) for k, v in groups.items()}
        out["stress"] = man["stress"]["paths"]
        out["stages"] = f"{report_dir(self.scale)}/stages.json"
        return out

    def stage_inputs(self) -> dict:
        runs = self.stage_runs()
        return {"metrics": [r["metrics"] for r in runs], "finals": [r["final"] for r in runs]}


def fill_label(fill: dict) -> str:
    """A readable name of a fill configuration."""
    m = fill.get("method")
    if m == "ipf":
        occ = fill.get("occupancy", "hull")
        return ("IPF+MCIS (paper)" if fill.get("mcis") else "IPF w/o MCIS") if occ == "hull" else \
            f"IPF {occ}-following" + ("" if fill.get("mcis") else " w/o MCIS")
    if m == "global":
        return "global (PhysGaussian)"
    if m == "none":
        return "no filling (gaussians only)"
    return str(m)


def job_manifest(config: dict, params: dict, kind: str = "report") -> dict:
    """The manifest a report job's params name (``kind`` report or stages), rebuilt from the
    workflow's config inside the job; a digest that no longer matches is a stale job."""
    spec = spec_for(config, params["scale"])
    man = spec.manifest() if kind == "report" else spec.stage_manifest()
    if short_hash(man) != params.get("manifest"):
        raise ConfigError("benchmark", f"the {kind} job's manifest {params.get('manifest')} is not the config's "
                                       f"({short_hash(man)}); run snakemake again")
    return man
