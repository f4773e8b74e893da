"""The fill stage: hull ray casting, voxel occupancy, MCIS, counts, degenerate instances,
particles.h5 and fill_report.json (with a synthetic ground truth and a built-in scene)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgs_steps import cluster as CL
from physgs_steps import fill as F
from physgs_steps import fill_report as FR
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError, InputError
from physgs_steps.gaussians import GaussianScene
from physgs_steps.scene_io import save_gaussians

LOG = logging.getLogger("test_fill")


def fcfg(**over):
    return dict(section_defaults("fill"), **over)


def sphere_shell(n, center, radius, rng):
    d = rng.normal(size=(n, 3))
    return np.asarray(center) + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def cup_shell(n, center, r_out, r_in, height, floor, rng):
    """[n, 3] points on an open-topped thick cup (outer wall, underside, rim, inner wall, cavity floor)."""
    areas = np.array([2 * np.pi * r_out * height, np.pi * r_out ** 2, np.pi * (r_out ** 2 - r_in ** 2),
                      2 * np.pi * r_in * (height - floor), np.pi * r_in ** 2])
    comp = rng.choice(5, size=n, p=areas / areas.sum())
    th = rng.uniform(0, 2 * np.pi, n)
    u = rng.random(n)
    rho = np.select([comp == 0, comp == 1, comp == 2, comp == 3],
                    [np.full(n, r_out), r_out * np.sqrt(u), np.sqrt(r_in ** 2 + u * (r_out ** 2 - r_in ** 2)),
                     np.full(n, r_in)], r_in * np.sqrt(u))
    z = np.select([comp == 0, comp == 1, comp == 2, comp == 3], [u * height, np.zeros(n), np.full(n, height),
                                                                  floor + u * (height - floor)], np.full(n, floor))
    return np.asarray(center) + np.stack([rho * np.cos(th), rho * np.sin(th), z], axis=1)


def gauss_arrays(points, scale=0.003):
    n = len(points)
    return {"opacities": np.full(n, 0.95, np.float32), "log_scales": np.full((n, 3), np.log(scale), np.float32),
            "quats": np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))}


def fill(points, labels, **over):
    g = gauss_arrays(points)
    return F.fill_scene(points, labels, g["opacities"], g["log_scales"], g["quats"], fcfg(**over), LOG)


# ---------------------------------------------------------------------------- hull ray casting
def test_hull_ray_casting_equals_the_inside_test():
    rng = np.random.default_rng(0)
    pts = sphere_shell(1500, [0.5, 0.5, 0.5], 0.2, rng)
    eq, vol = F.convex_hull(pts, 0.0)
    assert vol == pytest.approx(4 / 3 * np.pi * 0.2 ** 3, rel=0.05)
    q = rng.uniform(0.25, 0.75, size=(3000, 3))
    occ = F.hull_ray_occupancy(eq, q, F.random_directions(5, rng))
    assert occ.min() >= 0 and occ.max() <= 1
    inside = np.all(q @ eq[:, :3].T + eq[:, 3] <= 0, axis=1)
    assert ((occ > 0.6) == inside).mean() > 0.999


def test_hull_occupancy_counts_crossings_per_ray():
    # unit cube [0,1]^3 as half-spaces; a point outside looking at the cube crosses twice (even)
    eq = np.array([[-1, 0, 0, 0], [1, 0, 0, -1], [0, -1, 0, 0], [0, 1, 0, -1], [0, 0, -1, 0], [0, 0, 1, -1]], float)
    d = np.array([[1.0, 0, 0], [0, 0, 1.0]])
    q = np.array([[0.5, 0.5, 0.5], [-1.0, 0.5, 0.5], [2.0, 0.5, 0.5]])
    occ = F.hull_ray_occupancy(eq, q, d)
    assert occ.tolist() == [1.0, 0.0, 0.0]


# ---------------------------------------------------------------------------- voxel fields
def _voxel_sphere(n=40, r=12, thickness=1.0):
    g = np.indices((n, n, n)) - n / 2 + 0.5
    dist = np.sqrt((g ** 2).sum(0))
    return np.abs(dist - r) <= thickness / 2 + 0.5, dist < r


def test_enclosed_and_surface_occupancy_of_a_closed_and_a_holed_shell():
    shell, truth = _voxel_sphere()
    inside = F.enclosed(shell, 0)
    assert inside.sum() > 0 and not (inside & shell).any()
    assert (inside <= truth).all() and inside.sum() > 0.8 * (truth & ~shell).sum()
    holed = shell.copy()
    holed[18:22, 18:22, 30:] = False  # a 4-voxel hole at the top
    assert F.enclosed(holed, 0).sum() == 0  # leaks without closing
    occ = F.surface_occupancy_field(holed, [1, 2, 3])
    assert occ[20, 20, 20] == pytest.approx(2 / 3)  # radius 1 does not close a 4-voxel hole, 2 and 3 do
    assert F.surface_occupancy_field(shell, [1, 2, 3])[20, 20, 20] == pytest.approx(1.0)
    assert occ[0, 0, 0] == 0.0


def test_physgaussian_rule_on_a_sphere_and_an_open_cup():
    shell, truth = _voxel_sphere()
    inner = F.physgaussian_interior(shell, [], "+z")
    assert (inner <= truth).all() and inner.sum() > 0.8 * (truth & ~shell).sum()
    cup = shell.copy()
    cup[:, :, 26:] = False  # open the top: rays up from the cavity escape
    open_inner = F.physgaussian_interior(cup, [], "+z")
    assert open_inner[20, 20, 20] == 0
    assert F.physgaussian_interior(cup, ["+z"], "-z")[20, 20, 20]  # excluding +z brings the cavity back


# ---------------------------------------------------------------------------- MCIS
def test_mcis_weights_and_draws():
    d = np.array([0.0, 0.02, 0.2])
    p = F.mcis_probabilities(d, 0.02)
    w = np.array([1.0, np.exp(-0.5), 1e-6])
    np.testing.assert_allclose(p, w / w.sum())
    rng = np.random.default_rng(0)
    idx = F.draw(50, 100, np.full(100, 0.01), False, rng)
    assert idx.size == 50 and np.unique(idx).size == 50
    idx = F.draw(500, 3, p, True, rng)
    assert idx.size == 500 and np.bincount(idx, minlength=3)[2] == 0
    # without replacement, heavy candidates come first
    p2 = np.r_[np.full(10, 1.0), np.full(990, 1e-6)]
    idx = F.draw(10, 1000, p2 / p2.sum(), False, rng)
    assert set(idx.tolist()) == set(range(10))
    assert F.draw(5, 3, None, False, rng).size == 3


# ---------------------------------------------------------------------------- whole filling
def test_sphere_fill_counts_volume_and_inside():
    rng = np.random.default_rng(1)
    pts = sphere_shell(4000, [0.5, 0.5, 0.5], 0.15, rng)
    labels = np.zeros(len(pts), np.int32)
    res = fill(pts, labels, occupancy="hull", mcis=True)
    inst = res.instances[0]
    v = 4 / 3 * np.pi * 0.15 ** 3
    dx = 1 / 32
    assert inst.status == "filled" and inst.volume == pytest.approx(v, rel=0.05)
    ppc = fcfg()["particles_per_cell"]  # the default
    assert res.x.shape[0] == inst.n_filled == round(ppc * inst.volume / dx ** 3)
    assert (np.linalg.norm(res.x - 0.5, axis=1) < 0.15 + 0.002).all()  # Qhull pre-merge tolerance 0.001
    assert (res.label == 0).all() and inst.duplicates == 0
    total_vol = res.vol_gaussians.sum() + res.vol_filled.sum()
    assert total_vol == pytest.approx(inst.volume, rel=1e-4)
    # MCIS pulls particles towards the surface compared to a uniform draw
    uni = fill(pts, labels, occupancy="hull", mcis=False)
    r_mcis = np.linalg.norm(res.x - 0.5, axis=1).mean()
    r_uni = np.linalg.norm(uni.x - 0.5, axis=1).mean()
    assert r_mcis > r_uni + 0.005
    # the paper's multinomial draw repeats candidates
    rep = fill(pts, labels, occupancy="hull", mcis=True, mcis_replace=True)
    assert rep.instances[0].duplicates > 0


def test_surface_occupancy_leaves_the_cup_hollow_empty_and_hull_does_not():
    rng = np.random.default_rng(2)
    # thick-walled cup, wall 0.06 thick so that its interior is resolvable
    pts = cup_shell(20000, [0.5, 0.5, 0.3], 0.2, 0.14, 0.3, 0.06, rng)
    labels = np.zeros(len(pts), np.int32)
    rho = lambda x: np.linalg.norm(x[:, :2] - 0.5, axis=1)  # noqa: E731
    in_hollow = lambda x: (rho(x) < 0.13) & (x[:, 2] > 0.37)  # noqa: E731
    hull = fill(pts, labels, occupancy="hull", mcis=True)
    surf = fill(pts, labels, occupancy="surface", mcis=False)
    assert in_hollow(hull.x).sum() > 100
    assert surf.x.shape[0] > 500 and in_hollow(surf.x).sum() == 0
    in_wall = (rho(surf.x) > 0.14) & (rho(surf.x) < 0.2) | (surf.x[:, 2] < 0.36)
    assert in_wall.mean() > 0.99
    assert surf.instances[0].voxel_size is not None


def test_global_filling_labels_by_nearest_gaussian():
    rng = np.random.default_rng(3)
    a = sphere_shell(6000, [0.33, 0.5, 0.5], 0.12, rng)
    b = sphere_shell(3000, [0.67, 0.5, 0.5], 0.1, rng)
    pts = np.concatenate([a, b])
    labels = np.r_[np.zeros(len(a), np.int32), np.ones(len(b), np.int32)]
    res = fill(pts, labels, method="global", mcis=False)
    assert res.x.shape[0] > 1000 and res.voxel_size is not None
    near_a = np.linalg.norm(res.x - [0.33, 0.5, 0.5], axis=1) < 0.12
    near_b = np.linalg.norm(res.x - [0.67, 0.5, 0.5], axis=1) < 0.1
    assert (near_a | near_b).mean() > 0.99
    assert (res.label[near_a] == 0).all() and (res.label[near_b] == 1).all()


def test_method_none_keeps_gaussians_with_shell_volume():
    rng = np.random.default_rng(4)
    pts = sphere_shell(2000, [0.5, 0.5, 0.5], 0.15, rng)
    res = fill(pts, np.zeros(len(pts), np.int32), method="none")
    assert res.x.shape == (0, 3) and res.instances[0].status == "not_filled"
    assert res.vol_gaussians.sum() == pytest.approx(res.instances[0].volume)
    assert "dx/2" in res.instances[0].volume_source


def test_degenerate_instances_fall_back_without_filling():
    rng = np.random.default_rng(5)
    ball = sphere_shell(3000, [0.35, 0.5, 0.5], 0.12, rng)
    leaf = np.c_[rng.uniform(0.6, 0.8, 500), rng.uniform(0.4, 0.6, 500), np.full(500, 0.5)]  # a plane
    speck = np.array([[0.5, 0.8, 0.8], [0.51, 0.8, 0.8], [0.5, 0.81, 0.8]])
    pts = np.concatenate([ball, leaf, speck])
    labels = np.r_[np.zeros(3000), np.ones(500), np.full(3, 2)].astype(np.int32)
    res = fill(pts, labels)
    st = [i.status for i in res.instances]
    assert st == ["filled", "flat", "too_small"]
    assert (res.label == 0).all()
    assert any("flat" not in w and "too few" in w for w in res.warnings) or len(res.warnings) == 2
    rows = res.gaussian_rows
    leaf = rows[(rows >= 3000) & (rows < 3500)]
    assert leaf.size > 0 and res.vol_gaussians[leaf].min() > 0  # flat instance still has mass
    # with the thickness check off, Qhull itself fails on the plane: reported, not raised
    res2 = fill(pts, labels, min_thickness=0.0)
    assert res2.instances[1].status == "degenerate" and "Qhull" in res2.instances[1].reason


def test_max_filled_caps_the_total():
    rng = np.random.default_rng(6)
    pts = sphere_shell(2000, [0.5, 0.5, 0.5], 0.15, rng)
    res = fill(pts, np.zeros(len(pts), np.int32), max_filled=500)
    assert res.x.shape[0] <= 500 and any("max_filled" in w for w in res.warnings)


def test_bad_fill_config_names_the_key():
    with pytest.raises(ConfigError, match=r"fill\.occupancy"):
        F.fill_config({"fill": {"occupancy": "mesh"}})
    with pytest.raises(ConfigError, match=r"fill\.threshold"):
        F.fill_config({"fill": {"threshold": 1.5}})


# ---------------------------------------------------------------------------- report
class SphereGT:
    """A tiny ground truth: one solid ball per instance, one empty box region."""

    def __init__(self, centers, radii):
        self.c, self.r = np.asarray(centers, float), np.asarray(radii, float)
        self.instance_names = [f"ball{i}" for i in range(len(radii))]
        self.bounds = ((self.c - self.r[:, None]).min(0), (self.c + self.r[:, None]).max(0))

    def inside(self, p, instance=None):
        ks = range(len(self.r)) if instance is None else [instance]
        return np.any([np.linalg.norm(p - self.c[k], axis=1) < self.r[k] for k in ks], axis=0)

    def instance_of(self, p):
        out = np.full(len(p), -1, np.int32)
        for k in range(len(self.r)):
            out[(out < 0) & self.inside(p, k)] = k
        return out

    def sdf(self, p, instance=None):
        ks = range(len(self.r)) if instance is None else [instance]
        return np.min([np.linalg.norm(p - self.c[k], axis=1) - self.r[k] for k in ks], axis=0)

    def empty_regions(self):
        return {"between": lambda p: np.all((p > [0.45, 0.45, 0.45]) & (p < [0.55, 0.55, 0.55]), axis=1)}


def test_nearest_distance_is_scipys_default_tree_bitwise(monkeypatch):
    """MCIS distances from the tree shape fill uses are the default cKDTree's, bit for bit, for
    points inside a surface cloud (where the shapes differ most in speed) and outside it."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    surf = np.concatenate([sphere_shell(20000, [0.5, 0.5, 0.5], 0.2, rng),
                           cup_shell(5000, [0.2, 0.2, 0.1], 0.08, 0.06, 0.1, 0.02, rng)])
    q = np.concatenate([rng.uniform(0.3, 0.7, (3000, 3)), rng.uniform(0.0, 1.0, (1000, 3)), surf[:50]])
    d = F.nearest_distance(surf, q)
    assert d.tobytes() == cKDTree(surf).query(q, k=1)[0].tobytes()
    assert (d[-50:] == 0).all()
    monkeypatch.setenv(F.TREE_ENV, "scipy")  # the A/B knob: scipy's default tree, the same numbers
    assert F.nearest_distance(surf, q).tobytes() == d.tobytes()


