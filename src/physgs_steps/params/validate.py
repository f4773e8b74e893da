"""Checking material parameters: scene pins (strict) and model answers (clamp or reject).

* Pins come from the user's scene file, so a bad value is a :class:`ConfigError` naming
  ``scene.instances[i].<key>``; nothing is silently changed.  ``rigid`` (and ``fixed``,
  which implies it) pins whether the instance is simulated as a rigid body; otherwise the
  answer's ``rigid`` or the material's knowledge-base flag decides.
* Answers come from a VLM: an answer that is not a JSON object with the asked keys is an
  :class:`AnswerError` (the backend retries, then falls back to the prior).  Field-level
  problems are repaired and recorded: E <= 0, density <= 0, non-numbers and unknown model
  names are *rejected* (the prior's value is kept), nu outside [0, nu_max] and values outside
  the configured limits or the material's E_range are *clamped*.
"""
from __future__ import annotations

import json
import math
import re
from typing import Any

from .. import materials_kb
from ..materials_kb import FRICTION_ANGLE_MAX
from ..errors import ConfigError

PIN_KEYS = ("material", "elasticity", "plasticity", "E", "nu", "density",
            "yield_stress", "friction_angle", "cohesion", "fracture_strain", "fracture_softening", "rigid")
VALUE_KEYS = ("elasticity", "plasticity", "E", "nu", "density")
PLASTICITY_ANSWER_KEYS = ("yield_stress", "friction_angle", "cohesion")
# Tearing parameters: the knowledge base or a scene pin sets them; a model is never asked for them.
PLASTICITY_PIN_KEYS = PLASTICITY_ANSWER_KEYS + ("fracture_strain", "fracture_softening")
REQUIRED_ANSWER_KEYS = ("material", "elasticity", "plasticity", "E", "nu", "density")
OPTIONAL_ANSWER_KEYS = ("rigid",)  # asked unless pinned; a missing or unreadable answer keeps the material's flag

DEFAULT_LIMITS = {"E_min": 1.0e3, "E_max": 1.0e9, "nu_max": 0.49, "density_min": 1.0, "density_max": 25000.0,
                  "friction_angle_max": 44.0, "cohesion_max": 0.2}


class AnswerError(ValueError):
    """A model answer that cannot be used at all (not JSON, missing keys, wrong types)."""


# --------------------------------------------------------------------------- pins
def check_pins(entry: dict, index: int, kb: dict, source: str | None = None) -> dict:
    """The pinned values of scene instance ``index`` in canonical form.

    Args:
        entry: one item of the scene's ``instances`` list.
        index: its position (for error messages).
        kb: knowledge base.
        source: the scene file, named in errors.
    Returns:
        dict with the pinned keys of :data:`PIN_KEYS` only (material resolved to its KB
        name, model names canonical, numbers as float).
    Raises:
        ConfigError naming ``scene.instances[index].<key>`` (and ``source``).
    """
    try:
        return _check_pins(entry, index, kb)
    except ConfigError as e:
        raise ConfigError(e.key, e.problem, e.source or source) from None


def _check_pins(entry: dict, index: int, kb: dict) -> dict:
    if not isinstance(entry, dict):
        raise ConfigError(f"scene.instances[{index}]", f"must be a mapping, got {type(entry).__name__}")
    key = f"scene.instances[{index}]"
    pins: dict[str, Any] = {}
    if entry.get("material") is not None:
        pins["material"] = materials_kb.resolve_material_name(entry["material"], kb, f"{key}.material")
    if entry.get("elasticity") is not None:
        pins["elasticity"] = materials_kb.normalize_elasticity(entry["elasticity"], f"{key}.elasticity")
    if entry.get("plasticity") is not None:
        pins["plasticity"] = materials_kb.normalize_plasticity(entry["plasticity"], f"{key}.plasticity")
    checks = {
        "E": lambda v: v > 0, "density": lambda v: v > 0, "nu": lambda v: 0 <= v < 0.5,
        "yield_stress": lambda v: v > 0, "friction_angle": lambda v: 0 <= v < FRICTION_ANGLE_MAX, "cohesion": lambda v: v >= 0,
        "fracture_strain": lambda v: v > 0, "fracture_softening": lambda v: v > 0,
    }
    ranges = {"E": "> 0 Pa", "density": "> 0 kg/m^3", "nu": "in [0, 0.5)", "yield_stress": "> 0 Pa",
              "friction_angle": f"in [0, {FRICTION_ANGLE_MAX:g}) degrees (the angle of repose)", "cohesion": ">= 0",
              "fracture_strain": "> 0 (principal Hencky strain)", "fracture_softening": "> 0 (inelastic strain to full damage)"}
    for k in ("rigid", "fixed"):
        v = entry.get(k)
        if v is not None and not isinstance(v, bool):
            raise ConfigError(f"{key}.{k}", f"must be true or false, got {v!r}")
    if entry.get("fixed") and entry.get("rigid") is False:
        raise ConfigError(f"{key}.fixed", "a fixed instance is a fixed rigid body: it cannot be pinned rigid: false")
    if entry.get("rigid") is not None:
        pins["rigid"] = bool(entry["rigid"])
    if entry.get("fixed"):
        pins["rigid"] = True  # fixed implies rigid
    for k, ok in checks.items():
        v = entry.get(k)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(f"{key}.{k}", f"must be a finite number, got {v!r}")
        if not ok(v):
            raise ConfigError(f"{key}.{k}", f"must be {ranges[k]}, got {v}")
        pins[k] = float(v)
    return pins


