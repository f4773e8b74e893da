"""Stage ``render``: final.h5 -> video.mp4, contact_sheet.png, render.json.

Inputs: ``frames`` (final.h5), ``scene`` (scene.ply, sim frame), ``transform``
(transform.json), ``carrier`` (carrier.h5: which stored particles carry each gaussian),
optional ``cameras`` (an INRIA cameras.json, source frame).

final.h5 is streamed once, frame after frame; gaussians the simulation does not move
(static surroundings, static instances) are drawn at rest in every frame. A frame held at
rest (the same stored row as the frame before) reuses the deformed gaussians, and its image
too when the camera has not moved. The frames go in batches (``render.batch``, bounded by GPU
memory: :func:`frames_per_call`): a batch's new states are deformed in one stack, checked
against their cameras with one read-back and drawn in one gsplat call, and their coverage
counts come back in one read-back (on a GPU each small op is a launch paid on the host and
each read-back a synchronisation); every frame gets the bits it gets alone
(tests/test_render_batch.py). ``PHYSGS_RENDER_PER_FRAME=1`` does that work frame by frame.
Outputs: ``video`` (H.264 mp4), ``contact_sheet`` (PNG grid of frames), ``report``
(render.json), optional ``frames`` (folder of PNGs; default ``frames/`` next to the video
when ``render.png_frames`` is set).

Bad input is reported, never rendered into a silent black video:
* a camera inside the object (inside the 2-98 % box of the simulated gaussians' centres with
  > 5 % of them behind the near plane), or all of them behind the near plane: RenderError;
* some gaussians behind the near plane (clipped): logged per frame, listed in the report;
* NaN/inf positions or deformation gradients: RenderError, or with ``on_nonfinite: hide``
  the frame is drawn without them (logged, counted in the report);
* frames in which nothing covers a pixel: logged and listed; if that is every frame,
  RenderError (and no video is written).
"""
from __future__ import annotations

import logging
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from ..carrier import load_carrier
from ..config import load_schema, validate
from ..errors import ConfigError, InputError, RenderError
from ..final_frames import FinalFrames
from ..prepare import load_transform
from ..runtime import project_root, write_json
from ..scene_io import load_gaussians
from . import cameras as C
from .deform import (NONFINITE_POLICIES, CarrierMap, Gaussians, SourceMap, check_frame, covers_all, deform_frames,
                     rest_gaussians)
from .renderer import Renderer, RenderSettings, resolve_backend
from .video import FrameDir, VideoWriter, contact_sheet, sheet_indices, write_png

NEAR_FRACTION = 1e-3  # automatic near plane: this fraction of the scene size
FAR_FACTOR = 1e3  # automatic far plane: this many scene sizes beyond the farthest camera's distance
CLIP_WARN_FRACTION = 0.05  # > 5 % of the centres behind the near plane: clipped (inside the box: error)
COVERED_ALPHA = 0.5  # a pixel counts as covered at accumulated alpha above this
# "1": the frames of a batch are deformed, checked against their cameras and counted (coverage)
# one at a time, with a host synchronisation each, as before the batched loop (an A/B knob)
PER_FRAME_ENV = "PHYSGS_RENDER_PER_FRAME"
# Gaussian rows (frames x simulated gaussians) deformed in one stack.  The stack saves host
# launches; its scratch tensors grow with it.  Measured on one H100 (2026-11-28, `physgs bench
# pipeline bear --structures server --no-cold`, whole 16-frame batches in one stack): default
# bear (46k gaussians) render's deform part 0.09-0.12 s against 0.45 s frame by frame, peak GPU
# 1427-1429 against 1303 MiB; 300k bear at 1080p (4 frames a batch) 0.41 against 0.45 s, but
# peak GPU 2035 against 1751 MiB.  So a stack holds at most 2^19 rows: 11 frames of the default
# bear, one frame at a time from 2^19 gaussians up (memory as frame by frame, where the stack
# gained nothing).
DEFORM_ROWS = 1 << 19


