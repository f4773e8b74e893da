"""Stage `vlm_params`: material models and parameters per instance -> params.json.

inputs  {"scene": scene.ply, "labels": labels.npz, "clusters": clusters.json}
outputs {"params": params.json}
cfg     {"materials": {...}, "scene": {"prompt", "instances", ...}, "device": "cpu" | "cuda"}

Per cluster label: the scene-config entry it matched (clusters.json ``config_index``) gives
the hint and the pinned values; unmatched labels have the prompt alone.  Pinned values are
never asked for; an instance whose pins determine everything skips the backend, and a scene
that pins everything can skip the stage (:func:`fully_pinned`, :func:`pinned_params`).
A VLM answer that stays invalid after the retry, or a backend that cannot run, falls back to
the prior for that instance with the reason recorded (``materials.on_failure: error`` stops
instead).
"""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np

from .. import materials_kb
from ..errors import ConfigError, InputError
from ..runtime import read_json_input, write_json
from . import prior as prior_mod
from .prompt import BackendError, Question, ask
from .validate import (asked_keys, check_collider, check_pins, check_velocity, finalize_answer, is_fully_pinned,
                       merge_pins)

BACKENDS = ("prior", "qwen3vl", "openai")


# --------------------------------------------------------------------------- pins only
def fully_pinned(scene_cfg: dict, n_instances: int | None = None) -> bool:
    """True when the scene's pins determine every instance's parameters.

    Args:
        scene_cfg: the validated scene dict (``instances`` list).
        n_instances: number of cluster labels K when known; then the scene must list
            exactly K instances (each label needs an entry to take pins from).
    """
    entries = scene_cfg.get("instances") or []
    if not entries or (n_instances is not None and len(entries) != n_instances):
        return False
    kb = materials_kb.load_kb()
    return all(is_fully_pinned(check_pins(e, i, kb, scene_cfg.get("_path"))) for i, e in enumerate(entries))


def pinned_params(scene_cfg: dict, clusters: dict | None = None, kb: dict | None = None) -> dict:
    """params.json content built from pins alone (for a scene where :func:`fully_pinned`).

    Args:
        scene_cfg: the validated scene dict.
        clusters: clusters.json content; label -> entry through ``config_index``.  Without
            it label i takes entry i.
        kb: knowledge base (default: the packaged one).
    Raises:
        ConfigError when an instance is not fully pinned or a label matched no entry.
    """
    kb = kb or materials_kb.load_kb()
    entries = scene_cfg.get("instances") or []
    prompt = scene_cfg.get("prompt") or ""
    src = scene_cfg.get("_path")
    index = _label_config_index(clusters, len(entries)) if clusters else list(range(len(entries)))
    if any(ci is None for ci in index):
        raise ConfigError("scene.instances", _unmatched_message(clusters, index.index(None), entries), src)
    matches = prior_mod.match_scene(prompt, [entries[ci] for ci in index], kb)
    out = []
    for label, ci in enumerate(index):
        pins = check_pins(entries[ci], ci, kb, src)
        if not is_fully_pinned(pins):
            raise ConfigError(f"scene.instances[{ci}]", "not fully pinned: give `material`, or elasticity, plasticity, "
                                                  "E, nu, density and the plasticity model's parameters", src)
        values, notes = merge_pins(materials_kb.material_params(matches[label].material, kb), pins, kb)
        out.append(_record(label, entries[ci], ci, values, check_velocity(entries[ci], ci),
                           {"source": "pinned", "backend": "pinned", "pinned": sorted(pins), "clamped": notes}))
    return _document(out, "pinned", prompt, kb, None)


def _unmatched_message(clusters: dict, label: int, entries: list) -> str:
    """What to change when cluster ``label`` matched no entry of a fully pinned scene."""
    rec = next((r for r in clusters.get("instances", []) if r.get("label") == label), {})
    n, lo, hi = rec.get("count"), rec.get("bbox_min"), rec.get("bbox_max")
    box = f" (box {[round(v, 3) for v in lo]}..{[round(v, 3) for v in hi]})" if lo and hi else ""
    msg = (f"the clustering found {clusters.get('n_instances')} objects but the scene lists {len(entries)}; cluster "
           f"label {label} ({n} gaussians{box}) matched no scene instance, so it has no pins. Either list it as an instance "
           "of its own (with `at` inside that box and its material)")
    near = rec.get("unmatched") or {}
    if near:
        nl = near["nearest_label"]
        msg += (f", or make it part of label {nl}: cluster.merge: [[{min(nl, label)}, {max(nl, label)}]], or "
                f"cluster.eps above the gap of {near['gap']:.3g} (now {clusters.get('eps')}), or "
                f"cluster.fragment_fraction above {near['fraction']:.3g} (now {clusters.get('fragment_fraction')})")
    return msg + " (under `config: {cluster: ...}` in the scene file)"


