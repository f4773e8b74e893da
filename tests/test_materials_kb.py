"""The material knowledge base file and its loader / name normalisation."""
from __future__ import annotations

import pytest
import yaml

from physgs_steps import materials_kb as mkb
from physgs_steps.errors import ConfigError, InputError

REQUIRED = ["jelly", "rubber", "elastomer", "metal", "sand", "snow", "plasticine", "water", "foam",
            "stone", "honey", "bread", "plant", "wood", "plastic"]
SOFT = ["jelly", "foam", "bread", "rubber", "elastomer"]
NEAR_RIGID = ["stone", "metal", "wood"]


@pytest.fixture(scope="module")
def kb():
    return mkb.load_kb()


def test_required_materials_and_keys(kb):
    for name in REQUIRED:
        assert name in kb, name
        e = kb[name]
        for k in ("elasticity", "plasticity", "E", "E_range", "E_real", "nu", "density",
                  "plasticity_params", "aliases", "source"):
            assert k in e, (name, k)
        assert e["elasticity"] in mkb.ELASTICITY_MODELS and e["plasticity"] in mkb.PLASTICITY_MODELS
        lo, hi = e["E_range"]
        assert 0 < lo <= e["E"] <= hi
        assert 0 <= e["nu"] < 0.5 and e["density"] > 0
        assert set(e["plasticity_params"]) == set(mkb.PLASTICITY_PARAM_KEYS)
        for req in mkb.REQUIRED_PLASTICITY_PARAMS[e["plasticity"]]:
            assert e["plasticity_params"][req] is not None, (name, req)
        assert e["source"].strip() and "\n" not in e["source"].strip()


def test_effective_moduli_scale(kb):
    for name in SOFT:
        assert 1e4 <= kb[name]["E"] <= 1e6, name
    for name in NEAR_RIGID:
        assert 1e7 <= kb[name]["E"] <= 1e8, name
    # handbook values are kept separately and are far stiffer for the rigid materials
    assert kb["metal"]["E_real"] >= 1e11 and kb["stone"]["E_real"] >= 1e10
    assert kb["water"]["E_real"] is None  # a liquid has no Young's modulus


def test_file_is_plain_yaml_with_float_numbers():
    raw = yaml.safe_load(mkb.default_kb_path().read_text())
    text = mkb.default_kb_path().read_text()
    assert "E_real" in text.split("\njelly:")[0]  # header comment explains effective vs handbook E
    for name, e in raw.items():
        for k in ("E", "nu", "density"):
            assert isinstance(e[k], (int, float)) and not isinstance(e[k], bool), (name, k, e[k])
        assert all(isinstance(v, (int, float)) for v in e["E_range"]), name


@pytest.mark.parametrize("word,expected", [
    ("jelly", "jelly"), ("Rubber", "rubber"), ("play-doh", "plasticine"), ("steel", "metal"),
    ("Aluminium", "metal"), ("leaf", "plant"), ("granite", "stone"), ("memory foam", "foam"),
    ("memory_foam", "foam"), ("syrup", "honey"),
])
def test_get_material_by_name_or_alias(word, expected):
    assert mkb.get_material(word)["name"] == expected


def test_get_material_unknown_lists_valid_names():
    with pytest.raises(ConfigError) as ei:
        mkb.get_material("unobtainium", key="scene.instances[0].material")
    msg = str(ei.value)
    assert "scene.instances[0].material" in msg and "unobtainium" in msg and "jelly" in msg and "stone" in msg


def test_get_material_returns_a_copy():
    e = mkb.get_material("jelly")
    e["E"] = -1
    assert mkb.get_material("jelly")["E"] > 0


