"""The openai backend against an OpenAI-compatible HTTP server on loopback started here."""
from __future__ import annotations

import base64
import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from physgs_steps.config import section_defaults
from physgs_steps.errors import ConfigError, InputError
from physgs_steps.params import stage
from physgs_steps.params.openai_backend import OpenAIBackend, to_openai_messages
from physgs_steps.params.prompt import BackendError

LOG = logging.getLogger("test.openai")

GOOD = {"material": "metal", "elasticity": "StVK", "plasticity": "von Mises", "E": 2.0e11, "nu": 0.3,
        "density": 7850, "yield_stress": 2.5e8, "friction_angle": None, "cohesion": None,
        "reason": "a steel can"}


class FakeServer:
    """Serves queued replies: a dict is sent as the assistant's text (JSON), a str as raw text,
    an int as that HTTP status. Records every request (headers, body)."""

    def __init__(self):
        self.replies: list = []
        self.requests: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server API
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                outer.requests.append({"path": self.path, "headers": dict(self.headers), "body": body})
                reply = outer.replies.pop(0) if outer.replies else 500
                if isinstance(reply, int):
                    self.send_response(reply)
                    self.end_headers()
                    self.wfile.write(b'{"error": "test"}')
                    return
                text = json.dumps(reply) if isinstance(reply, dict) else reply
                data = json.dumps({"choices": [{"message": {"role": "assistant", "content": text}}]}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()
        self.base_url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server():
    s = FakeServer()
    yield s
    s.close()


def materials_cfg(server, **openai):
    m = section_defaults("materials")
    m["backend"] = "openai"
    m["openai"].update({"base_url": server.base_url, "model": "tiny-vl", "api_key_env": "PHYSGS_TEST_KEY",
                        "timeout_s": 5.0, "retries": 1, "backoff_s": 0.01, "n_views": 0}, **openai)
    return m


def write_inputs(tmp_path, n_labels=1):
    np.savez(tmp_path / "labels.npz", labels=np.arange(n_labels, dtype=np.int32).repeat(10))
    (tmp_path / "clusters.json").write_text(json.dumps({"n_instances": n_labels, "instances": [
        {"label": k, "count": 10, "config_index": 0 if k == 0 else None} for k in range(n_labels)]}))
    return ({"scene": str(tmp_path / "scene.ply"), "labels": str(tmp_path / "labels.npz"),
             "clusters": str(tmp_path / "clusters.json")}, {"params": str(tmp_path / "params.json")})


SCENE = {"prompt": "a jelly bear is thrown against a metal can",
         "instances": [{"name": "can", "hint": "an aluminium can"}]}


def run(tmp_path, server, n_labels=1, **openai):
    inputs, outputs = write_inputs(tmp_path, n_labels)
    cfg = {"materials": materials_cfg(server, **openai), "scene": SCENE, "device": "cpu"}
    summary = stage.run(inputs, outputs, cfg, LOG)
    return json.loads((tmp_path / "params.json").read_text()), summary


def test_valid_answer_is_validated_and_clamped(tmp_path, server, monkeypatch):
    monkeypatch.setenv("PHYSGS_TEST_KEY", "sk-test")
    server.replies = [GOOD]
    doc, _ = run(tmp_path, server)
    can = doc["instances"][0]
    assert can["provenance"]["source"] == "openai" and "fallback_reason" not in can["provenance"]
    assert (can["material"], can["elasticity"], can["plasticity"]) == ("metal", "stvk_hencky", "von_mises")
    assert can["E"] == 1.0e8                                  # handbook 200 GPa clamped to metal's effective range
    assert can["plasticity_params"]["yield_stress"] == 2.5e8
    clamped = {n["key"] for n in can["provenance"]["clamped"]}
    assert "E" in clamped and can["provenance"]["answer_reason"] == "a steel can"
    assert json.loads(can["provenance"]["raw_answer"]) == GOOD
    req = server.requests[0]
    assert req["path"] == "/v1/chat/completions" and req["headers"]["Authorization"] == "Bearer sk-test"
    body = req["body"]
    assert body["model"] == "tiny-vl" and body["temperature"] == 0.0
    assert body["response_format"] == {"type": "json_object"}
    user = body["messages"][1]["content"]
    assert "an aluminium can" in user and "stone: elasticity=fixed_corotated" in user and '"E"' in user


def test_invalid_then_valid_uses_the_retry(tmp_path, server, monkeypatch):
    monkeypatch.delenv("PHYSGS_TEST_KEY", raising=False)
    server.replies = ["I think it is metal.", dict(GOOD, E=5e7)]
    doc, _ = run(tmp_path, server)
    can = doc["instances"][0]
    assert can["provenance"]["source"] == "openai" and can["E"] == 5e7
    assert len(can["provenance"]["attempts"]) == 2 and "no JSON object" in can["provenance"]["attempts"][0]["error"]
    second = server.requests[1]["body"]["messages"]
    assert second[-2] == {"role": "assistant", "content": "I think it is metal."}
    assert "cannot be used" in second[-1]["content"]
    assert "Authorization" not in server.requests[0]["headers"]


def test_garbage_twice_falls_back_to_prior(tmp_path, server):
    server.replies = ["garbage", '{"material": "metal"}']
    doc, summary = run(tmp_path, server)
    prov = doc["instances"][0]["provenance"]
    assert prov["source"] == "prior" and "lacks keys" in prov["fallback_reason"]
    assert doc["instances"][0]["material"] == "metal"   # the prior reads "aluminium" in the hint
    assert summary["fallbacks"] == 1


def test_transport_errors_are_retried_then_fall_back(tmp_path, server):
    server.replies = [503, GOOD]
    doc, _ = run(tmp_path, server)
    assert doc["instances"][0]["provenance"]["source"] == "openai" and len(server.requests) == 2
    server.requests.clear()
    server.replies = [500, 502, 500, 500]
    doc, _ = run(tmp_path, server, n_labels=2)
    for inst in doc["instances"]:
        assert inst["provenance"]["source"] == "prior" and "HTTP 50" in inst["provenance"]["fallback_reason"]
    assert len(server.requests) == 4      # 2 instances x (1 + retries=1)
    server.replies = [400]
    doc, _ = run(tmp_path, server)
    assert "HTTP 400" in doc["instances"][0]["provenance"]["fallback_reason"]


def test_unreachable_server(tmp_path):
    backend = OpenAIBackend({"base_url": "http://127.0.0.1:9/v1", "model": "m", "timeout_s": 1, "retries": 1,
                             "backoff_s": 0.0}, LOG)
    with pytest.raises(BackendError, match="cannot reach"):
        backend.send([{"role": "user", "content": "hi"}])


def test_images_are_png_data_urls():
    img = np.zeros((8, 6, 3), np.uint8)
    img[2, 3] = [255, 0, 0]
    msgs = to_openai_messages([{"role": "user", "content": "look", "images": [img, img]}])
    parts = msgs[0]["content"]
    assert parts[0] == {"type": "text", "text": "look"} and len(parts) == 3
    url = parts[1]["image_url"]["url"]
    assert url.startswith("data:image/png;base64,")
    from io import BytesIO

    from PIL import Image

    back = np.asarray(Image.open(BytesIO(base64.b64decode(url.split(",", 1)[1]))))
    assert np.array_equal(back, img)


def test_bad_openai_config():
    with pytest.raises(ConfigError, match="materials.openai.base_url"):
        OpenAIBackend({"base_url": "localhost:8000", "model": "m"}, LOG)


def write_scene(tmp_path):
    """A two-label scene.ply with labels.npz / clusters.json (label 0 matches the scene entry)."""
    from physgs_steps import save_gaussians
    from physgs_steps.gaussians import GaussianScene

    rng = np.random.default_rng(0)
    n = 200
    means = np.concatenate([rng.normal([0.4, 0.5, 0.3], 0.04, (n, 3)), rng.normal([0.7, 0.5, 0.3], 0.04, (n, 3))])
    scene = GaussianScene(means=means, log_scales=np.full((2 * n, 3), np.log(0.01)),
                          quats=np.tile([1, 0, 0, 0], (2 * n, 1)), opacity_logits=np.full(2 * n, 3.0),
                          sh=np.full((2 * n, 1, 3), 0.8, np.float32))
    save_gaussians(scene, tmp_path / "scene.ply")
    inputs, outputs = write_inputs(tmp_path, 2)
    np.savez(tmp_path / "labels.npz", labels=np.repeat(np.arange(2, dtype=np.int32), n))
    return inputs, outputs


def test_views_are_sent_and_renderer_failures_degrade_to_text(tmp_path, server, monkeypatch):
    from physgs_steps.params import views

    calls = []

    def fake_views(scene, mask, n_views, size, elevation_deg, fov_deg, backend):
        calls.append((int(mask.sum()), n_views, size))
        if len(calls) == 2:
            raise RuntimeError("renderer exploded")
        return np.full((n_views, size, size, 3), 128, np.uint8)

    monkeypatch.setattr(views, "instance_views", fake_views)
    inputs, outputs = write_scene(tmp_path)
    server.replies = [GOOD, GOOD]
    cfg = {"materials": materials_cfg(server, n_views=2, image_size=32), "scene": SCENE, "device": "cpu"}
    stage.run(inputs, outputs, cfg, LOG)
    doc = json.loads((tmp_path / "params.json").read_text())
    assert calls == [(200, 2, 32), (200, 2, 32)]
    first, second = (r["body"]["messages"][1]["content"] for r in server.requests)
    assert [p["type"] for p in first] == ["text", "image_url", "image_url"]
    assert "2 images show this object" in first[0]["text"]
    assert isinstance(second, str) and "images show" not in second
    p0, p1 = (i["provenance"] for i in doc["instances"])
    assert p0["n_views"] == 2 and "views_error" not in p0
    assert p1["n_views"] == 0 and "renderer exploded" in p1["views_error"]
    assert p0["source"] == p1["source"] == "openai"


def test_scene_and_labels_must_agree(tmp_path, server):
    inputs, outputs = write_scene(tmp_path)
    np.savez(tmp_path / "labels.npz", labels=np.array([0, 1] * 5, np.int32))
    server.replies = [GOOD, GOOD]
    cfg = {"materials": materials_cfg(server, n_views=1, image_size=32), "scene": SCENE, "device": "cpu"}
    with pytest.raises(InputError, match="400 gaussians but labels.npz has 10"):
        stage.run(inputs, outputs, cfg, LOG)
