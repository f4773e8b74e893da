"""CPU renderer on analytic cases, and its parts against independent references."""
from __future__ import annotations

import math

import pytest
import torch

from physgs_steps.render import cpu
from physgs_steps.render.sh import C1, eval_sh, view_colors

W, H = 64, 64
F_PX = 100.0
BLACK = torch.zeros(3)


def _camera():
    """Camera at the origin looking along +z (OpenCV), principal point on the centre of pixel (32, 32)."""
    vm = torch.eye(4)
    k = torch.tensor([[F_PX, 0.0, 32.5], [0.0, F_PX, 32.5], [0.0, 0.0, 1.0]])
    return vm, k


def _iso(means, sigmas):
    """[N, 3] means, [N] isotropic standard deviations -> covariances [N, 3, 3]."""
    s = torch.as_tensor(sigmas, dtype=torch.float32)
    return torch.eye(3).expand(len(means), 3, 3) * (s ** 2)[:, None, None]


def _render(means, covs, opac, cols, bg=BLACK, compositor="taichi", **kw):
    vm, k = _camera()
    return cpu.rasterize(torch.as_tensor(means, dtype=torch.float32), covs, torch.as_tensor(opac, dtype=torch.float32),
                         torch.as_tensor(cols, dtype=torch.float32), vm, k, W, H, bg, compositor=compositor, **kw)


@pytest.mark.parametrize("compositor", ["taichi", "torch"])
def test_single_gaussian_footprint_and_colour(compositor):
    # sigma 0.1 at depth 2 with f = 100: 5 px standard deviation, variance 25 + eps2d 0.3
    col = [1.0, 0.5, 0.25]
    img, alpha = _render([[0.0, 0.0, 2.0]], _iso([[0, 0, 2]], [0.1]), [0.8], [col], compositor=compositor)
    var = 25.0 + 0.3
    # centre pixel (row 32, col 32): q = 0
    assert alpha[32, 32].item() == pytest.approx(0.8, abs=1e-6)
    assert img[32, 32].tolist() == pytest.approx([0.8 * c for c in col], abs=1e-6)
    # 5 px to the right and 3 px up
    a = 0.8 * math.exp(-0.5 * (25 + 9) / var)
    assert alpha[29, 37].item() == pytest.approx(a, rel=1e-5)
    assert img[29, 37].tolist() == pytest.approx([a * c for c in col], rel=1e-5)
    # footprint edge: alpha >= 1/255 up to d = sqrt(2 var ln(0.8 * 255)) = 16.4 px, nothing beyond
    assert alpha[32, 32 + 16].item() == pytest.approx(0.8 * math.exp(-0.5 * 256 / var), rel=1e-5)
    assert alpha[32, 32 + 17].item() == 0.0
    assert alpha[32 - 17, 32].item() == 0.0
    # isotropic: symmetric footprint
    assert alpha[32, 32 - 7].item() == pytest.approx(alpha[32 - 7, 32].item(), rel=1e-6)


@pytest.mark.parametrize("compositor", ["taichi", "torch"])
def test_occlusion_order_of_two(compositor):
    red, blue, bg = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], torch.tensor([0.0, 1.0, 0.0])
    means = [[0.0, 0.0, 3.0], [0.0, 0.0, 2.0]]  # blue far, red near (input order must not matter)
    covs = _iso(means, [0.1, 0.1])
    img, alpha = _render(means, covs, [0.9, 0.6], [blue, red], bg=bg, compositor=compositor)
    a_red, a_blue = 0.6, 0.9  # at the centre pixel q = 0 for both
    expect = [a_red, (1 - a_red) * (1 - a_blue), a_blue * (1 - a_red)]  # r, g (background), b
    assert img[32, 32].tolist() == pytest.approx(expect, abs=1e-6)
    assert alpha[32, 32].item() == pytest.approx(1 - (1 - a_red) * (1 - a_blue), abs=1e-6)
    # move blue in front: now blue dominates
    img2, _ = _render([[0.0, 0.0, 3.0], [0.0, 0.0, 4.0]], covs, [0.9, 0.6], [blue, red], bg=bg, compositor=compositor)
    expect2 = [a_red * (1 - a_blue), (1 - a_red) * (1 - a_blue), a_blue]
    assert img2[32, 32].tolist() == pytest.approx(expect2, abs=1e-6)


