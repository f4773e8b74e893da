"""The simulation region: static surroundings outside ``region.box`` (prepare), static
instances (cluster), no particles for either (fill), drawn at rest (carrier)."""
from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgs_steps import cluster as CL
from physgs_steps import fill as F
from physgs_steps import prepare
from physgs_steps.carrier import load_carrier
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError
from physgs_steps.gaussians import GaussianScene
from physgs_steps.plan import scene_view
from physgs_steps.scene_io import load_gaussians, save_gaussians

LOG = logging.getLogger("test.region")


def _capture(rng) -> GaussianScene:
    """Source frame (metres, z up): a table top (a slab 2 x 2 x 0.1 at z 0..0.1), a ball of
    radius 0.1 resting on it at (0, 0, 0.3), a cube of side 0.2 next to it at (0.5, 0, 0.25),
    and a far wall (x = 5) that must not decide the scale."""
    def shell(n, c, r):
        d = rng.normal(size=(n, 3))
        return np.asarray(c) + r * d / np.linalg.norm(d, axis=1, keepdims=True)

    table = np.c_[rng.uniform(-1, 1, (3000, 2)), rng.uniform(0.0, 0.1, 3000)]
    ball = shell(1500, [0.0, 0.0, 0.3], 0.1)
    cube = rng.uniform([0.4, -0.1, 0.15], [0.6, 0.1, 0.35], (1500, 3))
    wall = np.c_[np.full(500, 5.0), rng.uniform(-1, 1, (500, 2))]
    means = np.concatenate([table, ball, cube, wall])
    n = len(means)
    return GaussianScene(means=means, log_scales=np.full((n, 3), np.log(0.01)), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                         opacity_logits=np.full(n, 2.0), sh=np.zeros((n, 1, 3)))


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    d = tmp_path_factory.mktemp("region")
    save_gaussians(_capture(np.random.default_rng(0)), d / "src.ply")
    return d


def _prepare(d, scene_cfg):
    outs = {"scene": str(d / "scene.ply"), "transform": str(d / "transform.json")}
    prepare.run({"source": str(d / "src.ply")}, outs, {"scene": scene_cfg, "prepare": section_defaults("prepare")}, LOG)
    return outs


def _cluster(d, scene_cfg):
    outs = {"labels": str(d / "labels.npz"), "clusters": str(d / "clusters.json")}
    ccfg = section_defaults("cluster")
    ccfg["eps"] = 0.04
    CL.run({"scene": str(d / "scene.ply")}, outs, {"scene": scene_cfg, "cluster": ccfg}, LOG)
    return outs, json.loads(Path(outs["clusters"]).read_text())


def test_region_box_keeps_the_surroundings_static(staged):
    d = staged
    scene_cfg = {"source": str(d / "src.ply"), "region": {"box": [[-0.7, -0.3, 0.05], [0.7, 0.3, 0.5]]}}
    _prepare(d, scene_cfg)
    sim = load_gaussians(d / "scene.ply")
    rec = json.loads((d / "transform.json").read_text())
    static = sim.extras["static"] != 0
    assert sim.n == 6500 and rec["n_static"] == int(static.sum())
    assert static[6000:].all() and not static[3000:6000].any()  # the far wall and most of the table are static
    # the domain is fitted to what is simulated (ball, cube, the table's top layer in the box), not the far wall
    lo, hi = np.quantile(sim.means[~static], [0.01, 0.99], axis=0)  # prepare.trim_quantile
    assert (hi - lo).max() == pytest.approx(0.5, abs=1e-3)
    assert sim.means[6000:, 0].min() > 1.0  # static gaussians may lie outside the domain
    with pytest.raises(ConfigError, match="region.box.*contains none"):
        _prepare(d, {"source": str(d / "src.ply"), "region": {"box": [[9, 9, 9], [10, 10, 10]]}})
    with pytest.raises(ConfigError, match="region.box.*below"):
        _prepare(d, {"source": str(d / "src.ply"), "region": {"box": [[1, 0, 0], [0, 1, 1]]}})