def test_recall_union_of_gaussians_and_filled_equals_covering_by_all():
    """_recall_records asks the filled particles only about samples the gaussians leave
    uncovered; the counts equal covering by all particles of the instance at once."""
    rng = np.random.default_rng(11)
    gauss = np.concatenate([sphere_shell(3000, [0.3, 0.5, 0.5], 0.1, rng), sphere_shell(3000, [0.7, 0.5, 0.5], 0.1, rng)])
    filled = np.concatenate([[0.3, 0.5, 0.5] + rng.uniform(-0.07, 0.07, (500, 3)),
                             [0.7, 0.5, 0.5] + rng.uniform(-0.07, 0.07, (500, 3))])
    x = np.concatenate([gauss, filled])
    lab = np.r_[np.zeros(3000), np.ones(3000), np.zeros(500), np.ones(500)].astype(np.int32)
    samples = FR.eval_grid(np.array([0.15, 0.35, 0.35]), np.array([0.85, 0.65, 0.65]), 0.01)
    sgt = np.where(np.linalg.norm(samples - [0.3, 0.5, 0.5], axis=1) < 0.1, 0,
                   np.where(np.linalg.norm(samples - [0.7, 0.5, 0.5], axis=1) < 0.1, 1, -1))
    recs = FR._recall_records(x, lab, 6000, [0, 1], samples, sgt, ["a", "b"], 0.005)
    for j, r in enumerate(recs):
        t = samples[sgt == j]
        assert r["covered"] == int(FR._covered(t, x[lab == j], 0.005).sum())
        assert r["covered_gaussians_only"] == int(FR._covered(t, x[:6000][lab[:6000] == j], 0.005).sum())
        assert r["covered_gaussians_only"] < r["covered"] < r["volume_samples"]


