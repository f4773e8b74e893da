"""Backend choice and one interface over the CPU renderer and gsplat.

``auto`` picks gsplat when CUDA is present (and gsplat loads), else the CPU renderer.
Both take :class:`~physgs_steps.render.deform.Gaussians` and :class:`~physgs_steps.render.cameras.Camera`
lists and return uint8 images plus the accumulated alpha (coverage checks use it).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import ConfigError
from ..gaussians import sh_degree_from_k
from . import cpu
from .cameras import Camera
from .deform import Gaussians
from .sh import view_colors

BACKENDS = ("auto", "cpu", "gsplat")
_LOG = logging.getLogger("physgs.render")


@dataclass
class RenderSettings:
    """Renderer settings shared by both backends.

    Attributes:
        background: RGB in [0, 1].
        sh_degree: cap on the SH bands used (0..3).
        near, far: clipping distances (camera z, scene units).
        eps2d: 2D low-pass added to projected covariances (px^2).
        compositor: CPU only, ``taichi`` (fast) or ``torch``.
    """

    background: tuple = (1.0, 1.0, 1.0)
    sh_degree: int = 3
    near: float = 0.01
    far: float = 1000.0
    eps2d: float = 0.3
    compositor: str = "taichi"


def resolve_backend(backend: str, device: str = "auto") -> tuple[str, str]:
    """The backend to use and why.

    Args:
        backend: ``auto`` | ``cpu`` | ``gsplat`` (config ``render.backend``).
        device: global ``device`` (``auto`` | ``cpu`` | ``cuda``); ``cpu`` keeps ``auto`` on the CPU.
    Returns:
        (``cpu`` or ``gsplat``, reason in words).
    """
    from .gsplat_backend import cuda_ready

    if backend not in BACKENDS:
        raise ConfigError("render.backend", f"unknown backend {backend!r}; allowed: {', '.join(BACKENDS)}")
    if backend == "cpu":
        return "cpu", "render.backend is cpu"
    if backend == "auto" and device == "cpu":
        return "cpu", "device is cpu"
    ok, why = cuda_ready()
    if backend == "gsplat":
        if not ok:
            raise ConfigError("render.backend", f"gsplat needs CUDA, but {why}; use backend auto or cpu")
        return "gsplat", "render.backend is gsplat"
    if ok:
        return "gsplat", "CUDA is available"
    return "cpu", f"no usable CUDA renderer ({why})"


class Renderer:
    """Renders frames (frame i with camera i) or one scene from many cameras."""

    def __init__(self, backend: str, settings: RenderSettings | None = None):
        if backend not in ("cpu", "gsplat"):
            raise ConfigError("render.backend", f"Renderer needs a resolved backend (cpu or gsplat), got {backend!r}")
        self.backend = backend
        self.settings = settings or RenderSettings()
        self.device = torch.device("cuda" if backend == "gsplat" else "cpu")

    def degree(self, g: Gaussians) -> int:
        """SH bands used for these gaussians: the configured cap or what the coefficients hold."""
        return min(int(self.settings.sh_degree), sh_degree_from_k(int(g.sh.shape[1])))

    def render_frames(self, frames: list[Gaussians], cameras: list[Camera]) -> tuple[np.ndarray, torch.Tensor]:
        """Frame i seen by camera i.

        Returns:
            ([B, H, W, 3] uint8 on the host, [B, H, W] float32 alpha as a torch tensor on the
            renderer's device: the stage reduces it there to a coverage figure per frame; at
            1080p copying it to the host cost more than the images).
        """
        if len(frames) != len(cameras):
            raise ValueError(f"{len(frames)} frames but {len(cameras)} cameras")
        s = self.settings
        if self.backend == "gsplat":
            from .gsplat_backend import render_frames

            rgb, alpha = render_frames(frames, cameras, s.background, self.degree(frames[0]), s.near, s.far, s.eps2d)
            return rgb.numpy(), alpha
        out = [self._cpu_one(g, cam) for g, cam in zip(frames, cameras)]
        return np.stack([o[0] for o in out]), torch.from_numpy(np.stack([o[1] for o in out]))

    def render_views(self, g: Gaussians, cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
        """One set of gaussians from every camera (cameras of one image size).

        Returns:
            ([C, H, W, 3] uint8, [C, H, W] float32 alpha).
        """
        s = self.settings
        if self.backend == "gsplat":
            from .gsplat_backend import render_views

            rgb, alpha = render_views(g, cameras, s.background, self.degree(g), s.near, s.far, s.eps2d)
            return rgb.numpy(), alpha.numpy()
        out = [self._cpu_one(g, cam) for cam in cameras]
        return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])

    def _cpu_one(self, g: Gaussians, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
        s = self.settings
        vm = torch.as_tensor(cam.viewmat, dtype=torch.float32)
        k = torch.as_tensor(cam.K, dtype=torch.float32)
        campos = torch.as_tensor(cam.position, dtype=torch.float32)
        colors = view_colors(g.means, g.sh, campos, self.degree(g), g.rotations)
        bg = torch.as_tensor(s.background, dtype=torch.float32)
        rgb, alpha = cpu.rasterize(g.means, g.covars, g.opacities, colors, vm, k, cam.width, cam.height, bg,
                                   near=s.near, far=s.far, eps2d=s.eps2d, compositor=s.compositor)
        img = (rgb.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
        return img.numpy(), alpha.numpy()
