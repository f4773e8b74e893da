"""Stage `metrics`: the paper's four video scores and the simulation's plausibility figures.

inputs  {"video": video.mp4, "frames": final.h5, "params": params.json}
outputs {"metrics": metrics.json}
cfg     {"metrics": {...}, "scene": {"prompt": ...}, "device": ...}

metrics.json (docs/CONTRACTS.md): ``clip_score`` (CS), ``aesthetic_score`` (AS),
``semantic_adherence`` (SA), ``physical_commonsense`` (PC), each in the shape of
:mod:`.scores`, plus ``physical`` (:mod:`.physical`), ``video``, ``text``, ``materials``,
``bgdo`` and ``schema_version``. Every score is a value or null with the reason; nothing is
downloaded, and torch/transformers are imported only when a score is computed.
"""
from __future__ import annotations

import logging

from ..errors import ConfigError, InputError
from ..runtime import read_json_input, write_json
from . import videophy2
from .clip_aesthetic import image_scores
from .physical import physical_figures
from .scores import scrub_nonfinite
from .video import read_frames

SCHEMA_VERSION = 2


def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    mc = cfg.get("metrics")
    if not isinstance(mc, dict):
        raise ConfigError("metrics", "the stage needs the validated `metrics` config section")
    vc = mc.get("videophy2") or {}
    vp_backend = videophy2.select_backend(vc)   # config mistakes stop here, before any work
    text = mc.get("text") or (cfg.get("scene") or {}).get("prompt") or ""
    params = _read_params(inputs["params"])
    physical = physical_figures(inputs["frames"], float(mc.get("moved_threshold", 0.005)),
                                float(mc.get("domain_margin", 0.0)), log)

    requests = {"clip": ("even", int(mc.get("n_frames", 16)))}
    if vp_backend == "inprocess":
        requests["videophy2"] = ("segments", int((vc.get("inprocess") or {}).get("n_frames", 8)))
    video, sampled = read_frames(inputs["video"], requests)
    clip_ids, clip_frames = sampled["clip"]
    if not clip_ids:
        raise InputError(inputs["video"], "no frame could be decoded")
    video["sampled_frames"] = clip_ids
    log.info("video %s: %d frames at %s fps, %dx%d; %d sampled for CLIP/aesthetic", inputs["video"], video["n_frames"],
             video["fps"], video["width"], video["height"], len(clip_ids))

    clip, aesthetic = image_scores(clip_frames, clip_ids, text, mc, cfg.get("device"), log)
    sa_pc = _videophy2(vp_backend, vc, inputs["video"], sampled.get("videophy2"), text, cfg.get("device"), log)
    doc = {
        "schema_version": SCHEMA_VERSION,
        "clip_score": clip,
        "aesthetic_score": aesthetic,
        "semantic_adherence": sa_pc["sa"],
        "physical_commonsense": sa_pc["pc"],
        "physical": physical,
        "video": video,
        "text": text,
        "materials": [{k: inst.get(k) for k in ("label", "name", "material", "elasticity", "plasticity", "E", "nu", "density")}
                      | {"source": (inst.get("provenance") or {}).get("source")} for inst in params.get("instances", [])],
        "bgdo": params.get("bgdo"),
    }
    doc, bad = scrub_nonfinite(doc)
    if bad:
        log.warning("non-finite numbers written as null: %s", ", ".join(bad[:10]))
    write_json(outputs["metrics"], doc)
    for key in ("clip_score", "aesthetic_score", "semantic_adherence", "physical_commonsense"):
        log.info("%s (%s): %s", doc[key]["column"], key, _fmt(doc[key]))
    log.info("physical checks %s -> %s", physical["checks"], outputs["metrics"])
    return {"clip_score": clip["value"], "aesthetic_score": aesthetic["value"],
            "semantic_adherence": sa_pc["sa"]["value"], "physical_commonsense": sa_pc["pc"]["value"],
            "all_checks_pass": physical["all_checks_pass"]}


def _videophy2(backend: str, vc: dict, video_path: str, sampled, text: str, global_device, log) -> dict:
    """{"sa": entry, "pc": entry} from the selected VideoPhy2 backend."""
    tasks = [t for t in videophy2.TASKS if t in vc.get("tasks", list(videophy2.TASKS))]
    mapping = vc.get("mapping", "linear")
    out = {t: videophy2.not_rated(t, "not in metrics.videophy2.tasks") for t in videophy2.TASKS if t not in tasks}
    if backend in ("none", "unconfigured"):
        reason = videophy2.not_configured_reason(backend)
        return out | {t: videophy2.not_rated(t, reason) for t in tasks}
    if backend == "official":
        from .videophy2_official import configured, rate

        if not configured(vc.get("official") or {}):
            reason = ("metrics.videophy2.backend is official but no rater is configured: set "
                      "metrics.videophy2.official.command, or .python, .repo and .checkpoint")
            return out | {t: videophy2.not_rated(t, reason, videophy2.BACKENDS["official"]) for t in tasks}
        return out | rate(video_path, text, tasks, vc["official"], mapping, log)
    from .videophy2_inprocess import rate

    ic = vc.get("inprocess") or {}
    if not ic.get("model_path"):
        reason = "metrics.videophy2.backend is inprocess but metrics.videophy2.inprocess.model_path is not set"
        return out | {t: videophy2.not_rated(t, reason, videophy2.BACKENDS["inprocess"]) for t in tasks}
    ids, frames = sampled
    return out | rate(frames, ids, text, tasks, ic, mapping, global_device, log)


def _fmt(m: dict) -> str:
    if m.get("value") is None:
        return f"null ({m.get('reason')})"
    stand_in = "" if m.get("paper_metric") else " [stand-in, not the paper's metric]"
    return f"{m['value']:.4f} ({m.get('backend')}){stand_in}"


def _read_params(path: str) -> dict:
    doc = read_json_input(path, "params file")
    if not isinstance(doc, dict) or not isinstance(doc.get("instances"), list):
        raise InputError(path, "params.json needs an 'instances' list")
    return doc