@pytest.mark.parametrize("kind,name,canon", [
    ("elasticity", "sigma", "stvk_hencky"), ("plasticity", "sigma", "j_clamp"),
    ("elasticity", "StVK", "stvk_hencky"), ("elasticity", "Fixed Corotated", "fixed_corotated"),
    ("elasticity", "neo-Hookean elasticity", "neo_hookean"), ("plasticity", "von Mises", "von_mises"),
    ("plasticity", "Drucker-Prager plasticity", "drucker_prager"), ("plasticity", "none", "identity"),
    ("plasticity", "fluid", "fluid"), ("elasticity", "fluid", "fluid"),
])
def test_normalize_model(kind, name, canon):
    assert mkb.normalize_model(kind, name) == canon
    assert mkb.is_model_name(kind, name)


@pytest.mark.parametrize("kind,name", [("elasticity", "von_mises"), ("plasticity", "neo_hookean"),
                                       ("elasticity", ""), ("plasticity", 3)])
def test_normalize_model_rejects(kind, name):
    with pytest.raises(ConfigError) as ei:
        mkb.normalize_model(kind, name, key="materials.x")
    assert "materials.x" in str(ei.value) and "valid" in str(ei.value)
    assert not mkb.is_model_name(kind, name)


def test_full_plasticity_params_defaults():
    full = mkb.full_plasticity_params({"yield_stress": 10})
    assert full == {"yield_stress": 10.0, "friction_angle": None, "cohesion": 0.0, "j_min": 0.05, "j_max": 1.2,
                    "fracture_strain": None, "fracture_softening": 0.2}


def test_material_params_and_table():
    p = mkb.material_params("sand")
    assert p["plasticity"] == "mohr_coulomb" and p["plasticity_params"]["friction_angle"] > 0
    table = mkb.kb_table_text()
    assert table.count("\n") + 1 == len(mkb.material_names())
    assert "friction_angle=" in table and "yield_stress=" in table


GOOD = {"elasticity": "fixed_corotated", "plasticity": "identity", "E": 1.0e+5, "E_range": [1.0e+4, 1.0e+6],
        "E_real": None, "nu": 0.3, "density": 1000.0, "plasticity_params": {}, "aliases": ["goo"],
        "source": "test"}


@pytest.mark.parametrize("change,needle", [
    ({"E": "50 kPa"}, "finite number"),
    ({"E": 1.0e+7}, "outside E_range"),
    ({"nu": 0.5}, "nu must lie"),
    ({"elasticity": "bogus"}, "unknown elasticity"),
    ({"plasticity": "von_mises"}, "needs plasticity_params"),
    ({"plasticity_params": {"yield": 3}}, "unknown plasticity_params"),
    ({"aliases": []}, "at least one alias"),
    ({"source": None}, "source must be"),
])
def test_malformed_kb_is_an_input_error(tmp_path, change, needle):
    entry = dict(GOOD, **change)
    p = tmp_path / "kb.yaml"
    p.write_text(yaml.safe_dump({"goo": entry}))
    with pytest.raises(InputError) as ei:
        mkb.load_kb(p)
    assert str(p) in str(ei.value) and needle in str(ei.value)


def test_scientific_notation_is_a_number(tmp_path):
    """YAML 1.1 reads 5e4 as a string; the knowledge base reads it as YAML 1.2 does: a number."""
    p = tmp_path / "kb.yaml"
    p.write_text(yaml.safe_dump({"goo": GOOD}).replace("E: 100000.0", "E: 5e4").replace("- 10000.0", "- 1e4"))
    assert "E: 5e4" in p.read_text() and "- 1e4" in p.read_text()
    kb = mkb.load_kb(p)
    assert kb["goo"]["E"] == 5e4 and kb["goo"]["E_range"][0] == 1e4


def test_duplicate_alias_is_rejected(tmp_path):
    p = tmp_path / "kb.yaml"
    p.write_text(yaml.safe_dump({"goo": GOOD, "slime": dict(GOOD, aliases=["goo"])}))
    with pytest.raises(InputError, match="names both"):
        mkb.load_kb(p)


def test_missing_kb_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        mkb.load_kb(tmp_path / "none.yaml")
