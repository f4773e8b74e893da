"""Rendering of (deformed) gaussians: cameras, SH, CPU and gsplat backends, video output.

Public entry points:
    render_static(scene, cameras, backend="auto") -> [C, H, W, 3] uint8
    orbit_cameras(center, radius, n, elevation_deg, fov_deg, width, height) -> list[Camera]
    stage.run(inputs, outputs, cfg, log)  (the Snakemake stage)
"""
from __future__ import annotations

import numpy as np

from ..gaussians import GaussianScene
from .cameras import Camera, load_inria_cameras, look_at, orbit_cameras
from .deform import Gaussians
from .renderer import Renderer, RenderSettings, resolve_backend

__all__ = ["Camera", "orbit_cameras", "load_inria_cameras", "look_at", "render_static", "Renderer",
           "RenderSettings", "resolve_backend", "Gaussians"]


def render_static(scene: GaussianScene, cameras: list[Camera], backend: str = "auto",
                  background=(1.0, 1.0, 1.0), sh_degree: int = 3) -> np.ndarray:
    """Render an undeformed scene from several cameras.

    Args:
        scene: gaussians in the cameras' world frame.
        cameras: C cameras (any sizes; cameras of one size are rendered together on gsplat).
        backend: ``auto`` | ``cpu`` | ``gsplat``.
        background: RGB in [0, 1].
        sh_degree: cap on the SH degree used.
    Returns:
        [C, H, W, 3] uint8 when all cameras share a size (else an object array of [H, W, 3] images).
    """
    name, _ = resolve_backend(backend)
    r = Renderer(name, RenderSettings(background=tuple(background), sh_degree=sh_degree))
    g = Gaussians.from_scene(scene, r.device)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, c in enumerate(cameras):
        groups.setdefault((c.width, c.height), []).append(i)
    out: list = [None] * len(cameras)
    for idx in groups.values():
        imgs, _ = r.render_views(g, [cameras[i] for i in idx])
        for i, img in zip(idx, imgs):
            out[i] = img
    if len(groups) == 1:
        return np.stack(out)
    arr = np.empty(len(out), dtype=object)
    for i, img in enumerate(out):
        arr[i] = img
    return arr
