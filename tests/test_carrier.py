"""The particle budget and the gaussian carrier (physgs_steps.carrier, render.deform.CarrierMap),
final.h5's storage and error budget (physgs_steps.final_frames) and final_sim's per-frame host
work: the writer and the physical figures against the code they replaced (issue #18)."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from physgs_steps.carrier import build_carrier, load_carrier, particle_spacing, representatives, write_carrier
from physgs_steps.errors import InputError, SimulationError
from physgs_steps.final_frames import F16_BOUND_ABS, F16_BOUND_REL, F16_MAX, FinalFrames, FinalWriter, to_float16
from physgs_steps.physical import PhysicalFigures, det3
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


def test_final_frames_block_reads_match_single_rows(tmp_path, monkeypatch):
    """FinalFrames reads rows in blocks: any access order (forward, backward, repeated, held
    frames) gives exactly the rows h5py reads one by one, with blocks of 1, 3 and all rows;
    so do its views (x_view, F_minus_I), kept across block reads."""
    import physgs_steps.final_frames as ff

    rng = np.random.default_rng(6)
    m, t = 40, 9
    x = rng.uniform(0.2, 0.8, (t, m, 3)).astype(np.float32)
    F = (np.eye(3) + rng.normal(0.0, 0.2, (t, m, 3, 3))).astype(np.float32)
    with h5py.File(tmp_path / "final.h5", "w") as h:
        w = FinalWriter(h, np.arange(m), np.arange(t) / 30.0)
        for k in range(t):
            w.hold(k) if k == 5 else w.frame(k, x[k], F[k])
        w.finish({})
    with h5py.File(tmp_path / "final.h5", "r") as h:
        rows = h["frame_row"][...]
        ref_x, ref_f = h["x"][...], h["F_minus_I"][...]
    order = list(range(t)) + list(reversed(range(t))) + [4, 4, 0, 8, 2]
    for rows_per_block in (1, 3, t):
        monkeypatch.setattr(ff, "READ_BLOCK_BYTES", rows_per_block * m * (3 * 4 + 9 * 2))
        with FinalFrames(tmp_path / "final.h5") as fr:
            for k in order:
                xk, fk = fr.x(k), fr.F(k)
                np.testing.assert_array_equal(xk, ref_x[rows[k]])
                np.testing.assert_array_equal(fk, ref_f[rows[k]].astype(np.float32) + np.eye(3, dtype=np.float32))
                xk[:] = -1.0  # a caller's change does not reach the cached block
                assert fr.x(k)[0, 0] == ref_x[rows[k]][0, 0]
            # the render stage's no-copy reads: views of the stored rows (F - I as stored, float16),
            # still the right rows after later reads have replaced the block they came from
            views = [(k, fr.x_view(k), fr.F_minus_I(k)) for k in order]
            for k, xv, dv in views:
                assert dv.dtype == np.float16
                np.testing.assert_array_equal(xv, ref_x[rows[k]])
                np.testing.assert_array_equal(dv, ref_f[rows[k]])


# ---------------------------------------------------------------- final_sim's per-frame work (#18)
def test_to_float16_is_numpy_astype_bit_for_bit():
    """Every finite float16 value, the midpoints between neighbours (ties to even) and the
    float32 numbers next to both, signed, plus random float32 bit patterns below F16_MAX."""
    h = np.arange(0, 0x7C00, dtype=np.uint16).view(np.float16).astype(np.float32)
    nxt = np.append(h[1:], np.float32(65520.0))
    mid = ((h.astype(np.float64) + nxt) / 2).astype(np.float32)   # exact: 12 significant bits
    v = np.concatenate([h, mid] + [np.nextafter(a, t) for a in (h, mid) for t in (np.float32(0), np.float32(np.inf))])
    rng = np.random.default_rng(3)
    bits = rng.integers(0, 2 ** 32, 400_000, dtype=np.uint64).astype(np.uint32).view(np.float32)
    v = np.concatenate([v, bits[np.isfinite(bits)]])
    v = v[np.abs(v) < F16_MAX]
    v = np.concatenate([v, -v, np.float32([-0.0])])
    assert len(v) > 800_000
    np.testing.assert_array_equal(to_float16(v).view(np.uint16), v.astype(np.float16).view(np.uint16))
    blocks = v[:200_001].reshape(-1, 1)   # several conversion blocks, an odd length
    np.testing.assert_array_equal(to_float16(blocks).view(np.uint16), blocks.astype(np.float16).view(np.uint16))


class _ReferenceWriter(FinalWriter):
    """final.h5 as FinalWriter wrote it before #18: a row appended per stored frame (two
    resizes), the entry-wise float16 check, numpy's float16 conversion, h5py's write."""

    def __init__(self, h5, particle_index, time, codec=None, to_source=None):
        super().__init__(h5, particle_index, time, codec, to_source)
        for name in ("x", "F_minus_I"):
            del h5[name]
        m = self.m
        self.dx = h5.create_dataset("x", (0, m, 3), np.float32, maxshape=(None, m, 3), chunks=(1, m, 3), **(codec or {}))
        self.dF = h5.create_dataset("F_minus_I", (0, m, 3, 3), np.float16, maxshape=(None, m, 3, 3),
                                    chunks=(1, m, 3, 3), **(codec or {}))

    def frame(self, k, x, F):
        dev = np.asarray(F, np.float32) - np.eye(3, dtype=np.float32)
        big = np.abs(dev) >= F16_MAX
        if big.any():
            raise SimulationError(f"frame {k}: {int(big.any(axis=(1, 2)).sum())} particles have |F - I| >= {F16_MAX:g} "
                                  "(the simulation exploded); final.h5 stores F - I in float16")
        r = self.rows
        self.dx.resize(r + 1, axis=0)
        self.dF.resize(r + 1, axis=0)
        self.dx[r] = np.asarray(x, np.float32)
        self.dF[r] = dev.astype(np.float16)
        self.frame_row[k] = r
        self.rows += 1
        sub = np.asarray(x, np.float64)[:: self._stride]
        sub = sub[np.isfinite(sub).all(axis=1)]
        if self._to_source is not None and sub.shape[0]:
            sub = np.asarray(self._to_source(sub), np.float64)
        if sub.shape[0]:
            b = np.percentile(sub, [1.0, 99.0], axis=0)
            self.lo, self.hi = np.minimum(self.lo, b[0]), np.maximum(self.hi, b[1])


def _frames(m, t, rng):
    """Frames that reach every branch: F = I at frame 0 (all-zero F - I: float16 subnormal
    path), NaN rows in x and F (the writer's and the figures' general paths), entries next to
    +-F16_MAX and in the float16 subnormal range, particles outside the unit cube."""
    x = rng.uniform(0.1, 0.9, (t, m, 3)).astype(np.float32)
    F = (np.eye(3) + rng.normal(0.0, 0.3, (t, m, 3, 3)) * rng.uniform(0, 3, (t, m, 1, 1))).astype(np.float32)
    F[0] = np.eye(3)
    F[2, :5] = np.eye(3) + rng.normal(0, 1e-6, (5, 3, 3))
    F[2, 5, 0, 1], F[2, 6, 1, 1] = 65503.0, -65500.0
    x[5, 3] = np.nan
    F[6, 7, 2, 2] = np.nan
    x[7, :10, 2] = -0.2
    return x, F


def _write(cls, path, x, F, held, truncate=None, to_source=None, figures=False, codec=None):
    """Frames through a writer; with ``figures`` as final_sim's frame callbacks hand them over
    (the figures take F - I from the writer)."""
    t, m = x.shape[:2]
    with h5py.File(path, "w") as h:
        w = cls(h, np.arange(m) * 3, np.arange(t) / 30.0, codec, to_source)
        fig = PhysicalFigures(t)
        for k in range(t):
            if k in held:
                w.hold(k)
                if figures:
                    fig.repeat(k)
            else:
                dev = w.frame(k, x[k], F[k])
                if figures:
                    fig.add(k, x[k], F[k], f_minus_i=dev)
        if truncate:
            w.truncate(truncate)
        w.finish({"stats": {"rows": w.rows}})
        return w.rows


@pytest.mark.parametrize("held, truncate, to_source, codec", [((3, 4, 9), None, False, "none"),
                                                              ((10, 11), 10, True, "none"), ((1,), None, False, "gzip")])
def test_final_writer_bit_for_bit_as_before(tmp_path, held, truncate, to_source, codec):
    """The writer (preallocated rows, H5Dwrite_chunk or with a codec h5py's write, to_float16,
    one-sum checks), fed as final_sim feeds it (the figures after each frame), writes the
    datasets and attributes of the writer it replaced."""
    from physgs_steps.final_frames import codec_options

    rng = np.random.default_rng(11)
    x, F = _frames(5000, 12, rng)   # 5000 > MOTION_ROWS: the strided motion subset
    to_src = (lambda p: p * 2.0 + np.array([0.1, -3.0, 7.0])) if to_source else None
    codec = codec_options(codec)
    ref = _write(_ReferenceWriter, tmp_path / "ref.h5", x, F, held, truncate, to_src, codec=codec)
    rows = _write(FinalWriter, tmp_path / "new.h5", x, F, held, truncate, to_src, True, codec)
    assert rows == ref
    with h5py.File(tmp_path / "ref.h5") as a, h5py.File(tmp_path / "new.h5") as b:
        assert sorted(a) == sorted(b) and dict(a.attrs) == dict(b.attrs)
        for k in a:
            assert a[k].shape == b[k].shape and a[k].dtype == b[k].dtype and a[k].chunks == b[k].chunks, k
            assert a[k].maxshape == b[k].maxshape and a[k].compression == b[k].compression, k
            assert a[k][()].tobytes() == b[k][()].tobytes(), k
        assert np.isnan(b["x"][5 - sum(h < 5 for h in held), 3]).all()   # the NaN row is stored as before
    with FinalFrames(tmp_path / "new.h5") as fr:
        assert fr.motion_box[0] == ("source" if to_source else "sim")


def test_final_writer_allocates_only_written_rows(tmp_path):
    """Rows are preallocated for every frame but chunks exist only where written: a clip held
    at rest after 3 of 150 frames takes 3 rows of space, and finish() shrinks x to 3 rows."""
    m, t = 20000, 150
    rng = np.random.default_rng(2)
    with h5py.File(tmp_path / "f.h5", "w") as h:
        w = FinalWriter(h, np.arange(m), np.arange(t) / 30.0)
        for k in range(t):
            w.frame(k, rng.random((m, 3), np.float32), np.eye(3, dtype=np.float32) + rng.random((m, 3, 3), np.float32)) \
                if k < 3 else w.hold(k)
        w.finish({})
    row = m * 3 * 4 + m * 9 * 2
    size = (tmp_path / "f.h5").stat().st_size
    assert 3 * row < size < 3 * row + 200_000, size
    with FinalFrames(tmp_path / "f.h5") as fr:
        assert fr.rows == 3 and fr.frame_row.tolist() == [0, 1] + [2] * (t - 2)


def test_final_writer_overflow_names_the_frame_and_stores_nothing_of_it(tmp_path):
    """The float16 overflow of F - I at frame 2 raises the SimulationError naming the frame, the
    particle count and float16, and leaves frame 2 unwritten (final_sim then fails without a
    final.h5: tests/test_mpm_stages.py)."""
    m, t = 100, 8
    rng = np.random.default_rng(4)
    x = rng.random((t, m, 3)).astype(np.float32)
    F = np.broadcast_to(np.eye(3, dtype=np.float32), (t, m, 3, 3)).copy()
    F[2, 7] *= 1e6
    with h5py.File(tmp_path / "f.h5", "w") as h:
        w = FinalWriter(h, np.arange(m), np.arange(t) / 30.0)
        w.frame(0, x[0], F[0])
        w.frame(1, x[1], F[1])
        with pytest.raises(SimulationError, match=r"frame 2: 1 particles have \|F - I\| >= 65504.*float16"):
            w.frame(2, x[2], F[2])
        assert w.rows == 2 and (w.frame_row[2:] == -1).all()


def _result_bits(r):
    import json

    return json.dumps(r, sort_keys=True)


def test_physical_figures_fast_path_as_general_path():
    """Frames without NaN/inf take PhysicalFigures._add_finite: every figure bit for bit that
    of the general path except the centre of mass (pairwise sum), which stays within the
    stated bound 2 (M - 1) 2^-53 mean|x| + one rounding; det3 as the cofactor expression on
    [M, 3, 3] views (the code before #18)."""
    rng = np.random.default_rng(8)
    m, t = 3000, 10
    x, F = _frames(m, t, rng)
    # positions spanning magnitudes and signs: sums that are not exact in float64
    x[4] = (rng.uniform(-1, 1, (m, 3)) * 10.0 ** rng.uniform(-9, 0, (m, 1))).astype(np.float32)
    eye = np.eye(3, dtype=np.float32)
    for inputs in ("float32", "float64"):
        fast, slow = PhysicalFigures(t, margin=0.05), PhysicalFigures(t, margin=0.05)
        for k in range(t):
            xk, Fk = (x[k], F[k]) if inputs == "float32" else (x[k].astype(np.float64), F[k].astype(np.float64))
            if k == 8:
                fast.repeat(k), slow.repeat(k)
                continue
            dev = (F[k] - eye) if np.isfinite(F[k]).all() and inputs == "float32" else None
            fast.add(k, xk, Fk, f_minus_i=dev)
            slow._add_general(k, xk, Fk)
        bound = 2 * (m - 1) * 2.0 ** -53 * np.nanmean(np.abs(x.astype(np.float64)), axis=1) + 2.0 ** -52 * np.abs(slow.com)
        bound[8] = bound[7]   # held: frame 7's centre
        assert (np.abs(fast.com - slow.com) <= bound + 1e-300).all()
        assert np.array_equal(np.isnan(fast.com), np.isnan(slow.com))
        a, b = fast.result(np.arange(t) / 30.0), slow.result(np.arange(t) / 30.0)
        ca, cb = a.pop("com_displacement"), b.pop("com_displacement")
        assert _result_bits(a) == _result_bits(b), inputs
        assert ca["value"] == pytest.approx(cb["value"], rel=1e-9, abs=1e-15)
        assert fast.n_nonfinite == slow.n_nonfinite > 0 and fast.out_frac_max == slow.out_frac_max > 0
    G = F[3].astype(np.float64)
    expr = (G[:, 0, 0] * (G[:, 1, 1] * G[:, 2, 2] - G[:, 1, 2] * G[:, 2, 1])
            - G[:, 0, 1] * (G[:, 1, 0] * G[:, 2, 2] - G[:, 1, 2] * G[:, 2, 0])
            + G[:, 0, 2] * (G[:, 1, 0] * G[:, 2, 1] - G[:, 1, 1] * G[:, 2, 0]))
    assert det3(F[3], np.float64).tobytes() == expr.tobytes() == det3(G).tobytes()
    assert det3(np.zeros((0, 3, 3))).shape == (0,)
