"""The material knowledge base (``data/materials.yaml``) and the canonical model names.

The knowledge base is a data file: one entry per material a user may name, with its
elasticity and plasticity models, a simulation-effective Young's modulus ``E`` and the
range ``E_range`` it may be clamped to, the handbook value ``E_real``, Poisson's ratio,
density, plasticity parameters, whether an object of it is simulated as a rigid body
(``rigid``, default false), the words that name it (``aliases``, ``descriptors``) and a
one-line ``source``.  It is read by the prior matcher, quoted to the VLMs as expert priors
and used by the simulator as the preset table for ``material: <name>`` pins.

Model names follow docs/CONTRACTS.md; :func:`normalize_model` also accepts the usual
spellings ("Fixed Corotated", "StVK", "von Mises", "Drucker-Prager") and the PhysGaussian
alias ``sigma`` (elasticity -> ``stvk_hencky``, plasticity -> ``j_clamp``).
"""
from __future__ import annotations

import copy
import functools
import math
import re
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from .errors import ConfigError, InputError

ELASTICITY_MODELS = ("fixed_corotated", "neo_hookean", "stvk_hencky", "volume", "fluid")
PLASTICITY_MODELS = ("identity", "j_clamp", "von_mises", "drucker_prager", "mohr_coulomb", "fluid")
MODEL_NAMES = {"elasticity": ELASTICITY_MODELS, "plasticity": PLASTICITY_MODELS}
# a granular material's friction angle is its angle of repose, which must stay below 45 degrees
# (mpm/material.py: its return map's surface is set from tan(phi))
FRICTION_ANGLE_MAX = 45.0  # degrees, exclusive

# Spellings accepted for each canonical name (after lower-casing and mapping spaces and
# hyphens to "_"; see _squash).  "sigma" is PhysGaussian's name for the Hencky/J-clamp pair.
_ELASTICITY_ALIASES = {
    "fixed_corotated": ["fixed_corotated", "fixedcorotated", "corotated", "fixed_corotational", "corotational"],
    "neo_hookean": ["neo_hookean", "neohookean", "neo_hooke", "neohooke"],
    "stvk_hencky": ["stvk_hencky", "stvk", "st_vk", "stvkhencky", "hencky", "st_venant_kirchhoff",
                    "saint_venant_kirchhoff", "sigma"],
    "volume": ["volume", "volumetric", "volume_preserving"],
    "fluid": ["fluid", "liquid", "fluid_elasticity"],
}
_PLASTICITY_ALIASES = {
    "identity": ["identity", "none", "no", "elastic", "no_plasticity", "purely_elastic"],
    "j_clamp": ["j_clamp", "jclamp", "sigma", "snow"],
    "von_mises": ["von_mises", "vonmises", "mises", "j2"],
    "drucker_prager": ["drucker_prager", "druckerprager", "drucker", "dp", "sand"],
    "mohr_coulomb": ["mohr_coulomb", "mohrcoulomb", "mohr", "mc", "coulomb", "granular"],
    "fluid": ["fluid", "liquid"],
}
_ALIASES = {"elasticity": _ELASTICITY_ALIASES, "plasticity": _PLASTICITY_ALIASES}

# Plasticity parameters every params.json entry carries (CONTRACTS.md), with the values used
# when a model does not need them or an entry does not set them.
PLASTICITY_PARAM_KEYS = ("yield_stress", "friction_angle", "cohesion", "j_min", "j_max", "fracture_strain",
                         "fracture_softening")
PLASTICITY_PARAM_DEFAULTS: dict[str, float | None] = {
    "yield_stress": None, "friction_angle": None, "cohesion": 0.0, "j_min": 0.05, "j_max": 1.2,
    "fracture_strain": None, "fracture_softening": 0.2,
}
# Parameters a plasticity model cannot run without.
REQUIRED_PLASTICITY_PARAMS = {
    "identity": (), "fluid": (), "von_mises": ("yield_stress",),
    "drucker_prager": ("friction_angle", "cohesion"), "mohr_coulomb": ("friction_angle", "cohesion"),
    "j_clamp": ("j_min", "j_max"),
}

