"""Real spherical harmonics (degree 0-3) as used by 3D Gaussian Splatting, in torch.

The basis, its sign convention and the ``+ 0.5`` offset follow the INRIA reference
renderer (and gsplat), so colours computed here equal what those renderers compute from
the same coefficients and view directions.

Deformed gaussians: the SH coefficients describe radiance in the gaussian's *rest*
frame. When the simulation rotates a gaussian by ``R`` (polar rotation of its
deformation gradient), its colour seen along world direction ``d`` is the rest-frame
radiance along ``R^T d``. This module therefore rotates the *view directions* (one
3x3 product per gaussian) instead of the coefficients (a Wigner-D rotation per band),
which is exact and much cheaper.
"""
from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis functions up to ``degree`` at unit directions.

    Args:
        degree: 0..3.
        dirs: [..., 3] unit vectors.
    Returns:
        [..., (degree + 1) ** 2] basis values.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB from SH coefficients seen along ``dirs``: ``max(sum_k c_k Y_k(d) + 0.5, 0)``.

    Args:
        sh: [..., K, 3] coefficients, K >= (degree + 1) ** 2 (extra bands are ignored).
        dirs: [..., 3] view directions (camera -> gaussian), need not be normalised.
        degree: bands used, 0..3.
    Returns:
        [..., 3] colours, >= 0 (not clipped above; the compositor clips the image).
    """
    k = (degree + 1) ** 2
    if sh.shape[-2] < k:
        raise ValueError(f"SH degree {degree} needs {k} coefficients per channel, got {sh.shape[-2]}")
    if degree == 0:
        rgb = C0 * sh[..., 0, :]
    else:
        d = torch.nn.functional.normalize(dirs, dim=-1)
        basis = sh_basis(degree, d)  # [..., k]
        rgb = (basis.unsqueeze(-1) * sh[..., :k, :]).sum(dim=-2)
    return torch.clamp_min(rgb + 0.5, 0.0)


def view_colors(means: torch.Tensor, sh: torch.Tensor, campos: torch.Tensor, degree: int,
                rotations: torch.Tensor | None = None) -> torch.Tensor:
    """Per-gaussian colour for one camera.

    Args:
        means: [N, 3] gaussian centres (world frame of the camera).
        sh: [N, K, 3] rest-frame SH coefficients.
        campos: [3] camera centre.
        degree: SH bands used (0..3).
        rotations: optional [N, 3, 3] rotations R taking each gaussian's rest frame to its
            current frame; the view direction d is evaluated as R^T d.
    Returns:
        [N, 3] colours.
    """
    if degree == 0:
        return eval_sh(sh, means, 0)
    dirs = means - campos.to(means)
    if rotations is not None:
        dirs = torch.einsum("nji,nj->ni", rotations, dirs)
    return eval_sh(sh, dirs, degree)
