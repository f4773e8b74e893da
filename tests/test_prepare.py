"""Tests of the prepare stage: normalisation into the simulation domain, filters, transform.json."""
from __future__ import annotations

import json
import logging
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import yaml

from physgs_steps import load_gaussians, prepare, save_gaussians
from physgs_steps.errors import ConfigError, InputError
from physgs_steps.gaussians import GaussianScene

LOG = logging.getLogger("test.prepare")
SCHEMAS = Path(__file__).resolve().parents[1] / "workflow" / "schemas"
AXES = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1], "-x": [-1, 0, 0], "-y": [0, -1, 0], "-z": [0, 0, -1]}


# ---------------------------------------------------------------------------- helpers
def box_scene(n=2000, lo=(2.0, -1.0, 0.0), hi=(6.0, 1.0, 3.0), seed=0, degree=1) -> GaussianScene:
    """A scene of n gaussians uniform in a box (metres), labelled by x half."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(lo, hi, size=(n, 3))
    q = rng.normal(size=(n, 4))
    return GaussianScene(
        means=means, log_scales=np.log(rng.uniform(0.01, 0.05, size=(n, 3))),
        quats=q / np.linalg.norm(q, axis=1, keepdims=True), opacity_logits=rng.normal(size=n) * 2,
        sh=rng.normal(size=(n, (degree + 1) ** 2, 3)),
        extras={"label": (means[:, 0] > np.mean([lo[0], hi[0]])).astype(np.int32)})


def run_file(tmp_path, scene: GaussianScene, transform=None, prep=None, name="src.ply"):
    src = tmp_path / name
    save_gaussians(scene, src)
    outs = {"scene": str(tmp_path / "out" / "scene.ply"), "transform": str(tmp_path / "out" / "transform.json")}
    scene_cfg = {"source": str(src)}
    if transform is not None:
        scene_cfg["transform"] = transform
    cfg = {"scene": scene_cfg, "prepare": prep or {}}
    summary = prepare.run({"source": str(src)}, outs, cfg, LOG)
    return summary, load_gaussians(outs["scene"]), json.loads(Path(outs["transform"]).read_text()), outs


def covariances(scene: GaussianScene) -> np.ndarray:
    return scene.covariances().astype(np.float64)


def assert_cov_close(a: np.ndarray, b: np.ndarray, rel: float = 1e-4) -> None:
    """[N, 3, 3] covariances equal up to ``rel`` times each gaussian's largest entry (float32 data)."""
    err = np.abs(a - b).max(axis=(1, 2))
    assert (err <= rel * np.abs(b).max(axis=(1, 2))).all(), float((err / np.abs(b).max(axis=(1, 2))).max())


# ---------------------------------------------------------------------------- placement
def test_default_placement_full_box(tmp_path):
    scene = box_scene()
    summary, sim, rec, outs = run_file(tmp_path, scene, prep={"trim_quantile": 0.0})
    lo, hi = sim.bounds()
    np.testing.assert_allclose((hi - lo).max(), 0.5, rtol=1e-6)
    np.testing.assert_allclose((lo + hi) / 2, [0.5, 0.5, 0.5], atol=1e-6)
    assert summary["n_input"] == summary["n_kept"] == scene.n
    for key in ("scale", "rotation", "src_center", "sim_center", "source", "n_input", "n_kept",
                "bounds_src", "bounds_sim"):
        assert key in rec, key
    assert rec["n_kept"] == scene.n and np.allclose(rec["rotation"], np.eye(3))
    np.testing.assert_allclose(rec["bounds_sim"]["min"], lo, atol=1e-6)
    np.testing.assert_allclose(rec["bounds_src"]["max"], scene.bounds()[1], atol=1e-6)
    np.testing.assert_allclose(rec["scale"], 0.5 / np.ptp(scene.means, axis=0).max(), rtol=1e-6)
    # SH stay in the source frame, extras follow, opacities unchanged
    assert np.array_equal(sim.sh, scene.sh) and np.array_equal(sim.opacity_logits, scene.opacity_logits)
    assert np.array_equal(sim.extras["label"], scene.extras["label"])
    # scales and orientations: covariance maps as s^2 R S R^T
    s, R = rec["scale"], np.asarray(rec["rotation"])
    assert_cov_close(covariances(sim), s * s * (R @ covariances(scene) @ R.T))