_ENTRY_KEYS = {"elasticity", "plasticity", "E", "E_range", "E_real", "nu", "density",
               "plasticity_params", "aliases", "descriptors", "source", "rigid"}
_REQUIRED_KEYS = _ENTRY_KEYS - {"descriptors", "rigid"}


def _squash(name: str) -> str:
    """Lower-case, drop the words 'elasticity'/'plasticity'/'model', join words with '_'."""
    s = re.sub(r"[\s\-/.]+", "_", str(name).strip().lower())
    s = re.sub(r"_?(elasticity|plasticity|model)$", "", s).strip("_")
    return s


@functools.lru_cache(maxsize=None)
def _alias_lookup(kind: str) -> dict[str, str]:
    return {a: canon for canon, names in _ALIASES[kind].items() for a in names}


def normalize_model(kind: str, name: Any, key: str | None = None) -> str:
    """The canonical model name of ``name``.

    Args:
        kind: "elasticity" or "plasticity".
        name: a canonical name or an accepted spelling ("StVK", "von Mises", "sigma").
        key: config key reported in the error (default: ``kind``).
    Raises:
        ConfigError naming the valid names when ``name`` is unknown.
    """
    if kind not in MODEL_NAMES:
        raise ValueError(f"kind must be 'elasticity' or 'plasticity', got {kind!r}")
    key = key or kind
    if not isinstance(name, str) or not name.strip():
        raise ConfigError(key, f"{kind} model must be a non-empty string, got {name!r}; valid: {', '.join(MODEL_NAMES[kind])}")
    canon = _alias_lookup(kind).get(_squash(name))
    if canon is None:
        raise ConfigError(key, f"unknown {kind} model {name!r}; valid: {', '.join(MODEL_NAMES[kind])} "
                               f"(aliases: sigma, stvk, von mises, drucker-prager, ...)")
    return canon


def normalize_elasticity(name: Any, key: str = "elasticity") -> str:
    return normalize_model("elasticity", name, key)


def normalize_plasticity(name: Any, key: str = "plasticity") -> str:
    return normalize_model("plasticity", name, key)


def is_model_name(kind: str, name: Any) -> bool:
    """True when ``name`` normalises to a canonical ``kind`` model name."""
    try:
        normalize_model(kind, name)
    except ConfigError:
        return False
    return True


def full_plasticity_params(params: dict | None) -> dict:
    """All plasticity parameters: ``params`` over :data:`PLASTICITY_PARAM_DEFAULTS`.

    ``fracture_strain`` (null: the material never tears) and ``fracture_softening`` switch on
    tearing for any plasticity model (mpm/materials.py, class Fracture)."""
    out = dict(PLASTICITY_PARAM_DEFAULTS)
    for k, v in (params or {}).items():
        out[k] = None if v is None else float(v)
    return out


# --------------------------------------------------------------------------- loading
def default_kb_path() -> Path:
    return Path(str(resources.files("physgs_steps") / "data" / "materials.yaml"))


def load_kb(path: str | Path | None = None) -> dict[str, dict]:
    """The knowledge base as ``{material name: entry}`` (a deep copy; validated).

    Each entry has the file's keys with model names canonical, ``plasticity_params``
    expanded to all five keys, ``descriptors`` defaulted to ``[]`` and ``name`` added.

    Raises:
        InputError when the file is missing, not YAML, or an entry is malformed.
    """
    return copy.deepcopy(_load_kb_cached(str(Path(path) if path else default_kb_path())))


