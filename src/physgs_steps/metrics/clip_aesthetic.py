"""CLIP score (CS) and LAION aesthetic score (AS) of sampled video frames.

* CS: mean cosine similarity between the CLIP embeddings of the frames and of the prompt.
* AS: a LAION-style predictor (a chain of Linear layers on the L2-normalised CLIP image
  embedding; the improved-aesthetic-predictor head is 768-1024-128-64-16-1 on ViT-L/14)
  averaged over the same frames.

Weights come from local paths only (nothing is downloaded). A path that is not set, or that
does not exist on this machine, makes the score null with the reason. A path that exists but
holds something else (another model type, missing weights, a head whose input size does not
match the CLIP embedding) is a configuration mistake: :class:`ConfigError` naming the key.
torch and transformers are imported only when a score is computed.
"""
from __future__ import annotations

import logging
import os
import re
import threading
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .scores import measured, unavailable

_CLIP_CACHE: dict[tuple[str, str], tuple] = {}
_LOCK = threading.Lock()
CLIP_KEY, AES_KEY = "metrics.clip_model_path", "metrics.aesthetic_model_path"
# (hidden size, layers, patch size) of the vision towers of the released CLIP models
_VIT_NAMES = {(768, 12, 32): "ViT-B/32", (768, 12, 16): "ViT-B/16", (1024, 24, 14): "ViT-L/14",
              (1280, 32, 14): "ViT-H/14", (1664, 48, 14): "ViT-bigG/14"}


class WeightsAbsent(Exception):
    """The configured weights are not on this machine (the score is null with this reason)."""


def _local(path: str) -> Path | None:
    p = Path(os.path.expanduser(str(path)))
    return p if p.exists() else None


def clip_architecture(model) -> dict:
    """What a loaded CLIPModel is: variant name, image size, embedding size."""
    vc = model.config.vision_config
    key = (int(vc.hidden_size), int(vc.num_hidden_layers), int(vc.patch_size))
    return {"variant": _VIT_NAMES.get(key, f"ViT ({key[0]}-d, {key[1]} layers, patch {key[2]})"),
            "image_size": int(vc.image_size), "embedding_dim": int(model.config.projection_dim)}


def load_clip(path: str, device: str):
    """(model, processor) of a local CLIP checkpoint, loaded once per process.

    Raises:
        WeightsAbsent: the path does not exist and is not a hub id in the local cache.
        ConfigError: the path exists but does not hold a complete transformers CLIPModel.
    """
    key = (str(path), device)
    with _LOCK:
        if key in _CLIP_CACHE:
            return _CLIP_CACHE[key]
        from transformers import AutoConfig, AutoProcessor, CLIPModel

        local = _local(path)
        src = str(local) if local else str(path)
        try:
            cfg = AutoConfig.from_pretrained(src, local_files_only=True)
        except (OSError, ValueError) as e:
            if local is None:
                raise WeightsAbsent(f"{path!r} is neither a folder on this machine nor a model in the local "
                                    f"Hugging Face cache (nothing is downloaded)") from None
            raise ConfigError(CLIP_KEY, f"{src} is not a transformers model folder (no readable config.json): "
                                        f"{_first_line(e)}") from None
        if getattr(cfg, "model_type", None) != "clip":
            raise ConfigError(CLIP_KEY, f"{src} holds a {getattr(cfg, 'model_type', None)!r} model, not CLIP "
                                        f"(expected config.json with model_type 'clip', e.g. openai/clip-vit-large-patch14)")
        try:
            model, info = CLIPModel.from_pretrained(src, local_files_only=True, output_loading_info=True)
            processor = AutoProcessor.from_pretrained(src, local_files_only=True)
        except (OSError, ValueError, RuntimeError) as e:
            raise ConfigError(CLIP_KEY, f"cannot load the CLIP checkpoint in {src}: {_first_line(e)}") from None
        missing = [k for k in info.get("missing_keys") or [] if not k.endswith("position_ids")]
        if missing:
            raise ConfigError(CLIP_KEY, f"{src} lacks weights for {len(missing)} CLIP parameters (e.g. {missing[:3]}): "
                                        f"not a complete CLIP checkpoint")
        if not hasattr(processor, "image_processor") or not hasattr(processor, "tokenizer"):
            raise ConfigError(CLIP_KEY, f"{src} has no CLIP processor (image processor + tokenizer)")
        _CLIP_CACHE[key] = (model.to(device).eval(), processor)
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
    """[(weight [out, in], bias [out] or None)] of a LAION-style aesthetic MLP, in layer order.

    Accepts the improved-aesthetic-predictor state dicts (``layers.0.weight``, ...,
    ``layers.7.bias``), a single Linear (``weight``, ``bias``) as in the first LAION
    predictor, and .safetensors files with the same keys.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not such a state dict (unreadable, not a chain of Linear
            layers, or not ending in one output).
    """
    import torch

    p = Path(os.path.expanduser(str(path)))
    if not p.is_file():
        raise FileNotFoundError(f"{p} does not exist")
    try:
        if p.suffix == ".safetensors":
            from safetensors.torch import load_file

            sd = load_file(str(p))
        else:
            sd = torch.load(str(p), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - pickle, zip and safetensors errors have no common base
        raise ValueError(f"{p}: not a readable torch state dict ({type(e).__name__}: {_first_line(e)})") from None
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict) or not all(hasattr(v, "shape") for v in sd.values()):
        raise ValueError(f"{p}: expected a state dict of tensors, got {type(sd).__name__}")
    if "weight" in sd:
        layers = [(sd["weight"], sd.get("bias"))]
    else:
        idx = sorted({int(m.group(1)) for k in sd for m in [re.search(r"(\d+)\.weight$", k)] if m})
        if not idx:
            raise ValueError(f"{p}: no '<i>.weight' Linear layers in the state dict (keys: {list(sd)[:6]})")
        prefix = {i: next(k[: -len(".weight")] for k in sd if re.search(rf"(^|\.){i}\.weight$", k)) for i in idx}
        layers = [(sd[prefix[i] + ".weight"], sd.get(prefix[i] + ".bias")) for i in idx]
    for j, (w, b) in enumerate(layers):
        if w.ndim != 2 or (b is not None and tuple(b.shape) != (w.shape[0],)):
            raise ValueError(f"{p}: layer {j} is not a Linear layer (weight {tuple(w.shape)})")
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