def check_velocity(entry: dict | None, index: int | None) -> list[float]:
    """The instance's initial velocity [3] in m/s (default zeros)."""
    v = (entry or {}).get("velocity")
    if v is None:
        return [0.0, 0.0, 0.0]
    key = f"scene.instances[{index}].velocity"
    if not isinstance(v, (list, tuple)) or len(v) != 3 or not all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v):
        raise ConfigError(key, f"must be three finite numbers [vx, vy, vz] in m/s, got {v!r}")
    return [float(x) for x in v]


def check_collider(entry: dict | None, index: int | None) -> dict:
    """The instance's placement flags for params.json: ``fixed`` (bool), ``surface`` and
    ``friction`` (used when it is fixed: the static collider's surface kind and Coulomb
    coefficient).  Defaults: not fixed, separate, 0.5."""
    e = entry or {}
    key = f"scene.instances[{index}]"
    surface = e.get("surface") or "separate"
    if surface not in ("sticky", "slip", "separate"):
        raise ConfigError(f"{key}.surface", f"must be sticky, slip or separate, got {surface!r}")
    fr = e.get("friction")
    fr = 0.5 if fr is None else fr
    if isinstance(fr, bool) or not isinstance(fr, (int, float)) or not math.isfinite(fr) or fr < 0:
        raise ConfigError(f"{key}.friction", f"must be a number >= 0, got {fr!r}")
    return {"fixed": bool(e.get("fixed") or False), "surface": surface, "friction": float(fr)}


def is_fully_pinned(pins: dict) -> bool:
    """True when the pins alone determine every parameter (a material preset, or all values).

    A pinned ``material`` selects that KB preset, which fixes everything not pinned
    otherwise.  Without it, elasticity, plasticity, E, nu, density and the parameters the
    plasticity model needs (von_mises: yield_stress; drucker_prager: friction_angle) must
    all be pinned.
    """
    if "material" in pins:
        return True
    if not all(k in pins for k in VALUE_KEYS):
        return False
    need = [k for k in materials_kb.REQUIRED_PLASTICITY_PARAMS[pins["plasticity"]]
            if k in PLASTICITY_ANSWER_KEYS and k != "cohesion"]
    return all(k in pins for k in need)


def asked_keys(pins: dict) -> list[str]:
    """The answer keys a model is asked for: everything not pinned."""
    keys = [k for k in REQUIRED_ANSWER_KEYS if k not in pins]
    keys += [k for k in PLASTICITY_ANSWER_KEYS if k not in pins]
    keys += [k for k in OPTIONAL_ANSWER_KEYS if k not in pins]
    return keys


# --------------------------------------------------------------------------- answers
def parse_answer(text: str, asked: list[str]) -> dict:
    """The JSON object in a model's reply (code fences and surrounding prose allowed).

    Raises:
        AnswerError when no JSON object is found or a required asked key is missing or has
        the wrong type.
    """
    if not isinstance(text, str) or not text.strip():
        raise AnswerError("empty answer")
    obj = _first_json_object(text)
    if obj is None:
        snippet = text.strip().replace("\n", " ")[:80]
        raise AnswerError(f"no JSON object in the answer (starts {snippet!r})")
    missing = [k for k in asked if k in REQUIRED_ANSWER_KEYS and k not in obj]
    if missing:
        raise AnswerError(f"JSON answer lacks keys {missing}")
    for k in ("material", "elasticity", "plasticity"):
        if k in asked and not isinstance(obj.get(k), str):
            raise AnswerError(f"'{k}' must be a string, got {obj.get(k)!r}")
    for k in ("E", "nu", "density"):
        if k in asked and _number(obj.get(k)) is None:
            raise AnswerError(f"'{k}' must be a number, got {obj.get(k)!r}")
    return obj