@functools.lru_cache(maxsize=4)
def _load_kb_cached(path: str) -> dict[str, dict]:
    p = Path(path)
    if not p.exists():
        raise InputError(p, "material knowledge base does not exist")
    from .config import load_yaml  # YAML 1.2 floats: E: 5e4 is a number

    try:
        raw = load_yaml(p.read_text())
    except yaml.YAMLError as e:
        raise InputError(p, f"not valid YAML: {e}") from None
    if not isinstance(raw, dict) or not raw:
        raise InputError(p, "must be a non-empty mapping of material name -> entry")
    kb = {str(name): _check_entry(p, str(name), entry) for name, entry in raw.items()}
    _check_words_unique(p, kb)
    return kb


def _check_entry(path: Path, name: str, e: Any) -> dict:
    where = f"entry '{name}'"
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name):
        raise InputError(path, f"{where}: material names are lower-case identifiers")
    if not isinstance(e, dict):
        raise InputError(path, f"{where}: must be a mapping")
    missing, unknown = _REQUIRED_KEYS - set(e), set(e) - _ENTRY_KEYS
    if missing or unknown:
        raise InputError(path, f"{where}: missing keys {sorted(missing)}, unknown keys {sorted(unknown)}")
    out = dict(e)
    out["name"] = name
    try:
        out["elasticity"] = normalize_elasticity(e["elasticity"], f"{name}.elasticity")
        out["plasticity"] = normalize_plasticity(e["plasticity"], f"{name}.plasticity")
    except ConfigError as err:
        raise InputError(path, str(err)) from None
    for k in ("E", "nu", "density"):
        out[k] = _positive_number(path, f"{where}: {k}", e[k], allow_zero=(k == "nu"))
    if out["nu"] >= 0.5:
        raise InputError(path, f"{where}: nu must lie in [0, 0.5), got {out['nu']}")
    rng = e["E_range"]
    if not (isinstance(rng, list) and len(rng) == 2):
        raise InputError(path, f"{where}: E_range must be [lo, hi]")
    lo, hi = (_positive_number(path, f"{where}: E_range", v) for v in rng)
    if not lo <= out["E"] <= hi:
        raise InputError(path, f"{where}: E = {out['E']} lies outside E_range [{lo}, {hi}]")
    out["E_range"] = [lo, hi]
    if e["E_real"] is not None:
        out["E_real"] = _positive_number(path, f"{where}: E_real", e["E_real"])
    out["plasticity_params"] = _check_plasticity_params(path, where, out["plasticity"], e["plasticity_params"])
    if not isinstance(e.get("rigid", False), bool):
        raise InputError(path, f"{where}: rigid must be true or false, got {e.get('rigid')!r}")
    out["rigid"] = bool(e.get("rigid", False))
    for k in ("aliases", "descriptors"):
        words = e.get(k) or []
        if not isinstance(words, list) or not all(isinstance(w, str) and w.strip() for w in words):
            raise InputError(path, f"{where}: {k} must be a list of non-empty strings")
        out[k] = [w.strip().lower() for w in words]
    if not out["aliases"]:
        raise InputError(path, f"{where}: needs at least one alias")
    if not isinstance(e["source"], str) or not e["source"].strip():
        raise InputError(path, f"{where}: source must be a one-line reference or rationale")
    return out


def _check_plasticity_params(path: Path, where: str, model: str, pp: Any) -> dict:
    if not isinstance(pp, dict):
        raise InputError(path, f"{where}: plasticity_params must be a mapping")
    bad = set(pp) - set(PLASTICITY_PARAM_KEYS)
    if bad:
        raise InputError(path, f"{where}: unknown plasticity_params {sorted(bad)}; valid: {', '.join(PLASTICITY_PARAM_KEYS)}")
    for k, v in pp.items():
        _positive_number(path, f"{where}: plasticity_params.{k}", v, allow_zero=k == "cohesion")
    full = full_plasticity_params(pp)
    need = [k for k in REQUIRED_PLASTICITY_PARAMS[model] if full[k] is None]
    if need:
        raise InputError(path, f"{where}: plasticity '{model}' needs plasticity_params {need}")
    return full


