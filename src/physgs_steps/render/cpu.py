"""A CPU gaussian rasteriser in torch with gsplat's camera model and compositing rules.

It reproduces ``gsplat.rasterization(..., rasterize_mode="classic")`` (pinhole camera,
``packed`` or not makes no difference to the image):

* projection: world -> camera with the 4x4 ``viewmat`` (OpenCV axes), EWA 2D covariance
  ``J W Sigma W^T J^T`` with the Jacobian evaluated at the centre clamped to 1.3x the
  field of view (as gsplat does), plus ``eps2d`` (0.3 px^2) on the diagonal: the 2D
  low-pass filter of 3DGS (gsplat's default, *not* the Mip-Splatting "antialiased" mode,
  so no opacity compensation);
* culling: centre depth outside ``[near, far]``, opacity below 1/255, degenerate 2D
  covariance, or a bounding box entirely outside the image;
* extent: ``min(3.33, sqrt(2 ln(255 opacity)))`` standard deviations per image axis (the
  3-sigma cut, tightened where the opacity makes the tail invisible; beyond it alpha
  would be below 1/255 and gsplat skips it anyway);
* per pixel (centre at +0.5): ``alpha = min(0.999, o exp(-q/2))``, skipped if below 1/255;
  front-to-back in increasing centre depth ``C += c alpha T``, ``T *= 1 - alpha``; a
  pixel stops (exclusive) at the first gaussian that would bring T to 1e-4 or below;
  the background is added as ``bg * T``.

Binning (torch): the image is cut into square tiles; each gaussian is listed in every tile
its bounding box touches, and every tile's list is sorted by depth (a depth argsort, then a
stable sort by tile id).

Compositing, two interchangeable implementations of the same rules:

* ``taichi`` (default, :mod:`.ti_composite`): one parallel loop over pixels, each walking its
  tile's list and stopping at termination, like gsplat's CUDA kernel. Work is proportional
  to the entries a pixel actually visits.
* ``torch``: tiles are processed in batches; chunks of ``chunk`` list entries are evaluated
  for all pixels of all tiles at once ([tiles, chunk, pixels] tensors), transmittance within
  a chunk is a cumulative product, and tiles whose pixels have all terminated (or whose
  lists are exhausted) leave the batch (early termination per tile). About 5-20x slower,
  no Taichi needed; it also cross-checks the kernel in the tests.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..errors import RenderError

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_MIN = 1e-4
EXTENT_SIGMAS = 3.33
MAX_TILE_ENTRIES = 32_000_000  # gaussian-tile pairs per image (about 3 GB of index arrays)


@dataclass
class Projected:
    """Gaussians that survived culling for one camera (M of them).

    Attributes:
        ids: [M] int64 indices into the input gaussians.
        means2d: [M, 2] pixel coordinates of the centres.
        conics: [M, 3] inverse 2D covariance (a, b, c) of [[a, b], [b, c]].
        depths: [M] camera-space z of the centres.
        radii: [M, 2] half extent of the bounding box in pixels (x, y), integer valued.
        opacities: [M] opacity in [1/255, 1].
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    radii: torch.Tensor
    opacities: torch.Tensor

    @property
    def n(self) -> int:
        return int(self.ids.shape[0])


