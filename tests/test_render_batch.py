"""The render stage's batched loop: the frames of a batch are deformed, checked against their
cameras and counted (coverage) together, with one read-back per batch. Each frame gets the
bits it gets alone, and errors name the same first frame as the frame-by-frame loop
(PHYSGS_RENDER_PER_FRAME=1). The unit tests run on CUDA too where it is present, the stage on
gsplat where it loads."""
from __future__ import annotations

import json
import logging

import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from physgs_steps.carrier import build_carrier, particle_spacing, representatives, write_carrier
from physgs_steps.config import section_defaults
from physgs_steps.errors import RenderError
from physgs_steps.final_frames import FinalWriter
from physgs_steps.gaussians import GaussianScene
from physgs_steps.prepare import SceneTransform
from physgs_steps.render import cameras as C
from physgs_steps.render.deform import CarrierMap, SourceMap, deform, deform_frames, polar_rotation, rest_gaussians
from physgs_steps.render.stage import PER_FRAME_ENV, check_cameras, coverage_counts, run
from physgs_steps.runtime import write_json
from physgs_steps.scene_io import save_gaussians

LOG = logging.getLogger("test.render_batch")
# the stacks against single frames on every device here: on CUDA other kernels (cuBLAS batched
# products, reductions) run than on the CPU, and the bits are checked there too
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Same shape, dtype and bytes."""
    return a.shape == b.shape and a.dtype == b.dtype and a.contiguous().view(torch.uint8).equal(b.contiguous().view(torch.uint8))


def _twisting_frames(x0: np.ndarray, frames: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """x [T, M, 3], F [T, M, 3, 3]: a body turning, squashing and falling, with per-particle
    noise in F growing with the frame (the polar rotations converge after different numbers of
    iterations in different frames)."""
    c = x0.mean(axis=0)
    xs, Fs = [], []
    for k in range(frames):
        rot = Rotation.from_euler("zx", [12.0 * k, 5.0 * k], degrees=True).as_matrix()
        A = rot @ np.diag([1.0, 1.0, 1.0 - 0.04 * k])
        xs.append((x0 - c) @ A.T + c - [0.0, 0.0, 0.01 * k])
        Fs.append(A + rng.normal(0.0, 0.02 * k, (len(x0), 3, 3)))
    return np.asarray(xs, np.float32), np.asarray(Fs, np.float32)


def _inputs(d, frames=8, hold=(), nan_frame=None, away_frame=None):
    """A scene of 500 gaussians with SH degree 1 carried by ~1 particle per sub-cell (budget
    carrier, 8 drivers, tears cut) through twisting frames; frames in ``hold`` repeat the frame
    before; ``nan_frame`` gets 5 NaN particles; ``away_frame`` is moved 3 m along -y (behind
    the camera of :func:`_camera_json`)."""
    rng = np.random.default_rng(0)
    n = 500
    pts = rng.normal(size=(n, 3))
    pts = 0.1 * pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.uniform(0.7, 1.0, (n, 1))
    src = GaussianScene(means=pts + [0.0, 0.0, 0.2], log_scales=np.log(rng.uniform(0.01, 0.03, (n, 3))),
                        quats=rng.normal(size=(n, 4)), opacity_logits=np.full(n, 2.0), sh=rng.normal(0, 0.5, (n, 4, 3)))
    t = SceneTransform(R=Rotation.from_euler("z", 40, degrees=True).as_matrix(), scale=2.0,
                       src_center=np.array([0.0, 0.0, 0.2]), sim_center=np.array([0.5, 0.5, 0.5]))
    sim = t.to_sim_scene(src)
    save_gaussians(sim, d / "scene.ply")
    write_json(d / "transform.json", t.to_dict())
    s = particle_spacing(1 / 32, 4)
    reps = representatives(sim.means, s)
    c = build_carrier(sim.means, np.zeros(n, np.int32), sim.means[reps], np.zeros(len(reps), np.int32), reps,
                      "budget", 8, s)
    write_carrier(d / "carrier.h5", c)
    x, F = _twisting_frames(sim.means[reps][c.drivers], frames, rng)
    if nan_frame is not None:
        x[nan_frame, :5] = np.nan
    if away_frame is not None:
        x[away_frame] += 2.0 * 3.0 * np.asarray(t.R)[:, 1] * -1.0  # 3 m along -y of the source frame (scale 2)
    with h5py.File(d / "final.h5", "w") as f:
        w = FinalWriter(f, c.drivers, np.arange(frames) / 30.0, to_source=t.to_source)
        for k in range(frames):
            w.hold(k) if k in hold else w.frame(k, x[k], F[k])
        w.finish({"stats": {"test": True}})
    return {"frames": str(d / "final.h5"), "scene": str(d / "scene.ply"), "transform": str(d / "transform.json"),
            "carrier": str(d / "carrier.h5")}


def _camera_json(d) -> str:
    """cameras.json with one camera at y = -0.8 looking at the blob."""
    c2w = np.linalg.inv(C.look_at([0.0, -0.8, 0.3], [0.0, 0.0, 0.15]))
    (d / "cameras.json").write_text(json.dumps([{"img_name": "v", "position": c2w[:3, 3].tolist(),
                                                 "rotation": c2w[:3, :3].tolist(), "fx": 60.0, "fy": 60.0,
                                                 "width": 64, "height": 48}]))
    return str(d / "cameras.json")


def _cfg(render=None, camera=None):
    r = section_defaults("render")
    r.update({"backend": "cpu", "width": 64, "height": 48, "png_frames": True,
              "contact_sheet": {"frames": 4, "columns": 2, "tile_width": 64}})
    r.update(render or {})
    return {"render": r, "scene": {"camera": camera or {"azimuth_deg": -90.0, "elevation_deg": 10.0}}, "device": "cpu"}


def _render(d, inputs, cfg, name, monkeypatch, per_frame: bool) -> tuple[dict, dict]:
    """Run the stage into d/name; ({png name: bytes}, render.json)."""
    monkeypatch.setenv(PER_FRAME_ENV, "1" if per_frame else "0")
    out = {"video": str(d / name / "video.mp4"), "contact_sheet": str(d / name / "contact_sheet.png"),
           "report": str(d / name / "render.json")}
    run(inputs, out, cfg, LOG)
    pngs = {p.name: p.read_bytes() for p in sorted((d / name / "frames").glob("*.png"))}
    return pngs, json.loads((d / name / "render.json").read_text())


@pytest.mark.parametrize("batch, camera, deform_rows", [
    (16, None, None), (16, None, 1),  # 1: the batch's states deformed one frame a stack (stage.DEFORM_ROWS)
    (2, {"azimuth_deg": -90.0, "elevation_deg": 10.0, "azimuth_per_frame_deg": 7.0}, None)])
def test_batched_loop_renders_the_per_frame_loops_frames_bit_for_bit(tmp_path, monkeypatch, batch, camera,
                                                                    deform_rows):
    """Batch larger than the video (16 > 8 frames) with a still camera, and batches of 2 with a
    turning one; held frames (2, 3 and 7 repeat the frame before: the batch of frames 2 and 3
    has no state of its own), a frame with hidden rows (5)."""
    import physgs_steps.render.stage as S

    if deform_rows is not None:
        monkeypatch.setattr(S, "DEFORM_ROWS", deform_rows)
    inputs = _inputs(tmp_path, hold=(2, 3, 7), nan_frame=5)
    cfg = _cfg({"batch": batch, "on_nonfinite": "hide"}, camera)
    one, rep1 = _render(tmp_path, inputs, cfg, "one", monkeypatch, per_frame=True)
    many, rep = _render(tmp_path, inputs, cfg, "many", monkeypatch, per_frame=False)
    assert len(one) == 8 and one.keys() == many.keys()
    assert [k for k in one if one[k] != many[k]] == []
    assert (tmp_path / "one" / "contact_sheet.png").read_bytes() == (tmp_path / "many" / "contact_sheet.png").read_bytes()
    for key in ("coverage", "clipped_frames", "hidden_nonfinite", "reused", "empty_frames"):
        assert rep[key] == rep1[key], key
    assert rep["hidden_nonfinite"] == {"5": rep["hidden_nonfinite"]["5"]} and rep["hidden_nonfinite"]["5"] > 0
    assert rep["reused"]["states"] == 3 and rep["reused"]["images"] == (3 if camera is None else 0)
    assert rep["timings"]["frames_per_call"] == min(batch, 16) and rep["sh_degree"] == 1
    assert len({one[k] for k in one}) > 4  # the frames differ: the twist is drawn


@pytest.mark.parametrize("nan_frame, away_frame, message", [
    (None, 3, "frame 3: every gaussian is behind the near plane"),
    (4, 3, "frame 3: every gaussian is behind the near plane"),   # the earlier frame's camera error first
    (2, 3, "frame 2: 5 of"),                                       # the earlier frame's NaN error first
])
def test_batched_loop_raises_for_the_same_first_frame(tmp_path, monkeypatch, nan_frame, away_frame, message):
    inputs = dict(_inputs(tmp_path, frames=6, nan_frame=nan_frame, away_frame=away_frame), cameras=_camera_json(tmp_path))
    cfg = _cfg(camera={"mode": "cameras_json"})
    for per_frame in (True, False):
        with pytest.raises(RenderError, match=message):
            _render(tmp_path, inputs, cfg, "out", monkeypatch, per_frame)
        assert not (tmp_path / "out" / "video.mp4").exists()


def _blob(rng, n, centre, device="cpu") -> torch.Tensor:
    return torch.from_numpy(rng.normal(0.0, 0.1, (n, 3)) + centre).float().to(device)


@pytest.mark.parametrize("device", DEVICES)
def test_camera_check_of_a_batch_raises_for_the_same_frame_as_frame_by_frame(device):
    """Frame 3 of 5 has every centre behind the near plane; frame 1 clips a few (warned);
    frame 4 (after the error) sits inside the object."""
    rng = np.random.default_rng(2)
    cam = C.Camera(C.look_at([0.0, -1.0, 0.0], [0.0, 0.0, 0.0]), C.intrinsics_from_fov(50, 64, 48), 64, 48)
    means = [_blob(rng, 3000, c, device) for c in ([0, 0, 0], [0.3, -0.9, 0], [0, 0.1, 0], [0, -2.0, 0], [0, -1.0, 0])]
    frames = [10, 11, 12, 13, 14]
    clipped_b, clipped_1 = [], []
    with pytest.raises(RenderError) as batched:
        check_cameras(frames, means, [cam] * 5, 0.01, clipped_b)
    with pytest.raises(RenderError) as single:
        for f, m in zip(frames, means):
            check_cameras([f], [m], [cam], 0.01, clipped_1)
    assert str(batched.value) == str(single.value) and str(batched.value).startswith("frame 13: every gaussian is behind")
    assert clipped_b == clipped_1 and [f for f, _ in clipped_b] == [11]
    with pytest.raises(RenderError, match="frame 14: the camera at .* is inside the object"):
        check_cameras(frames[4:], means[4:], [cam], 0.01, [])
    # sets of other sizes (hidden rows left out) and an empty one: one view at a time, the same checks
    sizes = [means[0], means[1][:2000], means[2][:0], means[4]]
    cams = [cam, C.orbit_cameras([0, 0, 0], 1.5, 1, 20.0, 40.0, 64, 48)[0], cam, cam]
    assert C.check_views(sizes, cams, 0.01) == [C.check_view(m, c, 0.01) for m, c in zip(sizes, cams)]
    assert C.check_views(means, [cam] * 5, 0.01) == [C.check_view(m, cam, 0.01) for m in means]


@pytest.mark.parametrize("device", DEVICES)
def test_coverage_of_a_batch_equals_frame_by_frame(device):
    rng = np.random.default_rng(3)
    alpha = torch.from_numpy(rng.uniform(0.0, 1.0, (5, 17, 23)).astype(np.float32)).to(device)
    alpha[2] = 0.5  # exactly at the threshold: not covered
    alpha[3, :4] = 0.0
    counts = coverage_counts(alpha)
    assert counts == coverage_counts(alpha, per_frame=True) == [int((a > 0.5).sum()) for a in alpha]
    assert counts[2] == 0 and all(isinstance(c, int) for c in counts)


@pytest.mark.parametrize("device", DEVICES)
def test_deform_of_a_stack_gives_each_frames_bits(device):
    """deform_frames of B frames = B calls of one frame (deform), bit for bit: a partial index,
    hidden rows, polar rotations of frames converging after different iteration counts."""
    rng = np.random.default_rng(4)
    t = SceneTransform(R=Rotation.from_euler("zyx", [30, -20, 10], degrees=True).as_matrix(), scale=2.5,
                       src_center=np.array([0.1, -0.2, 0.3]), sim_center=np.array([0.5, 0.5, 0.4]))
    smap = SourceMap.from_transform(t)
    n = 2003  # not a multiple of the CPU's vector width: the scalar tails of the vectorised loops
    src = GaussianScene(means=rng.normal(0, 0.05, (n, 3)), log_scales=np.log(rng.uniform(0.003, 0.01, (n, 3))),
                        quats=rng.normal(size=(n, 4)), opacity_logits=rng.normal(2.0, 1.0, n), sh=rng.normal(0, 0.4, (n, 4, 3)))
    rest = rest_gaussians(t.to_sim_scene(src), smap, device)
    index = torch.from_numpy(np.sort(rng.choice(n, 1500, replace=False))).to(device)
    x, F = _twisting_frames(rng.normal(0.5, 0.05, (1500, 3)), 5, rng)
    F[3, :7] *= -1.0  # inverted rows: the SVD path
    xt = smap.points(torch.from_numpy(x).to(device, torch.float64)).float()
    Ft = smap.linear(torch.from_numpy(F).to(device))
    hide = torch.from_numpy(rng.uniform(size=(5, 1500)) < 0.05).to(device)
    for h in (None, hide):
        stack = deform_frames(rest, index, xt, Ft, True, h)
        for b in range(5):
            one = deform(rest, index, xt[b], Ft[b], None, True, None if h is None else h[b])
            for key in ("means", "covars", "opacities", "rotations"):
                assert _bits(getattr(stack[b], key), getattr(one, key)), (b, key)
    R = polar_rotation(Ft)
    assert all(_bits(R[b], polar_rotation(Ft[b])) for b in range(5))
    # frames of 15 rows: alone, the CPU computes them in the scalar tail of its vectorised loops,
    # in a stack in the vector body (whose pow rounds differently)
    Fs = torch.from_numpy(_twisting_frames(rng.normal(size=(15, 3)), 40, rng)[1]).to(device)  # [40, 15, 3, 3]
    R = polar_rotation(Fs)
    assert all(_bits(R[b], polar_rotation(Fs[b])) for b in range(40))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cut", [True, False])
def test_carrier_of_a_stack_gives_each_frames_bits(cut, device):
    rng = np.random.default_rng(5)
    gx = rng.uniform(0.4, 0.6, (3001, 3))
    s = particle_spacing(1 / 32, 4)
    reps = representatives(gx, s)
    c = build_carrier(gx, np.zeros(len(gx), np.int32), gx[reps], np.zeros(len(reps), np.int32), reps, "budget", 8, s)
    if not cut:
        c.spacing = 0.0  # no tear distance
    x0 = gx[reps][np.argsort(reps)]
    cmap = CarrierMap.build(c, c.drivers, gx, x0, device)
    cmap.chunk = 1000  # several passes
    x, F = _twisting_frames(x0, 4, rng)
    x[2, :40, 0] += 0.2  # a tear in frame 2
    x, F = torch.from_numpy(x).to(device), torch.from_numpy(F).to(device)
    xs, Fs = cmap.apply(x, F)
    for b in range(4):
        x1, F1 = cmap.apply(x[b], F[b])
        assert _bits(xs[b], x1) and _bits(Fs[b], F1)


@pytest.mark.gpu
def test_batched_loop_on_gsplat_renders_the_per_frame_loops_frames_bit_for_bit(tmp_path, monkeypatch):
    """The same on the GPU renderer (skipped without gsplat/CUDA): frames of a batch deformed in
    one stack on CUDA, against frame by frame."""
    from physgs_steps.render.gsplat_backend import cuda_ready

    ok, why = cuda_ready()
    if not ok:
        pytest.skip(f"gsplat/CUDA not usable: {why}")
    inputs = _inputs(tmp_path, hold=(2, 3, 7), nan_frame=5)
    cfg = _cfg({"backend": "gsplat", "batch": 3, "on_nonfinite": "hide"},
               {"azimuth_deg": -90.0, "elevation_deg": 10.0, "azimuth_per_frame_deg": 7.0})
    cfg["device"] = "cuda"
    one, rep1 = _render(tmp_path, inputs, cfg, "one", monkeypatch, per_frame=True)
    many, rep = _render(tmp_path, inputs, cfg, "many", monkeypatch, per_frame=False)
    assert len(one) == 8 and [k for k in one if one[k] != many.get(k)] == []
    for key in ("coverage", "clipped_frames", "hidden_nonfinite", "reused", "empty_frames"):
        assert rep[key] == rep1[key], key
    assert rep["backend"] == "gsplat" and rep["timings"]["frames_per_call"] == 3
