"""Stage `metrics`: scores of the final video and plausibility figures of the final simulation.

inputs  {"video": video.mp4, "frames": final.h5, "params": params.json}
outputs {"metrics": metrics.json}
cfg     {"metrics": {...}, "scene": {"prompt": ...}, "device": ...}

* ``clip_score``: mean cosine similarity between the CLIP embeddings of frames sampled
  evenly from the video and of the prompt (the paper's CS, e.g. 0.29), with per-frame values.
* ``aesthetic_score``: a LAION-style predictor (a chain of Linear layers on the
  L2-normalised CLIP image embedding) averaged over the same frames (the paper's AS).
  Both need local weights; without them they are ``{"value": null, "reason": ...}``.
* ``physical``: figures that need no weights (:mod:`physgs_steps.physical`): deformation
  ||F - I||_F, det F range, displacement, whether the objects moved and stayed in the
  domain, final speed, and pass/fail checks; final_sim accumulates them while simulating
  and stores them with final.h5, so this stage does not read the frames.
"""
from __future__ import annotations

import logging
import re
import threading
from pathlib import Path

import numpy as np

from .errors import ConfigError, InputError
from .runtime import read_json_input, write_json

_CLIP_CACHE: dict[tuple[str, str], tuple] = {}
_LOCK = threading.Lock()


def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    mc = cfg.get("metrics")
    if not isinstance(mc, dict):
        raise ConfigError("metrics", "the stage needs the validated `metrics` config section")
    text = mc.get("text") or (cfg.get("scene") or {}).get("prompt") or ""
    params = _read_params(inputs["params"])
    physical = physical_figures(inputs["frames"], float(mc.get("moved_threshold", 0.005)),
                                float(mc.get("domain_margin", 0.0)), log)
    video, frames = read_video_frames(inputs["video"], int(mc.get("n_frames", 16)))
    log.info("video %s: %d frames at %s fps, %dx%d; %d sampled for scores", inputs["video"], video["n_frames"],
             video["fps"], video["width"], video["height"], len(frames))
    device = _device(mc.get("device", "auto"), cfg.get("device"))
    clip, aesthetic = image_scores(frames, video["sampled_frames"], text, mc, device, log)
    doc = {
        "clip_score": clip,
        "aesthetic_score": aesthetic,
        "physical": physical,
        "video": video,
        "text": text,
        "materials": [{k: inst.get(k) for k in ("label", "name", "material", "elasticity", "plasticity", "E", "nu", "density")}
                      | {"source": (inst.get("provenance") or {}).get("source")} for inst in params.get("instances", [])],
        "bgdo": params.get("bgdo"),
    }
    write_json(outputs["metrics"], doc)
    log.info("clip_score %s, aesthetic_score %s, checks %s -> %s", _fmt(clip), _fmt(aesthetic),
             physical["checks"], outputs["metrics"])
    return {"clip_score": clip["value"], "aesthetic_score": aesthetic["value"],
            "all_checks_pass": physical["all_checks_pass"]}


def _fmt(m: dict) -> str:
    return f"{m['value']:.4f}" if m.get("value") is not None else f"null ({m.get('reason')})"


def _device(dev: str, global_device: str | None) -> str:
    if dev != "auto":
        return dev
    if global_device in ("cpu", "cuda"):
        return global_device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _read_params(path: str) -> dict:
    doc = read_json_input(path, "params file")
    if not isinstance(doc, dict) or not isinstance(doc.get("instances"), list):
        raise InputError(path, "params.json needs an 'instances' list")
    return doc


