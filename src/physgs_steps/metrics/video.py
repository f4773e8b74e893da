"""Reading the rendered video once and keeping only the frames the scores need.

Two samplings are used:

* ``even``: ``n`` frames spread evenly, first and last included (CLIP and aesthetic scores);
* ``segments``: the middle frame of each of ``n`` equal segments of the video (how the
  VideoPhy2 rater picks its frames), used by the in-process rater.

Seeking in H.264 is not frame exact and keeping every frame would cost GBs at 1080p, so the
frames are counted first, then decoded once in order keeping only the wanted ones.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

SAMPLINGS = ("even", "segments")


def sample_indices(t: int, n: int, how: str = "even") -> list[int]:
    """Sorted, distinct frame indices in [0, t) (at most ``n``).

    ``even``: round(linspace(0, t - 1, min(n, t))).
    ``segments``: with s = (t - 1) / n, frame floor(s / 2) + round(s * i) for i < n (the
    middle of each segment); a video shorter than ``n`` frames gives each frame at most once.
    """
    if t < 1 or n < 1:
        raise ValueError(f"need t >= 1 and n >= 1, got t={t}, n={n}")
    if how == "even":
        idx = np.linspace(0, t - 1, min(n, t)).round().astype(int)
    elif how == "segments":
        s = (t - 1) / n
        idx = int(s / 2) + np.round(s * np.arange(n)).astype(int)
    else:
        raise ValueError(f"unknown sampling {how!r}; choose from {SAMPLINGS}")
    return sorted(set(int(i) for i in np.clip(idx, 0, t - 1)))


def read_frames(path: str, requests: dict[str, tuple[str, int]]) -> tuple[dict, dict[str, tuple[list[int], list[np.ndarray]]]]:
    """Video facts and, per request name, the sampled frames.

    Args:
        path: a video file ffmpeg can decode.
        requests: name -> (sampling, n), e.g. {"clip": ("even", 16), "videophy2": ("segments", 8)}.
    Returns:
        (info {n_frames, fps, width, height}, {name: (indices, frames [H, W, 3] uint8)}).
    Raises:
        InputError when the file cannot be decoded or has no frame.
    """
    import imageio.v2 as imageio

    kept: dict[int, np.ndarray] = {}
    try:
        reader = imageio.get_reader(path, "ffmpeg")
        try:
            meta = reader.get_meta_data()
            t = int(reader.count_frames())
            if t < 1:
                raise InputError(path, "the video has no frames")
            wanted = {name: sample_indices(t, n, how) for name, (how, n) in requests.items()}
            want = set().union(*wanted.values()) if wanted else {0}
            last = max(want)
            for i, fr in enumerate(reader):
                if i in want:
                    kept[i] = np.ascontiguousarray(np.asarray(fr)[..., :3], dtype=np.uint8)
                if i >= last:
                    break
        finally:
            reader.close()
    except (OSError, RuntimeError, ValueError, IndexError) as e:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(path, f"cannot decode the video: {first}") from None
    if not kept:
        raise InputError(path, "no frame could be decoded")
    h, w = next(iter(kept.values())).shape[:2]
    fps = meta.get("fps")
    info = {"n_frames": t, "fps": float(fps) if isinstance(fps, (int, float)) and np.isfinite(fps) else None,
            "width": int(w), "height": int(h)}
    out = {}
    for name, idx in wanted.items():
        idx = [i for i in idx if i in kept]   # a frame past the decodable end is dropped
        out[name] = (idx, [kept[i] for i in idx])
    return info, out


def read_video_frames(path: str, n: int) -> tuple[dict, list[np.ndarray]]:
    """Video facts and ``n`` frames sampled evenly (first and last included).

    Returns:
        (info with n_frames, fps, width, height, sampled_frames; list of [H, W, 3] uint8).
    """
    info, out = read_frames(path, {"frames": ("even", n)})
    idx, frames = out["frames"]
    if not idx:
        raise InputError(path, "no frame could be decoded")
    return info | {"sampled_frames": idx}, frames
