"""The prior matcher on a table of prompts and hints."""
from __future__ import annotations

import pytest

from physgs_steps.errors import ConfigError
from physgs_steps.params.prior import Matcher, match_scene, tokens

D = None  # an unmatched cluster label

TABLE = [
    # (prompt, instances, expected materials, expected tiers)
    ("a rubber duck on a stone", [{"name": "duck"}, {"name": "stone"}], ["rubber", "stone"], ["prompt_clause", "name"]),
    ("a rubber duck drops onto a heavy stone and bounces off",
     [{"name": "duck", "hint": "a yellow rubber duck"}, {"name": "stone", "hint": "a heavy rigid stone"}],
     ["rubber", "stone"], ["hint", "hint"]),
    ("a jelly teddy bear is thrown against a metal can standing next to it",
     [{"name": "bear"}, {"name": "can"}], ["jelly", "metal"], ["prompt_clause", "prompt_clause"]),
    ("a soft jelly donut drops onto the table and wobbles", [{"name": "donut", "hint": "a soft donut"}],
     ["jelly"], ["prompt_clause"]),
    ("a ficus plant in a pot sways in a gentle wind",
     [{"name": "ficus", "hint": "a potted ficus plant with thin leaves"}], ["plant"], ["hint"]),
    ("a wicker basket drops onto a soft mat",
     [{"name": "basket", "hint": "a woven wicker basket"}, {"name": "mat", "hint": "a soft foam mat"}],
     ["wood", "foam"], ["hint", "hint"]),
    ("a soft loaf of bread is torn apart", [{"name": "bread", "hint": "a soft loaf of bread"}], ["bread"], ["hint"]),
    ("a sandcastle collapses", [{"name": "castle"}], ["sand"], ["prompt"]),
    ("", [{"name": "blob", "hint": "a blob of honey on a plate"}], ["honey"], ["hint"]),
    ("", [{"name": "thing", "hint": "a statue standing on snow"}], ["stone"], ["hint"]),
    ("", [{"name": "x", "hint": "made of play-doh"}], ["plasticine"], ["hint"]),
    ("pour water into a glass", [{"name": "liquid"}], ["water"], ["name"]),
    ("a wobbly teddy bear falls", [{"name": "bear"}], ["jelly"], ["prompt_clause_descriptor"]),
    ("a bouncy ball", [{"name": "ball"}], ["rubber"], ["prompt_clause"]),
    ("a pile of snowballs", [D], ["snow"], ["prompt"]),
    ("a rubber duck drops onto a heavy stone", [{"name": "duck"}, D], ["rubber", "stone"], ["prompt_clause", "prompt"]),
    ("a rubber duck drops onto a heavy stone", [D, D], ["rubber", "stone"], ["prompt", "prompt"]),
    ("a teddy bear", [{"name": "bear"}], ["jelly"], ["default"]),
    ("", [D], ["jelly"], ["default"]),
    ("Steel BOLTS and Granite rocks", [{"name": "bolts"}, {"name": "rocks"}], ["metal", "stone"],
     ["prompt_clause", "name"]),
]


@pytest.mark.parametrize("prompt,instances,materials,tiers", TABLE)
def test_prior_table(prompt, instances, materials, tiers):
    got = match_scene(prompt, instances)
    assert [g.material for g in got] == materials
    assert [g.tier for g in got] == tiers
    for g in got:
        assert g.reason and len(g.text_sha256) == 64
        if g.tier != "default":
            assert g.word and g.word in g.reason


def test_deterministic():
    a = match_scene("a rubber duck on a stone", [{"name": "duck"}, None])
    b = match_scene("a rubber duck on a stone", [{"name": "duck"}, None])
    assert [x.to_dict() for x in a] == [x.to_dict() for x in b]


def test_default_material_configurable_and_checked():
    assert match_scene("a thing", [{"name": "x"}], default_material="foam")[0].material == "foam"
    with pytest.raises(ConfigError, match="materials.default_material"):
        match_scene("a thing", [{"name": "x"}], default_material="unobtainium")


def test_longest_phrase_wins_and_plurals():
    m = Matcher()
    hits = m.hits(tokens("a sponge cake next to a sponge"))
    assert [(h.material, h.word) for h in hits] == [("bread", "sponge cake"), ("foam", "sponge")]
    assert [h.material for h in m.hits(tokens("two pebbles and three leaves"))] == ["stone", "plant"]


def test_hint_main_clause_beats_later_mentions():
    got = match_scene("", [{"name": "duck", "hint": "a duck of rubber sitting on a stone"}])[0]
    assert got.material == "rubber" and got.candidates == ["rubber", "stone"]