# --------------------------------------------------------------------------- stage
def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    mcfg = cfg.get("materials")
    if not isinstance(mcfg, dict):
        raise ConfigError("materials", "the stage needs the validated `materials` config section")
    scene_cfg = cfg.get("scene") or {}
    backend_name = mcfg.get("backend", "prior")
    if backend_name not in BACKENDS:
        raise ConfigError("materials.backend", f"unknown backend {backend_name!r}; valid: {', '.join(BACKENDS)}")
    kb = materials_kb.load_kb(mcfg.get("kb_path") or None)
    prompt = scene_cfg.get("prompt") or ""
    entries = scene_cfg.get("instances") or []

    labels = _read_labels(inputs["labels"])
    clusters = _read_json(inputs["clusters"])
    index = _label_config_index(clusters, len(entries), inputs["clusters"])
    k = len(index)
    if labels.size and int(labels.max()) >= k:
        raise InputError(inputs["labels"], f"label {int(labels.max())} but clusters.json has {k} instances")
    pins = {ci: check_pins(entries[ci], ci, kb, scene_cfg.get("_path")) for ci in set(index) if ci is not None}
    velocities = {ci: check_velocity(entries[ci], ci) for ci in pins}
    matches = prior_mod.match_scene(prompt, [entries[ci] if ci is not None else None for ci in index], kb,
                                    mcfg.get("default_material", "jelly"))
    log.info("%d instances, %d matched to scene entries; backend %s", k, sum(ci is not None for ci in index), backend_name)

    to_ask = [lab for lab, ci in enumerate(index) if not (ci is not None and is_fully_pinned(pins[ci]))]
    backend, backend_error = _make_backend(backend_name, mcfg, cfg.get("device"), log) if to_ask else (None, None)
    views_src = _ViewSource(inputs["scene"], labels, mcfg, log) if backend is not None else None

    records = []
    for lab, ci in enumerate(index):
        p = pins.get(ci, {}) if ci is not None else {}
        entry = entries[ci] if ci is not None else {}
        base = materials_kb.material_params(matches[lab].material, kb)
        if ci is not None and is_fully_pinned(p):
            values, notes = merge_pins(base, p, kb)
            prov = {"source": "pinned", "backend": backend_name, "pinned": sorted(p), "clamped": notes}
        elif backend is None:
            values, notes = merge_pins(base, p, kb)
            prov = {"source": "prior", "backend": backend_name, "pinned": sorted(p), "clamped": notes,
                    "prior": matches[lab].to_dict(), "prompt_sha256": matches[lab].text_sha256, "raw_answer": None}
            if backend_error:
                prov["fallback_reason"] = backend_error
        else:
            values, prov = _ask_backend(backend, lab, entry, p, prompt, base, matches[lab], kb, mcfg, views_src, log)
        records.append(_record(lab, entry, ci, values, velocities.get(ci, [0.0, 0.0, 0.0]), prov))
        r = records[-1]
        log.info("instance %d (%s): %s [%s], E=%.3g Pa, nu=%.3g, density=%.4g kg/m^3, %s/%s, %s  (%d/%d)",
                 lab, r["name"], values["material"], prov["source"], values["E"], values["nu"],
                 values["density"], values["elasticity"], values["plasticity"],
                 "fixed rigid" if r["fixed"] else "rigid" if r["rigid"] else "deformable", lab + 1, k)

    doc = _document(records, backend_name, prompt, kb, mcfg.get("kb_path"))
    if backend is not None:
        doc["backend_config"] = backend.describe()
    apply_initial_E(doc, mcfg.get("initial_E"), log)
    write_json(outputs["params"], doc)
    sources = {}
    for r in records:
        sources[r["provenance"]["source"]] = sources.get(r["provenance"]["source"], 0) + 1
    n_fallback = sum("fallback_reason" in r["provenance"] for r in records)
    log.info("wrote %s (%d instances; sources %s; %d fallbacks)", outputs["params"], k, sources, n_fallback)
    return {"backend": backend_name, "n_instances": k, "sources": sources, "fallbacks": n_fallback}