@pytest.mark.parametrize("compositor", ["taichi", "torch"])
def test_early_termination_is_exclusive(compositor):
    # three fully opaque gaussians (alpha clamped to 0.999): T = 1e-3 after the first; the second
    # would make it 1e-6 <= 1e-4, so the pixel stops before it (gsplat's rule)
    means = [[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 4.0]]
    cols = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    img, alpha = _render(means, _iso(means, [0.1, 0.1, 0.1]), [1.0, 1.0, 1.0], cols,
                         bg=torch.tensor([1.0, 1.0, 1.0]), compositor=compositor)
    assert img[32, 32].tolist() == pytest.approx([0.999 + 0.001, 0.001, 0.001], abs=1e-6)
    assert alpha[32, 32].item() == pytest.approx(0.999, abs=1e-6)


def test_near_plane_and_far_plane_cull():
    means = [[0.0, 0.0, 0.005], [0.0, 0.0, 50.0]]
    img, alpha = _render(means, _iso(means, [0.001, 0.5]), [1.0, 1.0], [[1, 1, 1], [1, 1, 1]], near=0.01, far=10.0)
    assert alpha.max().item() == 0.0
    img, alpha = _render(means, _iso(means, [0.001, 0.5]), [1.0, 1.0], [[1, 1, 1], [1, 1, 1]], near=0.001, far=100.0)
    assert alpha.max().item() > 0.9


def _random_scene(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.4, 0.3, 0.3]) + torch.tensor([0.0, 0.0, 2.5])
    a = torch.randn(n, 3, 3, generator=g) * 0.03
    covs = a @ a.transpose(1, 2) + 1e-5 * torch.eye(3)
    opac = torch.rand(n, generator=g) * 0.95 + 0.02
    cols = torch.rand(n, 3, generator=g)
    return means, covs, opac, cols


