"""The `openai` backend: any OpenAI-compatible chat-completions endpoint that accepts images.

For example a local vLLM serving Qwen3-VL (``vllm serve Qwen/Qwen3-VL-8B-Instruct``, then
``base_url: http://127.0.0.1:8000/v1``).  Only the standard library is used (urllib).  The
API key is read from the environment variable named by ``materials.openai.api_key_env``
(not sent when unset, as local servers need none).  Transport failures (connection refused,
timeouts, HTTP 429 and 5xx) are retried ``retries`` times with exponential backoff; other
HTTP errors fail at once.  Images travel as PNG data URLs.

``timeout_s`` is a real deadline for each attempt (connect, send, the whole answer), not
urllib's per-read socket timeout, which a server sending a byte every few seconds never
trips: a timer shuts the connection's socket when the deadline passes (:class:`_Deadline`).
"""
from __future__ import annotations

import base64
import http.client
import io
import json
import logging
import os
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np

from ..errors import ConfigError
from .prompt import BackendError

RETRY_STATUS = {408, 409, 425, 429, 500, 502, 503, 504}


def png_data_url(image: np.ndarray) -> str:
    """A ``data:image/png;base64,...`` URL of a [H, W, 3] uint8 image."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def to_openai_messages(messages: list[dict]) -> list[dict]:
    """Neutral messages (params/prompt.py) -> OpenAI chat messages with image_url parts."""
    out = []
    for m in messages:
        images = m.get("images") or []
        if images:
            parts = [{"type": "text", "text": m["content"]}]
            parts += [{"type": "image_url", "image_url": {"url": png_data_url(im)}} for im in images]
            out.append({"role": m["role"], "content": parts})
        else:
            out.append({"role": m["role"], "content": m["content"]})
    return out


class _Deadline:
    """A wall-clock limit on one HTTP exchange: when it passes, a timer shuts the socket of the
    connection, which ends a blocked send or receive at once."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.end = time.monotonic() + seconds
        self.fired = False
        self._timer: threading.Timer | None = None

    def remaining(self) -> float:
        return max(self.end - time.monotonic(), 1e-3)

    def arm(self, sock) -> None:
        self._timer = threading.Timer(self.remaining(), self._fire, args=(sock,))
        self._timer.daemon = True
        self._timer.start()

    def _fire(self, sock) -> None:
        self.fired = True
        try:
            sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()

    def opener(self) -> urllib.request.OpenerDirector:
        """A urllib opener (proxies and redirects as usual) whose connections obey this deadline."""
        deadline = self

        class HTTPConn(http.client.HTTPConnection):
            def connect(self):
                super().connect()
                deadline.arm(self.sock)

        class HTTPSConn(http.client.HTTPSConnection):
            def connect(self):
                super().connect()
                deadline.arm(self.sock)

        class HTTPHandler(urllib.request.HTTPHandler):
            def http_open(self, req):
                return self.do_open(HTTPConn, req)

        class HTTPSHandler(urllib.request.HTTPSHandler):
            def https_open(self, req):
                return self.do_open(HTTPSConn, req, context=self._context)

        return urllib.request.build_opener(HTTPHandler, HTTPSHandler)


class OpenAIBackend:
    """Chat-completions client with timeouts and transport retries."""

    name = "openai"

    def __init__(self, cfg: dict, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        base = cfg.get("base_url")
        if not isinstance(base, str) or not base.startswith(("http://", "https://")):
            raise ConfigError("materials.openai.base_url", f"must be an http(s) URL, got {base!r}")
        if not cfg.get("model"):
            raise ConfigError("materials.openai.model", "must name the served model")
        self.url = base.rstrip("/") + "/chat/completions"
        self.model = cfg["model"]
        self.timeout = float(cfg.get("timeout_s", 60.0))
        self.retries = int(cfg.get("retries", 2))
        self.backoff = float(cfg.get("backoff_s", 1.0))
        self.key_env = cfg.get("api_key_env") or ""

    def describe(self) -> dict:
        return {"url": self.url, "model": self.model, "timeout_s": self.timeout, "retries": self.retries,
                "api_key_env": self.key_env, "api_key_set": bool(self.key_env and os.environ.get(self.key_env))}

    def load(self) -> None:
        """Nothing to load; the server is contacted per question."""

    def _payload(self, messages: list[dict]) -> dict:
        body = {"model": self.model, "messages": to_openai_messages(messages),
                "temperature": float(self.cfg.get("temperature", 0.0)),
                "max_tokens": int(self.cfg.get("max_tokens", 512))}
        if self.cfg.get("json_mode", True):
            body["response_format"] = {"type": "json_object"}
        return body

    def send(self, messages: list[dict]) -> str:
        """The reply text; raises BackendError after the transport retries are spent."""
        data = json.dumps(self._payload(messages)).encode()
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(self.key_env) if self.key_env else None
        if key:
            headers["Authorization"] = f"Bearer {key}"
        last = ""
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(self.backoff * 2 ** (attempt - 1))
            req = urllib.request.Request(self.url, data=data, headers=headers, method="POST")
            deadline = _Deadline(self.timeout)
            try:
                try:
                    with deadline.opener().open(req, timeout=deadline.remaining()) as resp:
                        body = resp.read()
                finally:
                    deadline.cancel()
                if deadline.fired:
                    raise TimeoutError(f"no complete answer within materials.openai.timeout_s = {self.timeout:g} s")
            except urllib.error.HTTPError as e:
                detail = e.read()[:300].decode("utf-8", "replace") if e.fp else ""
                last = f"HTTP {e.code} from {self.url}: {detail}".strip()
                if e.code in RETRY_STATUS:
                    self.log.warning("openai backend: %s (attempt %d of %d)", last, attempt + 1, self.retries + 1)
                    continue
                raise BackendError(last) from None
            except (urllib.error.URLError, socket.timeout, TimeoutError, ConnectionError, http.client.HTTPException,
                    OSError) as e:
                reason = getattr(e, "reason", e)
                if deadline.fired:
                    reason = f"no complete answer within materials.openai.timeout_s = {self.timeout:g} s"
                last = f"cannot reach {self.url}: {reason}"
                self.log.warning("openai backend: %s (attempt %d of %d)", last, attempt + 1, self.retries + 1)
                continue
            return _reply_text(body, self.url)
        raise BackendError(f"{last} (gave up after {self.retries + 1} attempts)")


def _reply_text(body: bytes, url: str) -> str:
    try:
        obj = json.loads(body)
        content = obj["choices"][0]["message"]["content"]
    except (ValueError, KeyError, IndexError, TypeError):
        raise BackendError(f"{url} returned no chat completion: {body[:200]!r}") from None
    if isinstance(content, list):   # some servers return content parts
        content = "".join(p.get("text", "") for p in content if isinstance(p, dict))
    if not isinstance(content, str):
        raise BackendError(f"{url} returned non-text content {type(content).__name__}")
    return content
