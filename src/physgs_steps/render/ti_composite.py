"""Front-to-back compositing of depth-sorted tile lists in a Taichi CPU kernel.

One parallel loop over pixels; each pixel walks its tile's list (prepared in torch by
:func:`physgs_steps.render.cpu.bin_tiles`) in depth order and stops at the first
gaussian that would bring its transmittance to 1e-4 or below, exactly like gsplat's
CUDA rasteriser. This is the fast path of the CPU renderer (the pure-torch chunked
compositor in ``cpu.py`` computes the same image and serves as its cross-check).

(No ``from __future__ import annotations`` here: Taichi reads the annotations.)
The kernel takes only ndarray arguments (no Taichi fields), so it works under whatever
Taichi runtime the process already has; if none is initialised it starts one on the CPU
with the project's offline cache (``runtime.cache_dir("taichi")``).
"""
import math

import taichi as ti
import torch

from ..runtime import cache_dir

_ALPHA_MIN = 1.0 / 255.0
_ALPHA_MAX = 0.999
_LOG_ALPHA_MIN = math.log(_ALPHA_MIN)
_T_MIN = 1e-4


def ensure_taichi(threads: int | None = None) -> None:
    """Initialise Taichi on the CPU unless this process already has a Taichi runtime.

    Args:
        threads: CPU threads for Taichi's parallel loops (None = all cores); only takes
            effect when this call starts the runtime.
    """
    from taichi.lang import impl

    if impl.get_runtime().prog is None:
        kw = {"cpu_max_num_threads": int(threads)} if threads else {}
        ti.init(arch=ti.cpu, offline_cache=True, offline_cache_file_path=str(cache_dir("taichi")),
                log_level=ti.WARN, default_fp=ti.f32, **kw)


@ti.kernel
def _composite_kernel(packed: ti.types.ndarray(dtype=ti.f32, ndim=2),  # [E, 9] mx my ca cb cc log(o) r g b
                      offsets: ti.types.ndarray(dtype=ti.i64, ndim=1),  # [n_tiles]
                      counts: ti.types.ndarray(dtype=ti.i64, ndim=1),  # [n_tiles]
                      background: ti.types.ndarray(dtype=ti.f32, ndim=1),  # [3]
                      tile: ti.i32, tiles_x: ti.i32,
                      out_rgb: ti.types.ndarray(dtype=ti.f32, ndim=3),  # [H, W, 3]
                      out_alpha: ti.types.ndarray(dtype=ti.f32, ndim=2)):  # [H, W]
    height, width = out_alpha.shape[0], out_alpha.shape[1]
    for i, j in ti.ndrange(height, width):
        t = (i // tile) * tiles_x + j // tile
        k = offsets[t]
        end = k + counts[t]
        px = ti.cast(j, ti.f32) + 0.5
        py = ti.cast(i, ti.f32) + 0.5
        trans = 1.0
        r = 0.0
        g = 0.0
        b = 0.0
        while k < end:
            dx = packed[k, 0] - px
            dy = packed[k, 1] - py
            half_q = 0.5 * (packed[k, 2] * dx * dx + packed[k, 4] * dy * dy) + packed[k, 3] * dx * dy
            # packed[k, 5] = log(opacity): alpha >= 1/255 <=> log_o - q/2 >= log(1/255); exp only then
            expo = packed[k, 5] - half_q
            if half_q >= 0.0 and expo >= _LOG_ALPHA_MIN:
                alpha = ti.min(_ALPHA_MAX, ti.exp(expo))
                nxt = trans * (1.0 - alpha)
                if nxt <= _T_MIN:
                    break
                w = alpha * trans
                r += w * packed[k, 6]
                g += w * packed[k, 7]
                b += w * packed[k, 8]
                trans = nxt
            k += 1
        out_rgb[i, j, 0] = r + trans * background[0]
        out_rgb[i, j, 1] = g + trans * background[1]
        out_rgb[i, j, 2] = b + trans * background[2]
        out_alpha[i, j] = 1.0 - trans


def composite_taichi(packed: torch.Tensor, offsets: torch.Tensor, counts: torch.Tensor, background: torch.Tensor,
                     tile: int, tiles_x: int, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Run the compositing kernel.

    Args:
        packed: [E, 9] float32 per list entry: mean x, mean y, conic a, b, c, log(opacity), r, g, b.
        offsets, counts: [n_tiles] int64 CSR layout of the per-tile lists.
        background: [3] float32.
        tile, tiles_x: tile edge and tiles per image row.
        width, height: image size.
    Returns:
        ([H, W, 3] colour, [H, W] alpha), float32.
    """
    ensure_taichi()
    rgb = torch.empty(height, width, 3, dtype=torch.float32)
    alpha = torch.empty(height, width, dtype=torch.float32)
    if packed.shape[0] == 0:  # Taichi cannot take a zero-size ndarray: nothing to draw
        rgb[:] = background.float()
        alpha.zero_()
        return rgb, alpha
    _composite_kernel(packed.float().contiguous(), offsets.long().contiguous(), counts.long().contiguous(),
                      background.float().contiguous(), int(tile), int(tiles_x), rgb, alpha)
    return rgb, alpha