def _ask_backend(backend, label, entry, pins, prompt, base, match, kb, mcfg, views_src, log) -> tuple[dict, dict]:
    """Values and provenance of one instance from a VLM backend (prior fallback on failure)."""
    start, start_notes = merge_pins(base, pins, kb)
    name = entry.get("name") or f"instance_{label}"
    images, views_error = views_src.views(label, mcfg.get(backend.name, {}))
    q = Question(label=label, name=name, hint=entry.get("hint"), prompt=prompt, pins=pins,
                 asked=asked_keys(pins), images=images)
    res = ask(backend.send, q, kb, retries=int(mcfg.get(backend.name, {}).get("answer_retries", 1)))
    prov = {"source": backend.name, "backend": backend.name, "pinned": sorted(pins), "prompt_sha256": res.prompt_sha256,
            "n_views": 0 if images is None else int(len(images)), "attempts": res.attempts,
            "raw_answer": res.attempts[-1]["raw"] if res.attempts else None, "prior": match.to_dict()}
    if views_error:
        prov["views_error"] = views_error
    if res.answer is None:
        if mcfg.get("on_failure", "fallback") == "error":
            raise ConfigError(f"materials.{backend.name}", f"instance {label} ({name}): {res.error}")
        log.warning("instance %d (%s): %s; using the prior (%s)", label, name, res.error, match.material)
        values, notes = start, start_notes
        prov.update({"source": "prior", "fallback_reason": res.error, "clamped": notes})
        return values, prov
    values, notes = finalize_answer(res.answer, start, pins, kb, mcfg.get("limits"),
                                    bool(mcfg.get("clamp_to_material_range", True)))
    prov.update({"clamped": notes, "answer_reason": res.answer.get("reason")})
    for n in notes:
        log.info("instance %d: %s %s=%r -> %r (%s)", label, n["action"], n["key"], n["value"], n["to"], n["reason"])
    return values, prov


def _make_backend(name: str, mcfg: dict, device: str | None, log: logging.Logger):
    """(backend or None, reason it is unavailable or None)."""
    if name == "prior":
        return None, None
    try:
        if name == "qwen3vl":
            from .qwen3vl import Qwen3VLBackend

            backend = Qwen3VLBackend(mcfg.get("qwen3vl", {}), device, log)
        else:
            from .openai_backend import OpenAIBackend

            backend = OpenAIBackend(mcfg.get("openai", {}), log)
        backend.load()
    except BackendError as e:
        if mcfg.get("on_failure", "fallback") == "error":
            raise ConfigError(f"materials.{name}", str(e)) from None
        log.warning("backend %s unavailable (%s); every instance uses the prior", name, e)
        return None, f"backend {name} unavailable: {e}"
    return backend, None


class _ViewSource:
    """Renders per-label views on demand (scene.ply is read once, only if views are wanted)."""

    def __init__(self, scene_path: str, labels: np.ndarray, mcfg: dict, log: logging.Logger) -> None:
        self.scene_path = scene_path
        self.labels = labels
        self.vcfg = mcfg.get("views", {})
        self.log = log
        self._scene = None

    def views(self, label: int, bcfg: dict) -> tuple[np.ndarray | None, str | None]:
        n = int(bcfg.get("n_views", 4))
        if n <= 0:
            return None, None
        try:
            if self._scene is None:
                from .. import load_gaussians

                self._scene = load_gaussians(self.scene_path)
                if self._scene.n != self.labels.shape[0]:
                    raise InputError(self.scene_path, f"{self._scene.n} gaussians but labels.npz has {self.labels.shape[0]} labels")
            from .views import instance_views

            imgs = instance_views(self._scene, self.labels == label, n, int(bcfg.get("image_size", 448)),
                                  float(self.vcfg.get("elevation_deg", 20.0)), float(self.vcfg.get("fov_deg", 40.0)),
                                  self.vcfg.get("renderer", "auto"))
            return imgs, None
        except InputError:
            raise
        except Exception as e:  # a renderer failure degrades to a text-only question
            msg = f"views not rendered ({type(e).__name__}: {e}); asked with text only"
            self.log.warning("instance %d: %s", label, msg)
            return None, msg