def test_scene_overrides_center_and_extent(tmp_path):
    _, sim, rec, _ = run_file(tmp_path, box_scene(), transform={"center": [0.4, 0.6, 0.3], "extent": 0.3},
                              prep={"trim_quantile": 0.0})
    lo, hi = sim.bounds()
    np.testing.assert_allclose((hi - lo).max(), 0.3, rtol=1e-6)
    np.testing.assert_allclose((lo + hi) / 2, [0.4, 0.6, 0.3], atol=1e-6)
    assert rec["sim_center"] == [0.4, 0.6, 0.3]


@pytest.mark.parametrize("up", sorted(AXES))
def test_up_axis_maps_to_plus_z(up):
    tcfg = prepare.transform_config({"transform": {"up_axis": up}})
    R = prepare.scene_rotation(tcfg)
    np.testing.assert_allclose(R @ AXES[up], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)


def test_up_axis_y_scene(tmp_path):
    # a tall column along source +y, with a marker gaussian at the top (+y end)
    scene = box_scene(lo=(0, 0, 0), hi=(0.2, 2.0, 0.3))
    top = int(np.argmax(scene.means[:, 1]))
    _, sim, rec, _ = run_file(tmp_path, scene, transform={"up_axis": "y"}, prep={"trim_quantile": 0.0})
    size = np.ptp(sim.means, axis=0)
    assert size[2] == size.max() and np.isclose(size[2], 0.5, rtol=1e-6)
    assert int(np.argmax(sim.means[:, 2])) == top
    R = np.asarray(rec["rotation"])
    assert_cov_close(covariances(sim), rec["scale"] ** 2 * (R @ covariances(scene) @ R.T))


def test_extra_rotations_like_physgaussian():
    tcfg = prepare.transform_config({"transform": {"rotation_degree": [90, 90], "rotation_axis": [0, "z"]}})
    R = prepare.scene_rotation(tcfg)
    # first +90 about x: y -> z, z -> -y; then +90 about z: x -> y, -y -> x
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    both = prepare.transform_config({"transform": {"rotation_degree": [90], "rotation_axis": ["x"],
                                                   "up_axis": "-x"}})
    np.testing.assert_allclose(prepare.scene_rotation(both),
                               prepare.up_rotation("-x") @ prepare.axis_rotation(90, 0), atol=1e-12)


def test_trim_quantile_ignores_floaters(tmp_path):
    body = box_scene(n=4000, lo=(0, 0, 0), hi=(1, 1, 1))
    rng = np.random.default_rng(3)
    floaters = box_scene(n=20, lo=(3, 3, 3), hi=(3.3, 3.3, 3.3), seed=5)  # 0.5 % far away
    scene = GaussianScene.concat([body, floaters]).subset(rng.permutation(4020))
    _, sim, rec, _ = run_file(tmp_path, scene, prep={"trim_quantile": 0.01, "drop_outside": True})
    # the body sets the scale (about 0.5 per unit), the floaters end up outside and are dropped
    assert 0.5 / 1.0 * 0.95 < rec["scale"] < 0.5 / 0.98 * 1.05
    assert rec["dropped"]["outside"] == 20 and rec["n_kept"] == 4000
    assert (sim.means >= prepare.MARGIN).all() and (sim.means <= 1 - prepare.MARGIN).all()
    with pytest.raises(ConfigError) as info:  # without drop_outside: an error with the numbers
        run_file(tmp_path, scene, prep={"trim_quantile": 0.01})
    msg = str(info.value)
    assert "transform.extent" in msg and "0.0469" in msg and "extent of at most" in msg and "drop_outside" in msg


def test_out_of_domain_center_error(tmp_path):
    with pytest.raises(ConfigError) as info:
        run_file(tmp_path, box_scene(), transform={"center": [0.1, 0.5, 0.5], "extent": 0.2})
    assert info.value.key == "transform.center" and "a center within" in str(info.value)
    assert not (tmp_path / "out" / "scene.ply").exists()


def test_extent_too_large_error(tmp_path):
    with pytest.raises(ConfigError) as info:
        run_file(tmp_path, box_scene(), transform={"extent": 0.95}, prep={"trim_quantile": 0.0})
    assert info.value.key == "transform.extent" and "at most 0.9062" in str(info.value)


# ---------------------------------------------------------------------------- filters
def test_min_opacity_filter(tmp_path):
    scene = box_scene()
    expect = int((scene.opacities < 0.3).sum())
    _, sim, rec, _ = run_file(tmp_path, scene, prep={"min_opacity": 0.3})
    assert rec["dropped"]["min_opacity"] == expect > 0 and sim.n == scene.n - expect
    assert (sim.opacities >= 0.3).all()
    keep = scene.opacities >= 0.3
    assert np.array_equal(sim.extras["label"], scene.extras["label"][keep])
    with pytest.raises(ConfigError, match="prepare.min_opacity"):
        run_file(tmp_path, scene, prep={"min_opacity": 0.99999})