def test_evaluate_precision_recall_leakage():
    rng = np.random.default_rng(7)
    gt = SphereGT([[0.3, 0.5, 0.5], [0.7, 0.5, 0.5]], [0.1, 0.1])
    surf = np.concatenate([sphere_shell(2000, gt.c[0], 0.1, rng), sphere_shell(2000, gt.c[1], 0.1, rng)])
    g_gt = np.r_[np.zeros(2000), np.ones(2000)].astype(np.int32)
    pred = 1 - g_gt  # predicted labels are swapped: the mapping must undo it
    good = np.concatenate([gt.c[0] + rng.uniform(-0.05, 0.05, (400, 3)), gt.c[1] + rng.uniform(-0.05, 0.05, (400, 3))])
    bad = rng.uniform(0.46, 0.54, (200, 3))  # in the empty region, labelled as ball 0
    x = np.concatenate([surf, good, bad])
    lab = np.concatenate([pred, np.ones(400), np.zeros(400), np.ones(200)]).astype(np.int32)
    filled = np.r_[np.zeros(4000, bool), np.ones(1000, bool)]
    ev = FR.evaluate(x, lab, filled, g_gt, 4000, gt, radius_src=0.01)
    assert [i["gt_instance"] for i in ev["instances"]] == [1, 0]
    assert ev["precision"] == pytest.approx(800 / 1000)
    assert ev["leakage"]["between"]["filled_inside"] == 200
    assert ev["leakage"]["between"]["share_of_filled"] == pytest.approx(0.2)
    assert 0 < ev["recall_gaussians_only"] < ev["recall"] <= 1
    ev0 = FR.evaluate(surf, pred, np.zeros(4000, bool), g_gt, 4000, gt, radius_src=0.01)
    assert ev0["precision"]["value"] is None and "no filled" in ev0["precision"]["reason"]