def _boolean(v: Any) -> bool | None:
    """True/False from a JSON boolean or the strings "true"/"false"/"yes"/"no"; else None."""
    if isinstance(v, bool):
        return v
    if isinstance(v, str) and v.strip().lower() in ("true", "yes", "false", "no"):
        return v.strip().lower() in ("true", "yes")
    return None


def _first_json_object(text: str) -> dict | None:
    dec = json.JSONDecoder()
    for m in re.finditer(r"\{", text):
        try:
            obj, _ = dec.raw_decode(text[m.start():])
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict):
            return obj
    return None


def _number(v: Any) -> float | None:
    """A finite float from a number or a numeric string ("2e5", "1.5e+05 Pa"); else None."""
    if isinstance(v, bool):
        return None
    if isinstance(v, (int, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, str):
        m = re.fullmatch(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*[a-zA-Z/^0-9°]*\s*", v)
        if m:
            x = float(m.group(1))
            return x if math.isfinite(x) else None
    return None


def finalize_answer(answer: dict, base: dict, pins: dict, kb: dict, limits: dict | None = None,
                    clamp_to_material_range: bool = True) -> tuple[dict, list[dict]]:
    """Turn a parsed answer into parameter values, repairing and recording every problem.

    Args:
        answer: output of :func:`parse_answer`.
        base: fallback values (the prior's params: material, elasticity, plasticity, E, nu,
            density, plasticity_params).
        pins: validated pins (they override everything and are never changed).
        kb: knowledge base.
        limits: global bounds (see :data:`DEFAULT_LIMITS`).
        clamp_to_material_range: clamp E into the answered material's ``E_range``.
    Returns:
        (values in params.json form without label/name/provenance, list of notes
        ``{"key", "value", "action": "clamped"|"rejected"|"filled", "to", "reason"}``).
    """
    lim = dict(DEFAULT_LIMITS, **(limits or {}))
    notes: list[dict] = []
    out = {k: base[k] for k in ("material", "elasticity", "plasticity", "E", "nu", "density")}
    out["rigid"] = bool(base.get("rigid", False))
    pp = dict(base["plasticity_params"])

    mat = answer.get("material")
    if "material" not in pins and mat is not None:
        try:
            mname = materials_kb.resolve_material_name(mat, kb, "answer.material")
        except ConfigError:
            notes.append(_note("material", mat, "rejected", base["material"],
                               f"not a knowledge-base material (valid: {', '.join(kb)}); values default to the prior's '{base['material']}'"))
        else:
            if mname != base["material"]:
                entry = kb[mname]
                out.update({k: entry[k] for k in ("elasticity", "plasticity", "E", "nu", "density", "rigid")})
                pp = dict(entry["plasticity_params"])
            out["material"] = mname

    for kind in ("elasticity", "plasticity"):
        if kind in pins or answer.get(kind) is None:
            continue
        try:
            out[kind] = materials_kb.normalize_model(kind, answer[kind], f"answer.{kind}")
        except ConfigError:
            notes.append(_note(kind, answer[kind], "rejected", out[kind],
                               f"unknown {kind} model; valid: {', '.join(materials_kb.MODEL_NAMES[kind])}"))

    _take_number(answer, out, notes, "E", positive=True, lo=lim["E_min"], hi=lim["E_max"], unit="Pa")
    _take_number(answer, out, notes, "density", positive=True, lo=lim["density_min"], hi=lim["density_max"], unit="kg/m^3")
    _take_number(answer, out, notes, "nu", positive=False, lo=0.0, hi=lim["nu_max"], unit="",
                 why_hi="Poisson's ratio must be < 0.5 (0.5 is incompressible, the Lame lambda diverges)")
    if clamp_to_material_range and out["material"] in kb:
        lo, hi = kb[out["material"]]["E_range"]
        if not lo <= out["E"] <= hi:
            to = min(max(out["E"], lo), hi)
            notes.append(_note("E", out["E"], "clamped", to,
                               f"outside the simulation-effective range of '{out['material']}' [{lo:.3g}, {hi:.3g}] Pa "
                               f"(answers often give handbook values; see materials.yaml header)"))
            out["E"] = to

    if "rigid" not in pins and answer.get("rigid") is not None:
        r = _boolean(answer["rigid"])
        if r is None:
            notes.append(_note("rigid", answer["rigid"], "rejected", out["rigid"],
                               f"not true or false; the flag of '{out['material']}' is kept"))
        else:
            out["rigid"] = r
    _take_plasticity_params(answer, pp, notes, lim)
    out.update({k: pins[k] for k in pins if k in out})
    for k in PLASTICITY_PIN_KEYS:
        if k in pins:
            pp[k] = pins[k]
    out["plasticity_params"] = _complete_plasticity_params(out["plasticity"], pp, out["material"], kb, notes)
    return out, notes


def _take_number(answer, out, notes, key, positive, lo, hi, unit, why_hi=None) -> None:
    if key not in answer or answer[key] is None:
        return
    v = _number(answer[key])
    if v is None:
        notes.append(_note(key, answer[key], "rejected", out[key], "not a finite number"))
        return
    if positive and v <= 0:
        notes.append(_note(key, v, "rejected", out[key], f"{key} must be > 0 {unit}".rstrip()))
        return
    if v < lo:
        notes.append(_note(key, v, "clamped", lo, f"below the lower limit {lo:g} {unit}".rstrip()))
        v = lo
    elif v > hi:
        notes.append(_note(key, v, "clamped", hi, why_hi or f"above the upper limit {hi:g} {unit}".rstrip()))
        v = hi
    out[key] = v


def _take_plasticity_params(answer, pp, notes, lim) -> None:
    bounds = {"yield_stress": (None, None), "friction_angle": (0.0, lim["friction_angle_max"]),
              "cohesion": (0.0, lim["cohesion_max"])}
    for k, (lo, hi) in bounds.items():
        if answer.get(k) is None:
            continue
        v = _number(answer[k])
        if v is None:
            notes.append(_note(k, answer[k], "rejected", pp.get(k), "not a finite number"))
            continue
        if k == "yield_stress" and v <= 0:
            notes.append(_note(k, v, "rejected", pp.get(k), "yield stress must be > 0 Pa"))
            continue
        if lo is not None and v < lo:
            notes.append(_note(k, v, "clamped", lo, f"below {lo:g}"))
            v = lo
        elif hi is not None and v > hi:
            notes.append(_note(k, v, "clamped", hi, f"above {hi:g}"))
            v = hi
        pp[k] = v


def _complete_plasticity_params(model: str, pp: dict, material: str, kb: dict, notes: list[dict]) -> dict:
    """Fill parameters the plasticity model needs but nobody gave, from the KB (recorded)."""
    full = materials_kb.full_plasticity_params(pp)
    for k in materials_kb.REQUIRED_PLASTICITY_PARAMS[model]:
        if full[k] is not None:
            continue
        donors = ([kb[material]] if material in kb else []) + [e for e in kb.values() if e["plasticity"] == model]
        donors += [e for e in kb.values() if k in materials_kb.REQUIRED_PLASTICITY_PARAMS[e["plasticity"]]]
        for e in donors:
            if e["plasticity_params"].get(k) is not None:
                full[k] = e["plasticity_params"][k]
                notes.append(_note(k, None, "filled", full[k],
                                   f"plasticity '{model}' needs {k}; taken from knowledge-base material '{e['name']}'"))
                break
    return full


def _note(key: str, value: Any, action: str, to: Any, reason: str) -> dict:
    return {"key": key, "value": value, "action": action, "to": to, "reason": reason}


def merge_pins(base: dict, pins: dict, kb: dict) -> tuple[dict, list[dict]]:
    """``base`` values (params.json form) with the pins applied.

    A pinned ``material`` replaces the base by that KB preset first; other pins override
    single values.  Plasticity parameters a pinned model needs and nobody gave are filled
    from the knowledge base and recorded in the returned notes.
    """
    notes: list[dict] = []
    if "material" in pins:
        base = materials_kb.material_params(pins["material"], kb)
    out = {k: base[k] for k in ("material", "elasticity", "plasticity", "E", "nu", "density")}
    out["rigid"] = bool(base.get("rigid", False))
    out.update({k: pins[k] for k in ("elasticity", "plasticity", "E", "nu", "density", "rigid") if k in pins})
    pp = dict(base["plasticity_params"])
    pp.update({k: pins[k] for k in PLASTICITY_PIN_KEYS if k in pins})
    out["plasticity_params"] = _complete_plasticity_params(out["plasticity"], pp, out["material"], kb, notes)
    return out, notes
