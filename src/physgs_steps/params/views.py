"""Views of one instance for the VLM: its gaussians alone, from an orbit around it.

scene.ply holds only the captured gaussians (the fill stage's interior particles live in
particles.h5), so rendering a label's subset of scene.ply shows the object as captured,
without filled particles and without the other instances.
"""
from __future__ import annotations

import math

import numpy as np

from ..gaussians import GaussianScene


def orbit_for(means: np.ndarray, fov_deg: float, margin: float = 1.15) -> tuple[np.ndarray, float]:
    """Centre and camera distance that keep a point set inside a camera's field of view.

    Args:
        means: [M, 3] gaussian centres of the instance.
        fov_deg: vertical field of view in degrees.
        margin: extra distance factor.
    Returns:
        ([3] centre of the 1%-99% quantile box, radius > 0).
    """
    lo = np.quantile(means, 0.01, axis=0) if len(means) > 100 else means.min(axis=0)
    hi = np.quantile(means, 0.99, axis=0) if len(means) > 100 else means.max(axis=0)
    center = 0.5 * (lo + hi)
    half_diag = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
    radius = margin * half_diag / math.sin(math.radians(fov_deg) / 2.0)
    return center.astype(np.float64), radius


def instance_views(scene: GaussianScene, mask: np.ndarray, n_views: int, size: int,
                   elevation_deg: float = 20.0, fov_deg: float = 40.0, backend: str = "auto") -> np.ndarray:
    """Render ``n_views`` square views of the gaussians selected by ``mask``.

    Args:
        scene: the scene (sim frame, z up).
        mask: [N] bool, the instance's gaussians.
        n_views: number of views, evenly spread in azimuth.
        size: image width = height in pixels.
        elevation_deg: camera elevation above the horizontal plane.
        fov_deg: vertical field of view.
        backend: renderer backend passed to ``render.render_static``.
    Returns:
        [C, H, W, 3] uint8 images.
    """
    from .. import render

    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (scene.n,) or not mask.any():
        raise ValueError(f"instance mask selects {int(mask.sum()) if mask.shape == (scene.n,) else 'a wrong shape of'} gaussians")
    sub = scene.subset(mask)
    center, radius = orbit_for(sub.means, fov_deg)
    cams = render.orbit_cameras(center, radius, n_views, elevation_deg, fov_deg, size, size)
    imgs = np.asarray(render.render_static(sub, cams, backend=backend))
    if imgs.ndim != 4 or imgs.shape[0] != n_views or imgs.shape[-1] != 3:
        raise ValueError(f"renderer returned images of shape {imgs.shape}, expected [{n_views}, H, W, 3]")
    return imgs.astype(np.uint8, copy=False)