def project(means: torch.Tensor, covars: torch.Tensor, opacities: torch.Tensor, viewmat: torch.Tensor,
            K: torch.Tensor, width: int, height: int, near: float = 0.01, far: float = 1e10,
            eps2d: float = 0.3) -> Projected:
    """Project 3D gaussians to the image plane (EWA splatting, gsplat's pinhole model).

    Args:
        means: [N, 3] centres (world).
        covars: [N, 3, 3] covariances (world).
        opacities: [N] in [0, 1].
        viewmat: [4, 4] world-to-camera (OpenCV axes).
        K: [3, 3] intrinsics.
        width, height: image size in pixels.
        near, far: clipping distances along the optical axis (camera z).
        eps2d: added to the diagonal of each 2D covariance (px^2).
    Returns:
        :class:`Projected` for the gaussians that can touch the image.
    """
    dt = means.dtype
    viewmat = viewmat.to(dt)
    K = K.to(dt)
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    mc = means @ rot.T + trans  # [N, 3]
    z = mc[:, 2]
    keep = (z >= near) & (z <= far) & (opacities >= ALPHA_MIN)
    ids = keep.nonzero().squeeze(1)
    mc, z, op = mc[ids], z[ids], opacities[ids]
    cov_c = rot @ covars[ids] @ rot.T  # [M, 3, 3]

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    rz = 1.0 / z
    tx = z * torch.minimum((width - cx) / fx + 0.3 * tan_x, torch.maximum(-(cx / fx + 0.3 * tan_x), mc[:, 0] * rz))
    ty = z * torch.minimum((height - cy) / fy + 0.3 * tan_y, torch.maximum(-(cy / fy + 0.3 * tan_y), mc[:, 1] * rz))
    zero = torch.zeros_like(z)
    jac = torch.stack([
        torch.stack([fx * rz, zero, -fx * tx * rz * rz], dim=-1),
        torch.stack([zero, fy * rz, -fy * ty * rz * rz], dim=-1),
    ], dim=1)  # [M, 2, 3]
    cov2 = jac @ cov_c @ jac.transpose(1, 2)  # [M, 2, 2]
    a = cov2[:, 0, 0] + eps2d
    b = 0.5 * (cov2[:, 0, 1] + cov2[:, 1, 0])
    c = cov2[:, 1, 1] + eps2d
    det = a * c - b * b
    means2d = torch.stack([fx * mc[:, 0] * rz + cx, fy * mc[:, 1] * rz + cy], dim=-1)

    extend = torch.clamp(torch.sqrt(2.0 * torch.log(op / ALPHA_MIN).clamp_min(0.0)), max=EXTENT_SIGMAS)
    rx = torch.ceil(extend * torch.sqrt(a.clamp_min(0.0)))
    ry = torch.ceil(extend * torch.sqrt(c.clamp_min(0.0)))
    ok = (det > 0) & torch.isfinite(det)
    ok &= (means2d[:, 0] + rx > 0) & (means2d[:, 0] - rx < width)
    ok &= (means2d[:, 1] + ry > 0) & (means2d[:, 1] - ry < height)
    ok &= (rx > 0) | (ry > 0)
    sel = ok.nonzero().squeeze(1)
    det = det[sel]
    conics = torch.stack([c[sel] / det, -b[sel] / det, a[sel] / det], dim=-1)
    return Projected(ids=ids[sel], means2d=means2d[sel], conics=conics, depths=z[sel],
                     radii=torch.stack([rx[sel], ry[sel]], dim=-1), opacities=op[sel])


@dataclass
class _TileLists:
    """Depth-sorted gaussian lists per tile (CSR layout)."""

    entries: torch.Tensor  # [E] int64 rows of the Projected arrays, grouped by tile, sorted by depth
    offsets: torch.Tensor  # [n_tiles] start of each tile's list in ``entries``
    counts: torch.Tensor  # [n_tiles] list lengths
    tiles_x: int
    tiles_y: int