# ---------------------------------------------------------------------------- config
def camera_config(scene_cfg: dict) -> dict:
    """The scene's ``camera`` block with defaults filled (scene_camera.schema.yaml)."""
    cam = dict((scene_cfg or {}).get("camera") or {})
    return validate(cam, load_schema("scene_camera.schema.yaml"), "scene camera", "camera")


def settings_from_config(rcfg: dict) -> RenderSettings:
    """Renderer settings; automatic (null) near/far planes are set by :func:`clip_planes`."""
    if rcfg["on_nonfinite"] not in NONFINITE_POLICIES:
        raise ConfigError("render.on_nonfinite", f"must be one of {NONFINITE_POLICIES}")
    near, far = rcfg.get("near"), rcfg.get("far")
    if near is not None and far is not None and far <= near:
        raise ConfigError("render.far", f"far ({far}) must exceed near ({near})")
    s = RenderSettings(background=tuple(float(v) for v in rcfg["background"]), sh_degree=int(rcfg["sh_degree"]),
                       eps2d=float(rcfg["eps2d"]), compositor=rcfg["cpu_compositor"])
    s.near = float(near) if near is not None else s.near
    s.far = float(far) if far is not None else s.far
    return s


def scene_size(transform) -> float:
    """S: the largest side of the scene's trimmed bounding box in source units (extent / scale)."""
    return float(transform.record.get("extent", 0.5)) / float(transform.scale)


def clip_planes(rcfg: dict, size: float, cams: list, center) -> tuple[float, float]:
    """(near, far) in source units: the configured values, or for null 1e-3 S and
    1e3 S + the largest camera distance from ``center`` (S = ``size``)."""
    near = rcfg.get("near")
    far = rcfg.get("far")
    near = NEAR_FRACTION * size if near is None else float(near)
    if far is None:
        reach = max(float(np.linalg.norm(c.position - np.asarray(center, np.float64))) for c in cams)
        far = FAR_FACTOR * size + reach
    if far <= near:
        raise ConfigError("render.far", f"far ({far:.4g}) must exceed near ({near:.4g}) (source units; the scene is "
                                        f"{size:.4g} units across): set render.near/far to null to follow the scene")
    return near, float(far)


def image_size(rcfg: dict, ccfg: dict) -> tuple[int, int]:
    w = ccfg.get("width") or rcfg["width"]
    h = ccfg.get("height") or rcfg["height"]
    if int(w) < 1 or int(h) < 1:
        raise ConfigError("render.width/height", f"image size {w}x{h} is empty")
    return int(w), int(h)


