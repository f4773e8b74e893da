"""The particle budget and the gaussian carrier (physgs_steps.carrier, render.deform.CarrierMap),
and final.h5's storage and error budget (physgs_steps.final_frames)."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from physgs_steps.carrier import build_carrier, load_carrier, particle_spacing, representatives, write_carrier
from physgs_steps.errors import InputError, SimulationError
from physgs_steps.final_frames import F16_BOUND_ABS, F16_BOUND_REL, FinalFrames, FinalWriter
from physgs_steps.render.deform import CarrierMap


def _shell(n, rng, c=(0.5, 0.5, 0.5), r=0.15):
    d = rng.normal(size=(n, 3))
    return np.asarray(c) + r * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_representatives_one_per_subcell_nearest_to_its_mean():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.0, 1.0, (5000, 3))
    cell = 0.1
    rows = representatives(pts, cell)
    keys = np.floor((pts - pts.min(0)) / cell).astype(int)
    occupied = {tuple(k) for k in keys}
    assert len(rows) == len(occupied) and len({tuple(k) for k in keys[rows]}) == len(rows)
    assert np.all(np.diff(rows) > 0)
    # in the sub-cell of the first representative, no point is nearer to the sub-cell's mean
    same = (keys == keys[rows[0]]).all(axis=1)
    mean = pts[same].mean(0)
    assert np.linalg.norm(pts[rows[0]] - mean) <= np.linalg.norm(pts[same] - mean, axis=1).min() + 1e-12
    assert particle_spacing(1 / 32, 8) == pytest.approx(1 / 64)


def _representatives_by_sorting(points, cell):
    """The definition of ``representatives`` written plainly (np.unique + lexsort): per sub-cell
    the row nearest to the mean of its rows, the first row among equally near ones."""
    keys = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    mean = np.stack([np.bincount(inv, weights=points[:, a]) for a in range(3)], axis=1) / counts[:, None]
    d2 = ((points - mean[inv]) ** 2).sum(axis=1)
    order = np.lexsort((d2, inv))
    first = np.r_[True, inv[order][1:] != inv[order][:-1]]
    return np.sort(order[first])


def test_representatives_equal_the_sorting_definition_with_ties_and_sparse_boxes():
    """The bincount / minimum.at form picks exactly the rows of the sorting form: on a dense
    cloud, with duplicated points (equal distances: the first row wins), and on a sparse cloud
    in a huge box (the path that numbers the occupied sub-cells)."""
    rng = np.random.default_rng(3)
    pts = _shell(4000, rng)
    dup = np.concatenate([pts, pts[::7], pts[::5]])[rng.permutation(4000 + 572 + 800)]
    grid = np.round(rng.uniform(0.0, 1.0, (3000, 3)) * 40) / 40  # lattice points: many exact ties
    sparse = np.concatenate([rng.uniform(0.0, 1.0, (500, 3)), rng.uniform(0.0, 1.0, (500, 3)) + 1e4])
    for p, cell in [(pts, 0.02), (dup, 0.02), (grid, 0.05), (sparse, 0.01), (pts[:1], 0.1)]:
        got = representatives(p, cell)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, _representatives_by_sorting(p, cell))
    assert representatives(np.zeros((0, 3)), 0.1).shape == (0,)


def _two_instance_carrier(rng, k=8):
    """Two shells (labels 0, 1) plus a static gaussian (label -1); particles: representatives + interior."""
    g0, g1 = _shell(3000, rng, (0.35, 0.5, 0.5), 0.1), _shell(3000, rng, (0.65, 0.5, 0.5), 0.1)
    gx = np.concatenate([g0, g1, [[0.5, 0.9, 0.9]]])
    glab = np.r_[np.zeros(3000), np.ones(3000), -1].astype(np.int32)
    s = particle_spacing(1 / 32, 8)
    reps = np.concatenate([representatives(g0, s), 3000 + representatives(g1, s)])
    inner = np.concatenate([_shell(400, rng, (0.35, 0.5, 0.5), 0.05), _shell(400, rng, (0.65, 0.5, 0.5), 0.05)])
    px = np.concatenate([gx[reps], inner])
    plab = np.concatenate([glab[reps], np.zeros(400), np.ones(400)]).astype(np.int32)
    prow = np.concatenate([reps, np.full(800, -1)])
    return gx, glab, px, plab, prow, build_carrier(gx, glab, px, plab, prow, "budget", k, s)


def test_budget_carrier_weights_instances_and_static(tmp_path):
    rng = np.random.default_rng(1)
    gx, glab, px, plab, prow, c = _two_instance_carrier(rng)
    assert c.index.shape == (6001, 8) and not c.identity
    assert c.static.tolist() == [False] * 6000 + [True] and (c.weight[-1] == 0).all() and (c.index[-1] == -1).all()
    np.testing.assert_allclose(c.weight[:6000].sum(axis=1), 1.0, rtol=1e-6)
    drv = c.drivers[c.index[:6000]]  # particle rows of every gaussian's drivers
    assert (plab[drv] == glab[:6000, None]).all()  # a gaussian never follows another object
    assert c.drivers.size < px.shape[0] and np.all(np.diff(c.drivers) > 0)
    np.testing.assert_array_equal(c.drivers, np.unique(drv))  # exactly the particles that drive a gaussian
    # the heaviest driver of a gaussian that is itself a representative is that particle
    r = int(prow[0])
    assert c.drivers[c.index[r, np.argmax(c.weight[r])]] == 0
    write_carrier(tmp_path / "c.h5", c)
    back = load_carrier(tmp_path / "c.h5", 6001)
    np.testing.assert_array_equal(back.index, c.index) and back.mode == "budget"
    with pytest.raises(InputError, match="has 6001 gaussians but scene.ply has 5"):
        load_carrier(tmp_path / "c.h5", 5)


def test_gaussians_mode_is_the_identity():
    rng = np.random.default_rng(2)
    gx = rng.uniform(0.3, 0.7, (50, 3))
    glab = np.zeros(50, np.int32)
    glab[:5] = -1  # static surroundings are no particles
    px = np.concatenate([gx[5:], rng.uniform(0.4, 0.6, (20, 3))])
    prow = np.r_[np.arange(5, 50), np.full(20, -1)]
    c = build_carrier(gx, glab, px, np.zeros(65, np.int32), prow, "gaussians", 8, 0.01)
    assert c.identity and c.static[:5].all() and not c.static[5:].any()
    np.testing.assert_array_equal(c.drivers, np.arange(45))
    np.testing.assert_array_equal(c.drivers[c.index[5:, 0]], np.arange(45))


def test_carrier_moves_gaussians_exactly_under_affine_motion():
    """x_g = sum w (x_p + F_p d): exact for rigid rotation and any affine map (plain averaging of
    displacements is not)."""
    rng = np.random.default_rng(3)
    gx, glab, px, plab, prow, c = _two_instance_carrier(rng)
    x0 = px[c.drivers]
    cmap = CarrierMap.build(c, c.drivers, gx, x0)
    assert cmap.rows.numel() == 6000
    R = Rotation.from_euler("xyz", [40, -25, 70], degrees=True).as_matrix()
    A = R @ np.diag([1.3, 0.8, 1.1])
    for M in (R, A):
        t = np.array([0.05, -0.02, 0.1])
        xt = x0 @ M.T + t
        F = np.broadcast_to(M, (len(x0), 3, 3))
        xs, Fs = cmap.apply(torch.from_numpy(xt), torch.from_numpy(np.ascontiguousarray(F)))
        np.testing.assert_allclose(xs.numpy(), gx[:6000] @ M.T + t, atol=1e-6)  # offsets kept in float32
        np.testing.assert_allclose(Fs.numpy(), np.broadcast_to(M, (6000, 3, 3)), atol=1e-6)
    # without the deformation term, a rotated surface would be off by up to a particle spacing
    w, i = cmap.weight.numpy(), cmap.index.numpy()
    naive = gx[:6000] + (w[..., None] * ((x0 @ R.T) - x0)[i]).sum(1)
    assert np.abs(naive - gx[:6000] @ R.T).max() > 1e-3


def test_carrier_keeps_gaussians_on_their_side_of_a_tear():
    """A body torn in two: a gaussian follows only the drivers that move with its heaviest one,
    so next to the tear it stays on its side instead of being drawn in the gap at the
    weighted mean of both sides."""
    rng = np.random.default_rng(6)
    gx = rng.uniform([0.3, 0.45, 0.45], [0.7, 0.55, 0.55], (4000, 3))
    s = particle_spacing(1 / 32, 4)
    reps = representatives(gx, s)
    c = build_carrier(gx, np.zeros(len(gx), np.int32), gx[reps], np.zeros(len(reps), np.int32), reps, "budget", 8, s)
    x0 = gx[reps][np.argsort(reps)]  # final.h5 column order: drivers sorted by particle row
    cmap = CarrierMap.build(c, c.drivers, gx, x0)
    right = x0[:, 0] > 0.5
    xt = x0 + np.where(right[:, None], [0.15, 0.0, -0.05], 0.0)  # the right half moved off: a gap
    F = torch.eye(3, dtype=torch.float64).repeat(len(x0), 1, 1)
    xs, _ = cmap.apply(torch.from_numpy(xt), F)
    moved = np.linalg.norm(xs.numpy() - gx[cmap.rows.numpy()], axis=1)
    both = (right[cmap.index.numpy()] & (cmap.weight.numpy() > 0)).any(1) & \
        (~right[cmap.index.numpy()] & (cmap.weight.numpy() > 0)).any(1)
    assert both.sum() > 100  # gaussians driven from both sides of the tear
    shift = np.linalg.norm([0.15, 0.0, -0.05])
    assert np.minimum(moved, np.abs(moved - shift)).max() < 1e-6  # each on one side, none in the gap


def test_carrier_drops_drivers_final_h5_does_not_store():
    rng = np.random.default_rng(4)
    gx, glab, px, plab, prow, c = _two_instance_carrier(rng)
    keep = c.drivers[plab[c.drivers] == 0]  # the simulation left instance 1 out (e.g. fixed rigid)
    cmap = CarrierMap.build(c, keep, gx, px[keep])
    rows = cmap.rows.numpy()
    assert set(rows.tolist()) == set(range(3000))
    xs, _ = cmap.apply(torch.from_numpy(px[keep]), torch.eye(3, dtype=torch.float64).repeat(len(keep), 1, 1))
    np.testing.assert_allclose(xs.numpy(), gx[:3000], atol=1e-6)


def test_final_h5_float16_error_budget_and_held_frames(tmp_path):
    rng = np.random.default_rng(5)
    m, t = 500, 6
    x = rng.uniform(0.2, 0.8, (t, m, 3)).astype(np.float32)
    F = (np.eye(3) + rng.normal(0.0, 0.3, (t, m, 3, 3)) * rng.uniform(0, 3, (t, m, 1, 1))).astype(np.float32)
    F[0] = np.eye(3)
    with h5py.File(tmp_path / "final.h5", "w") as h:
        w = FinalWriter(h, np.arange(m) * 2, np.arange(t) / 30.0)
        for k in range(t):
            w.hold(k) if k in (3, 4) else w.frame(k, x[k], F[k])
        w.finish({"stats": {"x": 1}})
    with FinalFrames(tmp_path / "final.h5") as fr:
        assert fr.rows == 4 and fr.frame_row.tolist() == [0, 1, 2, 2, 2, 3]
        np.testing.assert_array_equal(fr.particle_index, np.arange(m) * 2)
        for k in range(t):
            src = {3: 2, 4: 2}.get(k, k)
            np.testing.assert_array_equal(fr.x(k), x[src])  # positions exact (float32)
            err = np.abs(fr.F(k).astype(np.float64) - F[src])
            bound = F16_BOUND_REL * np.abs(F[src].astype(np.float64) - np.eye(3)) + F16_BOUND_ABS
            assert (err <= bound * (1 + 1e-6) + 1e-7).all()  # + float32 rounding of the sum
        assert fr.attr("stats") == {"x": 1}
    with h5py.File(tmp_path / "bad.h5", "w") as h:
        w = FinalWriter(h, np.arange(2), np.arange(2) / 30.0)
        with pytest.raises(SimulationError, match="float16"):
            w.frame(0, np.zeros((2, 3)), np.full((2, 3, 3), 1e6))