# --------------------------------------------------------------------------- video
def read_video_frames(path: str, n: int) -> tuple[dict, list[np.ndarray]]:
    """Video facts and ``n`` frames sampled evenly (first and last included).

    The frames are counted first, then decoded once in order keeping only the sampled ones
    (seeking in H.264 is not frame exact, and keeping every frame would cost GBs at 1080p).

    Returns:
        (info dict with n_frames, fps, width, height, sampled_frames; list of [H, W, 3] uint8).
    Raises:
        InputError when the file cannot be decoded or has no frame.
    """
    import imageio.v2 as imageio

    try:
        reader = imageio.get_reader(path, "ffmpeg")
        try:
            meta = reader.get_meta_data()
            t = int(reader.count_frames())
            if t < 1:
                raise InputError(path, "the video has no frames")
            idx = sorted(set(np.linspace(0, t - 1, min(n, t)).round().astype(int).tolist()))
            want, kept = set(idx), {}
            for i, fr in enumerate(reader):
                if i in want:
                    kept[i] = np.ascontiguousarray(np.asarray(fr)[..., :3], dtype=np.uint8)
                if i >= idx[-1]:
                    break
        finally:
            reader.close()
    except (OSError, RuntimeError, ValueError, IndexError) as e:
        raise InputError(path, f"cannot decode the video: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    idx = [i for i in idx if i in kept]
    if not idx:
        raise InputError(path, "no frame could be decoded")
    h, w = kept[idx[0]].shape[:2]
    info = {"n_frames": t, "fps": meta.get("fps"), "width": int(w), "height": int(h), "sampled_frames": idx}
    return info, [kept[i] for i in idx]


# --------------------------------------------------------------------------- CLIP scores
def load_clip(path: str, device: str):
    """(model, processor) of a local CLIP checkpoint, loaded once per process."""
    key = (str(path), device)
    with _LOCK:
        if key not in _CLIP_CACHE:
            from transformers import AutoProcessor, CLIPModel

            model = CLIPModel.from_pretrained(path, local_files_only=True).to(device).eval()
            processor = AutoProcessor.from_pretrained(path, local_files_only=True)
            _CLIP_CACHE[key] = (model, processor)
        return _CLIP_CACHE[key]


def image_embeddings(model, processor, frames: list[np.ndarray], batch: int = 8):
    """[F, D] L2-normalised CLIP image embeddings (float32, CPU) of [H, W, 3] uint8 frames."""
    import torch
    from PIL import Image

    dev = next(model.parameters()).device
    out = []
    with torch.inference_mode():
        for i in range(0, len(frames), batch):
            iin = processor(images=[Image.fromarray(f) for f in frames[i:i + batch]], return_tensors="pt")
            out.append(_pooled(model.get_image_features(pixel_values=iin["pixel_values"].to(dev))).float())
    return torch.nn.functional.normalize(torch.cat(out), dim=-1).cpu()


def text_embedding(model, processor, text: str):
    """[D] L2-normalised CLIP text embedding (float32, CPU); the text is truncated to the model's length."""
    import torch

    dev = next(model.parameters()).device
    max_len = int(getattr(model.config.text_config, "max_position_embeddings", 77))
    with torch.inference_mode():
        tin = processor(text=[text], return_tensors="pt", padding=True, truncation=True, max_length=max_len)
        t = _pooled(model.get_text_features(**{k: v.to(dev) for k, v in tin.items()})).float()
    return torch.nn.functional.normalize(t, dim=-1)[0].cpu()


def _pooled(out):
    """Projected embeddings from get_*_features (a tensor, or an output whose pooler_output is it)."""
    return out if hasattr(out, "dim") else out.pooler_output


def load_aesthetic(path: str) -> list[tuple]:
    """[(weight [out, in], bias [out])] of a LAION-style aesthetic MLP, in layer order.

    Accepts the improved-aesthetic-predictor state dicts (``layers.0.weight``, ...,
    ``layers.7.bias``), a single Linear (``weight``, ``bias``) as in the first LAION
    predictor, and .safetensors files with the same keys.
    """
    import torch

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p} does not exist")
    if p.suffix == ".safetensors":
        from safetensors.torch import load_file

        sd = load_file(str(p))
    else:
        sd = torch.load(str(p), map_location="cpu", weights_only=True)
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise ValueError(f"{p}: expected a state dict, got {type(sd).__name__}")
    if "weight" in sd:
        layers = [(sd["weight"], sd.get("bias"))]
    else:
        idx = sorted({int(m.group(1)) for k in sd for m in [re.search(r"(\d+)\.weight$", k)] if m})
        if not idx:
            raise ValueError(f"{p}: no '<i>.weight' Linear layers in the state dict (keys: {list(sd)[:6]})")
        prefix = {i: next(k[: -len(".weight")] for k in sd if re.search(rf"(^|\.){i}\.weight$", k)) for i in idx}
        layers = [(sd[prefix[i] + ".weight"], sd.get(prefix[i] + ".bias")) for i in idx]
    for j in range(1, len(layers)):
        if layers[j][0].shape[1] != layers[j - 1][0].shape[0]:
            raise ValueError(f"{p}: layer {j} takes {layers[j][0].shape[1]} inputs but layer {j - 1} gives {layers[j - 1][0].shape[0]}")
    if layers[-1][0].shape[0] != 1:
        raise ValueError(f"{p}: the last layer must output one score, got {layers[-1][0].shape[0]}")
    return [(w.float(), None if b is None else b.float()) for w, b in layers]


