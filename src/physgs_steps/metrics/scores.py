"""The one shape every video score of metrics.json has (docs/CONTRACTS.md, "metrics.json").

Each of ``clip_score``, ``aesthetic_score``, ``semantic_adherence`` and
``physical_commonsense`` is a dict with at least these keys:

* ``column``: the paper's column (``CS``, ``AS``, ``SA``, ``PC``);
* ``value``: a finite float, or null when the score could not be computed;
* ``reason``: null when there is a value, else why not (a missing weight, the rater's error);
* ``backend``: what produced it (``clip``, ``laion_aesthetic``, ``videophy2_official``,
  ``videophy2_inprocess``), null when nothing was run;
* ``paper_metric``: true when the value is the paper's metric (its model and recipe), false
  for a stand-in (the in-process VideoPhy2 rater), null when there is no value;
* ``scale``: the range of ``value``.

Backend-specific details (per-frame values, raw ratings, the command, ...) are extra keys.
"""
from __future__ import annotations

import math
from typing import Any

COLUMNS = {"clip_score": "CS", "aesthetic_score": "AS", "semantic_adherence": "SA", "physical_commonsense": "PC"}
SCALES = {"CS": "cosine similarity, -1..1 (the paper reports about 0.2-0.3)",
          "AS": "LAION aesthetic, about 1..10",
          "SA": "0..1, mapped from VideoPhy2's 1-5 rating (see mapping)",
          "PC": "0..1, mapped from VideoPhy2's 1-5 rating (see mapping)"}
BASE_KEYS = ("column", "value", "reason", "backend", "paper_metric", "scale")


def measured(key: str, value: float, backend: str, paper_metric: bool, **details: Any) -> dict:
    """A computed score; a non-finite value becomes null with the reason."""
    col = COLUMNS[key]
    v = float(value)
    if not math.isfinite(v):
        return unavailable(key, f"the computed value is not finite ({v})", backend=backend, **details)
    return {"column": col, "value": v, "reason": None, "backend": backend, "paper_metric": bool(paper_metric),
            "scale": SCALES[col], **details}


def unavailable(key: str, reason: str, backend: str | None = None, **details: Any) -> dict:
    """A score that could not be computed: value null, and why."""
    col = COLUMNS[key]
    if not reason:
        raise ValueError("an unavailable score needs a reason")
    return {"column": col, "value": None, "reason": str(reason), "backend": backend, "paper_metric": None,
            "scale": SCALES[col], **details}


def scrub_nonfinite(obj: Any, path: str = "") -> tuple[Any, list[str]]:
    """A copy of ``obj`` with NaN/inf floats replaced by None, and the paths replaced (strict JSON)."""
    bad: list[str] = []

    def walk(o, p):
        if isinstance(o, float) and not math.isfinite(o):
            bad.append(p or "<root>")
            return None
        if isinstance(o, dict):
            return {k: walk(v, f"{p}.{k}" if p else str(k)) for k, v in o.items()}
        if isinstance(o, (list, tuple)):
            return [walk(v, f"{p}[{i}]") for i, v in enumerate(o)]
        return o

    return walk(obj, path), bad


def tail(text: str | bytes | None, n: int = 1500) -> str:
    """The last ``n`` characters of a process output (decoded leniently)."""
    if text is None:
        return ""
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    text = text.strip()
    return text if len(text) <= n else "..." + text[-n:]
