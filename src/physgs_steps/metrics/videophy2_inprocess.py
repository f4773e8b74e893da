"""An in-process stand-in for the VideoPhy-2 rater: its questions asked of a local Qwen3-VL.

For users without the official rater (which needs its own old-transformers environment and
a GPU). The frames (the middle of ``n_frames`` equal segments, as the rater samples) are
given to the Qwen3-VL that the params stage loads (:mod:`physgs_steps.params.qwen3vl`, same
loading and cache) as images in temporal order, followed by VideoPhy2's question for the task
and a request for one digit. Greedy decoding; the first number of the answer must be a whole
1-5 (:func:`.videophy2.parse_rating`), anything else is a null score with the answer in the
reason. The values are labelled ``backend: videophy2_inprocess``, ``paper_metric: false``
and carry :data:`.videophy2.INPROCESS_LABEL`: they are not the paper's metric.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .videophy2 import BACKENDS, INPROCESS_LABEL, QUESTIONS, not_rated, parse_rating, rated

KEY = "metrics.videophy2.inprocess"
BACKEND = BACKENDS["inprocess"]


def prompt(task: str, caption: str, n_images: int) -> str:
    """The text that follows the ``n_images`` frames."""
    return (f"The {n_images} images above are frames of one video, in temporal order.\n"
            f"{QUESTIONS[task].format(caption=caption)}\nAnswer with a single digit from 1 to 5.")


def check_model_folder(path: str) -> None:
    """A configured folder that exists must hold a Qwen3-VL (ConfigError naming the key otherwise)."""
    p = Path(os.path.expanduser(str(path)))
    if not p.is_dir():
        return   # absent weights (or a hub id): reported as a null score by the loader
    cfg = p / "config.json"
    try:
        model_type = json.loads(cfg.read_text()).get("model_type")
    except (OSError, ValueError, AttributeError) as e:
        raise ConfigError(f"{KEY}.model_path", f"{p} has no readable config.json ({e}); expected a Qwen3-VL "
                                               f"checkpoint folder") from None
    if not str(model_type).startswith("qwen3_vl"):
        raise ConfigError(f"{KEY}.model_path", f"{p} holds a {model_type!r} model; the in-process VideoPhy2 rater "
                                               f"needs a Qwen3-VL checkpoint (model_type qwen3_vl)")


def _resized(frames: list[np.ndarray], size: int | None) -> list[np.ndarray]:
    """Frames whose longest side is at most ``size`` pixels (aspect kept)."""
    if not size:
        return frames
    from PIL import Image

    out = []
    for f in frames:
        h, w = f.shape[:2]
        s = size / max(h, w)
        out.append(f if s >= 1 else np.asarray(Image.fromarray(f).resize((max(1, round(w * s)), max(1, round(h * s))),
                                                                           Image.BICUBIC)))
    return out


def rate(frames: list[np.ndarray], frame_ids: list[int], caption: str, tasks: list[str], ic: dict, mapping: str,
         global_device: str | None, log: logging.Logger) -> dict:
    """{task: score entry} from the local Qwen3-VL; every failure is a null score with the reason."""
    from ..params.prompt import BackendError
    from ..params.qwen3vl import Qwen3VLBackend

    path = ic.get("model_path")
    check_model_folder(path)
    backend = Qwen3VLBackend({"model_path": path, "device": ic.get("device", "auto"), "dtype": ic.get("dtype", "auto"),
                              "max_new_tokens": int(ic.get("max_new_tokens", 16))}, global_device, log)
    common = {"label": INPROCESS_LABEL, "model": str(path), "frames": frame_ids, "model_config": backend.describe()}
    try:
        backend.load()
    except BackendError as e:
        return {t: not_rated(t, f"cannot load the in-process rater's model ({KEY}.model_path): {e}", BACKEND, **common)
                for t in tasks}
    images = _resized(frames, ic.get("image_size"))
    out = {}
    for task in tasks:
        if task == "sa" and not caption:
            out[task] = not_rated(task, "no caption: the scene has no prompt and metrics.text is not set", BACKEND, **common)
            continue
        text = prompt(task, caption, len(images))
        details = common | {"prompt": text, "prompt_sha256": hashlib.sha256(text.encode()).hexdigest()}
        t0 = time.perf_counter()
        try:
            answer = backend.send([{"role": "user", "content": text, "images": images}])
        except BackendError as e:
            out[task] = not_rated(task, f"the in-process rater failed: {e}", BACKEND, **details)
            continue
        details |= {"raw_answers": [answer], "seconds": round(time.perf_counter() - t0, 2)}
        rating, why = parse_rating(answer)
        log.info("VideoPhy2 %s (in-process, not the paper's metric): answer %r -> %s", task, answer[:80], rating)
        out[task] = (rated(task, [rating], mapping, BACKEND, False, **details) if rating is not None
                     else not_rated(task, f"unusable answer: {why}", BACKEND, **details))
    return out
