"""VideoPhy2 SA / PC: the official rater against fake rater commands (success, crash, timeout,
malformed output), the in-process rater on a tiny random Qwen3-VL, parsing and mapping."""
from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time

import pytest

from physgs_steps import metrics
from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError
from physgs_steps.metrics import videophy2, videophy2_official
from physgs_steps.metrics.video import sample_indices

from test_metrics import files, strict_json  # noqa: F401 (files: a fixture)

LOG = logging.getLogger("test.videophy2")
PROMPT = "a jelly bear falls"

# A stand-in for VIDEOPHY2/inference.py: the same command line and CSV columns; FAKE_MODE
# (an environment variable, set through metrics.videophy2.official.env) picks a behaviour.
FAKE_RATER = r'''
import argparse, csv, os, sys, time
ap = argparse.ArgumentParser()
for a in ("--input_csv", "--output_csv", "--task", "--checkpoint"):
    ap.add_argument(a)
ap.add_argument("--num_frames", type=int, default=32)
a = ap.parse_args()
mode = os.environ.get("FAKE_MODE", "ok")
rows = list(csv.DictReader(open(a.input_csv, newline="")))
assert list(rows[0]) == ["caption", "videopath"], list(rows[0])
for r in rows:
    if not os.path.isfile(r["videopath"]):
        sys.exit("cannot open video " + r["videopath"])
print("loading checkpoint", a.checkpoint, "frames", a.num_frames, flush=True)
if mode == "crash":
    sys.stderr.write("Traceback (most recent call last):\nRuntimeError: CUDA error: no CUDA-capable device\n")
    sys.exit(3)
if mode == "sleep":
    open(os.environ["FAKE_PID_FILE"], "w").write(str(os.getpid()))
    time.sleep(60)
if mode == "no_output":
    sys.exit(0)
cell = {"sa": "4.0", "pc": "2.0"}[a.task]
cell = {"zero": "0.0", "text": "four", "fraction": "3.5", "big": "7"}.get(mode, cell)
header = ["", "caption", "videopath", "rating" if mode == "no_score_column" else "score"]
with open(a.output_csv, "w", newline="") as f:
    w = csv.writer(f)
    w.writerow(header)
    for i, r in enumerate(rows):
        w.writerow([i, r["caption"], "/elsewhere.mp4" if mode == "other_video" else r["videopath"], cell])
        print(a.task, "answer for", repr(r["caption"]), ":", cell)
'''


@pytest.fixture
def fake_rater(tmp_path):
    script = tmp_path / "fake_inference.py"
    script.write_text(FAKE_RATER)
    ckpt = tmp_path / "videophy_2_auto"
    ckpt.mkdir()
    return script, ckpt


def template_cfg(script, ckpt, **over):
    oc = {"command": f"{shutil.which('python3') or sys.executable} {script} --input_csv {{input_csv}} "
                     f"--output_csv {{output_csv}} --task {{task}} --checkpoint {{checkpoint}} --num_frames {{num_frames}}",
          "checkpoint": str(ckpt), "version": "fake-1"}
    oc.update(over)
    return oc


def cfg_for(videophy2_cfg: dict, prompt=PROMPT, **m):
    c = section_defaults("metrics")
    c.update(m)
    vc = c["videophy2"]
    for k, v in videophy2_cfg.items():
        vc[k] = (vc[k] | v) if isinstance(v, dict) else v
    return {"metrics": c, "scene": {"prompt": prompt}, "device": "cpu"}


# ------------------------------------------------------------------ protocol
def test_parse_rating():
    assert videophy2.parse_rating("4") == (4, None)
    assert videophy2.parse_rating(" Rating: 3/5.") == (3, None)
    assert videophy2.parse_rating("I would say five.") == (5, None)
    assert videophy2.parse_rating("2.\nBecause ...") == (2, None)
    for bad, why in (("", "no rating"), ("great video", "no rating"), ("0", "is 0"), ("6", "is 6"),
                     ("4.5", "is 4.5"), ("x4", "no rating"), ("44", "is 44")):
        r, reason = videophy2.parse_rating(bad)
        assert r is None and why in reason, (bad, reason)


def test_mapping_and_rated_entry():
    assert [videophy2.map_rating(r, "linear") for r in range(1, 6)] == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert [videophy2.map_rating(r, "threshold") for r in range(1, 6)] == [0, 0, 0, 1, 1]
    with pytest.raises(ValueError):
        videophy2.map_rating(0, "linear")
    e = videophy2.rated("pc", [3, 5], "threshold", "videophy2_official", True)
    assert e["column"] == "PC" and e["value"] == 0.5 and e["ratings"] == [3, 5]
    assert e["value_by_mapping"] == {"linear": 0.75, "threshold": 0.5} and e["mapping"]["name"] == "threshold"