def _reference_composite(p: cpu.Projected, colors, bg):
    """Independent dense reference: every projected gaussian against every pixel, in depth order."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    trans = torch.ones(H, W, dtype=torch.float64)
    rgb = torch.zeros(H, W, 3, dtype=torch.float64)
    done = torch.zeros(H, W, dtype=torch.bool)
    for i in torch.argsort(p.depths, stable=True).tolist():
        dx, dy = p.means2d[i, 0].double() - xs, p.means2d[i, 1].double() - ys
        a, b, c = p.conics[i].double()
        q = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp(p.opacities[i].double() * torch.exp(-q), max=0.999)
        use = (q >= 0) & (alpha >= 1 / 255) & ~done
        nxt = trans * (1 - alpha)
        stop = use & (nxt <= 1e-4)
        done |= stop
        use &= ~stop
        rgb += torch.where(use, alpha * trans, 0.0)[..., None] * colors[i].double()
        trans = torch.where(use, nxt, trans)
    return (rgb + trans[..., None] * bg.double()).float(), (1 - trans).float()


def test_compositors_match_dense_reference():
    means, covs, opac, cols = _random_scene(300)
    vm, k = _camera()
    bg = torch.tensor([0.2, 0.3, 0.4])
    p = cpu.project(means, covs, opac, vm, k, W, H)
    assert p.n > 200
    ref_rgb, ref_a = _reference_composite(p, cols[p.ids], bg)
    for comp, tile in [("taichi", 8), ("taichi", 16), ("taichi", 4), ("torch", 16), ("torch", 8)]:
        rgb, alpha = cpu.rasterize(means, covs, opac, cols, vm, k, W, H, bg, compositor=comp, tile=tile)
        assert (rgb - ref_rgb).abs().max().item() < 2e-4, (comp, tile)
        assert (alpha - ref_a).abs().max().item() < 2e-4, (comp, tile)


def test_projection_matches_gsplat_torch_reference():
    ref = pytest.importorskip("gsplat.cuda._torch_impl")
    means, covs, opac, _ = _random_scene(500, seed=3)
    vm = torch.tensor([[0.96, 0.0, -0.28, 0.1], [0.0, 1.0, 0.0, -0.05], [0.28, 0.0, 0.96, 0.2], [0, 0, 0, 1.0]])
    k = torch.tensor([[80.0, 0.0, 30.0], [0.0, 90.0, 34.0], [0.0, 0.0, 1.0]])
    p = cpu.project(means, covs, opac, vm, k, W, H, eps2d=0.3)
    radii, means2d, depths, conics, _ = ref._fully_fused_projection(means, covs, vm[None], k[None], W, H, eps2d=0.3)
    assert torch.allclose(p.means2d, means2d[0, p.ids], atol=1e-3)
    assert torch.allclose(p.depths, depths[0, p.ids], atol=1e-5)
    assert torch.allclose(p.conics, conics[0, p.ids], rtol=1e-3, atol=1e-6)
    # everything we keep lies inside gsplat's (looser, opacity-independent) bounding boxes
    assert bool((radii[0, p.ids] > 0).all())


def test_empty_image_when_nothing_in_view():
    img, alpha = _render([[0.0, 0.0, -2.0]], _iso([[0, 0, -2]], [0.1]), [1.0], [[1, 0, 0]], bg=torch.tensor([0.5, 0.5, 0.5]))
    assert alpha.max().item() == 0.0
    assert torch.allclose(img, torch.full((H, W, 3), 0.5))


def test_sh_matches_gsplat_reference_and_degree_zero():
    ref = pytest.importorskip("gsplat.cuda._torch_impl")
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(50, 16, 3, generator=g) * 0.3
    dirs = torch.randn(50, 3, generator=g)
    for deg in range(4):
        ours = eval_sh(sh, dirs, deg)
        theirs = torch.clamp_min(ref._spherical_harmonics(deg, dirs, sh) + 0.5, 0.0)
        assert torch.allclose(ours, theirs, atol=1e-5), deg
    # degree 1 along +x: 0.5 + C0 c0 - C1 c3
    c = torch.zeros(1, 4, 3)
    c[0, 0] = 0.1
    c[0, 3] = 0.2
    assert eval_sh(c, torch.tensor([[2.0, 0.0, 0.0]]), 1)[0, 0].item() == pytest.approx(0.5 + 0.28209479 * 0.1 - C1 * 0.2)


def test_view_colors_rotated_frame():
    # a gaussian rotated by Q and seen from Q d looks like the unrotated one seen from d
    g = torch.Generator().manual_seed(2)
    sh = torch.randn(1, 16, 3, generator=g) * 0.3
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = (q * torch.sign(torch.det(q))).float()
    mean = torch.tensor([[0.1, -0.2, 0.3]])
    cam = torch.tensor([1.0, 2.0, -0.5])
    base = view_colors(mean, sh, cam, 3)
    cam_rot = mean[0] + q @ (cam - mean[0])
    rotated = view_colors(mean, sh, cam_rot, 3, rotations=q[None])
    assert torch.allclose(base, rotated, atol=1e-5)
    assert not torch.allclose(base, view_colors(mean, sh, cam_rot, 3), atol=1e-3)


def test_too_many_tile_entries_is_a_clear_error(monkeypatch):
    from physgs_steps.errors import RenderError

    monkeypatch.setattr(cpu, "MAX_TILE_ENTRIES", 10)
    with pytest.raises(RenderError, match="camera very close"):
        _render([[0.0, 0.0, 0.5]], _iso([[0, 0, 0.5]], [0.2]), [1.0], [[1, 0, 0]])
