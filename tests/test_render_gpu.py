"""gsplat backend against the CPU renderer (needs CUDA; skipped without it)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physgs_steps.gaussians import GaussianScene
from physgs_steps.render import orbit_cameras, render_static
from physgs_steps.render.deform import Gaussians, SourceMap, deform
from physgs_steps.render.gsplat_backend import cuda_ready
from physgs_steps.render.renderer import Renderer, RenderSettings

pytestmark = pytest.mark.gpu


@pytest.fixture(scope="module", autouse=True)
def _need_cuda():
    ok, why = cuda_ready()
    if not ok:
        pytest.skip(f"gsplat/CUDA not usable: {why}")


def _scene(n=3000, seed=0) -> GaussianScene:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return GaussianScene(means=d * 0.2, log_scales=np.log(rng.uniform(0.004, 0.02, (n, 3))), quats=rng.normal(size=(n, 4)),
                         opacity_logits=rng.normal(2.0, 1.0, n), sh=rng.normal(0, 0.3, (n, 16, 3)))


def _psnr(a, b) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def test_static_views_agree_with_cpu():
    scene = _scene()
    cams = orbit_cameras([0, 0, 0], 0.9, 4, 20.0, 40.0, 160, 120)
    gpu = render_static(scene, cams, backend="gsplat")
    cpu = render_static(scene, cams, backend="cpu")
    assert gpu.shape == cpu.shape == (4, 120, 160, 3)
    assert min(_psnr(a, b) for a, b in zip(gpu, cpu)) >= 35.0


def test_deformed_batched_frames_agree_with_cpu():
    scene = _scene(seed=1)
    cams = orbit_cameras([0, 0, 0], 0.9, 3, 20.0, 40.0, 128, 128, azimuth_step_deg=10.0)
    frames = {}
    for backend in ("gsplat", "cpu"):
        r = Renderer(backend, RenderSettings(background=(0.0, 0.0, 0.0)))
        rest = Gaussians.from_scene(scene, r.device)
        gs = []
        for t in range(3):
            F = torch.tensor([[1.0 + 0.1 * t, 0.2 * t, 0], [0, 1.0, 0], [0, 0, 1.0 - 0.1 * t]], device=r.device)
            x = rest.means @ F.T + torch.tensor([0.0, 0.0, 0.02 * t], device=r.device)
            gs.append(deform(rest, torch.arange(rest.n, device=r.device), x, F.expand(rest.n, 3, 3), SourceMap.identity(),
                             with_rotation=True))
        frames[backend], _ = r.render_frames(gs, cams)
    assert min(_psnr(a, b) for a, b in zip(frames["gsplat"], frames["cpu"])) >= 35.0
