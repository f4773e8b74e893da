"""The cluster stage: DBSCAN (exact and voxel), noise policy, boxes, merges, bad input."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from physgs_steps import cluster as CL
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError
from physgs_steps.gaussians import GaussianScene
from physgs_steps.scene_io import save_gaussians

LOG = logging.getLogger("test_cluster")


def sphere_shell(n, center, radius, rng):
    """[n, 3] points on a sphere."""
    d = rng.normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def box_shell(n, center, half, rng):
    """[n, 3] points on the surface of an axis-aligned box of half-sides ``half``."""
    p = rng.uniform(-1, 1, size=(n, 3))
    ax = rng.integers(0, 3, n)
    p[np.arange(n), ax] = np.sign(p[np.arange(n), ax])
    return np.asarray(center) + p * np.asarray(half)


def two_objects(n, rng, noise=0):
    """A sphere (larger) and a box 0.08 apart, plus ``noise`` scattered floaters."""
    a = sphere_shell(n * 6 // 10, [0.36, 0.5, 0.5], 0.14, rng)
    b = box_shell(n - n * 6 // 10, [0.68, 0.5, 0.45], [0.09, 0.09, 0.09], rng)
    pts = [a, b]
    if noise:
        pts.append(rng.uniform(0.25, 0.75, size=(noise, 3)))
    return np.concatenate(pts)


def write_scene(path, points, extras=None):
    n = len(points)
    scene = GaussianScene(
        means=points, log_scales=np.full((n, 3), np.log(0.003)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        opacity_logits=np.full(n, 3.0), sh=np.zeros((n, 1, 3)), extras=extras or {})
    save_gaussians(scene, path)
    return str(path)


def run_cluster(tmp_path, points, cluster=None, instances=None, extras=None):
    ply = write_scene(tmp_path / "scene.ply", points, extras)
    out = {"labels": str(tmp_path / "labels.npz"), "clusters": str(tmp_path / "clusters.json")}
    cfg = {"cluster": dict(section_defaults("cluster"), **(cluster or {})),
           "scene": {"source": "test", "instances": instances or []}}
    CL.run({"scene": ply}, out, cfg, LOG)
    return CL.load_labels(out["labels"]), json.loads(Path(out["clusters"]).read_text())


# ---------------------------------------------------------------------------- DBSCAN
@pytest.mark.parametrize("noise", [0, 60])
def test_voxel_dbscan_agrees_with_exact(noise):
    rng = np.random.default_rng(1)
    pts = two_objects(12000, rng, noise)
    exact = CL.dbscan_labels(pts, 0.05, 10, "exact")
    voxel = CL.dbscan_labels(pts, 0.05, 10, "voxel")
    assert len(np.unique(exact[exact >= 0])) == 2
    assert adjusted_rand_score(exact, voxel) > 0.99
    # after the noise policy both give the same instance of every gaussian
    a, _ = CL.assign_noise(pts, CL.sort_by_size(exact))
    b, _ = CL.assign_noise(pts, CL.sort_by_size(voxel))
    assert (a == b).mean() > 0.995


@pytest.mark.parametrize("name", ["bear_can", "duck_stone", "basket_mat"])
def test_voxel_dbscan_agrees_with_exact_on_builtin_scenes(name):
    from physgs_steps.builtin_scenes import make_scene
    from physgs_steps.prepare import normalise_scene, prepare_config, transform_config

    scene, _ = make_scene(name, n_gaussians=8000, seed=3)
    sim, _, _ = normalise_scene(scene, transform_config({"source": f"builtin:{name}"}),
                                prepare_config({"prepare": section_defaults("prepare")}), name, LOG)
    pts = sim.means.astype(np.float64)
    from sklearn.cluster import DBSCAN

    raw = CL.dbscan_labels(pts, 0.05, 10, "exact")
    assert (raw == DBSCAN(eps=0.05, min_samples=10).fit(pts).labels_).all()
    exact, _ = CL.assign_noise(pts, CL.sort_by_size(raw))
    voxel, _ = CL.assign_noise(pts, CL.sort_by_size(CL.dbscan_labels(pts, 0.05, 10, "voxel")))
    assert exact.max() == voxel.max() == 1
    assert (exact == voxel).all()
    # and the instances are the true objects
    assert adjusted_rand_score(sim.extras["gt_label"], voxel) == pytest.approx(1.0)


@pytest.mark.parametrize("weighted", [False, True])
def test_dbscan_is_scikit_learns(weighted):
    """Our k-d tree DBSCAN gives scikit-learn's labels exactly (numbering, border points,
    noise, sample weights), on clustered and on sparse uniform points."""
    from sklearn.cluster import DBSCAN

    rng = np.random.default_rng(5)
    sets = [two_objects(3000, rng, noise=80), rng.uniform(0, 1, size=(2500, 3))]
    for pts in sets:
        w = rng.integers(1, 4, len(pts)) if weighted else None
        for eps, ms in [(0.05, 10), (0.04, 3), (0.07, 25), (0.02, 1)]:
            ref = DBSCAN(eps=eps, min_samples=ms).fit(pts, sample_weight=w).labels_
            assert (CL.dbscan(pts, eps, ms, w) == ref).all(), (eps, ms)


def test_dbscan_labels_shapes_and_empty():
    assert CL.dbscan_labels(np.zeros((0, 3)), 0.05, 5).shape == (0,)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        CL.dbscan_labels(np.zeros((5, 2)), 0.05, 5)


# ---------------------------------------------------------------------------- stage
def test_run_writes_sorted_labels_and_matches_at(tmp_path):
    rng = np.random.default_rng(2)
    pts = two_objects(6000, rng)
    # the box is listed first, found by its `at`; the sphere (larger) is matched by size
    labels, rec = run_cluster(tmp_path, pts, instances=[{"name": "box", "at": [0.68, 0.5, 0.45]}, {"name": "ball"}])
    assert labels.dtype == np.int32 and labels.min() == 0 and labels.max() == 1
    counts = np.bincount(labels)
    assert counts[0] > counts[1]
    assert rec["n_instances"] == 2 and rec["method"] == "dbscan"
    names = {r["label"]: (r["name"], r["config_index"]) for r in rec["instances"]}
    assert names == {0: ("ball", 1), 1: ("box", 0)}
    assert [r["count"] for r in rec["instances"]] == counts.tolist()
    assert rec["noise"]["count"] == 0 and "nearest" in rec["noise"]["policy"]
    assert rec["seconds"] > 0
    with np.load(tmp_path / "labels.npz") as z:
        assert z["labels"].shape == (len(pts),)


def test_noise_joins_the_nearest_cluster_and_is_counted(tmp_path):
    rng = np.random.default_rng(3)
    pts = two_objects(6000, rng)
    floaters = np.array([[0.36, 0.5, 0.71], [0.68, 0.5, 0.62]])  # just outside each object
    labels, rec = run_cluster(tmp_path, np.concatenate([pts, floaters]), cluster={"min_samples": 10})
    sphere_label = labels[0]
    box_label = labels[len(pts) - 1]
    assert labels[-2] == sphere_label and labels[-1] == box_label
    assert rec["noise"]["count"] >= 2 and rec["noise"]["unlabelled"] >= 2
    assert rec["noise"]["max_distance"] > 0.03


def test_small_clusters_are_dissolved(tmp_path):
    rng = np.random.default_rng(4)
    pts = two_objects(6000, rng)
    speck = np.array([0.5, 0.5, 0.8]) + rng.normal(scale=0.003, size=(12, 3))  # a floater blob
    labels, rec = run_cluster(tmp_path, np.concatenate([pts, speck]), cluster={"min_cluster_fraction": 0.01})
    assert rec["n_instances"] == 2 and rec["noise"]["dissolved_clusters"] == 1
    assert rec["noise"]["dissolved_points"] == 12


def test_boxes_replace_dbscan(tmp_path):
    rng = np.random.default_rng(5)
    # two touching objects that DBSCAN cannot separate
    a = box_shell(3000, [0.4, 0.5, 0.5], [0.1, 0.1, 0.1], rng)
    b = box_shell(2000, [0.6, 0.5, 0.5], [0.1, 0.1, 0.1], rng)
    pts = np.concatenate([a, b])
    inst = [{"name": "right", "box": [[0.5001, 0.3, 0.3], [0.75, 0.7, 0.7]]},
            {"name": "left", "box": [[0.25, 0.3, 0.3], [0.5, 0.7, 0.7]]}]
    labels, rec = run_cluster(tmp_path, pts, instances=inst)
    assert rec["method"] == "boxes" and rec["n_instances"] == 2
    by_label = {r["label"]: r for r in rec["instances"]}
    left = labels[0]
    assert by_label[left]["name"] == "left" and by_label[left]["config_index"] == 1
    assert (labels[pts[:, 0] > 0.5001] != left).all()
    # DBSCAN on the same points merges them and warns (not strict)
    labels2, rec2 = run_cluster(tmp_path, pts, cluster={"method": "dbscan"}, instances=inst)
    assert rec2["n_instances"] == 1 and "cluster.eps" in rec2["warnings"][0]


def test_box_without_gaussians_is_an_error(tmp_path):
    rng = np.random.default_rng(6)
    pts = two_objects(3000, rng)
    inst = [{"name": "a", "box": [[0.2, 0.3, 0.3], [0.5, 0.7, 0.7]]}, {"name": "b", "box": [[0.9, 0.9, 0.9], [0.95, 0.95, 0.95]]}]
    with pytest.raises(ConfigError, match=r"instances\[1\]\.box.*no gaussian"):
        run_cluster(tmp_path, pts, instances=inst)


def test_merge_rules(tmp_path):
    rng = np.random.default_rng(7)
    pts = two_objects(4000, rng)
    labels, rec = run_cluster(tmp_path, pts, cluster={"merge": [[0, 1]]})
    assert rec["n_instances"] == 1 and (labels == 0).all()
    with pytest.raises(ConfigError, match=r"cluster\.merge\[0\].*label 5 does not exist"):
        run_cluster(tmp_path, pts, cluster={"merge": [[0, 5]]})


def test_all_noise_is_a_clear_error(tmp_path):
    rng = np.random.default_rng(8)
    pts = rng.uniform(0.25, 0.75, size=(300, 3))
    with pytest.raises(ConfigError, match=r"cluster\.eps.*all 300 gaussians as noise.*neighbour is"):
        run_cluster(tmp_path, pts, cluster={"eps": 0.005, "min_samples": 10})


def test_everything_merged_warns_or_fails_when_strict(tmp_path):
    rng = np.random.default_rng(9)
    pts = two_objects(4000, rng)
    inst = [{"name": "ball"}, {"name": "box"}]
    _, rec = run_cluster(tmp_path, pts, cluster={"eps": 0.2}, instances=inst)
    assert rec["n_instances"] == 1
    assert any("found 1 instance(s) but the scene lists 2" in w for w in rec["warnings"])
    with pytest.raises(ConfigError, match=r"cluster\.eps.*found 1 instance"):
        run_cluster(tmp_path, pts, cluster={"eps": 0.2, "strict": True}, instances=inst)


def test_ply_labels_method(tmp_path):
    rng = np.random.default_rng(10)
    pts = two_objects(3000, rng)
    given = (pts[:, 0] > 0.52).astype(np.int32)  # box = 1, but the sphere is larger
    labels, rec = run_cluster(tmp_path, pts, cluster={"method": "ply_labels"}, extras={"label": given})
    assert rec["method"] == "ply_labels"
    assert adjusted_rand_score(given, labels) == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="no integer `label`"):
        run_cluster(tmp_path, pts, cluster={"method": "ply_labels"})


def test_bad_config_values_name_the_key(tmp_path):
    rng = np.random.default_rng(11)
    pts = two_objects(2000, rng)
    with pytest.raises(ConfigError, match=r"cluster\.eps"):
        run_cluster(tmp_path, pts, cluster={"eps": "big"})
    with pytest.raises(ConfigError, match=r"cluster\.algorithm"):
        run_cluster(tmp_path, pts, cluster={"algorithm": "hdbscan"})
    with pytest.raises(ConfigError, match=r"instances\[0\]\.at"):
        run_cluster(tmp_path, pts, instances=[{"name": "a", "at": [0.5, 0.5]}])
    with pytest.raises(ConfigError, match=r"instances\[0\]\.box.*max corner"):
        run_cluster(tmp_path, pts, instances=[{"name": "a", "box": [[0.6, 0.3, 0.3], [0.5, 0.7, 0.7]]}])
