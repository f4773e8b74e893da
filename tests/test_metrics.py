"""The metrics stage: plausibility figures from final.h5, CLIP and aesthetic scores, the
metrics.json shape. VideoPhy2 (SA, PC): tests/test_metrics_videophy2.py."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from physgs_steps import metrics
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError, InputError
from physgs_steps.metrics.scores import BASE_KEYS

torch = pytest.importorskip("torch")

LOG = logging.getLogger("test.metrics")
T, NV = 5, 200


def write_final(path, x=None, f=None, time=None, store_figures=False):
    """A falling, uniformly swelling block: x_t = x_0 - 0.02 t e_z, F_t = (1 + 0.01 t) I
    (final.h5 as final_sim writes it; with ``store_figures`` also the figures it accumulates)."""
    from physgs_steps.final_frames import FinalWriter
    from physgs_steps.physical import PhysicalFigures

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.3, 0.6, (NV, 3))
    t = np.arange(T)
    if x is None:
        x = x0[None] + np.array([0.0, 0.0, -0.02])[None, None] * t[:, None, None]
    if f is None:
        f = (1.0 + 0.01 * t)[:, None, None, None] * np.eye(3)[None, None]
        f = np.broadcast_to(f, (T, NV, 3, 3))
    time = np.arange(T) / 30.0 if time is None else time
    acc = PhysicalFigures(T)
    with h5py.File(path, "w") as h:
        w = FinalWriter(h, np.arange(NV), time)
        for k in range(T):
            w.frame(k, np.asarray(x[k], np.float32), np.asarray(f[k], np.float32))
            acc.add(k, x[k], f[k])
        w.finish({"stats": {"test": True}, **({"physical": acc.result(time)} if store_figures else {})})


def write_video(path, n=6):
    import imageio.v2 as imageio

    w = imageio.get_writer(path, fps=10, codec="libx264", macro_block_size=16)
    for i in range(n):
        fr = np.zeros((64, 64, 3), np.uint8)
        fr[8 * i: 8 * i + 16, 10:40] = [200, 120, 40]
        w.append_data(fr)
    w.close()


@pytest.fixture
def files(tmp_path):
    write_final(tmp_path / "final.h5")
    write_video(tmp_path / "video.mp4")
    (tmp_path / "params.json").write_text(json.dumps({"instances": [
        {"label": 0, "name": "bear", "material": "jelly", "elasticity": "fixed_corotated", "plasticity": "identity",
         "E": 5e4, "nu": 0.3, "density": 1050.0, "provenance": {"source": "prior"}}], "backend": "prior"}))
    inputs = {k: str(tmp_path / f) for k, f in (("video", "video.mp4"), ("frames", "final.h5"), ("params", "params.json"))}
    return inputs, {"metrics": str(tmp_path / "metrics.json")}


def cfg_for(**m):
    c = section_defaults("metrics")
    c.update(m)
    return {"metrics": c, "scene": {"prompt": "a jelly bear falls"}, "device": "cpu"}


def strict_json(path):
    """metrics.json parsed with NaN/Infinity refused (strict JSON)."""
    def refuse(c):
        raise AssertionError(f"{path} contains {c}")
    return json.loads(open(path).read(), parse_constant=refuse)


SCORES = {"clip_score": "CS", "aesthetic_score": "AS", "semantic_adherence": "SA", "physical_commonsense": "PC"}


def test_without_weights_scores_are_null_with_reason(files):
    inputs, outputs = files
    summary = metrics.run(inputs, outputs, cfg_for(), LOG)
    doc = strict_json(outputs["metrics"])
    for key, col in SCORES.items():   # all four present, in the one shape, null with the reason
        assert set(BASE_KEYS) <= set(doc[key]) and doc[key]["column"] == col, doc[key]
        assert doc[key]["value"] is None and doc[key]["reason"] and doc[key]["paper_metric"] is None
    assert "clip_model_path" in doc["clip_score"]["reason"]
    assert "aesthetic_model_path" in doc["aesthetic_score"]["reason"]
    for key in ("semantic_adherence", "physical_commonsense"):
        assert "metrics.videophy2.official.command" in doc[key]["reason"] and "inprocess.model_path" in doc[key]["reason"]
    assert doc["schema_version"] == 2
    assert summary["clip_score"] is None and summary["all_checks_pass"] is True
    assert summary["semantic_adherence"] is None and summary["physical_commonsense"] is None
    assert doc["video"]["n_frames"] == 6 and doc["video"]["width"] == 64 and doc["video"]["fps"] == 10
    assert doc["materials"][0]["material"] == "jelly" and doc["materials"][0]["source"] == "prior"
    assert doc["text"] == "a jelly bear falls"


@pytest.mark.parametrize("stored", [False, True])
def test_physical_figures_are_exact(files, stored):
    inputs, _ = files
    if stored:  # as final_sim writes it: the figures accumulated while simulating, no frame is read
        write_final(inputs["frames"], store_figures=True)
    p = metrics.physical_figures(inputs["frames"])
    s = 1.0 + 0.01 * (T - 1)
    assert p["max_displacement"]["value"] == pytest.approx(0.02 * (T - 1), rel=1e-5)
    assert p["com_displacement"]["vector"][2] == pytest.approx(-0.02 * (T - 1), rel=1e-5)
    rel = 1e-4 if stored else 2.0 ** -11  # read back: F - I is stored in float16 (final_frames error budget)
    assert p["mean_deformation_last"]["value"] == pytest.approx((s - 1) * math.sqrt(3), rel=rel)
    assert p["max_deformation_last"]["value"] == pytest.approx((s - 1) * math.sqrt(3), rel=rel)
    assert p["det_F_min"]["value"] == pytest.approx(1.0, rel=1e-6)
    assert p["det_F_max"]["value"] == pytest.approx(s ** 3, rel=1e-3 if not stored else 1e-5)  # F - I read as float16
    assert p["final_mean_speed"]["value"] == pytest.approx(0.02 * 30, rel=1e-4)
    assert p["deformation_per_frame"][0] == pytest.approx(0.0, abs=1e-6) and len(p["deformation_per_frame"]) == T
    assert p["checks"] == {"finite": True, "moved": True, "stayed_in_domain": True, "no_inversion": True}


def test_failed_checks(tmp_path):
    rng = np.random.default_rng(1)
    x = np.broadcast_to(rng.uniform(0.3, 0.6, (NV, 3)), (T, NV, 3)).copy()
    x[-1, :10, 2] = 1.2            # 10 gaussians leave the domain at the end
    x[2, 0] = np.nan
    f = np.broadcast_to(np.eye(3), (T, NV, 3, 3)).copy()
    f[3, :5] = np.diag([1.0, 1.0, -0.5])   # inverted elements
    write_final(tmp_path / "f.h5", x=x, f=f)
    p = metrics.physical_figures(str(tmp_path / "f.h5"))
    assert p["checks"]["finite"] is False and p["non_finite_count"]["value"] == 1
    assert p["checks"]["stayed_in_domain"] is False
    assert p["out_of_domain_fraction_max"]["value"] == pytest.approx(10 / NV)
    assert p["checks"]["no_inversion"] is False and p["det_F_min"]["value"] == pytest.approx(-0.5)
    assert p["inverted_fraction_max"]["value"] == pytest.approx(5 / NV)
    assert p["all_checks_pass"] is False
    # a still scene did not move; the stored figures are re-judged under the stage's thresholds
    x_out = x.copy()
    x_out[np.isnan(x_out)] = 0.5
    write_final(tmp_path / "still.h5", x=np.broadcast_to(x_out[0], (T, NV, 3)).copy(), store_figures=True)
    p = metrics.physical_figures(str(tmp_path / "still.h5"), moved_threshold=1e-3)
    assert p["checks"]["moved"] is False and p["max_displacement"]["value"] == 0.0
    write_final(tmp_path / "out.h5", x=np.where(np.isnan(x), 0.5, x), store_figures=True)
    assert metrics.physical_figures(str(tmp_path / "out.h5"))["checks"]["stayed_in_domain"] is False
    assert metrics.physical_figures(str(tmp_path / "out.h5"), margin=0.25)["checks"]["stayed_in_domain"] is True


def test_bad_inputs(tmp_path, files):
    inputs, outputs = files
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(InputError, match="broken.mp4"):
        metrics.run(dict(inputs, video=str(tmp_path / "broken.mp4")), outputs, cfg_for(), LOG)
    with h5py.File(tmp_path / "nox.h5", "w") as h:
        h.create_dataset("F", data=np.zeros((1, 2, 3, 3)))
    with pytest.raises(InputError, match="nox.h5.*format"):
        metrics.physical_figures(str(tmp_path / "nox.h5"))
    (tmp_path / "p.json").write_text("{")
    with pytest.raises(InputError, match="p.json"):
        metrics.run(dict(inputs, params=str(tmp_path / "p.json")), outputs, cfg_for(), LOG)


# ------------------------------------------------------------------ tiny CLIP, built offline
def build_tiny_clip(folder) -> None:
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers
    from transformers import CLIPConfig, CLIPModel, CLIPProcessor, PreTrainedTokenizerFast
    from transformers.models.clip.image_processing_pil_clip import CLIPImageProcessorPil

    alphabet = sorted(pre_tokenizers.ByteLevel.alphabet())
    tok = Tokenizer(models.BPE(vocab={c: i for i, c in enumerate(alphabet)}, merges=[]))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    tok.add_special_tokens(["<|startoftext|>", "<|endoftext|>"])
    fast = PreTrainedTokenizerFast(tokenizer_object=tok, bos_token="<|startoftext|>", eos_token="<|endoftext|>",
                                   pad_token="<|endoftext|>", model_max_length=77)
    processor = CLIPProcessor(image_processor=CLIPImageProcessorPil(size={"shortest_edge": 32},
                                                                    crop_size={"height": 32, "width": 32}),
                              tokenizer=fast)
    cfg = CLIPConfig(text_config=dict(vocab_size=len(fast), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                      num_attention_heads=2, max_position_embeddings=77,
                                      eos_token_id=fast.eos_token_id, bos_token_id=fast.bos_token_id,
                                      pad_token_id=fast.pad_token_id),
                     vision_config=dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                                        image_size=32, patch_size=8),
                     projection_dim=16)
    torch.manual_seed(0)
    CLIPModel(cfg).eval().save_pretrained(folder)
    processor.save_pretrained(folder)


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_clip")
    build_tiny_clip(folder)
    return str(folder)


def reference_scores(clip_path, frames, text, mlp=None):
    """Independent computation through CLIPModel.forward (normalised embeddings)."""
    from PIL import Image
    from transformers import AutoProcessor, CLIPModel

    model = CLIPModel.from_pretrained(clip_path).eval()
    proc = AutoProcessor.from_pretrained(clip_path)
    inp = proc(text=[text], images=[Image.fromarray(f) for f in frames], return_tensors="pt", padding=True)
    with torch.no_grad():
        out = model(**inp)
        aes = mlp(out.image_embeds)[:, 0] if mlp is not None else None
    cos = (out.image_embeds @ out.text_embeds.T)[:, 0]
    return cos, aes


def test_clip_and_aesthetic_scores_with_tiny_models(files, tiny_clip, tmp_path):
    inputs, outputs = files
    torch.manual_seed(1)
    mlp = torch.nn.Sequential(torch.nn.Linear(16, 8), torch.nn.Dropout(0.2), torch.nn.Linear(8, 4),
                              torch.nn.Linear(4, 1)).eval()
    torch.save({f"layers.{k}": v for k, v in mlp.state_dict().items()}, tmp_path / "aes.pth")
    metrics.run(inputs, outputs, cfg_for(clip_model_path=tiny_clip, aesthetic_model_path=str(tmp_path / "aes.pth"),
                                         n_frames=3), LOG)
    doc = json.loads(open(outputs["metrics"]).read())
    clip, aes = doc["clip_score"], doc["aesthetic_score"]
    assert clip["frames"] == [0, 2, 5] and len(clip["per_frame"]) == 3
    _, frames = metrics.read_video_frames(inputs["video"], 3)
    cos, ref_aes = reference_scores(tiny_clip, frames, "a jelly bear falls", mlp)
    assert clip["value"] == pytest.approx(float(cos.mean()), abs=1e-5)
    assert aes["value"] == pytest.approx(float(ref_aes.mean()), abs=1e-5)
    assert -1.0 <= clip["value"] <= 1.0
    assert clip["backend"] == "clip" and aes["backend"] == "laion_aesthetic" and clip["reason"] is None
    assert clip["paper_metric"] is True and aes["architecture"]["layers"] == "16-8-4-1"


def test_absent_weights_are_null_wrong_weights_are_config_errors(files, tiny_clip, tmp_path):
    inputs, outputs = files
    # absent files: null with the reason naming the path (a machine without the weights)
    metrics.run(inputs, outputs, cfg_for(clip_model_path=tiny_clip, aesthetic_model_path=str(tmp_path / "none.pth"),
                                         n_frames=2), LOG)
    doc = strict_json(outputs["metrics"])
    assert doc["clip_score"]["value"] is not None and doc["clip_score"]["backend"] == "clip"
    assert doc["clip_score"]["architecture"] == {"variant": "ViT (32-d, 2 layers, patch 8)", "image_size": 32,
                                                 "embedding_dim": 16}
    assert doc["aesthetic_score"]["value"] is None and "none.pth" in doc["aesthetic_score"]["reason"]
    metrics.run(inputs, outputs, cfg_for(clip_model_path=str(tmp_path / "no_clip"), n_frames=2), LOG)
    doc = strict_json(outputs["metrics"])
    assert doc["clip_score"]["value"] is None and "no_clip" in doc["clip_score"]["reason"]

    # present but wrong: the stage stops naming the key and what is wrong, writing nothing
    def fails(match, **m):
        out = tmp_path / "bad_metrics.json"
        with pytest.raises(ConfigError, match=match):
            metrics.run(inputs, {"metrics": str(out)}, cfg_for(n_frames=2, **m), LOG)
        assert not out.exists()

    torch.save(torch.nn.Linear(768, 1).state_dict(), tmp_path / "l14.pth")   # LAION v1 style head, 768-d
    fails(r"metrics.aesthetic_model_path.*768-d.*16-d", clip_model_path=tiny_clip,
          aesthetic_model_path=str(tmp_path / "l14.pth"))
    torch.save({"layers.0.weight": torch.zeros(4, 16), "layers.2.weight": torch.zeros(2, 4)}, tmp_path / "two.pth")
    fails(r"metrics.aesthetic_model_path.*one score", clip_model_path=tiny_clip,
          aesthetic_model_path=str(tmp_path / "two.pth"))
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    fails(r"metrics.aesthetic_model_path.*not a readable", clip_model_path=tiny_clip,
          aesthetic_model_path=str(tmp_path / "junk.pth"))
    other = tmp_path / "not_clip"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"model_type": "bert", "hidden_size": 8}))
    fails(r"metrics.clip_model_path.*'bert' model, not CLIP", clip_model_path=str(other))
    (tmp_path / "empty").mkdir()
    fails(r"metrics.clip_model_path.*no readable config.json", clip_model_path=str(tmp_path / "empty"))
    partial = tmp_path / "partial_clip"   # a CLIP config with weights of only the text tower
    partial.mkdir()
    import shutil
    from safetensors.torch import load_file, save_file

    for f in (Path(tiny_clip)).iterdir():
        if f.name != "model.safetensors":
            shutil.copy(f, partial / f.name)
    sd = load_file(str(Path(tiny_clip) / "model.safetensors"))
    save_file({k: v for k, v in sd.items() if not k.startswith("vision_model")}, str(partial / "model.safetensors"),
              metadata={"format": "pt"})
    fails(r"metrics.clip_model_path.*lacks weights", clip_model_path=str(partial))


def test_default_path_imports_no_torch(files, tmp_path):
    """Without weights the stage never imports torch or transformers (fast start-up)."""
    import subprocess
    import sys

    inputs, _ = files
    code = (f"import json, logging, sys; from physgs_steps import metrics; from physgs_steps.config import section_defaults\n"
            f"cfg = {{'metrics': section_defaults('metrics'), 'scene': {{'prompt': 'p'}}, 'device': 'auto'}}\n"
            f"metrics.run({inputs!r}, {{'metrics': {str(tmp_path / 'm.json')!r}}}, cfg, logging.getLogger('t'))\n"
            f"print(sorted(m for m in ('torch', 'transformers') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "[]"
