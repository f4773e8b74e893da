"""The vlm_params stage with the prior backend, pins, and the pins-only helpers."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from physgs_steps import materials_kb
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError, InputError
from physgs_steps.params import stage

LOG = logging.getLogger("test.params")
CONTRACT_KEYS = {"label", "name", "material", "elasticity", "plasticity", "E", "nu", "density",
                 "plasticity_params", "velocity", "provenance"}


def write_inputs(tmp_path, counts, config_index):
    """labels.npz / clusters.json for K = len(counts) labels; scene.ply is not read by the prior."""
    labels = np.concatenate([np.full(c, k, np.int32) for k, c in enumerate(counts)])
    np.savez(tmp_path / "labels.npz", labels=labels)
    clusters = {"n_instances": len(counts), "method": "test",
                "instances": [{"label": k, "count": c, "bbox_min": [0, 0, 0], "bbox_max": [1, 1, 1],
                               "config_index": ci} for k, (c, ci) in enumerate(zip(counts, config_index))]}
    (tmp_path / "clusters.json").write_text(json.dumps(clusters))
    return ({"scene": str(tmp_path / "scene.ply"), "labels": str(tmp_path / "labels.npz"),
             "clusters": str(tmp_path / "clusters.json")}, {"params": str(tmp_path / "params.json")})


def cfg_for(scene, **materials):
    m = section_defaults("materials")
    m.update(materials)
    return {"materials": m, "scene": scene, "device": "cpu"}


def run_stage(tmp_path, scene, counts, config_index, **materials):
    inputs, outputs = write_inputs(tmp_path, counts, config_index)
    summary = stage.run(inputs, outputs, cfg_for(scene, **materials), LOG)
    return json.loads((tmp_path / "params.json").read_text()), summary


DUCK_STONE = {"prompt": "a rubber duck drops onto a heavy stone and bounces off",
              "instances": [{"name": "duck", "hint": "a yellow rubber duck", "velocity": [0.5, 0, 0]},
                            {"name": "stone", "hint": "a heavy rigid stone"}]}


def test_prior_stage_writes_contract_params(tmp_path):
    # labels are sorted by size: the stone (label 0) matched entry 1, the duck (label 1) entry 0
    doc, summary = run_stage(tmp_path, DUCK_STONE, [300, 100], [1, 0])
    assert doc["backend"] == "prior" and doc["prompt"] == DUCK_STONE["prompt"] and doc["history"] == []
    assert [i["label"] for i in doc["instances"]] == [0, 1]
    stone, duck = doc["instances"]
    assert set(stone) >= CONTRACT_KEYS and set(stone["plasticity_params"]) == set(materials_kb.PLASTICITY_PARAM_KEYS)
    assert (stone["name"], stone["material"]) == ("stone", "stone")
    assert (duck["name"], duck["material"]) == ("duck", "rubber")
    assert duck["velocity"] == [0.5, 0.0, 0.0] and stone["velocity"] == [0.0, 0.0, 0.0]
    kb = materials_kb.load_kb()
    assert duck["E"] == kb["rubber"]["E"] and duck["elasticity"] == kb["rubber"]["elasticity"]
    prov = duck["provenance"]
    assert prov["source"] == "prior" and "rubber" in prov["prior"]["reason"] and len(prov["prompt_sha256"]) == 64
    assert summary["sources"] == {"prior": 2} and summary["fallbacks"] == 0


def test_unmatched_labels_use_the_prompt(tmp_path):
    doc, _ = run_stage(tmp_path, {"prompt": "a rubber duck drops onto a heavy stone", "instances": []},
                       [300, 100], [None, None])
    assert [i["material"] for i in doc["instances"]] == ["rubber", "stone"]
    assert all(i["name"].startswith("instance_") and i["config_index"] is None for i in doc["instances"])


def test_partial_pins_are_kept(tmp_path):
    scene = {"prompt": "a jelly bear", "instances": [{"name": "bear", "E": 2.5e4, "plasticity": "sigma"}]}
    doc, _ = run_stage(tmp_path, scene, [50], [0])
    bear = doc["instances"][0]
    assert bear["material"] == "jelly" and bear["E"] == 2.5e4 and bear["plasticity"] == "j_clamp"
    assert bear["provenance"]["source"] == "prior" and bear["provenance"]["pinned"] == ["E", "plasticity"]


def test_fully_pinned_scene(tmp_path):
    scene = {"prompt": "two things", "instances": [
        {"name": "a", "material": "sand"},
        {"name": "b", "elasticity": "neo_hookean", "plasticity": "identity", "E": 3e5, "nu": 0.25, "density": 800,
         "velocity": [0, 0, -1]}]}
    assert stage.fully_pinned(scene) and stage.fully_pinned(scene, 2)
    assert not stage.fully_pinned(scene, 3)
    assert not stage.fully_pinned({"instances": [{"name": "a", "E": 1e5}]})
    assert not stage.fully_pinned({"instances": []})
    clusters = {"n_instances": 2, "instances": [{"label": 0, "config_index": 1}, {"label": 1, "config_index": 0}]}
    doc = stage.pinned_params(scene, clusters)
    b, a = doc["instances"]
    assert (b["label"], b["name"], b["E"], b["density"], b["velocity"]) == (0, "b", 3e5, 800.0, [0.0, 0.0, -1.0])
    assert a["material"] == "sand" and a["plasticity"] == "mohr_coulomb"
    assert all(i["provenance"]["source"] == "pinned" for i in doc["instances"])
    # the stage with any backend gives the same values without asking anything
    out, summary = run_stage(tmp_path, scene, [10, 5], [1, 0], backend="qwen3vl")
    assert summary["sources"] == {"pinned": 2}
    assert [(i["material"], i["E"]) for i in out["instances"]] == [(i["material"], i["E"]) for i in doc["instances"]]


def test_pinned_params_refuses_incomplete_pins():
    with pytest.raises(ConfigError, match=r"scene.instances\[0\]"):
        stage.pinned_params({"instances": [{"name": "a", "E": 1e5}]})
    with pytest.raises(ConfigError, match="matched no scene instance"):
        stage.pinned_params({"instances": [{"material": "jelly"}]},
                            {"n_instances": 2, "instances": [{"label": 0, "config_index": 0},
                                                             {"label": 1, "config_index": None}]})


def test_missing_weights_fall_back_to_prior_with_reason(tmp_path):
    q = dict(section_defaults("materials")["qwen3vl"], model_path=str(tmp_path / "no_such_model"))
    doc, summary = run_stage(tmp_path, DUCK_STONE, [300, 100], [1, 0], backend="qwen3vl", qwen3vl=q)
    for inst in doc["instances"]:
        assert inst["provenance"]["source"] == "prior"
        assert "no_such_model" in inst["provenance"]["fallback_reason"]
    assert summary["fallbacks"] == 2
    with pytest.raises(ConfigError, match="materials.qwen3vl"):
        run_stage(tmp_path, DUCK_STONE, [300, 100], [1, 0], backend="qwen3vl", qwen3vl=q, on_failure="error")


@pytest.mark.parametrize("clusters_change,needle", [
    ({"config_index": 5}, "config_index 5"),
    ({"label": 7}, "outside"),
])
def test_bad_clusters_json(tmp_path, clusters_change, needle):
    inputs, outputs = write_inputs(tmp_path, [10], [0])
    doc = json.loads((tmp_path / "clusters.json").read_text())
    doc["instances"][0].update(clusters_change)
    (tmp_path / "clusters.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=needle):
        stage.run(inputs, outputs, cfg_for(DUCK_STONE), LOG)
    assert not (tmp_path / "params.json").exists()


def test_labels_beyond_clusters_and_bad_npz(tmp_path):
    inputs, outputs = write_inputs(tmp_path, [10, 10], [0, 1])
    np.savez(tmp_path / "labels.npz", labels=np.array([0, 1, 2], np.int32))
    with pytest.raises(InputError, match="labels.npz"):
        stage.run(inputs, outputs, cfg_for(DUCK_STONE), LOG)
    np.savez(tmp_path / "labels.npz", other=np.zeros(3))
    with pytest.raises(InputError, match="labels"):
        stage.run(inputs, outputs, cfg_for(DUCK_STONE), LOG)


def test_bad_config(tmp_path):
    inputs, outputs = write_inputs(tmp_path, [10], [0])
    with pytest.raises(ConfigError, match="materials.backend"):
        stage.run(inputs, outputs, cfg_for(DUCK_STONE, backend="gpt"), LOG)
    bad = {"prompt": "", "instances": [{"name": "x", "nu": 0.7}]}
    with pytest.raises(ConfigError, match=r"scene.instances\[0\].nu"):
        stage.run(inputs, outputs, cfg_for(bad), LOG)