# ---------------------------------------------------------------------------- cameras
def motion_bounds(frames: FinalFrames, smap: SourceMap, rest_means: torch.Tensor,
                  static_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Source-frame box ([3] lo, [3] hi) of the motion: final.h5's ``motion_box`` (the union
    over frames of the 1-99 % box of the stored positions, recorded while simulating; a
    sim-frame box is mapped back through its corners); with nothing simulated, the 1-99 %
    box of the static gaussians."""
    box = frames.motion_box
    if box is not None:
        frame, lo, hi = box
        if frame == "source":
            return lo, hi
        corners = np.array([[(hi if (c >> a) & 1 else lo)[a] for a in range(3)] for c in range(8)])  # [8, 3]
        src = smap.points(torch.from_numpy(corners)).numpy()
        return src.min(axis=0), src.max(axis=0)
    if static_rows.size:
        p = rest_means[torch.as_tensor(static_rows, device=rest_means.device)].double().cpu().numpy()
        b = np.percentile(p, [1.0, 99.0], axis=0)
        return b[0], b[1]
    raise RenderError(f"{frames.path}: no finite particle positions in the rendered frames")


def build_cameras(ccfg: dict, rcfg: dict, frame_ids: list[int], bounds, cameras_path, log: logging.Logger) -> tuple[list[C.Camera], dict]:
    """One camera per rendered frame, and a record of how they were chosen.

    Args:
        ccfg: the scene's ``camera`` block; rcfg: the ``render`` section.
        frame_ids: simulated frame numbers being rendered (per-frame deltas use them).
        bounds: callable returning ([3] lo, [3] hi) of the motion, called only when needed.
        cameras_path: cameras.json path or None.
    """
    width, height = image_size(rcfg, ccfg)
    if ccfg["mode"] == "cameras_json":
        path = cameras_path or ccfg.get("cameras_json")
        if not path:
            raise ConfigError("camera.cameras_json", "mode is cameras_json but no cameras.json was given")
        path = Path(path)
        if not path.is_absolute() and not path.exists():
            path = project_root() / path
        cams = C.load_inria_cameras(path)
        i = int(ccfg["camera_index"])
        if i >= len(cams):
            raise ConfigError("camera.camera_index", f"{path} has {len(cams)} cameras, index {i} does not exist")
        cam = cams[i]
        w = ccfg.get("width") or rcfg["width"]
        h = ccfg.get("height") or max(1, int(round(w * cam.height / cam.width)))
        cam = cam.resized(int(w), int(h))
        log.info("camera %d (%s) of %s, rendered at %dx%d", i, cam.name, path, cam.width, cam.height)
        return [cam] * len(frame_ids), {"mode": "cameras_json", "path": str(path), "index": i, "name": cam.name,
                                        "position": cam.position.tolist(), "width": cam.width, "height": cam.height}
    look_at, radius = ccfg["look_at"], ccfg["radius"]
    record = {"mode": "orbit"}
    if look_at is None or radius is None:
        lo, hi = bounds()
        record["motion_bounds"] = [lo.tolist(), hi.tolist()]
        if look_at is None:
            look_at = ((lo + hi) / 2.0).tolist()
        if radius is None:
            sphere = 0.5 * float(np.linalg.norm(hi - lo))
            k = C.intrinsics_from_fov(ccfg["fov_deg"], width, height)
            half_fov = min(math.atan(0.5 * height / k[1, 1]), math.atan(0.5 * width / k[0, 0]))
            radius = max(sphere, 1e-6) * ccfg["fit_margin"] / math.sin(half_fov)
    f0 = frame_ids[0]
    cams = []
    for t in frame_ids:
        d = t - f0
        cam = C.orbit_cameras(look_at, radius + d * ccfg["radius_per_frame"], 1,
                              ccfg["elevation_deg"] + d * ccfg["elevation_per_frame_deg"], ccfg["fov_deg"],
                              width, height, azimuth_deg=ccfg["azimuth_deg"] + d * ccfg["azimuth_per_frame_deg"],
                              up=ccfg["up"])[0]
        cams.append(C.Camera(cam.viewmat, cam.K, cam.width, cam.height, f"orbit_frame_{t:05d}"))
    record.update({"look_at": [float(v) for v in look_at], "radius": float(radius), "fov_deg": ccfg["fov_deg"],
                   "azimuth_deg": ccfg["azimuth_deg"], "elevation_deg": ccfg["elevation_deg"],
                   "azimuth_per_frame_deg": ccfg["azimuth_per_frame_deg"], "width": width, "height": height})
    log.info("orbit camera: look_at %s, radius %.4g, elevation %.1f deg, azimuth %.1f deg (+%.3g/frame), %dx%d",
             [round(float(v), 4) for v in look_at], radius, ccfg["elevation_deg"], ccfg["azimuth_deg"],
             ccfg["azimuth_per_frame_deg"], width, height)
    return cams, record


def check_cameras(frames: list[int], means: list[torch.Tensor], cams: list[C.Camera], near: float,
                  clipped: list) -> None:
    """Raise on a camera inside the object or with everything behind it, for the first such
    frame in order; note clipped frames (``clipped``: (frame, fraction behind) pairs).

    Args:
        frames: B frame numbers; means: B [n_b, 3] centres of the simulated object (one
            device); cams: B cameras. One read-back for all (:func:`cameras.check_views`).
    """
    for frame, v, cam in zip(frames, C.check_views(means, cams, near), cams):
        where = f"camera at {np.round(cam.position, 4).tolist()}"
        if v.n and v.frac_behind >= 1.0:
            raise RenderError(f"frame {frame}: every gaussian is behind the near plane ({near}) of the {where}; "
                              "the camera looks away from the object (check camera.look_at / cameras.json)")
        if v.inside_box and v.frac_behind > CLIP_WARN_FRACTION:
            raise RenderError(f"frame {frame}: the {where} is inside the object ({100 * v.frac_behind:.0f}% of the "
                              f"gaussians lie behind its near plane); increase camera.radius or move the camera")
        if v.frac_behind > CLIP_WARN_FRACTION:
            clipped.append((frame, round(v.frac_behind, 4)))


def deform_states(states: list[tuple], smap: SourceMap, cmap: CarrierMap, rest: Gaussians, with_rotation: bool,
                  full: bool) -> tuple[list[Gaussians], list[torch.Tensor], list]:
    """Gaussians of B stored states, the states without non-finite rows in one pass.

    Args:
        states: B (x [M, 3] float32, F - I [M, 3, 3] as final.h5 stores it (float16), [M] bool
            non-finite rows or None), sim frame. The stacks go to the device as they are, and F
            = (F - I) + I is formed there in float32 (the values of FinalFrames.F, bit for bit).
        smap, cmap: the map to the source frame and the carrier; rest: the rest gaussians.
        with_rotation: polar rotations for view-dependent SH; full: ``covers_all(cmap.rows, N)``.
    Returns:
        (B :class:`Gaussians`; B [n_b, 3] centres of the simulated object, as drawn (hidden
        rows left out), for the camera check; B [Ns] bool hidden gaussians or None).
    """
    dev = rest.means.device
    gs, objs, hides = [None] * len(states), [None] * len(states), [None] * len(states)
    plain = [b for b, st in enumerate(states) if st[2] is None]
    per = max(1, DEFORM_ROWS // max(1, len(cmap.rows)))  # frames a stack: DEFORM_ROWS gaussian rows at most
    for group in _chunks(plain, per) + [[b] for b, st in enumerate(states) if st[2] is not None]:
        x = torch.from_numpy(np.stack([states[b][0] for b in group])).to(dev, torch.float64)  # [B, M, 3]
        dF = torch.from_numpy(np.stack([states[b][1] for b in group])).to(dev)  # [B, M, 3, 3] F - I (float16)
        F = dF.float() + torch.eye(3, device=dev)  # [B, M, 3, 3] float32
        xs, Fs = cmap.apply(smap.points(x).float(), smap.linear(F))  # [B, Ns, 3], [B, Ns, 3, 3] source frame
        hide = None if states[group[0]][2] is None else cmap.hidden(torch.as_tensor(states[group[0]][2]))  # [Ns]
        out = deform_frames(rest, cmap.rows, xs, Fs, with_rotation, None if hide is None else hide[None], full)
        for k, b in enumerate(group):
            gs[b], hides[b] = out[k], hide
            objs[b] = xs[k] if hide is None else xs[k][~hide.to(dev)]  # = the drawn centres g.means[rows]
    return gs, objs, hides


def coverage_counts(alpha: torch.Tensor, per_frame: bool = False) -> list[int]:
    """Pixels with alpha above COVERED_ALPHA in each of the frames alpha [B, H, W], read back
    once for the batch (``per_frame``: once a frame, the A/B of PER_FRAME_ENV)."""
    if per_frame:
        return [int((a > COVERED_ALPHA).sum()) for a in alpha]
    return (alpha > COVERED_ALPHA).flatten(1).sum(dim=1).tolist()


def _chunks(seq: list, n: int) -> list[list]:
    return [seq[i:i + n] for i in range(0, len(seq), n)]


def cpu_threads(requested: int | None, log: logging.Logger) -> int:
    """Threads for the CPU renderer: ``requested``, else the cores that are idle right now.

    Parallel loops stall at their barriers when other processes keep the cores busy (on a
    loaded 2-core machine two threads ran 2-10x slower than one), so ``null`` measures the
    idle CPU over 0.25 s and uses that many cores (at least one).
    """
    import os

    import psutil

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if requested:
        log.info("CPU renderer: %d threads (render.threads)", int(requested))
        return int(requested)
    busy = psutil.cpu_percent(interval=0.25) / 100.0
    idle = (psutil.cpu_count() or cores) * (1.0 - busy)
    n = max(1, min(cores, int(idle + 0.5)))
    log.info("CPU renderer: %d threads (%d cores, %.1f idle now)", n, cores, idle)
    return n


# ---------------------------------------------------------------------------- stage
def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Render the simulated frames into a video, a contact sheet and a report."""
    t_start = time.perf_counter()
    rcfg = cfg["render"]
    ccfg = camera_config(cfg.get("scene") or {})
    settings = settings_from_config(rcfg)
    t0 = time.perf_counter()
    had_gsplat = "gsplat" in __import__("sys").modules
    backend, why = resolve_backend(rcfg["backend"], cfg.get("device", "auto"))
    timings = {"backend": round(time.perf_counter() - t0, 3), "gsplat_was_loaded": had_gsplat, "cuda_start": None}
    if backend == "gsplat":
        from ..runtime import cuda_start_seconds

        timings["cuda_start"] = cuda_start_seconds(torch)
    log.info("backend %s (%s; %.2f s to find it%s)", backend, why, timings["backend"],
             "" if timings["cuda_start"] is None else f", first CUDA call {timings['cuda_start']:.2f} s")
    if backend == "cpu":
        threads = cpu_threads(rcfg.get("threads"), log)
        if rcfg["cpu_compositor"] == "taichi":
            from .ti_composite import ensure_taichi

            # the per-frame tensor work is small; one torch thread avoids stalls at OpenMP
            # barriers, the Taichi kernel (most of the time) gets the threads
            torch.set_num_threads(1)
            ensure_taichi(threads)
        else:
            torch.set_num_threads(threads)
    renderer = Renderer(backend, settings)
    dev = renderer.device

    t0 = time.perf_counter()
    transform = load_transform(inputs["transform"])
    smap = SourceMap.from_transform(transform)
    scene = load_gaussians(inputs["scene"], log)
    carrier = load_carrier(inputs["carrier"], scene.n)
    timings["read_scene"] = round(time.perf_counter() - t0, 3)
    with FinalFrames(inputs["frames"]) as frames:
        return _render_all(inputs, outputs, rcfg, ccfg, renderer, backend, why, smap, scene, carrier, frames, dev,
                           log, t_start, scene_size(transform), timings)


