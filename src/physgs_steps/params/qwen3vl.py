"""The `qwen3vl` backend: Qwen3-VL through transformers, weights from a local path or the cache.

Nothing is downloaded: ``materials.qwen3vl.model_path`` is a folder, or a hub id that must
already be in the local Hugging Face cache.  The model and processor are loaded once per
process and kept in :data:`_CACHE` (key: resolved path, device, dtype).

When the checkpoint's full processor cannot be built (transformers' Qwen3-VL processor also
builds a *video* processor, which needs torchvision), the image processor and tokenizer of
the same folder are used directly: the chat template is applied by the tokenizer and every
``<|image_pad|>`` marker is expanded to the number of merged patches of its image, which
is what the full processor does for images.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from .prompt import BackendError

_CACHE: dict[tuple[str, str, str], tuple[Any, Any]] = {}
_LOCK = threading.Lock()
LOAD_COUNT = {"n": 0}   # how many times weights were actually read (tests check the cache)


def resolve_device(device: str, global_device: str | None) -> str:
    """``auto`` -> the run's device (cfg["device"]), else cuda when available, else cpu."""
    if device not in ("auto", "cpu", "cuda") and not str(device).startswith("cuda:"):
        raise ConfigError("materials.qwen3vl.device", f"must be auto, cpu, cuda or cuda:<i>, got {device!r}")
    if device != "auto":
        return device
    if global_device in ("cpu", "cuda"):
        return global_device
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_dtype(dtype: str, device: str):
    """``auto`` -> bfloat16 on CUDA, float32 on CPU."""
    import torch

    table = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
    if dtype == "auto":
        return torch.bfloat16 if device.startswith("cuda") else torch.float32
    if dtype not in table:
        raise ConfigError("materials.qwen3vl.dtype", f"must be auto, float32, bfloat16 or float16, got {dtype!r}")
    return table[dtype]


def load(model_path: str, device: str, dtype: str, log: logging.Logger | None = None) -> tuple[Any, Any]:
    """(model, processor) for ``model_path``, loaded once per process.

    Raises:
        BackendError when the weights are not available locally or cannot be loaded.
    """
    torch_dtype = resolve_dtype(dtype, device)
    key = (str(model_path), device, str(torch_dtype))
    with _LOCK:
        if key in _CACHE:
            return _CACHE[key]
        t0 = time.perf_counter()
        try:
            from transformers import Qwen3VLForConditionalGeneration
        except ImportError as e:  # pragma: no cover - depends on the transformers version
            raise BackendError(f"transformers has no Qwen3-VL support ({e}); need transformers >= 4.57") from None
        src = _resolve_path(model_path)
        try:
            model = Qwen3VLForConditionalGeneration.from_pretrained(src, dtype=torch_dtype, local_files_only=True)
        except (OSError, ValueError) as e:
            raise BackendError(f"cannot load Qwen3-VL weights from {model_path!r} (nothing is downloaded): "
                               f"{str(e).splitlines()[0]}") from None
        model = model.to(device).eval()
        processor = _load_processor(src, log)
        LOAD_COUNT["n"] += 1
        if log:
            n = sum(p.numel() for p in model.parameters())
            log.info("loaded Qwen3-VL from %s (%.1fM parameters, %s, %s) in %.1f s", src, n / 1e6, device,
                     torch_dtype, time.perf_counter() - t0)
        _CACHE[key] = (model, processor)
        return _CACHE[key]


def _resolve_path(model_path: str) -> str:
    if not model_path:
        raise BackendError("materials.qwen3vl.model_path is empty")
    p = Path(os.path.expanduser(model_path))
    if p.is_dir():
        return str(p)
    if p.is_absolute() or model_path.startswith("."):
        raise BackendError(f"Qwen3-VL folder {p} does not exist")
    return model_path  # a hub id: only the local cache is consulted (local_files_only)


def _load_processor(src: str, log: logging.Logger | None):
    from transformers import AutoProcessor

    try:
        return AutoProcessor.from_pretrained(src, local_files_only=True)
    except (ImportError, OSError, ValueError, TypeError, AttributeError) as e:
        if log:
            log.info("full Qwen3-VL processor unavailable (%s); using its image processor and tokenizer",
                     str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__)
        return ImageTextProcessor.from_pretrained(src)


