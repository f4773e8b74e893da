"""Pins (strict) and model answers (clamped / rejected with recorded reasons)."""
from __future__ import annotations

import json

import pytest

from physgs_steps import materials_kb
from physgs_steps.errors import ConfigError
from physgs_steps.params import validate as V


@pytest.fixture(scope="module")
def kb():
    return materials_kb.load_kb()


ASK_ALL = V.asked_keys({})


def answer(**over):
    a = {"material": "rubber", "elasticity": "fixed_corotated", "plasticity": "identity",
         "E": 3e5, "nu": 0.4, "density": 1100, "yield_stress": None, "friction_angle": None, "cohesion": None,
         "reason": "a rubber toy"}
    a.update(over)
    return a


def test_parse_answer_accepts_fences_and_prose():
    text = "Sure! Here it is:\n```json\n" + json.dumps(answer()) + "\n```\nHope that helps {not json}"
    assert V.parse_answer(text, ASK_ALL)["material"] == "rubber"
    assert V.parse_answer('{"E": "2e5 Pa", "material": "jelly", "elasticity": "sigma", "plasticity": "none",'
                          ' "nu": "0.3", "density": 1000}', ASK_ALL)["E"] == "2e5 Pa"


@pytest.mark.parametrize("text,needle", [
    ("", "empty"),
    ("the material is rubber", "no JSON object"),
    ("[1, 2, 3]", "no JSON object"),
    (json.dumps({k: v for k, v in answer().items() if k != "E"}), "lacks keys ['E']"),
    (json.dumps(answer(E="very stiff")), "'E' must be a number"),
    (json.dumps(answer(material=3)), "'material' must be a string"),
])
def test_parse_answer_errors(text, needle):
    with pytest.raises(V.AnswerError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        V.parse_answer(text, ASK_ALL)


def test_parse_answer_only_requires_asked_keys():
    asked = V.asked_keys({"E": 1e5, "nu": 0.3, "density": 900.0})
    assert "E" not in asked and "material" in asked
    V.parse_answer(json.dumps({"material": "jelly", "elasticity": "fixed_corotated", "plasticity": "identity"}), asked)


def base(kb, name="jelly"):
    return materials_kb.material_params(name, kb)


def notes_by_key(notes):
    return {n["key"]: n for n in notes}


def test_finalize_valid_answer(kb):
    vals, notes = V.finalize_answer(answer(), base(kb), {}, kb)
    assert vals["material"] == "rubber" and vals["E"] == 3e5 and vals["nu"] == 0.4 and vals["density"] == 1100
    assert vals["plasticity_params"]["j_min"] == 0.05 and notes == []


def test_finalize_clamps_and_rejects(kb):
    vals, notes = V.finalize_answer(answer(material="steel", elasticity="StVK", plasticity="von Mises",
                                           E=2.0e11, nu=0.5, density=-5, yield_stress="2.5e8"), base(kb), {}, kb)
    n = notes_by_key(notes)
    assert vals["material"] == "metal" and vals["elasticity"] == "stvk_hencky" and vals["plasticity"] == "von_mises"
    # 2e11 is first clamped to the global E_max, then into metal's effective range
    assert vals["E"] == kb["metal"]["E_range"][1] and n["E"]["action"] == "clamped" and "metal" in n["E"]["reason"]
    assert vals["nu"] == 0.49 and n["nu"]["action"] == "clamped" and "0.5" in n["nu"]["reason"]
    assert vals["density"] == kb["metal"]["density"] and n["density"]["action"] == "rejected"
    assert vals["plasticity_params"]["yield_stress"] == 2.5e8


def test_finalize_negative_and_unknown(kb):
    vals, notes = V.finalize_answer(answer(material="unobtainium", elasticity="magic", E=-3, nu=-0.2),
                                    base(kb, "foam"), {}, kb)
    n = notes_by_key(notes)
    assert vals["material"] == "foam" and n["material"]["action"] == "rejected"
    assert vals["elasticity"] == kb["foam"]["elasticity"] and n["elasticity"]["action"] == "rejected"
    assert vals["E"] == kb["foam"]["E"] and n["E"]["action"] == "rejected" and "> 0" in n["E"]["reason"]
    assert vals["nu"] == 0.0 and n["nu"]["action"] == "clamped"


def test_finalize_without_material_range_clamp(kb):
    vals, notes = V.finalize_answer(answer(E=5e7), base(kb), {}, kb, clamp_to_material_range=False)
    assert vals["E"] == 5e7 and notes == []
    vals, notes = V.finalize_answer(answer(E=5e7), base(kb), {}, kb, limits={"E_max": 1e7},
                                    clamp_to_material_range=False)
    assert vals["E"] == 1e7 and notes[0]["action"] == "clamped"


def test_finalize_fills_missing_plasticity_params(kb):
    vals, notes = V.finalize_answer(answer(material="rubber", plasticity="drucker_prager", elasticity="stvk"),
                                    base(kb), {}, kb)
    assert vals["plasticity_params"]["friction_angle"] == kb["sand"]["plasticity_params"]["friction_angle"]
    n = notes_by_key(notes)
    assert n["friction_angle"]["action"] == "filled" and "sand" in n["friction_angle"]["reason"]


def test_pins_win_over_answers(kb):
    pins = V.check_pins({"E": 123456.0, "plasticity": "sigma"}, 0, kb)
    assert pins == {"E": 123456.0, "plasticity": "j_clamp"}
    vals, _ = V.finalize_answer(answer(E=9e5, plasticity="identity"), base(kb), pins, kb)
    assert vals["E"] == 123456.0 and vals["plasticity"] == "j_clamp"


@pytest.mark.parametrize("entry,key", [
    ({"E": -1}, "scene.instances[2].E"), ({"nu": 0.5}, "scene.instances[2].nu"),
    ({"density": 0}, "scene.instances[2].density"), ({"E": float("nan")}, "scene.instances[2].E"),
    ({"E": "1e5"}, "scene.instances[2].E"), ({"material": "kryptonite"}, "scene.instances[2].material"),
    ({"elasticity": "magic"}, "scene.instances[2].elasticity"), ({"friction_angle": 95}, "scene.instances[2].friction_angle"),
    ({"fracture_strain": 0}, "scene.instances[2].fracture_strain"),
    ({"fracture_softening": -0.1}, "scene.instances[2].fracture_softening"),
])
def test_bad_pins_are_config_errors(kb, entry, key):
    with pytest.raises(ConfigError) as ei:
        V.check_pins(entry, 2, kb)
    assert key in str(ei.value)


def test_tearing_from_kb_and_pins(kb):
    """Of the KB materials only bread tears by default; a scene pin sets an instance's tearing
    parameters, through both the answer path and the pin-only path (merge_pins)."""
    assert [k for k, e in kb.items() if e["plasticity_params"].get("fracture_strain") is not None] == ["bread"]
    pins = V.check_pins({"material": "bread", "fracture_strain": 0.03, "fracture_softening": 0.1}, 0, kb)
    vals, _ = V.merge_pins(base(kb), pins, kb)
    assert vals["plasticity_params"]["fracture_strain"] == 0.03
    assert vals["plasticity_params"]["fracture_softening"] == 0.1
    vals, _ = V.finalize_answer(answer(material="bread", plasticity="von_mises"), base(kb),
                                {"fracture_strain": 0.05}, kb)
    assert vals["plasticity_params"]["fracture_strain"] == 0.05
    vals, _ = V.merge_pins(base(kb), V.check_pins({"material": "bread"}, 0, kb), kb)
    assert vals["plasticity_params"]["fracture_strain"] == kb["bread"]["plasticity_params"]["fracture_strain"]
    vals, _ = V.finalize_answer(answer(material="bread", plasticity="von_mises"), base(kb), {}, kb)
    assert vals["plasticity_params"]["fracture_softening"] == kb["bread"]["plasticity_params"]["fracture_softening"]
    vals, _ = V.merge_pins(base(kb), V.check_pins({"material": "jelly"}, 0, kb), kb)
    assert vals["plasticity_params"]["fracture_strain"] is None


def test_velocity():
    assert V.check_velocity({}, 0) == [0.0, 0.0, 0.0]
    assert V.check_velocity({"velocity": [1, 0, -2.5]}, 0) == [1.0, 0.0, -2.5]
    with pytest.raises(ConfigError, match=r"scene.instances\[1\].velocity"):
        V.check_velocity({"velocity": [1, 2]}, 1)


def test_fully_pinned_rules(kb):
    assert V.is_fully_pinned(V.check_pins({"material": "jelly"}, 0, kb))
    everything = {"elasticity": "neo_hookean", "plasticity": "identity", "E": 1e5, "nu": 0.3, "density": 900}
    assert V.is_fully_pinned(V.check_pins(everything, 0, kb))
    assert not V.is_fully_pinned(V.check_pins(dict(everything, plasticity="von_mises"), 0, kb))
    assert V.is_fully_pinned(V.check_pins(dict(everything, plasticity="von_mises", yield_stress=1e3), 0, kb))
    assert not V.is_fully_pinned(V.check_pins({"E": 1e5}, 0, kb))


def test_merge_pins_material_preset_and_overrides(kb):
    vals, notes = V.merge_pins(base(kb), {"material": "sand", "E": 7e5}, kb)
    assert vals["material"] == "sand" and vals["E"] == 7e5 and vals["plasticity"] == "mohr_coulomb"
    vals, notes = V.merge_pins(base(kb), {"plasticity": "von_mises"}, kb)
    assert vals["plasticity_params"]["yield_stress"] is not None and notes[0]["action"] == "filled"