def test_static_instances_by_choice_and_pin(staged):
    d = staged
    box = {"box": [[-0.7, -0.3, 0.12], [0.7, 0.3, 0.5]]}  # above the table: ball and cube only
    base = {"source": str(d / "src.ply"), "region": box}
    _prepare(d, base)
    sim = load_gaussians(d / "scene.ply")
    static = sim.extras["static"] != 0
    ball_at = prepare.load_transform(d / "transform.json").to_sim([[0.0, 0.0, 0.3]])[0].tolist()
    instances = [{"name": "ball", "at": ball_at, "hint": "a rubber ball"}, {"name": "cube"}]
    outs, rec = _cluster(d, {**base, "instances": instances})
    labels = np.load(outs["labels"])["labels"]
    assert (labels[static] == CL.STATIC).all() and (labels[~static] >= 0).all()
    assert rec["n_instances"] == 2 and rec["static_instances"] == [] and rec["n_static_surroundings"] == int(static.sum())
    ball = next(r["label"] for r in rec["instances"] if r["name"] == "ball")
    # choose by hint: the cube is static
    _, rec2 = _cluster(d, {**base, "instances": instances, "region": {**box, "instances": ["a rubber ball"]}})
    assert rec2["static_instances"] == [1 - ball] and [r["static"] for r in rec2["instances"]].count(True) == 1
    # pin static: the same
    pinned = [instances[0], {"name": "cube", "static": True}]
    outs3, rec3 = _cluster(d, {**base, "instances": pinned})
    assert rec3["static_instances"] == [1 - ball] and CL.load_static_instances(outs3["labels"]) == [1 - ball]
    with pytest.raises(ConfigError, match=r"region.instances\[0\].*neither the name nor the hint"):
        _cluster(d, {**base, "instances": instances, "region": {**box, "instances": ["a duck"]}})
    with pytest.raises(ConfigError, match=r"region.instances\[0\].*label 5 does not exist"):
        _cluster(d, {**base, "instances": instances, "region": {**box, "instances": [5]}})
    with pytest.raises(ConfigError, match="nothing is left to simulate"):
        _cluster(d, {**base, "instances": [instances[0] | {"static": True}, pinned[1]]})
    # fill: static gaussians and static instances have no particles; the carrier draws them at rest
    fouts = {"particles": str(d / "particles.h5"), "carrier": str(d / "carrier.h5"), "report": str(d / "fill.json")}
    fcfg = section_defaults("fill")
    F.run({"scene": str(d / "scene.ply"), "labels": outs3["labels"], "transform": str(d / "transform.json")}, fouts,
          {"scene": base, "fill": fcfg}, LOG)
    c = load_carrier(fouts["carrier"], sim.n)
    labels3 = np.load(outs3["labels"])["labels"]
    np.testing.assert_array_equal(c.static, (labels3 == CL.STATIC) | (labels3 == 1 - ball))
    with h5py.File(fouts["particles"]) as h:
        assert set(np.unique(h["label"][()]).tolist()) == {ball}
        sx = h["static_x"][()]
        assert len(sx) > 0 and ((sx >= 0) & (sx <= 1)).all()  # collider geometry inside the domain
    report = json.loads(Path(fouts["report"]).read_text())
    assert report["instances"][1 - ball]["status"] == "static" and report["n_static_gaussians"] == int(c.static.sum())


def test_plan_views_leave_hints_out_unless_chosen_by_them():
    sc = {"source": "x.ply", "region": {"box": [[0, 0, 0], [1, 1, 1]], "instances": ["a duck", 0]},
          "instances": [{"name": "duck", "hint": "a duck"}, {"name": "stone", "hint": "grey", "static": True}]}
    v = scene_view(sc, "cluster")
    assert v["instances"] == [{"name": "duck", "at": None, "box": None, "hint": "a duck"},
                              {"name": "stone", "at": None, "box": None, "static": True}]
    assert v["region"] == {"instances": ["a duck", 0]}
    assert scene_view(sc, "prepare")["region"] == {"box": [[0, 0, 0], [1, 1, 1]]}


def test_static_table_instance_is_a_collider_the_dropped_jelly_rests_on(caplog):
    """A static instance (no particles: particles.h5 ``static_x`` points with its label) is a
    level-set collider of the simulation: a jelly block dropped 1 cm onto a static table top
    comes to rest on it (not on the ground 0.2 m below), and the table costs no particles.
    (Materials, grid and dynamics as the fixed-slab test of test_mpm_rigid.py: same kernels.)"""
    from physgs_steps.mpm import Material
    from physgs_steps.simulate import build_solver

    def box(lo, hi, s):
        axes = [np.arange(a + s / 2, b - 1e-9, s) for a, b in zip(lo, hi)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    s, h, top = 1 / 64, 0.125, 0.36
    table = box([0.30, 0.30, top - 3 * s], [0.70, 0.70, top], s)            # static instance 0, top face at `top`
    xj = box([0.43, 0.43, top + 0.01], [0.57, 0.57, top + 0.09], s)          # jelly 1 cm above it
    other = box([0.30, 0.30, 0.80], [0.40, 0.40, 0.82], s)                   # surroundings (label -1)
    parts = {"x": xj, "vol": np.full(len(xj), s ** 3), "label": np.ones(len(xj), np.int32),
             "static_x": np.r_[table, other], "static_label": np.r_[np.zeros(len(table), np.int32),
                                                                    np.full(len(other), -1, np.int32)]}
    jelly = Material("fixed_corotated", "identity", E=5.0e4, nu=0.3, density=1000.0, name="jelly")
    params = {"instances": [{"label": 0, "name": "table", "surface": "separate", "friction": 0.5}]}
    cfg = {"device": "cpu", "sim": {"n_grid": 32, "domain_size": 1.0},
           "scene": {"dynamics": {"ground": {"height": h, "friction": 0.5, "surface": "separate"}, "damping": 2.0}}}
    with caplog.at_level(logging.INFO):
        sol = build_solver(parts, [jelly], [1], cfg, LOG, params)
    assert sol.n_particles == len(xj)                                          # the table has no particles
    assert "static instance table (label 0): STATIC COLLIDER" in caplog.text
    assert "static surroundings (label -1): STATIC COLLIDER" in caplog.text
    dt = 0.4 * (1 / 32) / jelly.wave_speed
    for _ in range(int(0.75 / dt)):
        sol.substep(dt)
    st = sol.get_state()
    zj = st["x"][:, 2]
    # on the table top (within a quarter cell: the level set is sampled at the grid nodes), not in it
    assert zj.min() > top - 0.25 / 32 and zj.min() < top + 0.5 / 32
    assert np.abs(st["v"]).max() < 0.05
    # a static point inside the material at the start is left out (it would push the material),
    # with the table's points within a cell of the material touching it; the rest of the table stays
    touching = {**parts, "static_x": np.r_[table, xj[:1]], "static_label": np.zeros(len(table) + 1, np.int32)}
    from physgs_steps.simulate import static_colliders
    geoms = static_colliders(touching, params, cfg, LOG)
    left = geoms[0].points
    assert len(geoms) == 1 and np.linalg.norm(left - xj[0], axis=1).min() > 1 / 32
    assert 0.95 * len(table) < len(left) < len(table)