def test_segment_sampling():
    assert sample_indices(150, 4, "segments") == [18, 55, 92, 130]   # middles of 4 segments
    assert sample_indices(6, 3, "even") == [0, 2, 5]
    assert sample_indices(5, 32, "segments") == [0, 1, 2, 3, 4]         # short video: each frame once
    assert sample_indices(1, 8, "segments") == [0]


def test_backend_selection_and_config_errors(fake_rater):
    script, ckpt = fake_rater
    base = section_defaults("metrics")["videophy2"]
    assert videophy2.select_backend(base) == "unconfigured"
    assert videophy2.select_backend(base | {"backend": "none"}) == "none"
    assert videophy2.select_backend(base | {"inprocess": {"model_path": "/m"}}) == "inprocess"
    both = base | {"inprocess": {"model_path": "/m"}, "official": template_cfg(script, ckpt)}
    assert videophy2.select_backend(both) == "official"
    assert videophy2.select_backend(both | {"backend": "inprocess"}) == "inprocess"
    for oc, match in (({"command": "rate {input_csv} {task}"}, r"official.command.*lacks \{output_csv\}"),
                      ({"command": "rate {input_csv} {output_csv} {task} {gpu}"}, r"unknown placeholder.*gpu"),
                      ({"command": "rate {input_csv} {output_csv} {task} {checkpoint}"}, r"official.checkpoint is not set"),
                      ({"command": "rate {input_csv {output_csv} {task}"}, r"not a valid template"),
                      ({"python": "/usr/bin/python3"}, r"official.repo.*missing")):
        with pytest.raises(ConfigError, match=match):
            videophy2.select_backend(base | {"official": base["official"] | oc})


# ------------------------------------------------------------------ official rater, fake commands
def test_official_rater_through_the_stage(files, fake_rater):
    inputs, outputs = files
    script, ckpt = fake_rater
    summary = metrics.run(inputs, outputs, cfg_for({"official": template_cfg(script, ckpt)}), LOG)
    doc = strict_json(outputs["metrics"])
    sa, pc = doc["semantic_adherence"], doc["physical_commonsense"]
    for e, rating, value in ((sa, 4, 0.75), (pc, 2, 0.25)):
        assert e["value"] == value and e["ratings"] == [rating] and e["raw_scores"] == [f"{rating}.0"]
        assert e["backend"] == "videophy2_official" and e["paper_metric"] is True and e["reason"] is None
        assert e["mapping"] == {"name": "linear", "formula": "(rating - 1) / 4"}
        assert e["rater_version"]["label"] == "fake-1" and e["returncode"] == 0 and e["num_frames"] == 32
        assert f"--task {e['task']}" in e["command"] and str(ckpt) in e["command"]
        assert repr(PROMPT) in e["stdout_tail"]     # the scene prompt went in as the caption
    assert sa["value_by_mapping"]["threshold"] == 1.0 and pc["value_by_mapping"]["threshold"] == 0.0
    assert summary["semantic_adherence"] == 0.75 and summary["physical_commonsense"] == 0.25
    assert doc["clip_score"]["value"] is None     # the other scores are unaffected


