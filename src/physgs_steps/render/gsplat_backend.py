"""CUDA rendering with ``gsplat.rasterization`` (batched over frames and cameras).

Colours are evaluated by :mod:`physgs_steps.render.sh` (view directions rotated into each
gaussian's rest frame) and passed to gsplat as post-activation colours, so gsplat and the
CPU renderer see identical colours and differ only in rasterisation arithmetic.
Covariances are passed directly (``covars=``), so ``Sigma(t) = F Sigma F^T`` is rendered
without a detour through scales and quaternions. Settings mirror the CPU renderer:
``rasterize_mode="classic"`` (eps2d low-pass, no opacity compensation), pinhole camera.

Only call these functions after :func:`cuda_ready` returned True.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import torch

from .cameras import Camera, stack_cameras
from .deform import Gaussians
from .sh import view_colors


def extension_dir() -> str:
    """Where gsplat's JIT-compiled CUDA extension is built and found again: one folder per
    machine and user (``$PHYSGS_MACHINE_CACHE``, default ``~/.cache/physgs``), per Python, CUDA
    and torch version, whatever the workspace, XDG_CACHE_HOME or project.  An explicit
    TORCH_EXTENSIONS_DIR wins.  A gsplat wheel built with its CUDA code
    (``tools/build_wheelhouse.py --gsplat-cuda-arch``) needs none."""
    if os.environ.get("TORCH_EXTENSIONS_DIR"):
        return os.environ["TORCH_EXTENSIONS_DIR"]
    base = Path(os.environ.get("PHYSGS_MACHINE_CACHE") or Path.home() / ".cache" / "physgs")
    tag = f"py{sys.version_info.major}{sys.version_info.minor}_cu{(torch.version.cuda or 'none').replace('.', '')}" \
          f"_torch{torch.__version__.split('+')[0]}"
    return str(base / "torch_extensions" / tag)


def cuda_ready() -> tuple[bool, str]:
    """(True, "") when CUDA and gsplat's CUDA rasteriser are usable, else (False, reason)."""
    if not torch.cuda.is_available():
        return False, "torch.cuda.is_available() is False"
    os.environ["TORCH_EXTENSIONS_DIR"] = extension_dir()  # read by gsplat's JIT build (torch.utils.cpp_extension)
    try:
        from gsplat import rasterization  # noqa: F401
        from gsplat.cuda._backend import _C  # loads (or JIT-compiles, once) the CUDA extension
    except Exception as e:  # gsplat missing or its extension failed to load/build
        return False, f"gsplat cannot be imported: {type(e).__name__}: {e}"
    if _C is None:
        return False, "gsplat's CUDA extension is not available (no prebuilt csrc and the JIT build failed)"
    return True, ""


def _to_uint8(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)


def render_frames(frames: list[Gaussians], cameras: list[Camera], background, sh_degree: int,
                  near: float, far: float, eps2d: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Render frame i with camera i, all in one gsplat call.

    Args:
        frames: B gaussians on the CUDA device, each with the same N.
        cameras: B cameras of one image size.
        background: [3] colour.
        sh_degree: SH bands used (capped by the coefficients present).
    Returns:
        ([B, H, W, 3] uint8 images on the CPU, [B, H, W] float alpha on the GPU).
    """
    from gsplat import rasterization

    dev = frames[0].means.device
    vm, ks = stack_cameras(cameras)
    viewmats = torch.as_tensor(vm, dtype=torch.float32, device=dev)[:, None]  # [B, 1, 4, 4]
    Ks = torch.as_tensor(ks, dtype=torch.float32, device=dev)[:, None]  # [B, 1, 3, 3]
    # camera centres on the host (a 4x4 inverse on CUDA would load cuSOLVER, seconds once per process)
    centres = torch.as_tensor(np.linalg.inv(np.asarray(vm, np.float64))[:, :3, 3], dtype=torch.float32, device=dev)
    cols = []
    for g, campos in zip(frames, centres):
        cols.append(view_colors(g.means, g.sh, campos, sh_degree, g.rotations))
    colors = torch.stack(cols)[:, None]  # [B, 1, N, 3]
    means = torch.stack([g.means for g in frames])  # [B, N, 3]
    covars = torch.stack([g.covars for g in frames])  # [B, N, 3, 3]
    opac = torch.stack([g.opacities for g in frames])  # [B, N]
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev).expand(len(frames), 1, 3).contiguous()
    w, h = cameras[0].width, cameras[0].height
    with torch.no_grad():
        rgb, alpha, _ = rasterization(means, None, None, opac, colors, viewmats, Ks, w, h,
                                      near_plane=near, far_plane=far, eps2d=eps2d, sh_degree=None,
                                      backgrounds=bg, rasterize_mode="classic", covars=covars,
                                      packed=False)  # gsplat 1.5 rejects backgrounds when packed
    return _to_uint8(rgb[:, 0]).cpu(), alpha[:, 0, ..., 0].float()


def render_views(g: Gaussians, cameras: list[Camera], background, sh_degree: int,
                 near: float, far: float, eps2d: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Render one set of gaussians from C cameras in one gsplat call.

    Returns:
        ([C, H, W, 3] uint8 on the CPU, [C, H, W] float alpha on the CPU).
    """
    from gsplat import rasterization

    dev = g.means.device
    vm, ks = stack_cameras(cameras)
    viewmats = torch.as_tensor(vm, dtype=torch.float32, device=dev)
    Ks = torch.as_tensor(ks, dtype=torch.float32, device=dev)
    campos = torch.as_tensor(np.linalg.inv(np.asarray(vm, np.float64))[:, :3, 3], dtype=torch.float32, device=dev)
    colors = torch.stack([view_colors(g.means, g.sh, c, sh_degree, g.rotations) for c in campos])  # [C, N, 3]
    bg = torch.as_tensor(background, dtype=torch.float32, device=dev).expand(len(cameras), 3).contiguous()
    w, h = cameras[0].width, cameras[0].height
    with torch.no_grad():
        rgb, alpha, _ = rasterization(g.means, None, None, g.opacities, colors, viewmats, Ks, w, h,
                                      near_plane=near, far_plane=far, eps2d=eps2d, sh_degree=None,
                                      backgrounds=bg, rasterize_mode="classic", covars=g.covars,
                                      packed=False)  # gsplat 1.5 rejects backgrounds when packed
    return _to_uint8(rgb).cpu(), alpha[..., 0].float().cpu()
