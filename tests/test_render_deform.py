"""Deformed gaussians: frames back to the source frame, F Sigma F^T, polar rotations."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from physgs_steps.errors import RenderError
from physgs_steps.gaussians import GaussianScene
from physgs_steps.prepare import SceneTransform
from physgs_steps.render import cpu, orbit_cameras, render_static
from physgs_steps.render.deform import SourceMap, check_frame, deform, polar_rotation, rest_gaussians
from physgs_steps.render.renderer import Renderer, RenderSettings


def _scene(n=400, seed=0, sh_k=1) -> GaussianScene:
    rng = np.random.default_rng(seed)
    return GaussianScene(
        means=rng.normal(0, 0.05, (n, 3)) + [0.1, -0.2, 0.3],
        log_scales=np.log(rng.uniform(0.003, 0.01, (n, 3))),
        quats=rng.normal(size=(n, 4)),
        opacity_logits=rng.normal(2.0, 1.0, n),
        sh=rng.normal(0, 0.4, (n, sh_k, 3)),
    )


def _transform() -> SceneTransform:
    R = Rotation.from_euler("zyx", [30, -20, 10], degrees=True).as_matrix()
    return SceneTransform(R=R, scale=2.5, src_center=np.array([0.1, -0.2, 0.3]), sim_center=np.array([0.5, 0.5, 0.4]))


def test_identity_F_reproduces_static_render():
    src = _scene(sh_k=16)
    t = _transform()
    sim = t.to_sim_scene(src)
    smap = SourceMap.from_transform(t)
    rest = rest_gaussians(sim, smap)
    x = torch.from_numpy(sim.means)
    F = torch.eye(3).repeat(sim.n, 1, 1)
    g = deform(rest, torch.arange(sim.n), x, F, smap, with_rotation=True)
    assert torch.allclose(g.means, torch.from_numpy(src.means), atol=1e-5)
    assert torch.allclose(g.covars, torch.from_numpy(src.covariances()), atol=1e-8, rtol=1e-4)
    cams = orbit_cameras(src.means.mean(0), 0.5, 2, 25.0, 40.0, 48, 40)
    r = Renderer("cpu", RenderSettings(background=(0.0, 0.0, 0.0)))
    deformed, _ = r.render_frames([g, g], cams)
    static = render_static(src, cams, backend="cpu", background=(0.0, 0.0, 0.0))
    assert deformed.shape == static.shape == (2, 40, 48, 3)
    assert static.max() > 50
    assert np.abs(deformed.astype(int) - static.astype(int)).max() <= 1


def test_uniform_scale_F_scales_the_footprint():
    # one isotropic gaussian (sigma 0.01 source units) seen head-on at distance 1 with f = 200 px
    src = GaussianScene(means=np.zeros((1, 3)), log_scales=np.log(np.full((1, 3), 0.01)), quats=[[1, 0, 0, 0]],
                        opacity_logits=[3.0], sh=np.zeros((1, 1, 3)))
    t = _transform()
    smap = SourceMap.from_transform(t)
    rest = rest_gaussians(t.to_sim_scene(src), smap)
    vm = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0]])
    k = torch.tensor([[200.0, 0, 32.0], [0, 200.0, 32.0], [0, 0, 1.0]])
    for s in (1.0, 2.0, 3.0):
        x_sim = torch.from_numpy(t.to_sim(np.zeros((1, 3)))).float()
        g = deform(rest, torch.arange(1), x_sim, torch.eye(3)[None] * s, smap, with_rotation=False)
        p = cpu.project(g.means, g.covars, g.opacities, vm, k, 64, 64)
        var_px = (200.0 * 0.01 * s) ** 2 + 0.3
        a, b, c = p.conics[0].tolist()
        assert a == pytest.approx(1 / var_px, rel=1e-4) and c == pytest.approx(1 / var_px, rel=1e-4)
        assert abs(b) < 1e-6
        assert p.means2d[0].tolist() == pytest.approx([32.0, 32.0], abs=1e-4)


def test_deform_maps_positions_and_rotations_to_source_frame():
    t = _transform()
    smap = SourceMap.from_transform(t)
    sim = t.to_sim_scene(_scene(n=50))
    rest = rest_gaussians(sim, smap)
    rng = np.random.default_rng(4)
    x_sim = torch.from_numpy(rng.uniform(0.3, 0.7, (50, 3)).astype(np.float32))
    q_sim = Rotation.random(50, random_state=5).as_matrix()
    stretch = np.diag([1.3, 0.9, 0.8])
    F_sim = torch.from_numpy((q_sim @ stretch).astype(np.float32))
    g = deform(rest, torch.arange(50), x_sim, F_sim, smap, with_rotation=True)
    assert np.allclose(g.means.numpy(), t.to_source(x_sim.numpy()), atol=1e-5)
    # the source-frame polar rotation is R^T Q R
    expect = np.einsum("ji,njk,kl->nil", t.R, q_sim, t.R)
    assert np.allclose(g.rotations.numpy(), expect, atol=1e-4)
    # covariance follows F_src Sigma_src F_src^T
    F_src = np.einsum("ji,njk,kl->nil", t.R, F_sim.numpy().astype(np.float64), t.R)
    cov0 = rest.covars.numpy().astype(np.float64)
    assert np.allclose(g.covars.numpy(), F_src @ cov0 @ np.swapaxes(F_src, 1, 2), rtol=1e-4, atol=1e-10)


def test_polar_rotation_proper_even_for_inverted_F():
    rng = np.random.default_rng(7)
    F = torch.from_numpy(rng.normal(size=(200, 3, 3)))
    R = polar_rotation(F)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=F.dtype).expand(200, 3, 3), atol=1e-10)
    assert torch.allclose(torch.det(R), torch.ones(200, dtype=F.dtype), atol=1e-10)
    S = R.transpose(1, 2) @ F  # the stretch part is symmetric
    assert torch.allclose(S, S.transpose(1, 2), atol=1e-10)
    assert bool((torch.det(F) > 0).any()) and bool((torch.det(F) < 0).any())  # Newton rows and SVD rows
    from physgs_steps.render.deform import _polar_svd
    assert torch.allclose(R, _polar_svd(F), atol=1e-9)
    q = torch.from_numpy(Rotation.random(3, random_state=1).as_matrix())
    assert torch.allclose(polar_rotation(q @ torch.diag(torch.tensor([2.0, 1.0, 0.5], dtype=q.dtype))), q, atol=1e-10)


def test_unsimulated_gaussians_stay_at_rest_and_hidden_rows_vanish():
    t = _transform()
    smap = SourceMap.from_transform(t)
    src = _scene(n=30)
    sim = t.to_sim_scene(src)
    rest = rest_gaussians(sim, smap)
    index = torch.tensor([3, 7, 11])
    x_sim = torch.from_numpy(sim.means[[3, 7, 11]] + 0.01)
    F = torch.eye(3).repeat(3, 1, 1) * 1.5
    hide = torch.tensor([False, True, False])
    g = deform(rest, index, x_sim, F, smap, with_rotation=True, hide=hide)
    others = [i for i in range(30) if i not in (3, 7, 11)]
    assert torch.allclose(g.means[others], rest.means[others])
    assert torch.allclose(g.covars[others], rest.covars[others])
    assert torch.allclose(g.covars[3], rest.covars[3] * 2.25, rtol=1e-5)
    assert g.opacities[7].item() == 0.0 and g.opacities[3].item() > 0
    assert rest.opacities[7].item() > 0  # the rest state is not modified
    assert torch.allclose(g.rotations[others], torch.eye(3).expand(len(others), 3, 3))


def test_nonfinite_frame_policies():
    x = np.zeros((10, 3), np.float32)
    F = np.tile(np.eye(3, dtype=np.float32), (10, 1, 1))
    assert check_frame(4, x, F, "error") is None
    x[2, 1] = np.nan
    F[5, 0, 0] = np.inf
    with pytest.raises(RenderError, match="frame 4: 2 of 10 particles"):
        check_frame(4, x, F, "error")
    mask = check_frame(4, x, F, "hide")
    assert mask.tolist() == [i in (2, 5) for i in range(10)]
    with pytest.raises(RenderError, match="10 of 10"):
        check_frame(9, np.full((10, 3), np.nan, np.float32), F, "hide")
    # the finite-sum shortcut: huge finite float32 values pass, opposite infinities are caught
    big = np.full((10, 3), np.finfo(np.float32).max, np.float32)
    assert check_frame(1, big, np.tile(np.eye(3, dtype=np.float32), (10, 1, 1)), "error") is None
    F2 = np.tile(np.eye(3, dtype=np.float32), (10, 1, 1))
    F2[1, 2, 2], F2[8, 0, 1] = np.inf, -np.inf
    assert check_frame(2, np.zeros((10, 3), np.float32), F2, "hide").tolist() == [i in (1, 8) for i in range(10)]


def test_view_dependent_colour_follows_rotation():
    # a degree-1 gaussian rotated by 90 deg about z shows, from +x, the colour it had from -y
    sh = np.zeros((1, 4, 3))
    sh[0, 3] = [-1.0, 0.0, 0.0]  # red rises along +x of its rest frame (basis -C1 x)
    src = GaussianScene(means=np.zeros((1, 3)), log_scales=np.log(np.full((1, 3), 0.05)), quats=[[1, 0, 0, 0]],
                        opacity_logits=[5.0], sh=sh)
    smap = SourceMap.identity()
    rest = rest_gaussians(src, smap)
    rot = torch.from_numpy(Rotation.from_euler("z", 90, degrees=True).as_matrix()).float()[None]
    g = deform(rest, torch.arange(1), torch.zeros(1, 3), rot, smap, with_rotation=True)
    cam_x = orbit_cameras([0, 0, 0], 1.0, 1, 0.0, 30.0, 32, 32, azimuth_deg=0.0)   # on +x, looking along -x
    cam_y = orbit_cameras([0, 0, 0], 1.0, 1, 0.0, 30.0, 32, 32, azimuth_deg=-90.0)  # on -y, looking along +y
    r = Renderer("cpu", RenderSettings(background=(0.0, 0.0, 0.0)))
    rot_from_x, _ = r.render_frames([g], cam_x)
    rest_from_y, _ = r.render_frames([rest], cam_y)
    rest_from_x, _ = r.render_frames([rest], cam_x)
    assert abs(int(rot_from_x[0, 16, 16, 0]) - int(rest_from_y[0, 16, 16, 0])) <= 1
    assert abs(int(rot_from_x[0, 16, 16, 0]) - int(rest_from_x[0, 16, 16, 0])) > 20
    assert math.isfinite(float(rot_from_x.mean()))


def test_elementwise_3x3_products_match_matmul_with_broadcasting():
    """The CUDA path of the render's 3x3 algebra (written out, no batched GEMM) equals matmul."""
    from physgs_steps.render.deform import matvec3_elementwise, mul3_elementwise

    g = torch.Generator().manual_seed(3)
    a = torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    b = torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    r = torch.randn(3, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(mul3_elementwise(a, b), a @ b, atol=1e-12)
    assert torch.allclose(mul3_elementwise(r.T, a), r.T @ a, atol=1e-12)
    assert torch.allclose(mul3_elementwise(a, r), a @ r, atol=1e-12)
    v = torch.randn(5, 4, 3, generator=g, dtype=torch.float64)
    A = torch.randn(5, 4, 3, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(matvec3_elementwise(A, v), (A @ v.unsqueeze(-1)).squeeze(-1), atol=1e-12)