def test_official_rater_from_python_repo_checkpoint(files, fake_rater, tmp_path):
    inputs, outputs = files
    script, ckpt = fake_rater
    repo = tmp_path / "videophy"
    (repo / "VIDEOPHY2").mkdir(parents=True)
    shutil.copy(script, repo / "VIDEOPHY2" / "inference.py")
    commit = None
    if shutil.which("git"):
        git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
        subprocess.run(git[:3] + ["init", "-q"], check=True)
        subprocess.run(git + ["add", "."], check=True)
        subprocess.run(git + ["commit", "-qm", "rater"], check=True)
        commit = subprocess.run(git[:3] + ["rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    oc = {"python": sys.executable, "repo": str(repo), "checkpoint": str(ckpt), "num_frames": 8}
    metrics.run(inputs, outputs, cfg_for({"official": oc, "mapping": "threshold", "backend": "official"}), LOG)
    doc = strict_json(outputs["metrics"])
    sa, pc = doc["semantic_adherence"], doc["physical_commonsense"]
    assert (sa["value"], pc["value"]) == (1.0, 0.0) and sa["mapping"]["name"] == "threshold"
    assert "frames 8" in sa["stdout_tail"] and "--num_frames 8" in sa["command"]
    assert sa["rater_version"]["repo_commit"] == commit and sa["rater_version"]["checkpoint_commit"] is None


@pytest.mark.parametrize("mode, match", [
    ("crash", r"exited with status 3; stderr: .*CUDA error: no CUDA-capable device"),
    ("no_output", r"malformed rater output: the rater exited with status 0 but wrote no output CSV"),
    ("no_score_column", r"malformed rater output: its output CSV has no 'score'"),
    ("text", r"malformed rater output: its score 'four' is not a number"),
    ("fraction", r"malformed rater output: its score '3.5' is not a whole number"),
    ("big", r"malformed rater output: its score '7' is not a whole number from 0 to 5"),
    ("other_video", r"malformed rater output: its output CSV has 0 rows for"),
    ("zero", r"could not read its model's answer .*stdout: .*0\.0"),
])
def test_official_rater_failures_give_null_with_reason(files, fake_rater, mode, match):
    inputs, _ = files
    script, ckpt = fake_rater
    out = videophy2_official.rate(inputs["video"], PROMPT, ["pc"], template_cfg(script, ckpt, env={"FAKE_MODE": mode}),
                                  "linear", LOG)
    e = out["pc"]
    assert e["value"] is None and e["backend"] == "videophy2_official" and "ratings" not in e, e
    assert e["reason"] and re.search(match, e["reason"], re.DOTALL), e["reason"]


def _alive(pid: int) -> bool:
    try:
        state = [ln for ln in open(f"/proc/{pid}/status") if ln.startswith("State:")][0]
    except (OSError, IndexError):
        return False
    return "Z" not in state.split()[1]   # a zombie has exited


def test_official_rater_timeout_kills_it(files, fake_rater, tmp_path):
    inputs, _ = files
    script, ckpt = fake_rater
    pid_file = tmp_path / "rater.pid"
    oc = template_cfg(script, ckpt, env={"FAKE_MODE": "sleep", "FAKE_PID_FILE": str(pid_file)}, timeout_s=1.5)
    t0 = time.perf_counter()
    out = videophy2_official.rate(inputs["video"], PROMPT, ["sa"], oc, "linear", LOG)
    assert time.perf_counter() - t0 < 20
    e = out["sa"]
    assert e["value"] is None and "timed out after 1.5 s" in e["reason"] and "official.timeout_s" in e["reason"]
    pid = int(pid_file.read_text())
    for _ in range(50):          # the rater (a child of the shell) was killed with its process group
        if not _alive(pid):
            break
        time.sleep(0.1)
    assert not _alive(pid)


def test_missing_rater_and_missing_caption(files, fake_rater, tmp_path):
    inputs, outputs = files
    script, ckpt = fake_rater
    oc = {"python": sys.executable, "repo": str(tmp_path / "nowhere"), "checkpoint": str(ckpt)}
    metrics.run(inputs, outputs, cfg_for({"official": oc}), LOG)
    doc = strict_json(outputs["metrics"])
    for key in ("semantic_adherence", "physical_commonsense"):
        assert doc[key]["value"] is None and "not installed" in doc[key]["reason"] and "nowhere" in doc[key]["reason"]
    # no prompt: SA cannot be asked, PC still is; a task left out is null with its reason
    metrics.run(inputs, outputs, cfg_for({"official": template_cfg(script, ckpt)}, prompt=None), LOG)
    doc = strict_json(outputs["metrics"])
    assert doc["semantic_adherence"]["value"] is None and "no caption" in doc["semantic_adherence"]["reason"]
    assert doc["physical_commonsense"]["value"] == 0.25
    metrics.run(inputs, outputs, cfg_for({"official": template_cfg(script, ckpt), "tasks": ["sa"]}), LOG)
    doc = strict_json(outputs["metrics"])
    assert doc["semantic_adherence"]["value"] == 0.75
    assert doc["physical_commonsense"]["value"] is None and "metrics.videophy2.tasks" in doc["physical_commonsense"]["reason"]


def test_bad_videophy2_config_stops_the_stage_without_output(files):
    inputs, outputs = files
    with pytest.raises(ConfigError, match=r"metrics.videophy2.official.command"):
        metrics.run(inputs, outputs, cfg_for({"official": {"command": "rate {input_csv}"}}), LOG)
    assert not os.path.exists(outputs["metrics"])


# ------------------------------------------------------------------ in-process rater, tiny Qwen3-VL
@pytest.fixture(scope="module")
def tiny_qwen(tmp_path_factory):
    pytest.importorskip("transformers")
    from test_params_qwen3vl import build_tiny_qwen3vl

    folder = tmp_path_factory.mktemp("tiny_qwen3vl_rater")
    build_tiny_qwen3vl(folder)
    return str(folder)


@pytest.fixture
def scripted_answer(tiny_qwen, monkeypatch):
    """Make the tiny model answer a given text: its lm_head is replaced by one that emits the
    answer's tokens then <|im_end|> (everything else, processor and generate, is the real path)."""
    import torch

    from physgs_steps.params import qwen3vl

    model, processor = qwen3vl.load(tiny_qwen, "cpu", "float32")
    tok = processor.tokenizer
    eos = tok.convert_tokens_to_ids("<|im_end|>")
    vocab = model.lm_head.out_features

    class Scripted(torch.nn.Module):
        def __init__(self, ids):
            super().__init__()
            self.seq, self.i = list(ids) + [eos], 0

        def forward(self, h):   # h [B, L, hidden] -> logits [B, L, vocab]
            t = self.seq[min(self.i, len(self.seq) - 1)]
            self.i = 0 if t == eos else self.i + 1
            logits = torch.full(h.shape[:-1] + (vocab,), -1e4)
            logits[..., t] = 0.0
            return logits

    def answer(text):
        monkeypatch.setattr(model, "lm_head", Scripted(tok.encode(text, add_special_tokens=False)))
        monkeypatch.setattr(model.generation_config, "eos_token_id", eos)

    return answer


def inprocess_cfg(model_path, **over):
    ic = {"model_path": model_path, "device": "cpu", "dtype": "float32", "n_frames": 4, "max_new_tokens": 12} | over
    return {"inprocess": ic}


def test_inprocess_rater_parsable_answer(files, tiny_qwen, scripted_answer):
    inputs, outputs = files
    scripted_answer("Rating: 4")
    metrics.run(inputs, outputs, cfg_for(inprocess_cfg(tiny_qwen)), LOG)
    doc = strict_json(outputs["metrics"])
    for key in ("semantic_adherence", "physical_commonsense"):
        e = doc[key]
        assert e["value"] == 0.75 and e["ratings"] == [4] and e["raw_answers"] == ["Rating: 4"], (e["reason"], e.get("raw_answers"))
        assert e["backend"] == "videophy2_inprocess" and e["paper_metric"] is False
        assert "NOT the paper's metric" in e["label"] and e["frames"] == sample_indices(6, 4, "segments")
    assert f'"{PROMPT}"' in doc["semantic_adherence"]["prompt"] and PROMPT not in doc["physical_commonsense"]["prompt"]
    assert "4 images above" in doc["physical_commonsense"]["prompt"]


def test_inprocess_rater_garbage_answer_is_null(files, tiny_qwen, scripted_answer):
    inputs, _ = files
    from physgs_steps.metrics import videophy2_inprocess
    from physgs_steps.metrics.video import read_frames

    scripted_answer("great!!")
    _, sampled = read_frames(inputs["video"], {"v": ("segments", 3)})
    ids, frames = sampled["v"]
    ic = inprocess_cfg(tiny_qwen, image_size=32)["inprocess"]
    out = videophy2_inprocess.rate(frames, ids, PROMPT, ["sa", "pc"], ic, "linear", "cpu", LOG)
    for e in out.values():
        assert e["value"] is None and e["raw_answers"] == ["great!!"]
        assert e["reason"] == "unusable answer: no rating in the answer 'great!!'"


def test_inprocess_rater_untouched_random_model_runs(files, tiny_qwen):
    """The random model's own answer goes through unchanged: a rating or a null with it quoted."""
    inputs, outputs = files
    metrics.run(inputs, outputs, cfg_for(inprocess_cfg(tiny_qwen, max_new_tokens=4)), LOG)
    doc = strict_json(outputs["metrics"])
    for key in ("semantic_adherence", "physical_commonsense"):
        e = doc[key]
        answer = e["raw_answers"][0]
        rating, _ = videophy2.parse_rating(answer)
        assert e["value"] == (None if rating is None else videophy2.map_rating(rating, "linear"))
        assert rating is not None or repr(answer)[:20] in e["reason"]


def test_inprocess_rater_missing_or_wrong_model(files, tmp_path):
    inputs, outputs = files
    metrics.run(inputs, outputs, cfg_for(inprocess_cfg(str(tmp_path / "no_model"))), LOG)
    doc = strict_json(outputs["metrics"])
    e = doc["physical_commonsense"]
    assert e["value"] is None and "cannot load the in-process rater's model" in e["reason"] and "no_model" in e["reason"]
    other = tmp_path / "clip_folder"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"model_type": "clip"}))
    with pytest.raises(ConfigError, match=r"metrics.videophy2.inprocess.model_path.*'clip' model"):
        metrics.run(inputs, outputs, cfg_for(inprocess_cfg(str(other))), LOG)