def aesthetic_scores(layers: list[tuple], image_embeds, activation: str = "none"):
    """[F] scores of the MLP on [F, D] L2-normalised image embeddings."""
    import torch

    x = image_embeds.float()
    for j, (w, b) in enumerate(layers):
        x = torch.nn.functional.linear(x, w, b)
        if activation == "relu" and j < len(layers) - 1:
            x = torch.relu(x)
    return x[:, 0]


def image_scores(frames: list[np.ndarray], frame_ids: list[int], text: str, mc: dict, device: str,
                 log: logging.Logger) -> tuple[dict, dict]:
    """(clip_score, aesthetic_score) metric dicts; null values carry the reason."""
    clip_path, aes_path = mc.get("clip_model_path"), mc.get("aesthetic_model_path")
    if not clip_path:
        reason = "metrics.clip_model_path is not set (no CLIP weights; nothing is downloaded)"
        aes = "needs CLIP image embeddings, and " + reason
        return _null(reason), _null(aes if aes_path else "metrics.aesthetic_model_path is not set; " + aes)
    try:
        model, processor = load_clip(clip_path, device)
    except (OSError, ValueError, ImportError) as e:
        reason = f"cannot load CLIP from {clip_path!r}: {str(e).splitlines()[0] if str(e) else type(e).__name__}"
        log.warning("%s", reason)
        return _null(reason), _null("needs CLIP image embeddings: " + reason)
    img = image_embeddings(model, processor, frames)
    if text:
        cos = (img @ text_embedding(model, processor, text)).numpy().astype(float)
        clip = {"value": float(cos.mean()), "per_frame": [round(float(c), 6) for c in cos], "frames": frame_ids,
                "model": str(clip_path), "text": text,
                "definition": "mean cosine similarity of CLIP image and text embeddings"}
    else:
        clip = _null("no text: the scene has no prompt and metrics.text is not set")
    return clip, _aesthetic(img, frame_ids, aes_path, mc, log)


def _aesthetic(img, frame_ids, aes_path, mc, log) -> dict:
    if not aes_path:
        return _null("metrics.aesthetic_model_path is not set (no aesthetic predictor weights; nothing is downloaded)")
    try:
        layers = load_aesthetic(aes_path)
    except (OSError, ValueError, RuntimeError) as e:
        reason = f"cannot load the aesthetic predictor {aes_path!r}: {str(e).splitlines()[0]}"
        log.warning("%s", reason)
        return _null(reason)
    if layers[0][0].shape[1] != img.shape[1]:
        return _null(f"the aesthetic predictor takes {layers[0][0].shape[1]}-d embeddings but the CLIP model gives "
                     f"{img.shape[1]}-d ones (LAION predictors need ViT-L/14, 768-d)")
    act = mc.get("aesthetic_activation", "none")
    if act not in ("none", "relu"):
        raise ConfigError("metrics.aesthetic_activation", f"must be none or relu, got {act!r}")
    s = aesthetic_scores(layers, img, act).numpy().astype(float)
    return {"value": float(s.mean()), "per_frame": [round(float(v), 6) for v in s], "frames": frame_ids,
            "model": str(aes_path), "definition": "LAION aesthetic MLP on L2-normalised CLIP image embeddings (1-10 scale)"}


def _null(reason: str) -> dict:
    return {"value": None, "reason": reason}


# --------------------------------------------------------------------------- physical figures
def physical_figures(path: str, moved_threshold: float = 0.005, margin: float = 0.0,
                     log: logging.Logger | None = None) -> dict:
    """Plausibility figures of final.h5 (:mod:`physgs_steps.physical`): the record final_sim
    accumulated while simulating (attribute ``physical``), judged under ``moved_threshold``
    and ``margin``; recomputed by streaming the frames once only when the file has none.

    Args:
        path: final.h5 (:mod:`physgs_steps.final_frames`).
        moved_threshold: displacement (domain units) above which the scene counts as moving.
        margin: tolerance of the in-domain check (domain units).
    Returns:
        dict of metrics (each ``{"value", "description"}`` or ``{"value": None, "reason"}``),
        ``deformation_per_frame`` and ``checks`` / ``all_checks_pass``.
    """
    from .final_frames import FinalFrames
    from .physical import apply_thresholds, figures_from_file

    with FinalFrames(path) as fr:
        stored = fr.attr("physical")
    if stored is not None:
        if log:
            log.info("physical figures: stored with %s by final_sim", path)
        return apply_thresholds(stored, moved_threshold, margin)
    return figures_from_file(path, moved_threshold, margin, log)
