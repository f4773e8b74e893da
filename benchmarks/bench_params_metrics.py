"""Timing of the vlm_params and metrics stages (prints figures, asserts nothing).

    python benchmarks/bench_params_metrics.py                       # prior + plausibility figures (CPU)
    python benchmarks/bench_params_metrics.py --qwen3vl PATH --device cuda   # a real Qwen3-VL
    python benchmarks/bench_params_metrics.py --clip PATH_TO_CLIP   # CLIP score on a synthetic video

The Qwen3-VL run builds a two-instance synthetic scene (two coloured blobs), renders
``--views`` views of each with the project renderer and asks the model about both; it
prints the load time, seconds per instance, whether the answers were valid, and the peak
CUDA memory.
"""
from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from physgs_steps import save_gaussians
from physgs_steps.config import section_defaults
from physgs_steps.gaussians import GaussianScene
from physgs_steps.metrics import physical_figures, read_video_frames
from physgs_steps.params import stage
from physgs_steps.runtime import peak_rss_mb


def synthetic_inputs(folder: Path, n_per_instance: int, k: int) -> tuple[dict, dict, dict]:
    rng = np.random.default_rng(0)
    centers = [[0.3 + 0.4 * i / max(1, k - 1), 0.5, 0.3] for i in range(k)]
    means = np.concatenate([rng.normal(c, 0.05, (n_per_instance, 3)) for c in centers])
    n = len(means)
    sh = np.zeros((n, 1, 3), np.float32)
    for i in range(k):
        sh[i * n_per_instance:(i + 1) * n_per_instance, 0] = rng.uniform(-1.5, 1.5, 3)
    scene = GaussianScene(means=means, log_scales=np.full((n, 3), np.log(0.008)), quats=np.tile([1, 0, 0, 0], (n, 1)),
                          opacity_logits=np.full(n, 3.0), sh=sh)
    save_gaussians(scene, folder / "scene.ply")
    np.savez(folder / "labels.npz", labels=np.repeat(np.arange(k, dtype=np.int32), n_per_instance))
    (folder / "clusters.json").write_text(json.dumps({"n_instances": k, "instances": [
        {"label": i, "count": n_per_instance, "config_index": i if i < 2 else None} for i in range(k)]}))
    scene_cfg = {"prompt": "a rubber duck drops onto a heavy stone",
                 "instances": [{"name": "duck", "hint": "a yellow rubber duck"}, {"name": "stone", "hint": "a grey stone"}]}
    inputs = {"scene": str(folder / "scene.ply"), "labels": str(folder / "labels.npz"),
              "clusters": str(folder / "clusters.json")}
    return inputs, {"params": str(folder / "params.json")}, scene_cfg


def bench_prior(folder: Path, log) -> None:
    inputs, outputs, scene_cfg = synthetic_inputs(folder, 1000, 8)
    cfg = {"materials": section_defaults("materials"), "scene": scene_cfg, "device": "cpu"}
    t0 = time.perf_counter()
    stage.run(inputs, outputs, cfg, log)
    print(f"prior backend, K=8 instances: {time.perf_counter() - t0:.3f} s")


def bench_qwen3vl(folder: Path, path: str, device: str, views: int, log) -> None:
    import torch

    inputs, outputs, scene_cfg = synthetic_inputs(folder, 5000, 2)
    m = section_defaults("materials")
    m["backend"] = "qwen3vl"
    m["on_failure"] = "fallback"
    m["qwen3vl"].update({"model_path": path, "device": device, "n_views": views})
    cfg = {"materials": m, "scene": scene_cfg, "device": device}
    from physgs_steps.params import qwen3vl

    t0 = time.perf_counter()
    qwen3vl.load(path, qwen3vl.resolve_device(device, device), m["qwen3vl"]["dtype"], log)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    stage.run(inputs, outputs, cfg, log)
    t_ask = time.perf_counter() - t0
    doc = json.loads(Path(outputs["params"]).read_text())
    print(f"qwen3vl load: {t_load:.1f} s; 2 instances with {views} views: {t_ask:.1f} s ({t_ask / 2:.1f} s/instance)")
    for inst in doc["instances"]:
        p = inst["provenance"]
        print(f"  {inst['name']}: source={p['source']} material={inst['material']} E={inst['E']:.3g} "
              f"attempts={len(p.get('attempts', []))} fallback={p.get('fallback_reason')}")
    if torch.cuda.is_available():
        print(f"peak CUDA memory: {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB")


def bench_physical(folder: Path, t: int, nv: int) -> None:
    """The plausibility figures: accumulated while writing (as final_sim does), read back
    from the stored attribute (the metrics stage), and recomputed by streaming every frame."""
    from physgs_steps.final_frames import FinalWriter
    from physgs_steps.physical import PhysicalFigures, figures_from_file

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.3, 0.6, (nv, 3)).astype(np.float32)
    path = folder / "final.h5"
    times = np.arange(t) / 30.0
    acc = PhysicalFigures(t)
    t_acc = 0.0
    with h5py.File(path, "w") as h:
        w = FinalWriter(h, np.arange(nv), times)
        for i in range(t):
            x = x0 - np.float32(0.001 * i) * np.array([0, 0, 1], np.float32)
            f = np.eye(3, dtype=np.float32) + rng.normal(0, 0.01, (nv, 3, 3)).astype(np.float32)
            w.frame(i, x, f)
            t0 = time.perf_counter()
            acc.add(i, x, f)
            t_acc += time.perf_counter() - t0
        w.finish({"physical": acc.result(times)})
    t0 = time.perf_counter()
    physical_figures(str(path))
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    figures_from_file(str(path))
    t_stream = time.perf_counter() - t0
    print(f"plausibility figures, T={t}, Nv={nv}: accumulated while writing {t_acc:.2f} s, read back by metrics "
          f"{t_read:.3f} s, recomputed from the frames {t_stream:.2f} s (peak RSS {peak_rss_mb():.0f} MiB)")


def bench_clip(folder: Path, clip: str, n_frames: int) -> None:
    import imageio.v2 as imageio

    from physgs_steps.metrics import image_embeddings, load_clip, text_embedding

    video = folder / "video.mp4"
    w = imageio.get_writer(video, fps=30, codec="libx264")
    for i in range(150):
        fr = np.zeros((512, 512, 3), np.uint8)
        fr[100 + i: 250 + i, 150:350] = [220, 140, 60]
        w.append_data(fr)
    w.close()
    t0 = time.perf_counter()
    _, frames = read_video_frames(str(video), n_frames)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    model, proc = load_clip(clip, "cuda" if __import__("torch").cuda.is_available() else "cpu")
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    img = image_embeddings(model, proc, frames)
    (img @ text_embedding(model, proc, "an orange box falls")).mean()
    print(f"CLIP: decode 150 frames {t_read:.2f} s, load {t_load:.1f} s, score {n_frames} frames "
          f"{time.perf_counter() - t0:.2f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--qwen3vl", help="Qwen3-VL folder or cached hub id")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--clip", help="CLIP folder or cached hub id")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--gaussians", type=int, default=20000)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    log = logging.getLogger("bench")
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        bench_prior(folder, log)
        bench_physical(folder, args.frames, args.gaussians)
        if args.qwen3vl:
            bench_qwen3vl(folder, args.qwen3vl, args.device, args.views, log)
        if args.clip:
            bench_clip(folder, args.clip, 16)


if __name__ == "__main__":
    main()
