"""The qwen3vl backend for real, with a tiny randomly initialised Qwen3-VL built offline.

Its answers are garbage, so every instance must end in the prior fallback with the reason
and both raw answers recorded; the weights must be loaded once per process.
"""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

torch = pytest.importorskip("torch")
transformers = pytest.importorskip("transformers")

from physgs_steps import render, save_gaussians  # noqa: E402
from physgs_steps.config import section_defaults  # noqa: E402
from physgs_steps.gaussians import GaussianScene  # noqa: E402
from physgs_steps.params import qwen3vl, stage  # noqa: E402
from physgs_steps.render.cameras import orbit_cameras as _orbit_cameras  # noqa: E402

LOG = logging.getLogger("test.qwen3vl")
SPECIAL = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
           "<|image_pad|>", "<|video_pad|>"]
CHAT_TEMPLATE = (
    "{% for m in messages %}<|im_start|>{{ m['role'] }}\n"
    "{% if m['content'] is string %}{{ m['content'] }}{% else %}{% for c in m['content'] %}"
    "{% if c['type'] == 'image' %}<|vision_start|><|image_pad|><|vision_end|>{% else %}{{ c['text'] }}{% endif %}"
    "{% endfor %}{% endif %}<|im_end|>\n{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


def build_tiny_qwen3vl(folder) -> None:
    """A 2-layer Qwen3-VL with a byte-level tokenizer and a PIL image processor, saved to ``folder``."""
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, Qwen3VLConfig, Qwen3VLForConditionalGeneration
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    alphabet = pre_tokenizers.ByteLevel.alphabet()
    tok = Tokenizer(models.BPE(vocab={c: i for i, c in enumerate(sorted(alphabet))}, merges=[]))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    tok.add_special_tokens(SPECIAL)
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, eos_token="<|im_end|>", pad_token="<|endoftext|>",
                                   chat_template=CHAT_TEMPLATE)
    ids = {s: fast.convert_tokens_to_ids(s) for s in SPECIAL}
    image_processor = Qwen2VLImageProcessorPil(patch_size=16, temporal_patch_size=2, merge_size=2,
                                               min_pixels=32 * 32, max_pixels=64 * 64,
                                               image_mean=[0.5] * 3, image_std=[0.5] * 3)
    config = Qwen3VLConfig(
        text_config=dict(vocab_size=len(fast), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, num_key_value_heads=1, head_dim=16, max_position_embeddings=16384,
                         rope_parameters={"rope_type": "default", "rope_theta": 10000.0,
                                          "mrope_section": [2, 3, 3], "mrope_interleaved": True}),
        vision_config=dict(depth=2, hidden_size=32, intermediate_size=64, num_heads=2, patch_size=16,
                           spatial_merge_size=2, temporal_patch_size=2, out_hidden_size=32,
                           num_position_embeddings=64, deepstack_visual_indexes=[1]),
        image_token_id=ids["<|image_pad|>"], video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"], vision_end_token_id=ids["<|vision_end|>"])
    torch.manual_seed(0)
    model = Qwen3VLForConditionalGeneration(config).eval()
    model.save_pretrained(folder)
    fast.save_pretrained(folder)
    image_processor.save_pretrained(folder)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_qwen3vl")
    build_tiny_qwen3vl(folder)
    return str(folder)


def _points_render_static(scene, cameras, backend="auto"):
    """Test-only stand-in for render.render_static: gaussian centres drawn as coloured pixels."""
    out = []
    for cam in cameras:
        img = np.zeros((cam.height, cam.width, 3), np.uint8)
        pc = scene.means @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
        front = pc[:, 2] > 1e-3
        uv = (pc[front] / pc[front, 2:3]) @ cam.K.T
        u, v = uv[:, 0].astype(int), uv[:, 1].astype(int)
        ok = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        img[v[ok], u[ok]] = (scene.base_colors()[front][ok] * 255).astype(np.uint8)
        out.append(img)
    return np.stack(out)


@pytest.fixture
def renderer(monkeypatch):
    """The real renderer when it exists, else the stand-in above (only inside this test)."""
    if not hasattr(render, "render_static"):
        monkeypatch.setattr(render, "render_static", _points_render_static, raising=False)
    if not hasattr(render, "orbit_cameras"):
        monkeypatch.setattr(render, "orbit_cameras", _orbit_cameras, raising=False)


def write_scene(tmp_path):
    """Two blobs of gaussians (labels 0 and 1) in the sim frame, plus labels.npz and clusters.json."""
    rng = np.random.default_rng(0)
    n0, n1 = 300, 150
    means = np.concatenate([rng.normal([0.4, 0.5, 0.3], 0.05, (n0, 3)), rng.normal([0.7, 0.5, 0.2], 0.03, (n1, 3))])
    n = n0 + n1
    sh = np.zeros((n, 1, 3), np.float32)
    sh[:n0, 0] = [1.5, 1.2, -1.5]
    sh[n0:, 0] = [0.0, 0.0, 0.0]
    scene = GaussianScene(means=means, log_scales=np.full((n, 3), np.log(0.01)), quats=np.tile([1, 0, 0, 0], (n, 1)),
                          opacity_logits=np.full(n, 3.0), sh=sh)
    save_gaussians(scene, tmp_path / "scene.ply")
    np.savez(tmp_path / "labels.npz", labels=np.r_[np.zeros(n0, np.int32), np.ones(n1, np.int32)])
    (tmp_path / "clusters.json").write_text(json.dumps({"n_instances": 2, "instances": [
        {"label": 0, "count": n0, "config_index": 0}, {"label": 1, "count": n1, "config_index": None}]}))
    return ({k: str(tmp_path / f) for k, f in (("scene", "scene.ply"), ("labels", "labels.npz"),
                                               ("clusters", "clusters.json"))},
            {"params": str(tmp_path / "params.json")})


def cfg_for(model_path, **q):
    m = section_defaults("materials")
    m["backend"] = "qwen3vl"
    m["qwen3vl"].update({"model_path": model_path, "device": "cpu", "dtype": "float32", "max_new_tokens": 12,
                         "n_views": 2, "image_size": 64}, **q)
    scene = {"prompt": "a rubber duck drops onto a heavy stone",
             "instances": [{"name": "duck", "hint": "a yellow rubber duck", "E": 4.0e5}]}
    return {"materials": m, "scene": scene, "device": "cpu"}


def test_garbage_answers_end_in_recorded_prior_fallback(tmp_path, tiny_model, renderer):
    inputs, outputs = write_scene(tmp_path)
    before = qwen3vl.LOAD_COUNT["n"]
    summary = stage.run(inputs, outputs, cfg_for(tiny_model), LOG)
    doc = json.loads((tmp_path / "params.json").read_text())
    assert doc["backend"] == "qwen3vl" and doc["backend_config"]["device"] == "cpu"
    duck, other = doc["instances"]
    for inst in doc["instances"]:
        prov = inst["provenance"]
        assert prov["source"] == "prior" and prov["backend"] == "qwen3vl"
        assert "invalid answer after 2 attempt(s)" in prov["fallback_reason"]
        assert len(prov["attempts"]) == 2 and all(a["error"] for a in prov["attempts"])
        assert isinstance(prov["raw_answer"], str) and prov["n_views"] == 2 and "views_error" not in prov
        assert len(prov["prompt_sha256"]) == 64
    assert duck["material"] == "rubber" and duck["E"] == 4.0e5 and duck["provenance"]["pinned"] == ["E"]
    assert other["material"] == "stone"   # unmatched label: the other material of the prompt
    assert summary["fallbacks"] == 2
    # a second run in the same process reuses the loaded weights
    stage.run(inputs, outputs, cfg_for(tiny_model), LOG)
    assert qwen3vl.LOAD_COUNT["n"] - before <= 1


def test_text_only_question_and_image_token_expansion(tiny_model, renderer):
    backend = qwen3vl.Qwen3VLBackend({"model_path": tiny_model, "device": "cpu", "dtype": "float32",
                                      "max_new_tokens": 5}, "cpu", LOG)
    reply = backend.send([{"role": "user", "content": "Say {}", "images": []}])
    assert isinstance(reply, str)
    _, processor = qwen3vl.load(tiny_model, "cpu", "float32")
    images = [np.zeros((64, 64, 3), np.uint8), np.zeros((32, 48, 3), np.uint8)]
    from PIL import Image

    chat = [{"role": "user", "content": [{"type": "image"}, {"type": "image"}, {"type": "text", "text": "hi"}]}]
    text = processor.apply_chat_template(chat, add_generation_prompt=True, tokenize=False)
    enc = processor(text=[text], images=[Image.fromarray(i) for i in images], return_tensors="pt")
    grid = enc["image_grid_thw"]
    n_expected = int(sum(int(g.prod()) for g in grid) // 4)
    assert int(enc["mm_token_type_ids"].sum()) == n_expected
    assert int(enc["pixel_values"].shape[0]) == int(sum(int(g.prod()) for g in grid))


def test_bad_device_and_dtype_are_config_errors():
    from physgs_steps.errors import ConfigError

    with pytest.raises(ConfigError, match="materials.qwen3vl.device"):
        qwen3vl.resolve_device("tpu", "cpu")
    with pytest.raises(ConfigError, match="materials.qwen3vl.dtype"):
        qwen3vl.resolve_dtype("int8", "cpu")
    assert qwen3vl.resolve_device("auto", "cpu") == "cpu"
    assert qwen3vl.resolve_dtype("auto", "cpu") == torch.float32