def bin_tiles(p: Projected, width: int, height: int, tile: int) -> _TileLists:
    """List every projected gaussian in the tiles its bounding box touches, sorted by depth."""
    tiles_x, tiles_y = math.ceil(width / tile), math.ceil(height / tile)
    n_tiles = tiles_x * tiles_y
    m = p.n
    if m == 0:
        z = torch.zeros(n_tiles, dtype=torch.int64)
        return _TileLists(torch.zeros(0, dtype=torch.int64), z, z.clone(), tiles_x, tiles_y)
    # sort by depth first; a stable sort by tile id afterwards keeps depth order inside tiles
    by_depth = torch.argsort(p.depths, stable=True)
    mx, my = p.means2d[by_depth, 0] / tile, p.means2d[by_depth, 1] / tile
    rx, ry = p.radii[by_depth, 0] / tile, p.radii[by_depth, 1] / tile
    x0 = torch.floor(mx - rx).clamp(0, tiles_x).long()
    x1 = torch.ceil(mx + rx).clamp(0, tiles_x).long()
    y0 = torch.floor(my - ry).clamp(0, tiles_y).long()
    y1 = torch.ceil(my + ry).clamp(0, tiles_y).long()
    nx = x1 - x0
    cnt = nx * (y1 - y0)
    total = int(cnt.sum())
    if total > MAX_TILE_ENTRIES:
        raise RenderError(
            f"{m} gaussians touch {total} tiles in a {width}x{height} image (limit {MAX_TILE_ENTRIES}): they cover "
            "the image many times over; is the camera very close to or inside the object?")
    rows = torch.repeat_interleave(torch.arange(m), cnt)  # positions in depth order
    starts = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(rows.shape[0]) - starts[rows]
    nxr = nx[rows]
    tile_id = (y0[rows] + local // nxr) * tiles_x + x0[rows] + local % nxr
    tile_sorted, perm = torch.sort(tile_id, stable=True)
    entries = by_depth[rows[perm]]
    counts = torch.bincount(tile_sorted, minlength=n_tiles)
    offsets = torch.cumsum(counts, 0) - counts
    return _TileLists(entries, offsets, counts, tiles_x, tiles_y)


def composite(p: Projected, colors: torch.Tensor, width: int, height: int, background: torch.Tensor,
              tile: int = 16, chunk: int = 32, tile_batch: int = 512) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha-composite projected gaussians front to back.

    Args:
        p: projected gaussians (M).
        colors: [M, 3] colour of each projected gaussian (rows match ``p``).
        width, height: image size.
        background: [3] colour added with the remaining transmittance.
        tile: tile edge in pixels.
        chunk: list entries evaluated per step.
        tile_batch: tiles processed together (bounds memory to ~tile_batch*chunk*tile^2 floats).
    Returns:
        ([H, W, 3] colour, [H, W] alpha = 1 - final transmittance).
    """
    dt = colors.dtype
    lists = bin_tiles(p, width, height, tile)
    n_tiles = lists.tiles_x * lists.tiles_y
    npx = tile * tile
    out_rgb = torch.zeros(n_tiles, npx, 3, dtype=dt)
    out_t = torch.ones(n_tiles, npx, dtype=dt)
    occupied = (lists.counts > 0).nonzero().squeeze(1)
    if occupied.numel():
        # pixel centres relative to the tile centre, row-major inside the tile
        u = torch.arange(tile, dtype=dt) + 0.5 - 0.5 * tile
        # gather per-gaussian data in list order once
        g_mean = p.means2d.to(dt)[lists.entries]
        g_conic = p.conics.to(dt)[lists.entries]
        g_op = p.opacities.to(dt)[lists.entries]
        g_col = colors[lists.entries]
        for b0 in range(0, occupied.numel(), tile_batch):
            tiles = occupied[b0:b0 + tile_batch]
            rgb, trans = _composite_tiles(tiles, lists, g_mean, g_conic, g_op, g_col, u, tile, chunk)
            out_rgb[tiles] = rgb
            out_t[tiles] = trans
    img = out_rgb + out_t.unsqueeze(-1) * background.to(dt)
    img = img.view(lists.tiles_y, lists.tiles_x, tile, tile, 3).permute(0, 2, 1, 3, 4)
    img = img.reshape(lists.tiles_y * tile, lists.tiles_x * tile, 3)[:height, :width]
    alpha = (1.0 - out_t).view(lists.tiles_y, lists.tiles_x, tile, tile).permute(0, 2, 1, 3)
    alpha = alpha.reshape(lists.tiles_y * tile, lists.tiles_x * tile)[:height, :width]
    return img, alpha


def _composite_tiles(tiles, lists: _TileLists, g_mean, g_conic, g_op, g_col, u, tile: int, chunk: int):
    """Composite the lists of ``tiles`` ([A] tile ids); returns ([A, P, 3] rgb, [A, P] transmittance)."""
    dt = g_mean.dtype
    n = tiles.numel()
    npx = tile * tile
    rgb = torch.zeros(n, npx, 3, dtype=dt)
    trans = torch.ones(n, npx, dtype=dt)
    done = torch.zeros(n, npx, dtype=torch.bool)
    centre_x = ((tiles % lists.tiles_x) * tile).to(dt) + 0.5 * tile
    centre_y = ((tiles // lists.tiles_x) * tile).to(dt) + 0.5 * tile
    count = lists.counts[tiles]
    start = lists.offsets[tiles]
    last = max(int(lists.entries.shape[0]) - 1, 0)
    act = torch.arange(n)  # rows of the batch still compositing
    j = torch.arange(chunk)
    step = 0
    while act.numel():
        pos = start[act, None] + step * chunk + j  # [a, L]
        valid = (step * chunk + j)[None, :] < count[act, None]
        pos = pos.clamp(max=last)
        dx = g_mean[pos, 0] - centre_x[act, None]  # [a, L] centre offsets from the tile centre
        dy = g_mean[pos, 1] - centre_y[act, None]
        ca, cb, cc = g_conic[pos].unbind(-1)
        op = g_op[pos] * valid
        # q/2 = 0.5 ca (dx-u)^2 + 0.5 cc (dy-v)^2 + cb (dx-u)(dy-v), separable per pixel row/column:
        ddx = dx[..., None] - u  # [a, L, tile] along x
        ddy = dy[..., None] - u  # [a, L, tile] along y
        qx = 0.5 * ca[..., None] * ddx * ddx
        qy = 0.5 * cc[..., None] * ddy * ddy
        lhs = torch.stack([torch.ones_like(qy), cb[..., None] * ddy, qy], dim=-1)  # [a, L, ty, 3]
        rhs = torch.stack([qx, ddx, torch.ones_like(qx)], dim=-2)  # [a, L, 3, tx]
        half_q = torch.matmul(lhs, rhs).view(act.numel(), chunk, npx)  # [a, L, P]
        alpha = torch.clamp_max(op[..., None] * torch.exp(-half_q), ALPHA_MAX)
        alpha = alpha * ((alpha >= ALPHA_MIN) & (half_q >= 0))
        alpha = alpha * ~done[act, None, :]
        one_minus = 1.0 - alpha
        t0 = trans[act]  # [a, P]
        t_incl = torch.cumprod(one_minus, dim=1) * t0[:, None, :]
        alive = t_incl > T_MIN
        weight = alpha * (t_incl / one_minus) * alive  # alpha * T before this gaussian
        rgb[act] += torch.bmm(weight.transpose(1, 2), g_col[pos])
        n_alive = alive.sum(dim=1)  # [a, P], alive is a prefix along the chunk
        t_last = torch.gather(t_incl, 1, (n_alive - 1).clamp_min(0)[:, None, :]).squeeze(1)
        trans[act] = torch.where(n_alive > 0, t_last, t0)
        done[act] |= ~alive[:, -1, :]
        step += 1
        more = (count[act] > step * chunk) & ~done[act].all(dim=1)
        act = act[more]
    return rgb, trans


def composite_fast(p: Projected, colors: torch.Tensor, width: int, height: int, background: torch.Tensor,
                   tile: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Same contract as :func:`composite`, with the per-pixel walk in a Taichi kernel."""
    from .ti_composite import composite_taichi

    lists = bin_tiles(p, width, height, tile)
    e = lists.entries
    packed = torch.cat([p.means2d[e], p.conics[e], torch.log(p.opacities[e, None]), colors[e]], dim=1).float()
    return composite_taichi(packed, lists.offsets, lists.counts, background, tile, lists.tiles_x, width, height)


COMPOSITORS = ("taichi", "torch")


def rasterize(means: torch.Tensor, covars: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
              viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int, background: torch.Tensor,
              near: float = 0.01, far: float = 1e10, eps2d: float = 0.3, compositor: str = "taichi",
              tile: int | None = None, chunk: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Render one image.

    Args:
        means: [N, 3] centres, covars: [N, 3, 3], opacities: [N], colors: [N, 3] (this view's).
        viewmat: [4, 4] world-to-camera; K: [3, 3]; width, height: pixels.
        background: [3].
        compositor: ``taichi`` (per-pixel kernel, fast) or ``torch`` (chunked tensors).
        tile: tile edge in pixels (default 8 for taichi, 16 for torch).
    Returns:
        ([H, W, 3] colour, not clipped; [H, W] alpha).
    """
    if compositor not in COMPOSITORS:
        raise ValueError(f"compositor must be one of {COMPOSITORS}, got {compositor!r}")
    with torch.no_grad():
        p = project(means, covars, opacities, viewmat, K, width, height, near, far, eps2d)
        if compositor == "taichi":
            return composite_fast(p, colors[p.ids], width, height, background, tile=tile or 8)
        return composite(p, colors[p.ids], width, height, background, tile=tile or 16, chunk=chunk)
