"""Config validation (defaults, wrong types, unknown keys) and the artifact plan's sharing rules."""
import copy

import pytest

from physgs_steps import config as C
from physgs_steps import plan as P
from physgs_steps.errors import ConfigError


@pytest.fixture(scope="module")
def cfg():
    return C.load_config()


def test_every_section_has_defaults_and_descriptions():
    for section in C.SECTIONS:
        schema = C.load_schema(f"{section}.schema.yaml")
        assert schema.get("additionalProperties") is False, section
        for key, sub in schema.get("properties", {}).items():
            assert "description" in sub, f"{section}.{key} has no description"
            assert "default" in sub, f"{section}.{key} has no default"
        assert isinstance(C.section_defaults(section), dict)


def test_wrong_type_names_the_key(cfg):
    bad = copy.deepcopy(cfg)
    bad["fill"]["sigma"] = "wide"
    with pytest.raises(ConfigError, match=r"fill\.sigma"):
        C.validate_config(bad)


def test_unknown_key_is_rejected_with_allowed_list(cfg):
    bad = copy.deepcopy(cfg)
    bad["render"]["widht"] = 100
    with pytest.raises(ConfigError, match="widht"):
        C.validate_config(bad)


def test_unknown_scene_and_ablation(cfg):
    with pytest.raises(ConfigError, match="known scenes"):
        P.make_plan(cfg, "no_such_scene")
    with pytest.raises(ConfigError, match="unknown ablation"):
        P.make_plan(cfg, "bear", "no_such_ablation")


def test_ablations_share_upstream_artifacts(cfg):
    base = P.make_plan(cfg, "bear")
    no_bgdo = P.make_plan(cfg, "bear", "no_bgdo")
    no_mcis = P.make_plan(cfg, "bear", "no_mcis")
    assert no_bgdo.ids["fill"] == base.ids["fill"] and no_bgdo.ids["sim"] == base.ids["sim"]
    assert no_bgdo.steps == ["it0"] and len(base.steps) == 1 + cfg["bgdo"]["iterations"]
    assert no_bgdo.path("final") != base.path("final")
    assert no_mcis.ids["cluster"] == base.ids["cluster"] and no_mcis.ids["params"] == base.ids["params"]
    assert no_mcis.ids["fill"] != base.ids["fill"]


def test_render_change_touches_only_render(cfg):
    a = P.make_plan(cfg, "bear")
    c2 = copy.deepcopy(cfg)
    c2["render"]["fps"] = a.cfgs["render"]["render"]["fps"] + 1
    b = P.make_plan(C.validate_config(c2), "bear")
    assert a.ids == b.ids
    assert a.cfgs["render"] != b.cfgs["render"]


def test_bgdo_change_keeps_first_forward(cfg):
    a = P.make_plan(cfg, "bear")
    c2 = copy.deepcopy(cfg)
    c2["bgdo"]["reference_height"] = a.cfgs["bgdo"]["bgdo"]["reference_height"] * 2
    b = P.make_plan(C.validate_config(c2), "bear")
    assert a.path("forward", "it0") == b.path("forward", "it0")
    assert a.ids["bgdo"] != b.ids["bgdo"] and a.path("final") != b.path("final")


def test_parse_target_and_steps():
    assert P.parse_target("bear") == ("bear", None)
    assert P.parse_target("bear/ablations/no_ipf") == ("bear", "no_ipf")
    with pytest.raises(ConfigError):
        P.parse_target("bear/x")
    assert P.previous_step("it1-abc") == "it0" and P.previous_step("it3-abc") == "it2-abc"


def test_scene_camera_edit_reaches_only_render(cfg, tmp_path, repo):
    import yaml

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    data = yaml.safe_load((repo / "config" / "scenes" / "bear.yaml").read_text())
    (scenes / "bear.yaml").write_text(yaml.safe_dump(data))
    data["camera"] = dict(data.get("camera") or {}, elevation_deg=42.0)
    data["instances"][0]["hint"] = "a rubber teddy bear"
    (scenes / "bear2.yaml").write_text(yaml.safe_dump(data))
    c = copy.deepcopy(cfg)
    c["scenes_dir"] = str(scenes)
    a, b = P.make_plan(c, "bear"), P.make_plan(c, "bear2")
    for stage in ("prepare", "cluster", "fill", "sim", "bgdo", "metrics"):
        assert {k: v for k, v in a.cfgs[stage]["scene"].items() if k != "_path"} == \
               {k: v for k, v in b.cfgs[stage]["scene"].items() if k != "_path"}, stage
    assert a.cfgs["render"]["scene"]["camera"] != b.cfgs["render"]["scene"]["camera"]
    # a material hint changes the parameters (and so the simulation) but not clustering or filling
    assert a.ids["cluster"] == b.ids["cluster"] and a.ids["fill"] == b.ids["fill"]
    assert a.ids["params"] != b.ids["params"]
