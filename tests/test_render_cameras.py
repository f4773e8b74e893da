"""Cameras: look-at and orbit geometry, INRIA cameras.json, bad input."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from physgs_steps.errors import ConfigError, InputError, RenderError
from physgs_steps.render.cameras import Camera, check_view, intrinsics_from_fov, load_inria_cameras, look_at, orbit_cameras


def _project(cam: Camera, p) -> np.ndarray:
    pc = cam.viewmat[:3, :3] @ np.asarray(p, float) + cam.viewmat[:3, 3]
    return np.array([cam.K[0, 0] * pc[0] / pc[2] + cam.K[0, 2], cam.K[1, 1] * pc[1] / pc[2] + cam.K[1, 2], pc[2]])


def test_look_at_centres_target_and_keeps_up_up():
    cam = Camera(look_at([1.0, -2.0, 0.5], [0.1, 0.2, 0.3]), intrinsics_from_fov(40, 64, 48), 64, 48)
    u, v, z = _project(cam, [0.1, 0.2, 0.3])
    assert (u, v) == pytest.approx((32.0, 24.0)) and z > 0
    assert _project(cam, [0.1, 0.2, 0.4])[1] < 24.0  # higher in the world = higher in the image (smaller v)
    assert np.allclose(cam.position, [1.0, -2.0, 0.5])
    assert np.allclose(cam.viewmat[:3, :3] @ cam.viewmat[:3, :3].T, np.eye(3))


def test_orbit_cameras_geometry():
    cams = orbit_cameras([0.0, 0.0, 1.0], 2.0, 4, 30.0, 50.0, 32, 32)
    assert len(cams) == 4
    for i, c in enumerate(cams):
        d = c.position - [0.0, 0.0, 1.0]
        assert np.linalg.norm(d) == pytest.approx(2.0)
        assert math.degrees(math.asin(d[2] / 2.0)) == pytest.approx(30.0)
        assert math.degrees(math.atan2(d[1], d[0])) % 360 == pytest.approx((90.0 * i) % 360, abs=1e-9)
        assert _project(c, [0.0, 0.0, 1.0])[:2] == pytest.approx([16.0, 16.0])
    # vertical field of view
    assert 2 * math.degrees(math.atan(16 / cams[0].K[1, 1])) == pytest.approx(50.0)


def test_orbit_bad_values():
    with pytest.raises(ConfigError, match="elevation"):
        orbit_cameras([0, 0, 0], 1.0, 3, 80.0, 40.0, 16, 16, elevation_step_deg=5.0)
    with pytest.raises(ConfigError, match="radius"):
        orbit_cameras([0, 0, 0], 1.0, 3, 10.0, 40.0, 16, 16, radius_step=-0.6)
    with pytest.raises(ConfigError, match="empty"):
        orbit_cameras([0, 0, 0], 1.0, 1, 10.0, 40.0, 0, 16)
    with pytest.raises(RenderError, match="empty"):
        Camera(np.eye(4), np.eye(3), 0, 10)


def test_inria_cameras_json_roundtrip(tmp_path):
    ref = Camera(look_at([0.3, -1.2, 0.4], [0.0, 0.0, 0.05]), np.array([[500.0, 0, 400], [0, 510.0, 300], [0, 0, 1]]), 800, 600)
    c2w = np.linalg.inv(ref.viewmat)
    entry = {"id": 0, "img_name": "IMG_0001", "width": 800, "height": 600, "position": c2w[:3, 3].tolist(),
             "rotation": c2w[:3, :3].tolist(), "fx": 500.0, "fy": 510.0}
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps([entry, dict(entry, id=1, img_name="IMG_0002")]))
    cams = load_inria_cameras(path)
    assert len(cams) == 2 and cams[0].name == "IMG_0001"
    assert np.allclose(cams[0].viewmat, ref.viewmat) and np.allclose(cams[0].K, ref.K)
    half = cams[0].resized(400, 300)
    assert half.K[0, 0] == pytest.approx(250.0) and half.K[1, 2] == pytest.approx(150.0)


@pytest.mark.parametrize("content, problem", [
    ("not json", "not valid JSON"),
    ("[]", "non-empty"),
    ('[{"position": [0, 0, 0]}]', "lacks"),
    ('[{"position": [0, 0], "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1, "width": 4, "height": 4}]', "position must be"),
    ('[{"position": [0, 0, 0], "rotation": [[2,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1, "width": 4, "height": 4}]', "rotation"),
    ('[{"position": [0, 0, 0], "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1, "width": 0, "height": 4}]', "width/height"),
])
def test_inria_cameras_bad_files(tmp_path, content, problem):
    path = tmp_path / "cameras.json"
    path.write_text(content)
    with pytest.raises(InputError, match=problem):
        load_inria_cameras(path)
    with pytest.raises(InputError, match="does not exist"):
        load_inria_cameras(tmp_path / "missing.json")


def test_check_view_inside_and_behind():
    rng = np.random.default_rng(0)
    means = rng.uniform(-0.2, 0.2, (5000, 3))
    outside = orbit_cameras([0, 0, 0], 1.0, 1, 20.0, 40.0, 64, 64)[0]
    v = check_view(means, outside, 0.01)
    assert v.frac_behind == 0.0 and not v.inside_box and v.frac_in_view > 0.99
    inside = Camera(look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]), intrinsics_from_fov(40, 64, 64), 64, 64)
    v = check_view(means, inside, 0.01)
    assert v.inside_box and 0.4 < v.frac_behind < 0.6
    away = Camera(look_at([2.0, 0.0, 0.0], [3.0, 0.0, 0.0]), intrinsics_from_fov(40, 64, 64), 64, 64)
    assert check_view(means, away, 0.01).frac_behind == 1.0
    assert v.inside_box is True and check_view(means, outside, 0.01).inside_box is None  # no box where nothing is behind


def test_check_view_matches_numpy_reference():
    """The torch check (one read-back) gives the fractions and the percentile box of the plain numpy
    computation, for cameras outside, inside and at the edge of the centres, and on a subsample."""
    import torch

    rng = np.random.default_rng(1)
    means = rng.normal(0.0, 0.1, (30001, 3))
    cams = [orbit_cameras([0, 0, 0], 1.0, 1, 20.0, 40.0, 64, 48)[0],
            Camera(look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]), intrinsics_from_fov(60, 64, 48), 64, 48),
            Camera(look_at([0.0, 0.23, 0.0], [0.0, -1.0, 0.0]), intrinsics_from_fov(50, 64, 48), 64, 48),
            Camera(look_at([0.31, 0.0, 0.0], [1.0, 0.0, 0.0]), intrinsics_from_fov(50, 64, 48), 64, 48)]
    for cam in cams:
        m = means[:: int(np.ceil(len(means) / 20000))]
        pc = m @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        z = pc[:, 2]
        front = z >= 0.01
        zf = np.maximum(z, 0.01)
        u = cam.K[0, 0] * pc[:, 0] / zf + cam.K[0, 2]
        v_ = cam.K[1, 1] * pc[:, 1] / zf + cam.K[1, 2]
        in_img = front & (u >= 0) & (u < cam.width) & (v_ >= 0) & (v_ < cam.height)
        lo, hi = np.percentile(m, [2.0, 98.0], axis=0)
        inside = bool(((cam.position >= lo) & (cam.position <= hi)).all())
        for arg in (means, torch.from_numpy(means).float()):
            got = check_view(arg, cam, 0.01)
            assert got.n == len(m)
            tol = 1e-12 if isinstance(arg, np.ndarray) else 2e-3  # float32 centres move a few across the bounds
            assert abs(got.frac_behind - (1.0 - front.mean())) <= tol
            assert abs(got.frac_in_view - in_img.mean()) <= tol
            if got.frac_behind > 0:
                assert got.inside_box == inside
            else:
                assert got.inside_box is None
