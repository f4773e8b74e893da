"""Turn ground-truth solids into a 3DGS-like scene: flat gaussians on the outer surface.

Letters: N gaussians, M candidate surface samples.
"""
from __future__ import annotations

import math

import numpy as np

from ..gaussians import SH_C0, GaussianScene, rotmat_to_quat
from .ground_truth import GroundTruth

TANGENT_FACTOR = 0.85           # tangent std / sample spacing
TANGENT_JITTER = 0.12           # log-normal spread of each tangent std
NORMAL_RATIO = (0.1, 0.2)       # normal std / tangent std, uniform in this range
THIN_CAP = 0.5                  # tangent std <= THIN_CAP * part.feature
COLOR_NOISE = 0.03              # std of the per-gaussian colour noise
OPACITY_LOGIT = (3.0, 5.0)      # uniform range of opacity logits


def surface_samples(gt: GroundTruth, n: int, rng: np.random.Generator):
    """Area-uniform samples of the outer surface of every instance.

    Each part's surface is sampled analytically (counts proportional to area); a sample is
    kept when it lies outside every other part of its instance, so only the outer surface of
    the union remains (no interior faces). Then ``n`` of the kept samples are drawn.

    Returns (points [n, 3], normals [n, 3], label [n] int32, part index [n] int32,
    outer area in m^2).
    """
    parts = gt.parts()
    areas = np.array([p.solid.area() for _, p in parts])
    probs = areas / areas.sum()
    boxes = [[p.solid.aabb() for p in inst.parts] for inst in gt.instances]
    pts, nrm, part_idx = [], [], []
    drawn = kept = 0
    m = int(n * 1.6) + 64
    while kept < n:
        counts = rng.multinomial(m, probs)
        for j, ((k, part), c) in enumerate(zip(parts, counts)):
            x, nn = part.solid.sample(int(c), rng)
            ok = np.ones(len(x), dtype=bool)
            for other, (lo, hi) in zip(gt.instances[k].parts, boxes[k]):
                if other is part or not len(x):
                    continue
                near = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))  # only the other's box can hold it
                if len(near):
                    ok[near[other.solid.inside(x[near])]] = False
            pts.append(x[ok])
            nrm.append(nn[ok])
            part_idx.append(np.full(int(ok.sum()), j, dtype=np.int32))
            kept += int(ok.sum())
        drawn += m
        rate = max(kept / drawn, 1e-3)
        m = int((n - kept) / rate * 1.2) + 64
    pts = np.concatenate(pts)
    nrm = np.concatenate(nrm)
    part_idx = np.concatenate(part_idx)
    outer_area = float(areas.sum()) * kept / drawn
    pick = rng.choice(len(pts), size=n, replace=False)
    labels = np.array([k for k, _ in parts], dtype=np.int32)
    return pts[pick], nrm[pick], labels[part_idx[pick]], part_idx[pick], outer_area


def tangent_frames(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """[N, 3] unit normals -> [N, 3, 3] rotations whose columns are (t1, t2, normal),
    with t1 at a random angle around the normal."""
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    sign = np.where(nz >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    b1 = np.stack([1.0 + sign * nx * nx * a, sign * b, -sign * nx], axis=1)
    b2 = np.stack([b, sign + ny * ny * a, -ny], axis=1)
    psi = rng.random(len(normals)) * 2.0 * math.pi
    t1 = np.cos(psi)[:, None] * b1 + np.sin(psi)[:, None] * b2
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=2)


def gaussians_from_surface(gt: GroundTruth, n: int, rng: np.random.Generator) -> GaussianScene:
    """A GaussianScene of ``n`` flat surface gaussians of ``gt`` with extras['gt_label']."""
    pts, nrm, label, part_idx, outer_area = surface_samples(gt, n, rng)
    parts = [p for _, p in gt.parts()]
    spacing = math.sqrt(outer_area / n)
    feature = np.array([p.solid.feature for p in parts])[part_idx]
    base = np.minimum(TANGENT_FACTOR * spacing, THIN_CAP * feature)
    tang = base[:, None] * np.exp(rng.normal(0.0, TANGENT_JITTER, (n, 2)))
    normal_std = tang.mean(axis=1) * rng.uniform(*NORMAL_RATIO, n)
    scales = np.concatenate([tang, normal_std[:, None]], axis=1)
    colors = np.array([p.color for p in parts], dtype=np.float64)[part_idx]
    colors = np.clip(colors + rng.normal(0.0, COLOR_NOISE, (n, 3)), 0.01, 0.99)
    return GaussianScene(
        means=pts,
        log_scales=np.log(scales),
        quats=rotmat_to_quat(tangent_frames(nrm, rng)),
        opacity_logits=rng.uniform(*OPACITY_LOGIT, n),
        sh=((colors - 0.5) / SH_C0)[:, None, :],
        extras={"gt_label": label.astype(np.int32)},
    )