class ImageTextProcessor:
    """Image processor + tokenizer of a Qwen-VL checkpoint, for image+text prompts only."""

    def __init__(self, image_processor, tokenizer, image_token: str = "<|image_pad|>") -> None:
        self.image_processor = image_processor
        self.tokenizer = tokenizer
        self.image_token = image_token
        self.image_token_id = tokenizer.convert_tokens_to_ids(image_token)
        if self.image_token_id is None or self.image_token_id == tokenizer.unk_token_id:
            raise BackendError(f"tokenizer has no {image_token} token")

    @classmethod
    def from_pretrained(cls, src: str) -> "ImageTextProcessor":
        from transformers import AutoImageProcessor, AutoTokenizer

        try:
            try:
                ip = AutoImageProcessor.from_pretrained(src, local_files_only=True, backend="pil")
            except TypeError:
                ip = AutoImageProcessor.from_pretrained(src, local_files_only=True)
            tok = AutoTokenizer.from_pretrained(src, local_files_only=True)
        except (OSError, ValueError, ImportError) as e:
            raise BackendError(f"cannot load the Qwen3-VL processor from {src!r}: {str(e).splitlines()[0]}") from None
        if not getattr(tok, "chat_template", None):
            raise BackendError(f"the tokenizer in {src!r} has no chat template")
        return cls(ip, tok)

    def apply_chat_template(self, messages, add_generation_prompt=True, tokenize=False):
        return self.tokenizer.apply_chat_template(messages, add_generation_prompt=add_generation_prompt, tokenize=tokenize)

    def __call__(self, text: list[str], images=None, return_tensors="pt"):
        """input_ids, attention_mask, mm_token_type_ids and (with images) pixel_values, image_grid_thw."""
        import torch

        feats = {}
        text = list(text)
        if images:
            feats = dict(self.image_processor(images=images, return_tensors="pt"))
            merge = int(getattr(self.image_processor, "merge_size", 2))
            counts = [int(g.prod()) // merge**2 for g in feats["image_grid_thw"]]
            pieces = text[0].split(self.image_token)
            if len(pieces) != len(counts) + 1:
                raise BackendError(f"prompt has {len(pieces) - 1} image markers for {len(counts)} images")
            out = pieces[0]
            for n, rest in zip(counts, pieces[1:]):
                out += self.image_token * n + rest
            text[0] = out
        enc = dict(self.tokenizer(text, return_tensors=return_tensors))
        enc["mm_token_type_ids"] = (enc["input_ids"] == self.image_token_id).to(torch.int32)
        enc.update(feats)
        return enc

    def batch_decode(self, ids, skip_special_tokens=True):
        return self.tokenizer.batch_decode(ids, skip_special_tokens=skip_special_tokens)


class Qwen3VLBackend:
    """Answers questions with a local Qwen3-VL (greedy decoding, deterministic)."""

    name = "qwen3vl"

    def __init__(self, cfg: dict, global_device: str | None, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self.device = resolve_device(cfg.get("device", "auto"), global_device)
        self.dtype = cfg.get("dtype", "auto")
        self.max_new_tokens = int(cfg.get("max_new_tokens", 512))
        self.model_path = cfg.get("model_path")

    def describe(self) -> dict:
        return {"model_path": self.model_path, "device": self.device, "dtype": self.dtype,
                "max_new_tokens": self.max_new_tokens}

    def load(self) -> None:
        load(self.model_path, self.device, self.dtype, self.log)

    def send(self, messages: list[dict]) -> str:
        """Reply text of the model to the neutral messages (see params/prompt.py)."""
        import torch
        from PIL import Image

        model, processor = load(self.model_path, self.device, self.dtype, self.log)
        chat, images = [], []
        for m in messages:
            content = [{"type": "image"} for _ in m.get("images") or []]
            images += [Image.fromarray(np.asarray(im, dtype=np.uint8)) for im in m.get("images") or []]
            content.append({"type": "text", "text": m["content"]})
            chat.append({"role": m["role"], "content": content})
        try:
            text = processor.apply_chat_template(chat, add_generation_prompt=True, tokenize=False)
            inputs = processor(text=[text], images=images or None, return_tensors="pt")
            inputs = {k: (v.to(model.device) if hasattr(v, "to") else v) for k, v in dict(inputs).items()}
            with torch.inference_mode():
                out = model.generate(**inputs, max_new_tokens=self.max_new_tokens, do_sample=False)
        except BackendError:
            raise
        except (RuntimeError, ValueError, TypeError, IndexError) as e:
            raise BackendError(f"Qwen3-VL generation failed: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None
        new = out[:, inputs["input_ids"].shape[1]:]
        return processor.batch_decode(new, skip_special_tokens=True)[0]