# ---------------------------------------------------------------------------- stage end to end
def _pipeline(tmp_path, name, n, fills):
    from physgs_steps import prepare

    scene = {"source": f"builtin:{name}", "builtin": {"n_gaussians": n, "seed": 1}, "instances": []}
    p = {k: str(tmp_path / v) for k, v in [("scene", "scene.ply"), ("transform", "transform.json"),
                                          ("labels", "labels.npz"), ("clusters", "clusters.json")]}
    prepare.run({}, {"scene": p["scene"], "transform": p["transform"]},
                {"scene": scene, "prepare": section_defaults("prepare")}, LOG)
    CL.run({"scene": p["scene"]}, {"labels": p["labels"], "clusters": p["clusters"]},
           {"scene": scene, "cluster": section_defaults("cluster")}, LOG)
    out = {}
    for tag, over in fills.items():
        o = {"particles": str(tmp_path / f"particles_{tag}.h5"), "report": str(tmp_path / f"report_{tag}.json"),
             "carrier": str(tmp_path / f"carrier_{tag}.h5")}
        F.run({"scene": p["scene"], "labels": p["labels"], "transform": p["transform"]}, o,
              {"scene": scene, "fill": fcfg(n_grid=64, **over)}, LOG)
        out[tag] = o
    return p, out