def resolve_device(dev: str, global_device: str | None) -> str:
    """``auto`` -> the run's device, else CUDA when torch sees one (imports torch only then)."""
    if dev != "auto":
        return dev
    if global_device in ("cpu", "cuda"):
        return global_device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def image_scores(frames: list[np.ndarray], frame_ids: list[int], text: str, mc: dict, global_device: str | None,
                 log: logging.Logger) -> tuple[dict, dict]:
    """(clip_score, aesthetic_score) entries (scores.py shape); null values carry the reason."""
    clip_path, aes_path = mc.get("clip_model_path"), mc.get("aesthetic_model_path")
    act = mc.get("aesthetic_activation", "none")
    if act not in ("none", "relu"):
        raise ConfigError("metrics.aesthetic_activation", f"must be none or relu, got {act!r}")
    if not clip_path:
        reason = f"{CLIP_KEY} is not set (no CLIP weights; nothing is downloaded)"
        aes = "needs CLIP image embeddings, and " + reason
        return (unavailable("clip_score", reason),
                unavailable("aesthetic_score", aes if aes_path else f"{AES_KEY} is not set; " + aes))
    try:
        model, processor = load_clip(clip_path, resolve_device(mc.get("device", "auto"), global_device))
    except WeightsAbsent as e:
        reason = f"no CLIP weights at {CLIP_KEY} = {e}"
        log.warning("%s", reason)
        return unavailable("clip_score", reason), unavailable("aesthetic_score", "needs CLIP image embeddings: " + reason)
    arch = clip_architecture(model)
    img = image_embeddings(model, processor, frames)   # [F, D]
    if text:
        cos = (img @ text_embedding(model, processor, text)).numpy().astype(float)   # [F]
        clip = measured("clip_score", float(cos.mean()), "clip", True, per_frame=[round(float(c), 6) for c in cos],
                        frames=frame_ids, model=str(clip_path), architecture=arch, text=text,
                        definition="mean cosine similarity of CLIP image and text embeddings")
    else:
        clip = unavailable("clip_score", "no text: the scene has no prompt and metrics.text is not set", backend="clip")
    return clip, _aesthetic(img, frame_ids, aes_path, act, arch, log)


def _aesthetic(img, frame_ids, aes_path, act, arch, log) -> dict:
    if not aes_path:
        return unavailable("aesthetic_score", f"{AES_KEY} is not set (no aesthetic predictor weights; nothing is downloaded)")
    try:
        layers = load_aesthetic(aes_path)
    except FileNotFoundError as e:
        reason = f"no aesthetic predictor at {AES_KEY}: {e}"
        log.warning("%s", reason)
        return unavailable("aesthetic_score", reason)
    except ValueError as e:
        raise ConfigError(AES_KEY, str(e)) from None
    d_in = int(layers[0][0].shape[1])
    if d_in != img.shape[1]:
        raise ConfigError(AES_KEY, f"{aes_path} takes {d_in}-d embeddings but the CLIP model ({arch['variant']}) gives "
                                   f"{img.shape[1]}-d ones (the LAION predictors need ViT-L/14, 768-d)")
    s = aesthetic_scores(layers, img, act).numpy().astype(float)   # [F]
    sizes = [d_in] + [int(w.shape[0]) for w, _ in layers]
    return measured("aesthetic_score", float(s.mean()), "laion_aesthetic", True,
                    per_frame=[round(float(v), 6) for v in s], frames=frame_ids, model=str(aes_path),
                    architecture={"layers": "-".join(map(str, sizes)), "activation": act, "clip": arch["variant"]},
                    definition="LAION aesthetic MLP on L2-normalised CLIP image embeddings (about 1-10)")


def _first_line(e: BaseException) -> str:
    s = str(e).strip()
    return s.splitlines()[0] if s else type(e).__name__
