"""The question put to a vision-language model about one instance, and the ask/retry loop.

Messages use a neutral form that each backend translates::

    {"role": "system" | "user" | "assistant", "content": str, "images": [H, W, 3] uint8 arrays}

(``images`` only on the first user message).  The knowledge base is quoted as expert priors,
the allowed model names are listed, pinned values are stated as fixed and the answer format
is one strict JSON object with exactly the asked keys.
"""
from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .. import materials_kb
from .validate import AnswerError, parse_answer

SYSTEM_PROMPT = (
    "You are an expert in continuum mechanics and physically based animation. You choose the "
    "constitutive model and material parameters of one object for a Material Point Method (MPM) "
    "simulation of a scene reconstructed with 3D Gaussian splatting. You answer with a single JSON "
    "object and nothing else."
)

MODEL_HELP = {
    "elasticity": {
        "fixed_corotated": "rubber-like solids, jelly, plants, near-rigid objects",
        "neo_hookean": "hyperelastic solids with large stretch (elastomers, foam)",
        "stvk_hencky": "used with plasticity: metals, sand, snow, clay, bread",
        "volume": "volume-preserving pressure only",
        "fluid": "liquids (pressure only)",
    },
    "plasticity": {
        "identity": "purely elastic, returns to its shape",
        "von_mises": "ductile yielding (metal, clay, bread, viscous goo); needs yield_stress in Pa",
        "drucker_prager": "granular, Drucker-Prager cone (Klar et al. 2016); needs friction_angle in degrees and cohesion (log-strain offset, 0 for dry sand)",
        "mohr_coulomb": "granular (sand, snow), Mohr-Coulomb; needs friction_angle in degrees and cohesion (log-strain offset, 0 for dry sand)",
        "j_clamp": "clamps volume change (snow-like compaction)",
        "fluid": "liquids, no shear memory",
    },
}

_ANSWER_HINTS = {
    "material": "<closest knowledge-base material name>",
    "elasticity": "<elasticity model>",
    "plasticity": "<plasticity model>",
    "E": "<Young's modulus in Pa, simulation-effective scale>",
    "nu": "<Poisson's ratio, 0 <= nu < 0.5>",
    "density": "<kg/m^3>",
    "yield_stress": "<Pa, or null unless plasticity is von_mises>",
    "friction_angle": "<degrees, the angle of repose (below 45), or null unless plasticity is mohr_coulomb or drucker_prager>",
    "cohesion": "<number, or null unless plasticity is mohr_coulomb or drucker_prager>",
    "rigid": "<true if the object is visually rigid and should move as one rigid body, else false>",
}


@dataclass
class Question:
    """Everything a VLM backend needs to ask about one instance."""

    label: int
    name: str
    hint: str | None
    prompt: str
    pins: dict
    asked: list[str]
    images: np.ndarray | None = None    # [C, H, W, 3] uint8 views of the instance, or None


@dataclass
class DialogResult:
    """Outcome of asking: the parsed answer (or None) and every attempt with its error."""

    answer: dict | None
    attempts: list[dict] = field(default_factory=list)
    error: str | None = None
    prompt_sha256: str = ""


class BackendError(RuntimeError):
    """The backend cannot answer at all (no weights, server unreachable, generation failed)."""


def user_text(q: Question, kb: dict) -> str:
    """The user-turn text for question ``q`` (images are attached separately)."""
    obj = f"'{q.name}'" + (f", described as: {q.hint!r}" if q.hint else "")
    n_img = 0 if q.images is None else len(q.images)
    lines = [
        f"Scene description: {q.prompt!r}" if q.prompt else "Scene description: (none given)",
        f"Object: {obj}.",
    ]
    if n_img:
        lines.append(f"The {n_img} images show this object alone, from {n_img} viewpoints around it.")
    lines += [
        "",
        "Knowledge base of materials (expert priors). E is the SIMULATION-EFFECTIVE Young's modulus for a "
        "tabletop object in a 1 m domain on a 32-64 grid, not the handbook value; answer E on this scale:",
        materials_kb.kb_table_text(kb),
        "",
        "Allowed elasticity models:",
        *[f"- {k}: {v}" for k, v in MODEL_HELP["elasticity"].items()],
        "Allowed plasticity models:",
        *[f"- {k}: {v}" for k, v in MODEL_HELP["plasticity"].items()],
        "",
        "rigid: true for an object that does not visibly deform (stone, wood, metal, ceramic, glass, hard "
        "plastic): it is simulated as one rigid body that still collides with and pushes the soft objects; "
        "false for anything that should bend, squash, wobble, tear or flow.",
    ]
    if q.pins:
        lines += ["", "Fixed by the user (do not answer these): " +
                  ", ".join(f"{k} = {v}" for k, v in sorted(q.pins.items()))]
    template = {k: _ANSWER_HINTS[k] for k in q.asked}
    template["reason"] = "<one short sentence>"
    lines += ["", "Reply with only this JSON object, filled in (numbers as JSON numbers, no units):",
              json.dumps(template, indent=1)]
    return "\n".join(lines)


def first_messages(q: Question, kb: dict) -> list[dict]:
    images = [] if q.images is None else [np.asarray(im, dtype=np.uint8) for im in q.images]
    return [{"role": "system", "content": SYSTEM_PROMPT},
            {"role": "user", "content": user_text(q, kb), "images": images}]


def messages_sha256(messages: list[dict]) -> str:
    """sha256 over every message's role, text and image bytes."""
    h = hashlib.sha256()
    for m in messages:
        h.update(m["role"].encode())
        h.update(m["content"].encode())
        for im in m.get("images") or []:
            a = np.ascontiguousarray(im, dtype=np.uint8)
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


def ask(send: Callable[[list[dict]], str], q: Question, kb: dict, retries: int = 1) -> DialogResult:
    """Ask, validate with :func:`parse_answer`; on an invalid answer say why and ask again.

    Args:
        send: backend call, messages -> reply text; raises :class:`BackendError` when it
            cannot answer at all (then no retry is made).
        q: the question.
        kb: knowledge base.
        retries: extra attempts after an invalid answer.
    """
    messages = first_messages(q, kb)
    res = DialogResult(answer=None, prompt_sha256=messages_sha256(messages))
    for attempt in range(retries + 1):
        t0 = time.perf_counter()
        try:
            raw = send(messages)
        except BackendError as e:
            res.attempts.append({"raw": None, "error": f"backend: {e}", "seconds": round(time.perf_counter() - t0, 3)})
            res.error = f"backend failed: {e}"
            return res
        rec = {"raw": raw, "error": None, "seconds": round(time.perf_counter() - t0, 3)}
        res.attempts.append(rec)
        try:
            res.answer = parse_answer(raw, q.asked)
            return res
        except AnswerError as e:
            rec["error"] = str(e)
            res.error = f"invalid answer after {attempt + 1} attempt(s): {e}"
            messages = messages + [
                {"role": "assistant", "content": raw if isinstance(raw, str) else ""},
                {"role": "user", "content": f"That answer cannot be used: {e}. Reply again with only the JSON "
                                            f"object with the keys {', '.join(q.asked)}."},
            ]
    return res