def test_run_basket_mat_writes_particles_and_report(tmp_path):
    from physgs_steps.scene_io import load_gaussians

    p, out = _pipeline(tmp_path, "basket_mat", 8000, {"paper": {"particles": "gaussians"},
                                                      "surface": {"occupancy": "surface", "mcis": False}})
    scene = load_gaussians(p["scene"])
    with h5py.File(out["paper"]["particles"]) as h:
        x, lab, filled, vol, op = h["x"][:], h["label"][:], h["filled"][:], h["vol"][:], h["opacity"][:]
        assert h.attrs["n_gaussians"] == scene.n and h.attrs["n_instances"] == 2
        assert json.loads(h.attrs["config"])["method"] == "ipf" and h.attrs["particles"] == "gaussians"
        assert h["log_scales"].shape == (len(x), 3) and h["quats"].shape == (len(x), 4)
        np.testing.assert_array_equal(h["gaussian_row"][:scene.n], np.arange(scene.n))
        assert h["driver"][:scene.n].all() and not h["driver"][scene.n:].any()  # each gaussian drives itself
    assert x.dtype == np.float32 and lab.dtype == np.int32 and filled.dtype == bool and vol.dtype == np.float32
    np.testing.assert_array_equal(x[:scene.n], scene.means)  # the paper's way: every gaussian is a particle
    assert not filled[:scene.n].any() and filled[scene.n:].all() and filled.sum() > 0
    assert (op[filled] == 0).all() and (op[~filled] > 0).all() and (vol > 0).all()
    # the budget: one surface gaussian per sub-cell, the same filled interior, the same total volume
    with h5py.File(out["surface"]["particles"]) as h:
        rows, bx, bvol = h["gaussian_row"][:], h["x"][:], h["vol"][:]
        g = int((rows >= 0).sum())
        assert h.attrs["particles"] == "budget" and 0 < g < scene.n
        np.testing.assert_array_equal(bx[:g], scene.means[rows[:g]])
        assert (rows[g:] == -1).all() and np.all(np.diff(rows[:g]) > 0)
    paper = json.loads(Path(out["paper"]["report"]).read_text())
    surface = json.loads(Path(out["surface"]["report"]).read_text())
    for rep in (paper, surface):
        ev = rep["evaluation"]
        assert ev["available"] and set(ev["leakage"]) == {"gap", "basket_hollow"}
        assert {g["name"] for g in ev["ground_truth"]} == {"basket", "mat"}
        assert rep["timings"]["fill"]["seconds"] > 0 and rep["timings"]["cluster"]["seconds"] > 0
        assert rep["timings"]["fill"]["peak_alloc_mb"] > 0
    # the hull fills the basket's hollow, the surface-following test leaves it empty
    assert paper["evaluation"]["leakage"]["basket_hollow"]["filled_inside"] > 100
    assert surface["evaluation"]["leakage"]["basket_hollow"]["filled_inside"] == 0
    assert isinstance(paper["evaluation"]["precision"], float) and paper["evaluation"]["precision"] < 0.9