# --------------------------------------------------------------------------- helpers
def apply_initial_E(doc: dict, initial_E, log: logging.Logger | None = None) -> None:
    """``materials.initial_E``: give every instance of a params.json document that Young's
    modulus (Pa), in place, recording the replaced value in its provenance. None: no change.
    Neither materials.limits nor the material's E_range applies (a deliberate start value,
    e.g. the corrupted E0 of a BGDO robustness run)."""
    if initial_E is None:
        return
    if isinstance(initial_E, bool) or not isinstance(initial_E, (int, float)) or not np.isfinite(initial_E) \
            or initial_E <= 0:
        raise ConfigError("materials.initial_E", f"must be a positive number of Pa or null, got {initial_E!r}")
    for inst in doc["instances"]:
        before = inst.get("E")
        inst["E"] = float(initial_E)
        inst["provenance"] = {"source": "initial_E", "E_replaced": before, "previous": inst.get("provenance")}
        if log is not None:
            log.info("instance %s (%s): E %s -> %.4g Pa (materials.initial_E)", inst.get("label"), inst.get("name"),
                     "n/a" if before is None else f"{before:.4g}", float(initial_E))
    doc["initial_E"] = float(initial_E)


def _read_labels(path: str) -> np.ndarray:
    try:
        with np.load(path) as z:
            labels = np.asarray(z["labels"])
    except (OSError, ValueError, KeyError) as e:
        raise InputError(path, f"cannot read 'labels' from the npz: {e}") from None
    if labels.ndim != 1 or not np.issubdtype(labels.dtype, np.integer):
        raise InputError(path, f"'labels' must be a 1-D integer array, got {labels.dtype} {labels.shape}")
    if labels.size and labels.min() < -1:  # -1: static surroundings (outside region.box), no material
        raise InputError(path, f"'labels' has ids below -1 (min {labels.min()})")
    return labels


def _read_json(path: str) -> dict:
    return read_json_input(path, "clusters file")


def _label_config_index(clusters: dict, n_entries: int, path: str = "clusters.json") -> list[int | None]:
    """``config_index`` per label 0..K-1 (None = unmatched), checked against the scene's entries."""
    if not isinstance(clusters, dict) or not isinstance(clusters.get("instances"), list):
        raise InputError(path, "needs an 'instances' list")
    k = clusters.get("n_instances", len(clusters["instances"]))
    index: list[int | None] = [None] * int(k)
    for item in clusters["instances"]:
        lab, ci = item.get("label"), item.get("config_index")
        if not isinstance(lab, int) or not 0 <= lab < k:
            raise InputError(path, f"instance label {lab!r} outside 0..{k - 1}")
        if ci is not None and (not isinstance(ci, int) or not 0 <= ci < n_entries):
            raise InputError(path, f"label {lab}: config_index {ci!r} but the scene lists {n_entries} instances")
        index[lab] = ci
    return index


def _record(label: int, entry: dict, ci: int | None, values: dict, velocity: list[float], prov: dict) -> dict:
    """One params.json instance entry: the values plus ``rigid`` (a rigid body: the pin, the
    answer or the material's knowledge-base flag) and ``fixed``/``surface``/``friction`` (a
    fixed rigid instance is static geometry, a collider with that surface and friction)."""
    rec = {"label": int(label), "name": entry.get("name") or f"instance_{label}", "config_index": ci,
           "velocity": velocity, "provenance": prov}
    rec.update(values)
    rec.update(check_collider(entry, ci))
    rec["rigid"] = bool(rec.get("rigid", False)) or rec["fixed"]
    return rec


def _document(records: list[dict], backend: str, prompt: str, kb: dict, kb_path: str | None) -> dict:
    kb_path = Path(kb_path) if kb_path else materials_kb.default_kb_path()
    return {"instances": records, "backend": backend, "prompt": prompt, "history": [],
            "knowledge_base": {"path": str(kb_path), "materials": list(kb),
                               "sha256": hashlib.sha256(kb_path.read_bytes()).hexdigest() if kb_path.exists() else None}}


def run_pinned(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Stage used instead of ``vlm_params`` when the scene pins every instance completely:
    no backend is loaded or asked; params.json is built from the pins (and the knowledge base)."""
    scene_cfg = cfg.get("scene") or {}
    clusters = _read_json(inputs["clusters"])
    params = pinned_params(scene_cfg, clusters)
    apply_initial_E(params, (cfg.get("materials") or {}).get("initial_E"), log)
    write_json(outputs["params"], params)
    log.info("all %d instances pinned in the scene file: no material backend asked; wrote %s",
             len(params["instances"]), outputs["params"])
    return {"n_instances": len(params["instances"]), "backend": "pinned"}