def test_crop_box(tmp_path):
    scene = box_scene()
    box = [[2.0, -1.0, 0.0], [4.0, 1.0, 3.0]]
    keep = ((scene.means >= box[0]) & (scene.means <= box[1])).all(axis=1)
    _, sim, rec, _ = run_file(tmp_path, scene, transform={"crop_box": box}, prep={"trim_quantile": 0.0})
    assert rec["dropped"]["crop_box"] == int((~keep).sum()) and sim.n == int(keep.sum())
    assert (sim.extras["label"] == 0).all()  # only the low-x half survives
    assert np.all(np.asarray(rec["bounds_src"]["max"]) <= np.asarray(box[1]) + 1e-6)
    with pytest.raises(ConfigError, match="transform.crop_box.*contains none"):
        run_file(tmp_path, scene, transform={"crop_box": [[10, 10, 10], [11, 11, 11]]})
    with pytest.raises(ConfigError, match="transform.crop_box.*below"):
        run_file(tmp_path, scene, transform={"crop_box": [[5, 0, 0], [4, 1, 1]]})


def test_degenerate_scene(tmp_path):
    with pytest.raises(InputError, match="no spatial extent"):
        run_file(tmp_path, box_scene(n=1))


# ---------------------------------------------------------------------------- config
@pytest.mark.parametrize("transform,key", [
    ({"extent": -1}, "transform.extent"),
    ({"up_axis": "w"}, "transform.up_axis"),
    ({"center": [0.5, 0.5]}, "transform.center"),
    ({"scale": 2}, "transform"),
    ({"rotation_degree": [90], "rotation_axis": []}, "transform.rotation_axis"),
])
def test_bad_transform_config(transform, key):
    with pytest.raises(ConfigError) as info:
        prepare.transform_config({"transform": transform, "_path": "config/scenes/x.yaml"})
    assert info.value.key == key and "config/scenes/x.yaml" in str(info.value)


def test_bad_prepare_config():
    with pytest.raises(ConfigError) as info:
        prepare.prepare_config({"prepare": {"trim_quantile": 0.7}})
    assert info.value.key == "prepare.trim_quantile"
    assert prepare.prepare_config({}) == {"trim_quantile": 0.01, "min_opacity": 0.0, "drop_outside": False}


@pytest.mark.parametrize("name", ["prepare", "scene_transform"])
def test_schema_keys_documented(name):
    schema = yaml.safe_load((SCHEMAS / f"{name}.schema.yaml").read_text())
    assert schema["type"] == "object" and schema["additionalProperties"] is False
    for key, spec in schema["properties"].items():
        assert spec.get("description") and "default" in spec, key


def test_bad_source_config(tmp_path):
    outs = {"scene": str(tmp_path / "s.ply"), "transform": str(tmp_path / "t.json")}
    with pytest.raises(ConfigError, match="'source'"):
        prepare.run({}, outs, {"scene": {}}, LOG)
    with pytest.raises(InputError, match="file not found"):
        prepare.run({}, outs, {"scene": {"source": str(tmp_path / "nope.ply")}}, LOG)


# ---------------------------------------------------------------------------- transform.json
def test_load_transform_round_trip(tmp_path):
    scene = box_scene()
    _, sim, _, outs = run_file(tmp_path, scene, transform={"up_axis": "-y", "rotation_degree": [30],
                                                           "rotation_axis": [2], "extent": 0.4})
    tf = prepare.load_transform(outs["transform"])
    assert tf.R.shape == (3, 3) and tf.scale > 0
    np.testing.assert_allclose(tf.to_sim(scene.means), sim.means, atol=2e-6)
    np.testing.assert_allclose(tf.to_source(sim.means), scene.means, atol=2e-5)
    pts = np.random.default_rng(1).uniform(-5, 5, size=(100, 3))
    np.testing.assert_allclose(tf.to_source(tf.to_sim(pts)), pts, atol=1e-12)
    back = tf.to_source_scene(sim)
    np.testing.assert_allclose(back.log_scales, scene.log_scales, atol=1e-5)
    assert_cov_close(covariances(back), covariances(scene))