def test_run_without_ground_truth_and_stale_labels(tmp_path):
    rng = np.random.default_rng(8)
    pts = sphere_shell(3000, [0.5, 0.5, 0.5], 0.15, rng)
    n = len(pts)
    scene = GaussianScene(means=pts, log_scales=np.full((n, 3), np.log(0.003)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                          opacity_logits=np.full(n, 3.0), sh=np.zeros((n, 1, 3)))
    save_gaussians(scene, tmp_path / "scene.ply")
    np.savez(tmp_path / "labels.npz", labels=np.zeros(n, np.int32))
    inputs = {"scene": str(tmp_path / "scene.ply"), "labels": str(tmp_path / "labels.npz"), "transform": "unused"}
    outs = {"particles": str(tmp_path / "particles.h5"), "report": str(tmp_path / "report.json"),
            "carrier": str(tmp_path / "carrier.h5")}
    F.run(inputs, outs, {"scene": {"source": "my_capture.ply"}, "fill": fcfg()}, LOG)
    rep = json.loads(Path(outs["report"]).read_text())
    assert rep["evaluation"]["available"] is False and "ground-truth" in rep["evaluation"]["reason"]
    assert rep["n_filled"] > 0 and rep["timings"]["cluster"]["value"] is None
    np.savez(tmp_path / "labels.npz", labels=np.zeros(n - 1, np.int32))
    with pytest.raises(InputError, match="stale labels"):
        F.run(inputs, outs, {"scene": {"source": "my_capture.ply"}, "fill": fcfg()}, LOG)
