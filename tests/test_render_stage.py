"""The render stage end to end on tiny inputs: video written and read back, bad input."""
from __future__ import annotations

import json
import logging

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from physgs_steps.carrier import build_carrier, write_carrier
from physgs_steps.config import load_schema, section_defaults, validate
from physgs_steps.errors import ConfigError, InputError, RenderError
from physgs_steps.gaussians import GaussianScene
from physgs_steps.prepare import SceneTransform
from physgs_steps.render.cameras import look_at
from physgs_steps.render.stage import run
from physgs_steps.render.video import read_video
from physgs_steps.runtime import write_json
from physgs_steps.scene_io import save_gaussians

LOG = logging.getLogger("test.render")
T = 6


def _make_inputs(d, n=600, frames=T, nan_frame=None):
    """A red/blue blob of radius ~0.1 (source frame, metres) falling and squashing, in the sim frame."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(n, 3))
    pts = 0.1 * pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.uniform(0.8, 1.0, (n, 1))
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = np.where(pts[:, :1] > 0, [1.5, -1.5, -1.5], [-1.5, -1.5, 1.5])  # red +x half, blue -x half
    src = GaussianScene(means=pts + [0.0, 0.0, 0.2], log_scales=np.log(np.full((n, 3), 0.02)),
                        quats=np.tile([1.0, 0, 0, 0], (n, 1)), opacity_logits=np.full(n, 3.0), sh=sh)
    t = SceneTransform(R=Rotation.from_euler("z", 40, degrees=True).as_matrix(), scale=2.0,
                       src_center=np.array([0.0, 0.0, 0.2]), sim_center=np.array([0.5, 0.5, 0.5]))
    sim = t.to_sim_scene(src)
    save_gaussians(sim, d / "scene.ply")
    write_json(d / "transform.json", t.to_dict())
    x = np.stack([sim.means - [0, 0, 0.02 * k] for k in range(frames)]).astype(np.float32)
    F = np.tile(np.eye(3, dtype=np.float32), (frames, n, 1, 1))
    F[:, :, 2, 2] = np.linspace(1.0, 0.7, frames)[:, None]
    if nan_frame is not None:
        x[nan_frame, :5] = np.nan
    write_final_h5(d / "final.h5", x, F, np.arange(frames) / 30.0, to_source=t.to_source)
    rows = np.arange(n)  # every gaussian is a particle ('gaussians' mode): identity carrier
    write_carrier(d / "carrier.h5", build_carrier(sim.means, np.zeros(n, np.int32), sim.means, np.zeros(n, np.int32),
                                                  rows, "gaussians", 1, 0.01))
    return {"frames": str(d / "final.h5"), "scene": str(d / "scene.ply"), "transform": str(d / "transform.json"),
            "carrier": str(d / "carrier.h5")}


def write_final_h5(path, x, F, time, hold=(), to_source=None):
    """final.h5 (format 2) with frames x [T, M, 3], F [T, M, 3, 3]; frames in ``hold`` repeat the one before."""
    from physgs_steps.final_frames import FinalWriter

    with h5py.File(path, "w") as f:
        w = FinalWriter(f, np.arange(x.shape[1]), time, to_source=to_source)
        for k in range(len(time)):
            w.hold(k) if k in hold else w.frame(k, x[k], F[k])
        w.finish({"stats": {"test": True}})


def _outputs(d):
    return {"video": str(d / "out" / "video.mp4"), "contact_sheet": str(d / "out" / "contact_sheet.png"),
            "report": str(d / "out" / "render.json")}


def _cfg(render=None, camera=None):
    r = section_defaults("render")
    r.update({"backend": "cpu", "width": 64, "height": 48, "contact_sheet": {"frames": 4, "columns": 2, "tile_width": 64}})
    r.update(render or {})
    return {"render": r, "scene": {"camera": camera or {"azimuth_deg": -90.0, "elevation_deg": 10.0}}, "device": "cpu"}


def test_video_contact_sheet_and_report(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    summary = run(inputs, out, _cfg({"png_frames": True, "crf": 0}), LOG)
    assert summary["frames"] == T
    video = read_video(out["video"])
    assert video.shape == (T, 48, 64, 3)
    pngs = sorted((tmp_path / "out" / "frames").glob("frame_*.png"))
    assert [p.name for p in pngs] == [f"frame_{k:05d}.png" for k in range(T)]
    from PIL import Image
    first = np.asarray(Image.open(pngs[0]))
    assert np.abs(video[0].astype(int) - first.astype(int)).mean() < 3.0  # yuv420p chroma subsampling only
    # camera on -y looking at +y: +x (red half) is on the image's right, -x (blue) on the left
    assert first[:, 40:, 0].mean() > first[:, 40:, 2].mean() + 30
    assert first[:, :24, 2].mean() > first[:, :24, 0].mean() + 30
    # the object falls: its coverage moves down the image
    rows = lambda img: np.nonzero((img.astype(int).sum(-1) < 600).any(axis=1))[0]  # noqa: E731
    assert rows(video[-1]).mean() > rows(video[0]).mean()
    sheet = np.asarray(Image.open(out["contact_sheet"]))
    assert sheet.shape[1] > 2 * 64 and sheet.shape[0] > 2 * 48
    rep = json.loads(open(out["report"]).read())
    assert rep["backend"] == "cpu" and rep["frames_rendered"] == T and rep["sh_degree"] == 1
    assert rep["coverage"]["min"] > 0.02 and rep["empty_frames"] == [] and rep["clipped_frames"] == []


def test_every_nth_and_odd_size_padding(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    run(inputs, out, _cfg({"every_nth": 2, "width": 45, "height": 33}), LOG)
    video = read_video(out["video"])
    assert video.shape == (3, 34, 46, 3)


def test_nan_frame_is_an_error_or_hidden(tmp_path):
    inputs = _make_inputs(tmp_path, nan_frame=3)
    out = _outputs(tmp_path)
    with pytest.raises(RenderError, match="frame 3: 5 of 600"):
        run(inputs, out, _cfg(), LOG)
    assert not (tmp_path / "out" / "video.mp4").exists()
    run(inputs, out, _cfg({"on_nonfinite": "hide"}), LOG)
    rep = json.loads(open(out["report"]).read())
    assert rep["hidden_nonfinite"] == {"3": 5}
    assert read_video(out["video"]).shape[0] == T


def test_camera_inside_object_or_looking_away(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    with pytest.raises(RenderError, match="inside the object"):
        run(inputs, out, _cfg(camera={"look_at": [0.0, 0.0, 0.15], "radius": 0.02}), LOG)
    assert not (tmp_path / "out" / "video.mp4").exists()
    # behind: an INRIA camera looking away from the object
    vm = look_at([0.0, -1.0, 0.2], [0.0, -2.0, 0.2])
    c2w = np.linalg.inv(vm)
    cams = [{"position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(), "fx": 60.0, "fy": 60.0,
             "width": 64, "height": 48}]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    with pytest.raises(RenderError, match="behind the near plane"):
        run(dict(inputs, cameras=str(tmp_path / "cameras.json")), out, _cfg(camera={"mode": "cameras_json"}), LOG)


def test_object_out_of_view_is_an_error(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    # in front of the camera but far outside the narrow field of view
    with pytest.raises(RenderError, match="no rendered frame shows anything"):
        run(inputs, out, _cfg(camera={"look_at": [0.5, 0.5, 0.2], "radius": 1.0, "azimuth_deg": 180.0,
                                      "elevation_deg": 0.0, "fov_deg": 5.0}), LOG)
    assert not (tmp_path / "out" / "video.mp4").exists()
    assert not (tmp_path / "out" / "render.json").exists()


def test_cameras_json_mode(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    vm = look_at([0.0, -0.8, 0.3], [0.0, 0.0, 0.15])
    c2w = np.linalg.inv(vm)
    cams = [{"img_name": "view0", "position": c2w[:3, 3].tolist(), "rotation": c2w[:3, :3].tolist(),
             "fx": 400.0, "fy": 400.0, "width": 320, "height": 240}]
    (tmp_path / "cameras.json").write_text(json.dumps(cams))
    run(dict(inputs, cameras=str(tmp_path / "cameras.json")), out, _cfg(camera={"mode": "cameras_json"}), LOG)
    rep = json.loads(open(out["report"]).read())
    assert rep["camera"]["name"] == "view0" and (rep["width"], rep["height"]) == (64, 48)
    with pytest.raises(ConfigError, match="camera_index"):
        run(dict(inputs, cameras=str(tmp_path / "cameras.json")), out,
            _cfg(camera={"mode": "cameras_json", "camera_index": 3}), LOG)


def test_bad_files_and_config(tmp_path):
    inputs = _make_inputs(tmp_path)
    out = _outputs(tmp_path)
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f["x"] = np.zeros((2, 600, 3), np.float32)
    with pytest.raises(InputError, match="bad.h5.*format None"):  # an old or foreign file
        run(dict(inputs, frames=str(tmp_path / "bad.h5")), out, _cfg(), LOG)
    with h5py.File(tmp_path / "bad.h5", "a") as f:
        f.attrs["format"] = "physgs-final/2"
    with pytest.raises(InputError, match="missing datasets"):
        run(dict(inputs, frames=str(tmp_path / "bad.h5")), out, _cfg(), LOG)
    with h5py.File(tmp_path / "bad2.h5", "w") as f:
        f.attrs["format"] = "physgs-final/2"
        f["x"] = np.zeros((2, 600, 3), np.float32)
        f["F_minus_I"] = np.zeros((2, 600, 3, 3), np.float16)
        f["particle_index"] = np.arange(600, dtype=np.int64)
        f["time"] = np.zeros(3)
        f["frame_row"] = np.array([0, 1, 2], np.int32)
    with pytest.raises(InputError, match="frame_row spans"):
        run(dict(inputs, frames=str(tmp_path / "bad2.h5")), out, _cfg(), LOG)
    with pytest.raises(InputError, match="carrier.h5.*has 599 gaussians but scene.ply has 600"):
        from physgs_steps.carrier import load_carrier

        c = load_carrier(inputs["carrier"])
        c.index, c.weight, c.static = c.index[:-1], c.weight[:-1], c.static[:-1]
        write_carrier(tmp_path / "carrier.h5", c)
        run(inputs, out, _cfg(), LOG)
    schema = load_schema("render.schema.yaml")
    with pytest.raises(ConfigError, match="render.width"):
        validate({"width": 0}, schema, "test", "render")
    with pytest.raises(ConfigError, match="render.backend"):
        validate({"backend": "opengl"}, schema, "test", "render")
    with pytest.raises(ConfigError, match="camera.elevation_deg"):
        validate({"elevation_deg": 95}, load_schema("scene_camera.schema.yaml"), "test", "camera")


def test_final_frames_sheet_shows_each_videos_last_frame(tmp_path):
    """The before/after sheet (docs/MEASURED.md, rigid instances): one tile per video, its last frame."""
    from physgs_steps.render.video import VideoWriter, final_frames_sheet

    paths = []
    for k, colour in enumerate(([255, 0, 0], [0, 0, 255])):
        p = tmp_path / f"v{k}.mp4"
        w = VideoWriter(p, 64, 48, 10.0, crf=0)
        w.append(np.full((48, 64, 3), 255, np.uint8))
        w.append(np.broadcast_to(np.array(colour, np.uint8), (48, 64, 3)).copy())
        w.close()
        paths.append(p)
    sheet = final_frames_sheet(paths, ["main", "branch"], tmp_path / "s.png", columns=2, tile_width=64)
    assert (tmp_path / "s.png").exists()
    left, right = sheet[10:30, 10:50].reshape(-1, 3).mean(0), sheet[10:30, 78:118].reshape(-1, 3).mean(0)
    assert left[0] > 200 and left[2] < 60 and right[2] > 200 and right[0] < 60  # last frames, in order
    with pytest.raises(RenderError, match="one label per video"):
        final_frames_sheet(paths, ["main"], tmp_path / "t.png")


def test_frames_per_call_bounds_gpu_memory():
    """gsplat's frames per call: render.batch at most, render.batch_gaussians gaussian-frames at most."""
    from physgs_steps.render.stage import frames_per_call

    assert frames_per_call(16, 2_000_000, 20_000, 8_388_608, 512 * 512) == 16
    assert frames_per_call(16, 2_000_000, 300_000, 8_388_608, 512 * 512) == 6
    assert frames_per_call(16, 2_000_000, 300_000, 8_388_608, 1920 * 1080) == 4
    assert frames_per_call(16, 2_000_000, 1_000_000, 8_388_608, 512 * 512) == 2
    assert frames_per_call(16, 2_000_000, 10_000_000) == 1
