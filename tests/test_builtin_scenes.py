"""Tests of the built-in scenes (physgs_steps.builtin_scenes) and their SDF primitives."""
from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from sklearn.cluster import DBSCAN
from sklearn.metrics import adjusted_rand_score

from physgs_steps.builtin_scenes import BUILTIN_SCENES, DEFAULT_N_GAUSSIANS, ground_truth, make_scene
from physgs_steps.builtin_scenes import primitives as P
from physgs_steps.errors import ConfigError

K_GT = {"bear": 1, "bear_can": 2, "duck_stone": 2, "ficus": 1, "basket_mat": 2, "bread": 1, "ball_jelly": 2}
TWO = [s for s in BUILTIN_SCENES if K_GT[s] == 2]
SURFACE_TOL = 1e-5  # m; float32 means of a scene < 0.6 m across


@functools.lru_cache(maxsize=None)
def scene_of(name):
    return make_scene(name)


def normals_of(scene) -> np.ndarray:
    """[N, 3] third axis of every gaussian's rotation."""
    return scene.rotation_matrices()[:, :, 2].astype(np.float64)


def test_scene_names():
    assert BUILTIN_SCENES == ("bear", "bear_can", "duck_stone", "ficus", "basket_mat", "bread", "ball_jelly")
    assert set(K_GT) == set(BUILTIN_SCENES)


# ----------------------------------------------------------------------------- errors
def test_unknown_name_names_source_and_lists_valid():
    with pytest.raises(ConfigError) as e:
        make_scene("teapot")
    assert e.value.key == "source"
    for name in BUILTIN_SCENES:
        assert name in str(e.value)


@pytest.mark.parametrize("n", [99, 2_000_001, 0, -5, 1000.0, "1000", True])
def test_bad_n_gaussians(n):
    with pytest.raises(ConfigError) as e:
        make_scene("bear", n_gaussians=n)
    assert e.value.key == "builtin.n_gaussians"


@pytest.mark.parametrize("seed", [-1, 0.5, "0", None])
def test_bad_seed(seed):
    with pytest.raises(ConfigError) as e:
        make_scene("bear", n_gaussians=500, seed=seed)
    assert e.value.key == "builtin.seed"


def test_builtin_prefix_and_numpy_ints_accepted():
    scene, gt = make_scene("builtin:bread", n_gaussians=np.int64(300), seed=np.int32(2))
    assert scene.n == 300 and gt.instance_names == ["bread"]


