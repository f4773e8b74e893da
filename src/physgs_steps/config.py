"""Configuration: schema composition, validation with defaults, scene files, overrides.

The global config (``config/config.yaml``) has one section per stage family, each with its
own schema in ``workflow/schemas/<section>.schema.yaml``; ``config.schema.yaml`` holds the
top-level keys and points at the section files with ``$ref``. A scene file
(``config/scenes/<name>.yaml``) is validated against ``scene.schema.yaml`` (which refers to
``scene_*.schema.yaml`` fragments). A scene may override any global section under its
``config:`` key, and an ablation (``ablations:`` in the global config) overlays sections too.

Every error names the key path (``fill.sigma``) and the file it came from.
"""
from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from .errors import ConfigError
from .runtime import project_root

SECTIONS = ("prepare", "cluster", "fill", "materials", "sim", "bgdo", "render", "metrics")


def schema_dir() -> Path:
    return project_root() / "workflow" / "schemas"


@functools.lru_cache(maxsize=None)
def _load_schema_file(name: str) -> dict:
    path = schema_dir() / name
    if not path.exists():
        raise ConfigError(name, f"schema file {path} is missing")
    with open(path) as f:
        return yaml.safe_load(f) or {}


def _inline_refs(node: Any) -> Any:
    """Replace ``{"$ref": "file.schema.yaml"}`` by the referenced file's content (recursively)."""
    if isinstance(node, dict):
        if "$ref" in node and isinstance(node["$ref"], str) and node["$ref"].endswith(".yaml"):
            target = _inline_refs(copy.deepcopy(_load_schema_file(node["$ref"])))
            rest = {k: _inline_refs(v) for k, v in node.items() if k != "$ref"}
            target.update(rest)
            return target
        return {k: _inline_refs(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_inline_refs(v) for v in node]
    return node


@functools.lru_cache(maxsize=None)
def load_schema(name: str) -> dict:
    """A schema file with all file ``$ref``s inlined."""
    return _inline_refs(copy.deepcopy(_load_schema_file(name)))


def _defaults_validator():
    base = jsonschema.Draft7Validator
    validate_props = base.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for key, sub in properties.items():
                if isinstance(sub, dict) and "default" in sub and key not in instance:
                    instance[key] = copy.deepcopy(sub["default"])
        yield from validate_props(validator, properties, instance, schema)

    return jsonschema.validators.extend(base, {"properties": set_defaults})


_Validator = _defaults_validator()


def validate(instance: Any, schema: dict, source: str, prefix: str = "") -> Any:
    """Validate ``instance`` in place, filling defaults; raise ConfigError on the first error."""
    v = _Validator(schema)
    errors = sorted(v.iter_errors(instance), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        path = ".".join(str(p) for p in e.absolute_path)
        key = ".".join(p for p in (prefix, path) if p) or "<root>"
        msg = e.message
        if e.validator == "additionalProperties":
            allowed = sorted((e.schema.get("properties") or {}).keys())
            msg += f"; allowed keys: {', '.join(allowed)}"
        raise ConfigError(key, msg, source)
    return instance


def section_defaults(section: str) -> dict:
    """The fully defaulted config of one section (what an empty section validates to)."""
    return validate({}, load_schema(f"{section}.schema.yaml"), f"{section}.schema.yaml", section)


def deep_merge(base: dict, over: dict | None) -> dict:
    """A new dict: ``over`` merged into ``base`` (dicts merge recursively, other values replace)."""
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def read_yaml(path: str | Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise ConfigError(str(path), "file does not exist")
    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except yaml.YAMLError as e:
        raise ConfigError(str(path), f"not valid YAML: {e}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(str(path), f"top level must be a mapping, got {type(data).__name__}")
    return data


def validate_config(cfg: dict, source: str = "config/config.yaml") -> dict:
    """Validate the global config in place (defaults filled) and return it."""
    return validate(cfg, load_schema("config.schema.yaml"), source)


def load_config(path: str | Path | None = None) -> dict:
    path = Path(path) if path else project_root() / "config" / "config.yaml"
    return validate_config(read_yaml(path), str(path))


def scene_path(cfg: dict, scene: str) -> Path:
    d = Path(cfg.get("scenes_dir", "config/scenes"))
    if not d.is_absolute():
        d = project_root() / d
    return d / f"{scene}.yaml"


def load_scene(cfg: dict, scene: str) -> dict:
    """Read and validate ``config/scenes/<scene>.yaml`` (defaults filled)."""
    path = scene_path(cfg, scene)
    if not path.exists():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ConfigError("scene", f"no scene file {path}; known scenes: {', '.join(known)}")
    data = read_yaml(path)
    validate(data, load_schema("scene.schema.yaml"), str(path))
    overrides = data.get("config") or {}
    for section, over in overrides.items():
        if section not in SECTIONS:
            raise ConfigError(f"config.{section}", f"unknown section; allowed: {', '.join(SECTIONS)}", str(path))
    data["_name"] = scene
    data["_path"] = str(path)
    return data


def effective_section(cfg: dict, scene_cfg: dict, section: str, ablation: str | None = None) -> dict:
    """Global section, then the scene's override, then the ablation's overlay; validated."""
    merged = deep_merge(cfg.get(section) or {}, (scene_cfg.get("config") or {}).get(section))
    if ablation:
        abl = (cfg.get("ablations") or {}).get(ablation)
        if abl is None:
            raise ConfigError("ablations", f"unknown ablation '{ablation}'; known: {', '.join(sorted(cfg.get('ablations') or {}))}")
        merged = deep_merge(merged, abl.get(section))
    src = scene_cfg.get("_path", "scene") + (f" + ablation {ablation}" if ablation else "")
    return _validated_section(section, merged, src)


_SECTION_MEMO: dict[tuple, dict] = {}


def _validated_section(section: str, merged: dict, src: str) -> dict:
    """validate() of a section, remembered per (section, content): the plans of many variants
    validate the same sections (a benchmark has hundreds of plans). A valid section's result does
    not depend on where it came from; an invalid one raises (naming ``src``) and is not kept."""
    import json

    try:
        key = (section, json.dumps(merged))  # key order kept: Snakemake compares params as written
    except (TypeError, ValueError):  # not JSON-able: validate without the memo
        return validate(merged, load_schema(f"{section}.schema.yaml"), src, section)
    if key not in _SECTION_MEMO:
        if len(_SECTION_MEMO) > 4096:
            _SECTION_MEMO.clear()
        _SECTION_MEMO[key] = validate(merged, load_schema(f"{section}.schema.yaml"), src, section)
    return copy.deepcopy(_SECTION_MEMO[key])


def resolve_path(path: str) -> Path:
    """A path from a config file: absolute, or relative to the repository root."""
    p = Path(path)
    return p if p.is_absolute() else (project_root() / p).resolve()


def resolve_source(scene_cfg: dict) -> tuple[str, Path | None]:
    """('builtin', None) for ``builtin:<name>``, else ('file', absolute path)."""
    src = scene_cfg["source"]
    if src.startswith("builtin:"):
        return "builtin", None
    p = Path(src)
    if not p.is_absolute():
        p = (project_root() / p).resolve()
    return "file", p