def test_load_transform_errors(tmp_path):
    p = tmp_path / "t.json"
    p.write_text(json.dumps({"scale": 1.0, "rotation": np.eye(3).tolist(), "src_center": [0, 0, 0]}))
    with pytest.raises(InputError, match="missing keys.*sim_center"):
        prepare.load_transform(p)
    p.write_text(json.dumps({"scale": 1.0, "rotation": (2 * np.eye(3)).tolist(), "src_center": [0, 0, 0],
                             "sim_center": [0, 0, 0]}))
    with pytest.raises(InputError, match="not a proper rotation"):
        prepare.load_transform(p)
    p.write_text("{")
    with pytest.raises(InputError, match="not valid JSON"):
        prepare.load_transform(p)


# ---------------------------------------------------------------------------- real and built-in scenes
def test_real_donut(tmp_path, splats_dir):
    src = splats_dir / "gshairlod_donut_fused.ply"
    outs = {"scene": str(tmp_path / "scene.ply"), "transform": str(tmp_path / "transform.json")}
    summary = prepare.run({"source": str(src)}, outs, {"scene": {"source": str(src)}, "prepare": {}}, LOG)
    sim = load_gaussians(outs["scene"])
    assert summary["n_kept"] == sim.n == 45624
    assert (sim.means > prepare.MARGIN).all() and (sim.means < 1 - prepare.MARGIN).all()
    trimmed = np.quantile(sim.means, [0.01, 0.99], axis=0)
    np.testing.assert_allclose(np.ptp(trimmed, axis=0).max(), 0.5, rtol=1e-3)


def test_builtin_dispatch_with_stand_in(tmp_path, monkeypatch):
    """The built-in branch calls make_scene(name, **builtin) and keeps gt_label."""
    calls = []

    def make_scene(name, **kwargs):
        calls.append((name, kwargs))
        s = box_scene(n=500, seed=kwargs.get("seed", 0))
        s.extras["gt_label"] = s.extras.pop("label")
        return s, {"stand_in": True}

    fake = types.ModuleType("physgs_steps.builtin_scenes")
    fake.make_scene = make_scene
    monkeypatch.setitem(sys.modules, "physgs_steps.builtin_scenes", fake)
    outs = {"scene": str(tmp_path / "scene.ply"), "transform": str(tmp_path / "transform.json")}
    cfg = {"scene": {"source": "builtin:cube", "builtin": {"n_gaussians": 500, "seed": 2}}, "prepare": {}}
    prepare.run({}, outs, cfg, LOG)
    assert calls == [("cube", {"n_gaussians": 500, "seed": 2})]
    sim = load_gaussians(outs["scene"])
    assert sim.n == 500 and sim.extras["gt_label"].dtype == np.int32
    assert json.loads(Path(outs["transform"]).read_text())["source"] == "builtin:cube"


def test_builtin_bear(tmp_path):
    try:
        from physgs_steps.builtin_scenes import make_scene  # noqa: F401
    except ImportError as e:
        pytest.skip(f"physgs_steps.builtin_scenes.make_scene is not available yet ({e})")
    outs = {"scene": str(tmp_path / "scene.ply"), "transform": str(tmp_path / "transform.json")}
    cfg = {"scene": {"source": "builtin:bear", "builtin": {"n_gaussians": 3000, "seed": 0}}, "prepare": {}}
    summary = prepare.run({}, outs, cfg, LOG)
    sim = load_gaussians(outs["scene"])
    assert summary["n_kept"] == sim.n > 0
    assert "gt_label" in sim.extras and sim.extras["gt_label"].dtype == np.int32
    assert (sim.means > prepare.MARGIN).all() and (sim.means < 1 - prepare.MARGIN).all()


def test_builtin_scene_is_generated_once_per_process():
    """The warm worker runs prepare of the same built-in scene again: the second call reuses the
    scene generated before, as an independent copy equal to a fresh generation."""
    import logging

    from physgs_steps import prepare as P

    log = logging.getLogger("test_prepare")
    cfg = {"source": "builtin:bear", "builtin": {"n_gaussians": 500, "seed": 7}}
    P._BUILTIN_CACHE.clear()
    a, _ = P.load_source({}, cfg, log)
    assert len(P._BUILTIN_CACHE) == 1
    a.means[:] = 0.0  # a caller changing its copy
    b, _ = P.load_source({}, cfg, log)
    P._BUILTIN_CACHE.clear()
    c, _ = P.load_source({}, cfg, log)
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        assert np.array_equal(getattr(b, k), getattr(c, k)), k
    assert not np.array_equal(a.means, b.means)