# ----------------------------------------------------------------------------- determinism
@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_deterministic_for_a_seed(name):
    a, gta = make_scene(name, 1500, seed=3)
    b, gtb = make_scene(name, 1500, seed=3)
    c, _ = make_scene(name, 1500, seed=4)
    for field in ("means", "log_scales", "quats", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(a.extras["gt_label"], b.extras["gt_label"])
    np.testing.assert_array_equal(gta.bounds[0], gtb.bounds[0])
    assert not np.array_equal(a.means, c.means)


def test_minimum_count():
    scene, _ = make_scene("ficus", 100)
    assert scene.n == 100


# ----------------------------------------------------------------------------- per-scene structure
@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_counts_labels_and_fields(name):
    scene, gt = scene_of(name)
    n = DEFAULT_N_GAUSSIANS[name]
    assert n == (24000 if K_GT[name] == 2 else 20000)
    assert scene.n == n
    label = scene.extras["gt_label"]
    assert label.dtype == np.int32 and label.shape == (n,)
    assert len(gt.instance_names) == K_GT[name]
    assert sorted(np.unique(label)) == list(range(K_GT[name]))
    assert scene.sh.shape == (n, 1, 3) and scene.sh_degree == 0
    assert np.all((scene.opacity_logits >= 3.0) & (scene.opacity_logits <= 5.0))
    np.testing.assert_allclose(np.linalg.norm(scene.quats, axis=1), 1.0, atol=1e-5)
    for arr in (scene.means, scene.log_scales, scene.quats, scene.sh):
        assert np.all(np.isfinite(arr))
    # each gaussian's label is the instance whose surface it lies on
    for k in range(K_GT[name]):
        d = np.abs(gt.sdf(scene.means[label == k], instance=k))
        assert d.max() < SURFACE_TOL


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_gaussians_on_the_outer_surface_only(name):
    scene, gt = scene_of(name)
    d = gt.sdf(scene.means)
    assert np.abs(d).max() < SURFACE_TOL  # on the surface, and never inside a solid (no interior faces)
    # hollow: nothing deeper inside than the surface tolerance
    inner = scene.means.astype(np.float64) - 3e-4 * normals_of(scene)
    assert gt.inside(inner).mean() > 0.99


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_normals_point_outward(name):
    scene, gt = scene_of(name)
    x = scene.means.astype(np.float64)
    n = normals_of(scene)
    delta = 2e-4
    out = gt.sdf(x + delta * n)
    inn = gt.sdf(x - delta * n)
    assert np.all(out > inn)
    assert np.mean((out > 0) & (inn < 0)) > 0.99
    # the normal is the direction of the union sdf gradient
    sub = x[:2000]
    h = 1e-5
    grad = np.stack([(gt.sdf(sub + h * e) - gt.sdf(sub - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    cos = np.sum(P.normalize(grad) * n[:2000], axis=1)
    assert np.mean(cos > 0.95) > 0.98


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_flat_oriented_gaussians_at_sample_spacing(name):
    scene, _ = scene_of(name)
    s = scene.scales.astype(np.float64)
    ratio = s[:, 2] / s[:, :2].mean(axis=1)
    assert ratio.min() > 0.099 and ratio.max() < 0.201
    nn, _ = cKDTree(scene.means).query(scene.means, k=2)
    spacing = np.median(nn[:, 1])
    tangent = np.median(s[:, :2])
    assert 0.5 < tangent / spacing < 2.0


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_colour_per_part(name):
    scene, gt = scene_of(name)
    parts = [p for _, p in gt.parts()]
    d = np.stack([np.abs(p.solid.sdf(scene.means)) for p in parts], axis=1)
    owner = d.argmin(axis=1)
    colours = scene.base_colors()
    for j, part in enumerate(parts):
        c = colours[owner == j]
        if len(c) > 20:
            assert np.all(np.abs(np.median(c, axis=0) - part.color) < 0.03), part.name
            assert np.all(c.std(axis=0) < 0.05), part.name


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_bounds_resting_and_centred(name):
    scene, gt = scene_of(name)
    lo, hi = gt.bounds
    x = scene.means.astype(np.float64)
    assert np.all(x >= lo - 1e-6) and np.all(x <= hi + 1e-6)
    assert np.all(np.abs(x.min(axis=0) - lo) < 0.01) and np.all(np.abs(x.max(axis=0) - hi) < 0.01)
    assert abs(lo[2]) < 1e-9
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)
    assert 0.08 < (hi - lo).max() < 0.6


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_empty_regions_stay_empty(name):
    scene, gt = scene_of(name)
    regions = gt.empty_regions()
    if K_GT[name] == 2:
        assert "gap" in regions
    if name == "basket_mat":
        assert "basket_hollow" in regions
    lo, hi = gt.bounds
    probe = np.random.default_rng(0).uniform(lo, hi, (200_000, 3))
    for rname, region in regions.items():
        assert not region(scene.means).any(), rname
        pts = probe[region(probe)]
        assert len(pts) > 200, rname
        assert not gt.inside(pts).any(), rname


def test_landmarks():
    for name in ("bear", "bear_can"):
        _, gt = scene_of(name)
        belly = gt.landmarks["belly_center"][None]
        assert gt.inside(belly)[0] and gt.instance_of(belly)[0] == 0
        assert gt.inside(belly, instance="bear")[0]
    _, gt = scene_of("basket_mat")
    hollow = gt.landmarks["hollow_center"][None]
    assert gt.instance_of(hollow)[0] == -1 and not gt.inside(hollow)[0]
    assert gt.sdf(hollow)[0] > 0.05
    assert gt.empty_regions()["basket_hollow"](hollow)[0]
    assert gt.instance_of(gt.landmarks["basket_wall"][None])[0] == gt.instance_names.index("basket")
    assert gt.instance_of(gt.landmarks["mat_center"][None])[0] == gt.instance_names.index("mat")
    _, gt = scene_of("duck_stone")
    assert gt.instance_names == ["duck", "stone"]
    assert gt.instance_of(np.stack([gt.landmarks["duck_center"], gt.landmarks["stone_center"]])).tolist() == [0, 1]


def test_ground_truth_without_gaussians_matches():
    gt = ground_truth("bear_can")
    _, gt2 = scene_of("bear_can")
    np.testing.assert_array_equal(gt.bounds[1], gt2.bounds[1])
    assert gt.instance_names == ["bear", "can"]
    with pytest.raises(ValueError):
        gt.inside(np.zeros((3, 2)))
    with pytest.raises(ValueError):
        gt.sdf(np.zeros((1, 3)), instance="duck")


@pytest.mark.parametrize("name", TWO)
def test_instances_separated_by_air_gap(name):
    scene, gt = scene_of(name)
    x = scene.means.astype(np.float64)
    label = scene.extras["gt_label"]
    side = (gt.bounds[1] - gt.bounds[0]).max()
    d, _ = cKDTree(x[label == 0]).query(x[label == 1])
    assert d.min() >= 0.12 * side
    (alo, ahi), (blo, bhi) = gt.instances[0].aabb(), gt.instances[1].aabb()
    gap = np.maximum(blo - ahi, alo - bhi).max()
    assert gap >= 0.12 * side


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_dbscan_recovers_the_instances(name):
    scene, _ = scene_of(name)
    x = scene.means.astype(np.float64)
    x = (x - x.min(axis=0)) * (0.5 / np.ptp(x, axis=0).max())
    labels = DBSCAN(eps=0.06, min_samples=5).fit_predict(x)
    assert len(set(labels) - {-1}) == K_GT[name]
    assert np.mean(labels == -1) < 0.001
    assert adjusted_rand_score(scene.extras["gt_label"], labels) > 0.99


@pytest.mark.parametrize("name", BUILTIN_SCENES)
def test_parts_of_an_instance_overlap_and_show(name):
    _, gt = scene_of(name)
    rng = np.random.default_rng(1)
    for inst in gt.instances:
        samples = [p.solid.sample(3000, rng)[0] for p in inst.parts]
        m = len(inst.parts)
        adj = np.zeros((m, m), dtype=bool)
        for i in range(m):
            others_inside = np.zeros(len(samples[i]), dtype=bool)
            for j in range(m):
                if i != j:
                    hit = inst.parts[j].solid.inside(samples[i])
                    adj[i, j] |= hit.any()
                    adj[j, i] |= hit.any()
                    others_inside |= hit
            assert not others_inside.all(), f"{inst.name}.{inst.parts[i].name} is hidden inside other parts"
        n_comp, comp = connected_components(csr_matrix(adj), directed=False)
        assert n_comp == 1, f"{inst.name}: parts {[p.name for p, c in zip(inst.parts, comp) if c != comp[0]]} float free"


def test_scene_shapes_are_what_they_claim():
    _, gt = scene_of("bear")
    lo, hi = gt.bounds
    assert 0.27 < hi[2] - lo[2] < 0.33  # about 0.3 m tall
    _, gt = scene_of("ficus")
    leaves = [p for _, p in gt.parts() if p.name.startswith("leaf_")]
    assert 20 <= len(leaves) <= 40
    assert all(2 * min(p.solid.radii) < 0.006 for p in leaves)  # a few mm thick
    _, gt = scene_of("bread")
    ext = gt.bounds[1] - gt.bounds[0]
    assert ext[0] > 1.8 * ext[1] and ext[0] > 2 * ext[2]  # elongated loaf
    _, gt = scene_of("duck_stone")
    duck_lo = gt.instances[0].aabb()[0]
    stone_hi = gt.instances[1].aabb()[1]
    assert duck_lo[2] > stone_hi[2]  # the duck floats above the stone
    _, gt = scene_of("basket_mat")
    basket_lo = gt.instances[0].aabb()[0]
    mat_lo, mat_hi = gt.instances[1].aabb()
    assert basket_lo[2] > mat_hi[2] and mat_hi[2] - mat_lo[2] < 0.06  # a flat mat, 5 cm thick


# ----------------------------------------------------------------------------- primitives
ROT = Rotation.from_euler("xyz", [23, -41, 67], degrees=True).as_matrix()
PRIMITIVES = {
    "sphere": P.sphere([0.1, 0.0, 0.2], 0.05),
    "ellipsoid": P.ellipsoid([0.0, 0.1, 0.0], [0.08, 0.05, 0.02], rot=ROT),
    "capsule": P.capsule([0.0, 0.0, 0.0], [0.06, 0.03, 0.08], 0.02),
    "rounded_box": P.rounded_box([0.0, 0.0, 0.1], [0.06, 0.04, 0.03], 0.01, rot=ROT),
    "cylinder": P.cylinder([0.0, 0.0, 0.0], 0.04, 0.1, rounding=0.008, rot=ROT),
    "sharp_cylinder": P.cylinder([0.0, 0.0, 0.0], 0.05, 0.04),
    "torus": P.torus([0.0, 0.0, 0.0], 0.05, 0.015, rot=ROT),
    "cup": P.cup([0.0, 0.0, 0.0], 0.06, 0.05, 0.08, 0.012),
}
BLOB = P.blob([0.0, 0.0, 0.05], [0.1, 0.07, 0.05], [0.1, 0.08, 0.05], [[2.0, 0.5, 0.0], [0.0, 3.0, 1.0], [1.0, 1.0, 2.5]],
              [0.3, 1.0, 2.0])


@pytest.mark.parametrize("kind", list(PRIMITIVES) + ["blob"])
def test_samples_lie_on_surface_with_outward_normals(kind):
    prim = BLOB if kind == "blob" else PRIMITIVES[kind]
    x, n = prim.sample(5000, np.random.default_rng(0))
    assert x.shape == (5000, 3) and n.shape == (5000, 3)
    assert np.abs(prim.sdf(x)).max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
    h = 1e-6
    grad = np.stack([(prim.sdf(x + h * e) - prim.sdf(x - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    cos = np.sum(P.normalize(grad) * n, axis=1)
    assert np.mean(cos > 0.999) > 0.99
    lo, hi = prim.aabb()
    assert np.all(x >= lo - 1e-9) and np.all(x <= hi + 1e-9)
    assert np.all(x.min(axis=0) - lo < 0.003) and np.all(hi - x.max(axis=0) < 0.003)


@pytest.mark.parametrize("kind", list(PRIMITIVES))
def test_area_and_uniform_sampling_match_a_thin_shell(kind):
    """Points of the shell |sdf| < eps are area-uniform and their volume is 2 eps area."""
    prim = PRIMITIVES[kind]
    rng = np.random.default_rng(5)
    eps = 5e-4
    lo, hi = prim.aabb()
    lo, hi = lo - 2 * eps, hi + 2 * eps
    m = 400_000
    probe = rng.uniform(lo, hi, (m, 3))
    shell = probe[np.abs(prim.sdf(probe)) < eps]
    est_area = np.prod(hi - lo) * len(shell) / m / (2 * eps)
    tol = 0.03 if kind in ("cup", "sharp_cylinder") else 0.02  # sharp edges shave the inner shell
    assert abs(est_area / prim.area() - 1) < tol
    x, _ = prim.sample(len(shell) * 2, rng)
    edges = [np.linspace(lo[i], hi[i], 5) for i in range(3)]
    h_shell, _ = np.histogramdd(shell, bins=edges)
    h_samp, _ = np.histogramdd(x, bins=edges)
    tv = 0.5 * np.abs(h_shell / h_shell.sum() - h_samp / h_samp.sum()).sum()
    assert tv < 0.04


def test_ellipsoid_area_formula():
    assert abs(P.sphere([0, 0, 0], 0.1).area() - P.ellipsoid([0, 0, 0], [0.1, 0.1, 0.1]).area()) < 1e-12
    # prolate spheroid closed form
    a, c = 0.05, 0.12
    e = np.sqrt(1 - a * a / (c * c))
    exact = 2 * np.pi * a * a * (1 + c / (a * e) * np.arcsin(e))
    assert abs(P.ellipsoid([0, 0, 0], [a, a, c]).area() / exact - 1) < 1e-9


@pytest.mark.parametrize("radii", [[0.08, 0.05, 0.02], [0.04, 0.0168, 0.0015], [0.05, 0.05, 0.02], [0.05, 0.02, 0.02]])
def test_ellipsoid_distance_is_exact(radii):
    radii = np.array(radii)
    rng = np.random.default_rng(2)
    q = rng.normal(size=(3000, 3)) * radii * 0.9
    q[:300, 2] = 0.0  # degenerate: on the plane of the two largest axes
    q[300:400, 1:] = 0.0  # on the major axis
    q[400] = 0.0  # the centre
    d = P.ellipsoid_distance(q, radii)
    surf, _ = P.ellipsoid([0, 0, 0], radii).sample(300_000, rng)
    nn, _ = cKDTree(surf).query(q)
    assert np.all(np.abs(d) <= nn + 1e-12)  # no surface point is closer than d
    assert np.all(nn - np.abs(d) < 4e-4)  # and d is reached up to the sample spacing
    assert np.all((d < 0) == (np.sum((q / radii) ** 2, axis=1) < 1))
    assert abs(d[400] + radii.min()) < 1e-12


@pytest.mark.parametrize("kind", ["cup", "blob"])
def test_bound_sdf_is_conservative(kind):
    prim = BLOB if kind == "blob" else PRIMITIVES[kind]
    rng = np.random.default_rng(3)
    lo, hi = prim.aabb()
    q = rng.uniform(lo - 0.03, hi + 0.03, (4000, 3))
    d = prim.sdf(q)
    surf, _ = prim.sample(300_000, rng)
    nn, _ = cKDTree(surf).query(q)
    assert np.all(np.abs(d) <= nn + 1e-12)
    assert np.all((d < 0) == prim.inside(q))
    assert np.median(np.abs(d) / np.maximum(nn, 1e-9)) > 0.2  # a useful bound, not ~0


@pytest.mark.parametrize("name", ["bear", "ficus", "basket_mat"])
def test_union_sdf_equals_min_over_parts(name):
    _, gt = scene_of(name)
    lo, hi = gt.bounds
    q = np.random.default_rng(4).uniform(lo - 0.05, hi + 0.05, (20_000, 3))
    ref = np.min([p.solid.sdf(q) for _, p in gt.parts()], axis=0)
    np.testing.assert_array_equal(gt.sdf(q), ref)
    np.testing.assert_array_equal(gt.inside(q), ref < 0)


def test_the_stone_lies_in_its_resting_pose():
    """duck_stone's free stone starts at rest on the ground: its centre of mass lies above its
    lowest point and any small tilt raises it (a stable equilibrium). Before, it lay 2.8 degrees
    off that pose, its centre of mass 12 mm beside its lowest point: released in the simulation
    it rolled into it with 0.16 J and rocked about it for seconds."""
    gt = ground_truth("duck_stone")
    solid = gt.instances[gt.instance_names.index("stone")].parts[0].solid
    mesh = solid.mesh()
    v = solid.to_world(np.asarray(mesh.vertices, dtype=np.float64))
    com = solid.to_world(np.asarray(mesh.center_mass, dtype=np.float64)[None])[0]
    low = v[v[:, 2].argmin()]
    assert np.linalg.norm(low[:2] - com[:2]) < 3e-3  # a mesh edge (about 3 mm), not 12 mm

    def height(a):
        R = Rotation.from_rotvec([a[0], a[1], 0.0]).as_matrix()
        return (R @ com)[2] - (v @ R.T)[:, 2].min()

    h0 = height([0.0, 0.0])
    for d in np.radians([[1, 0], [-1, 0], [0, 1], [0, -1], [0.7, 0.7], [-0.7, 0.7]]):
        assert height(d) > h0 + 1e-6  # 1 degree either way lifts the centre of mass


def _surface_curvature(solid, x0, y0, z_lo, z_hi, half=0.025, n=9):
    """(curvature tensor [2, 2] (1/m, positive where the surface bulges away from the solid
    in its normal's z direction), slope in degrees, z at (x0, y0)) of the solid's surface
    z(x, y) around (x0, y0) between z_lo and z_hi (one crossing: its top if the solid is at
    z_lo, its bottom if at z_hi), from a quadratic fit of points found on vertical rays."""
    from scipy.optimize import brentq

    g = np.linspace(-half, half, n)
    X, Y = (a.ravel() for a in np.meshgrid(g, g))

    def f(x, y, z):
        return float(solid.sdf(np.array([[x, y, z]]))[0])

    Z = np.array([brentq(lambda z: f(x0 + a, y0 + b, z), z_lo, z_hi, xtol=1e-10) for a, b in zip(X, Y)])
    c = np.linalg.lstsq(np.stack([np.ones_like(X), X, Y, X * X, X * Y, Y * Y], 1), Z, rcond=None)[0]
    grad = c[1:3]
    H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]]) / (1.0 + grad @ grad) ** 1.5
    top = f(x0, y0, z_lo) < 0
    return (-H if top else H), float(np.degrees(np.arctan(np.linalg.norm(grad)))), float(c[0])


def test_the_duck_can_rest_on_the_stone():
    """duck_stone's duck lands on a stone top flat enough to balance on: a body whose centre of
    mass is h above its bottom rests on another only if the largest eigenvalue of the two
    surfaces' summed curvature tensors is below 1/h (1/h > 1/r + 1/R in 2-D). The old stone
    ([0.12, 0.09, 0.058]) had a top radius of 0.14 m across under the duck: h times the
    eigenvalue was 1.22 and the duck rolled off. The duck is dropped in its resting pose: its
    centre of mass above its lowest point (built upright it lay 7 mm ahead of it)."""
    gt = ground_truth("duck_stone")
    duck = gt.instances[gt.instance_names.index("duck")]
    solid = gt.instances[gt.instance_names.index("stone")].parts[0].solid
    body = next(p.solid for p in duck.parts if p.name == "body")
    lo, hi = duck.aabb()
    q = np.random.default_rng(1).uniform(lo, hi, (200_000, 3))
    inside = np.zeros(len(q), bool)
    for p in duck.parts:
        inside |= p.solid.inside(q)
    com = q[inside].mean(axis=0)  # uniform density
    # the body's lowest point: the ellipsoid's support point in -z
    A_inv = body.rot @ np.diag(body.radii**2) @ body.rot.T
    low = body.center - A_inv[:, 2] / np.sqrt(A_inv[2, 2])
    assert np.linalg.norm(com[:2] - low[:2]) < 1.5e-3  # resting pose: the centre of mass above it
    h = com[2] - low[2]
    assert 0.05 < h < 0.06
    k_duck, _, _ = _surface_curvature(body, low[0], low[1], low[2] - 0.01, body.center[2], half=0.006)
    v = solid.to_world(np.asarray(solid.mesh().vertices))
    k_stone, slope, _ = _surface_curvature(solid, low[0], low[1], float(v[:, 2].mean()), float(v[:, 2].max()) + 0.01)
    assert slope < 3.0
    assert np.linalg.eigvalsh(k_stone).min() > 0.0  # a convex top there, no saddle
    # stable, with margin (the duck alone on a plane: 0.80)
    assert h * np.linalg.eigvalsh(k_duck + k_stone).max() < 0.95