def frames_per_call(batch: int, batch_gaussians: int, n_gaussians: int, batch_pixels: int | None = None,
                    pixels: int = 1) -> int:
    """gsplat frames per call: ``batch`` at most, at most ``batch_gaussians`` gaussians and
    ``batch_pixels`` pixels summed over the call's frames (at least one frame): the bound on the
    renderer's GPU memory (per-gaussian projections and tile lists, per-pixel images)."""
    n = min(int(batch), int(batch_gaussians) // max(int(n_gaussians), 1))
    if batch_pixels is not None:
        n = min(n, int(batch_pixels) // max(int(pixels), 1))
    return max(1, n)


def _render_all(inputs, outputs, rcfg, ccfg, renderer, backend, why, smap, scene, carrier, frames, dev, log,
                t_start, size: float, timings: dict) -> dict:
    t0 = time.perf_counter()
    rest = rest_gaussians(scene, smap, dev)
    timings["rest_gaussians"] = round(time.perf_counter() - t0, 3)
    t0 = time.perf_counter()
    # the carrier works in the source frame: each frame's stored particles are mapped there (a few
    # thousand rows) before it spreads them over the gaussians, which then need no map
    x0_src = smap.points(torch.from_numpy(frames.x(0)).double()).numpy()
    means_src = smap.points(torch.from_numpy(scene.means).double()).numpy()
    cmap = CarrierMap.build(carrier, frames.particle_index, means_src, x0_src, dev, length_scale=1.0 / smap.scale)
    index = cmap.rows
    moving = torch.zeros(scene.n, dtype=torch.bool, device=index.device)
    moving[index] = True
    static_rows = torch.nonzero(~moving).squeeze(1).cpu().numpy()  # [N - Ns] drawn at rest
    log.info("carrier: %d gaussians move with %d stored particles (%s, %d per gaussian), %d drawn at rest; %.2f s",
             index.numel(), frames.m, "identity" if cmap.identity else "budget", cmap.index.shape[1],
             static_rows.size, time.perf_counter() - t0)
    timings["carrier"] = round(time.perf_counter() - t0, 3)
    full = covers_all(index, scene.n)  # once: deform_frames() would check it every batch
    sel = list(range(0, frames.n_frames, int(rcfg["every_nth"])))
    degree = renderer.degree(rest)
    log.info("%d gaussians, %d simulated, %d of %d frames to render (%d distinct stored states), SH degree %d",
             scene.n, index.numel(), len(sel), frames.n_frames, len({frames.row(t) for t in sel}), degree)

    cams, cam_record = build_cameras(
        ccfg, rcfg, sel, lambda: motion_bounds(frames, smap, rest.means, static_rows),
        inputs.get("cameras"), log)
    renderer.settings.near, renderer.settings.far = clip_planes(rcfg, size, cams, smap.src_center)
    log.info("clipping planes near %.4g, far %.4g source units (scene size %.4g units%s)", renderer.settings.near,
             renderer.settings.far, size, "" if rcfg.get("near") is not None else ", near/far follow it")
    width, height = cams[0].width, cams[0].height
    if width % 2 or height % 2:
        log.info("image %dx%d is padded to even size for H.264 (yuv420p)", width, height)

    sheet_pos = set(sheet_indices(len(sel), rcfg["contact_sheet"]["frames"]))
    sheet_imgs, sheet_labels = [], []
    coverage, clipped, hidden = [], [], {}
    frame_dir = None
    if rcfg["png_frames"]:
        frame_dir = FrameDir(outputs.get("frames") or Path(outputs["video"]).parent / "frames")
    # a batch of frames is deformed, checked and counted together, and drawn in one gsplat call
    # (the CPU renderer draws its frames one after the other)
    batch = frames_per_call(rcfg["batch"], rcfg["batch_gaussians"], scene.n, rcfg["batch_pixels"], width * height)
    if batch < int(rcfg["batch"]):
        log.info("%d frames per batch (render.batch %d, capped by render.batch_gaussians %d at %d gaussians "
                 "and render.batch_pixels %d at %dx%d)", batch, int(rcfg["batch"]), int(rcfg["batch_gaussians"]),
                 scene.n, int(rcfg["batch_pixels"]), width, height)
    per_frame = os.environ.get(PER_FRAME_ENV) == "1"
    if per_frame:
        log.info("%s=1: frames deformed, checked and counted one at a time", PER_FRAME_ENV)
    t_render = t_deform = t_read = 0.0
    next_log = 0.1
    prev = None      # (stored row, gaussians, camera) of the previous frame
    prev_img = None  # (image, coverage) of the previous frame
    reused = {"states": 0, "images": 0}
    try:
        vw = VideoWriter(outputs["video"], width, height, rcfg["fps"], rcfg["crf"], rcfg.get("preset", "medium"))
        with vw:
            for b0 in range(0, len(sel), batch):
                ids = sel[b0:b0 + batch]
                bcams = cams[b0:b0 + batch]
                rows = [frames.row(t) for t in ids]
                t0 = time.perf_counter()
                # frames with a state of their own; a frame held at rest (the stored row of the
                # frame before) reuses that frame's state
                before = [prev[0] if prev is not None else None] + rows[:-1]  # stored row of the frame before each
                own = [j for j in range(len(ids)) if rows[j] != before[j]]
                states, failed = {}, None
                for part in _chunks(own, 1 if per_frame else max(len(own), 1)):
                    read = []  # (j, (x, F - I, non-finite rows))
                    for j in part:
                        t1 = time.perf_counter()
                        # views of the stored row (no copies: deform_states stacks them); F - I in
                        # float16 as stored, non-finite exactly where F is
                        x, dF = frames.x_view(ids[j]), frames.F_minus_I(ids[j])
                        t_read += time.perf_counter() - t1
                        try:
                            bad = check_frame(ids[j], x, dF, rcfg["on_nonfinite"])
                        except RenderError as e:  # raised once the frames before it are checked
                            failed = e
                            break
                        if bad is not None:
                            log.warning("frame %d: %d stored particles with NaN/inf: the gaussians they carry are hidden",
                                        ids[j], int(bad.sum()))
                        read.append((j, (x, dF, bad)))
                    if read:
                        gl, objs, hides = deform_states([st for _, st in read], smap, cmap, rest, degree > 0, full)
                        for (j, _), g, hide in zip(read, gl, hides):
                            states[j] = g
                            if hide is not None:
                                hidden[ids[j]] = int(hide.sum())
                        check_cameras([ids[j] for j, _ in read], objs, [bcams[j] for j, _ in read],
                                      renderer.settings.near, clipped)
                    if failed is not None:
                        raise failed
                t_deform += time.perf_counter() - t0
                gs, copy = [], []  # copy[j]: frame j repeats the previous frame's image
                for j, cam in enumerate(bcams):
                    if j in states:
                        g, same = states[j], False
                    else:  # held at rest: the state of the frame before
                        g = prev[1]
                        reused["states"] += 1
                        same = np.array_equal(prev[2].viewmat, cam.viewmat) and np.array_equal(prev[2].K, cam.K)
                    gs.append(g)
                    copy.append(same)
                    prev = (rows[j], g, cam)
                t0 = time.perf_counter()
                todo = [j for j in range(len(ids)) if not copy[j]]
                imgs, covered = [None] * len(ids), [None] * len(ids)  # covered: fraction of pixels above COVERED_ALPHA
                if todo:
                    ri, ra = renderer.render_frames([gs[j] for j in todo], [bcams[j] for j in todo])  # ra [B', H, W]
                    for n_, (j, c) in enumerate(zip(todo, coverage_counts(ra, per_frame))):
                        imgs[j], covered[j] = ri[n_], c / ra[n_].numel()
                for j in range(len(ids)):
                    if copy[j]:
                        imgs[j], covered[j] = (imgs[j - 1], covered[j - 1]) if j > 0 else prev_img
                        reused["images"] += 1
                prev_img = (imgs[-1], covered[-1])
                t_render += time.perf_counter() - t0
                for k, t in enumerate(ids):
                    pos = b0 + k
                    coverage.append(covered[k])
                    vw.append(imgs[k])
                    if frame_dir is not None:
                        frame_dir.add(t, imgs[k])
                    if pos in sheet_pos:
                        sheet_imgs.append(imgs[k])
                        sheet_labels.append(f"frame {t}  t={frames.time[t]:.2f}s")
                done = b0 + len(ids)
                if done / len(sel) >= next_log or done == len(sel):
                    log.info("rendered %d/%d frames (%.1f frames/s rendering)", done, len(sel), done / max(t_render, 1e-9))
                    next_log = math.floor(done / len(sel) * 10 + 1) / 10
            empty = [sel[i] for i, c in enumerate(coverage) if c == 0.0]
            if len(empty) == len(sel):
                raise RenderError(f"no rendered frame shows anything (no pixel reaches alpha {COVERED_ALPHA}); "
                                  f"the object is outside the view of the {cam_record['mode']} camera")
        if frame_dir is not None:
            frame_dir.commit()
    except BaseException:
        if frame_dir is not None:
            frame_dir.discard()
        raise
    if empty:
        log.warning("%d frames show nothing (object out of view): %s", len(empty), _ranges(empty))
    if clipped:
        log.warning("%d frames have gaussians behind the near plane (clipped), e.g. frame %d (%.0f%%)",
                    len(clipped), clipped[0][0], 100 * clipped[0][1])

    t0 = time.perf_counter()
    sheet = contact_sheet(sheet_imgs, sheet_labels, rcfg["contact_sheet"]["columns"], rcfg["contact_sheet"]["tile_width"])
    write_png(outputs["contact_sheet"], sheet)
    timings.update({"frames_per_call": batch, "read_frames": round(t_read, 3), "deform": round(t_deform - t_read, 3),
                    "rasterize": round(t_render, 3), "encode_wait": round(vw.wait_seconds, 3),
                    "encode_finish": round(vw.close_seconds, 3), "contact_sheet": round(time.perf_counter() - t0, 3)})
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        timings["cuda_peak_allocated_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    log.info("fixed costs and parts: %s", timings)
    seconds = time.perf_counter() - t_start
    report = {
        "backend": backend, "backend_reason": why, "device": str(dev),
        "n_gaussians": scene.n, "n_simulated": int(index.numel()), "n_static": int(static_rows.size),
        "n_stored_particles": frames.m, "carrier": "identity" if cmap.identity else f"budget ({cmap.index.shape[1]} per gaussian)",
        "reused": reused, "deform_seconds": round(t_deform, 3),
        "frames_rendered": len(sel), "frames_total": frames.n_frames, "every_nth": int(rcfg["every_nth"]),
        "width": width, "height": height, "fps": rcfg["fps"], "sh_degree": degree,
        "camera": cam_record,
        "clip": {"near": renderer.settings.near, "far": renderer.settings.far, "scene_size": size},
        "coverage": {"min": min(coverage), "mean": float(np.mean(coverage)), "max": max(coverage)},
        "empty_frames": empty, "clipped_frames": clipped, "hidden_nonfinite": hidden,
        "render_seconds": round(t_render, 3), "render_frames_per_second": round(len(sel) / max(t_render, 1e-9), 2),
        "seconds": round(seconds, 3), "timings": timings,
        "outputs": {k: str(v) for k, v in outputs.items()},
        "png_frames": str(frame_dir.path) if frame_dir is not None else None,
    }
    write_json(outputs["report"], report)
    log.info("wrote %s (%d frames, %dx%d, %.3g fps), %s, %s in %.1f s (%.1f s rendering)", outputs["video"], len(sel),
             width, height, rcfg["fps"], outputs["contact_sheet"], outputs["report"], seconds, t_render)
    return {"frames": len(sel), "render_seconds": round(t_render, 3), "backend": backend, "timings": timings}


def _ranges(frames: list[int]) -> str:
    """'0-4, 9, 12-13' for [0, 1, 2, 3, 4, 9, 12, 13]."""
    out, start, prev = [], None, None
    for f in frames + [None]:
        if start is None:
            start = prev = f
        elif f is not None and f == prev + 1:
            prev = f
        else:
            out.append(f"{start}" if start == prev else f"{start}-{prev}")
            start = prev = f
    return ", ".join(out)