def _positive_number(path: Path, what: str, v: Any, allow_zero: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(path, f"{what} must be a finite number, got {v!r}")
    if v < 0 or (v == 0 and not allow_zero):
        raise InputError(path, f"{what} must be {'>= 0' if allow_zero else '> 0'}, got {v}")
    return float(v)


def _check_words_unique(path: Path, kb: dict[str, dict]) -> None:
    """Aliases and descriptors must each name one material, so matching is unambiguous."""
    for kind in ("aliases", "descriptors"):
        seen: dict[str, str] = {}
        for name, e in kb.items():
            for w in e[kind]:
                if w in seen and seen[w] != name:
                    raise InputError(path, f"{kind[:-1]} '{w}' names both '{seen[w]}' and '{name}'")
                seen[w] = name


# --------------------------------------------------------------------------- lookup
def material_names(kb: dict | None = None) -> list[str]:
    return list((kb or _load_kb_cached(str(default_kb_path()))).keys())


def alias_table(kb: dict | None = None) -> dict[str, str]:
    """``{word or name: material name}`` for every material name and alias."""
    kb = kb or _load_kb_cached(str(default_kb_path()))
    table = {}
    for name, e in kb.items():
        table[name] = name
        for a in e["aliases"]:
            table.setdefault(a, name)
    return table


def resolve_material_name(name_or_alias: Any, kb: dict | None = None, key: str = "material") -> str:
    """The KB name for a material name or alias (case-insensitive); ConfigError if unknown."""
    kb = kb or _load_kb_cached(str(default_kb_path()))
    if not isinstance(name_or_alias, str) or not name_or_alias.strip():
        raise ConfigError(key, f"material must be a non-empty string, got {name_or_alias!r}; valid: {', '.join(kb)}")
    word = re.sub(r"[\s_]+", " ", name_or_alias.strip().lower())
    table = alias_table(kb)
    for cand in (word, word.replace(" ", "_")):
        if cand in table:
            return table[cand]
    raise ConfigError(key, f"unknown material {name_or_alias!r}; valid: {', '.join(kb)}")


def get_material(name_or_alias: Any, kb: dict | None = None, key: str = "material") -> dict:
    """A copy of the KB entry for a material name or alias.

    Raises:
        ConfigError naming ``key`` and listing the valid material names when unknown.
    """
    kb = kb or _load_kb_cached(str(default_kb_path()))
    return copy.deepcopy(kb[resolve_material_name(name_or_alias, kb, key)])


def material_params(name_or_alias: Any, kb: dict | None = None, key: str = "material") -> dict:
    """The simulation parameters of a material in params.json form (no label/name/provenance)."""
    e = get_material(name_or_alias, kb, key)
    return {
        "material": e["name"], "elasticity": e["elasticity"], "plasticity": e["plasticity"],
        "E": e["E"], "nu": e["nu"], "density": e["density"],
        "plasticity_params": dict(e["plasticity_params"]), "rigid": e["rigid"],
    }


def kb_table_text(kb: dict | None = None) -> str:
    """A compact one-line-per-material table of the KB (quoted to VLMs as expert priors)."""
    kb = kb or _load_kb_cached(str(default_kb_path()))
    lines = []
    for name, e in kb.items():
        pp = {k: v for k, v in e["plasticity_params"].items()
              if k in REQUIRED_PLASTICITY_PARAMS[e["plasticity"]]}
        pp_txt = "".join(f", {k}={v:g}" for k, v in pp.items())
        lines.append(
            f"- {name}: elasticity={e['elasticity']}, plasticity={e['plasticity']}, "
            f"E={e['E']:.3g} Pa (range {e['E_range'][0]:.3g}-{e['E_range'][1]:.3g}), nu={e['nu']:g}, "
            f"density={e['density']:g} kg/m^3{pp_txt}, rigid={'true' if e['rigid'] else 'false'}"
        )
    return "\n".join(lines)
