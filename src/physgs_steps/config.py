"""Configuration: schema composition, validation with defaults, scene files, overrides.

The global config (``config/config.yaml``) has one section per stage family, each with its
own schema in ``workflow/schemas/<section>.schema.yaml``; ``config.schema.yaml`` holds the
top-level keys and points at the section files with ``$ref``. A scene file
(``config/scenes/<name>.yaml``) is validated against ``scene.schema.yaml`` (which refers to
``scene_*.schema.yaml`` fragments). A scene may override any global section under its
``config:`` key, and an ablation (``ablations:`` in the global config) overlays sections too.

Every error names the key path (``fill.sigma``) and the file it came from.

Numbers are read as people write them. YAML 1.1 (PyYAML, and Snakemake's own config
loader) reads ``5e4`` or ``2.0e4`` as strings, and Snakemake's ``--config`` reads every
nested value as a string. So :func:`validate` converts, before checking, every string
where the schema expects a number, an integer, a boolean or null and the string spells one
(``"5e4"`` -> 50000.0, ``"32"`` -> 32, ``"true"`` -> True, ``"null"`` -> None; an integral
float such as ``1.5e2`` where an integer is expected -> 150); any other string stays a
string and fails with the schema's message. Where physgs reads YAML itself (scene files,
the knowledge base) :class:`YamlLoader` resolves floats by the YAML 1.2 rule as well.
"""
from __future__ import annotations

import copy
import functools
import math
import re
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from .errors import ConfigError, InputError
from .runtime import project_root

SECTIONS = ("prepare", "cluster", "fill", "materials", "sim", "bgdo", "render", "metrics")


def schema_dir() -> Path:
    return project_root() / "workflow" / "schemas"


# ---------------------------------------------------------------------------- YAML
class YamlLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """PyYAML's safe loader with YAML 1.2's float rule: ``5e4``, ``1E-3`` and ``.5`` are floats
    (YAML 1.1 requires a dot and a signed exponent, so PyYAML reads ``5e4`` as a string).
    libyaml's parser where PyYAML has it (the rule is applied by the Python resolver either way):
    every Snakemake start reads the config, each scene file and the material knowledge base,
    0.3 s with the pure-Python parser on the 2-core machine."""


YamlLoader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?(?:[eE][-+]?[0-9]+)?
                |[-+]?\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                |[-+]?\.(?:inf|Inf|INF)
                |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def load_yaml(stream):
    """``yaml.load`` with :class:`YamlLoader` (a string or an open file)."""
    return yaml.load(stream, Loader=YamlLoader)


# ---------------------------------------------------------------------------- numbers as strings
_NUMBER = re.compile(r"^[-+]?(?:\d[\d_]*\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")
_TRUE, _FALSE, _NULL = {"true", "True", "TRUE"}, {"false", "False", "FALSE"}, {"null", "Null", "NULL", "~"}


def _types(schema: dict) -> set[str]:
    """The JSON types a schema admits (its ``type`` and those of ``anyOf``/``oneOf`` branches)."""
    t = schema.get("type")
    out = set(t if isinstance(t, list) else [t] if t else [])
    for branch in (schema.get("anyOf") or []) + (schema.get("oneOf") or []):
        if isinstance(branch, dict):
            out |= _types(branch)
    return out


def coerce_scalar(value: Any, schema: dict) -> Any:
    """``value`` converted to the type ``schema`` expects when it is a string spelling that
    type (numbers, booleans, null) or an integral float where only integers are allowed;
    otherwise ``value`` unchanged (the schema check then reports it)."""
    types = _types(schema)
    if isinstance(value, str) and "string" not in types:
        v = value.strip()
        if types & {"number", "integer"} and _NUMBER.match(v):
            num = float(v.replace("_", ""))
            if "integer" in types and num.is_integer() and ("number" not in types or re.fullmatch(r"[-+]?[\d_]+", v)):
                return int(num)
            return num
        if "boolean" in types and v in _TRUE | _FALSE:
            return v in _TRUE
        if "null" in types and v in _NULL:
            return None
    elif isinstance(value, float) and "integer" in types and "number" not in types and value.is_integer():
        return int(value)
    return value


def coerce(instance: Any, schema: dict) -> Any:
    """Apply :func:`coerce_scalar` through ``instance`` (in place for dicts and lists) along
    ``properties``, ``additionalProperties`` and ``items``; returns the (possibly new) value."""
    if not isinstance(schema, dict):
        return instance
    if isinstance(instance, dict):
        props = schema.get("properties") or {}
        extra = schema.get("additionalProperties")
        for key in list(instance):
            sub = props.get(key, extra if isinstance(extra, dict) else None)
            if sub is not None:
                instance[key] = coerce(instance[key], sub)
        return instance
    if isinstance(instance, list):
        items = schema.get("items")
        if isinstance(items, dict):
            for i, v in enumerate(instance):
                instance[i] = coerce(v, items)
        return instance
    return coerce_scalar(instance, schema)


# ---------------------------------------------------------------------------- schemas
# libyaml's loader where PyYAML has it: the 18 schema files took 0.7 s of every Snakemake start
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

@functools.lru_cache(maxsize=None)
def _load_schema_file(name: str) -> dict:
    path = schema_dir() / name
    if not path.exists():
        raise ConfigError(name, f"schema file {path} is missing")
    with open(path) as f:
        return yaml.load(f, Loader=_SAFE_LOADER) or {}


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


def problems(instance: Any, schema: dict, source: str, prefix: str = "") -> list[ConfigError]:
    """Every schema violation of ``instance`` (after :func:`coerce`, defaults filled in place),
    one ConfigError each, ordered by key path."""
    coerce(instance, schema)
    v = _Validator(schema)
    out = []
    for e in sorted(v.iter_errors(instance), key=lambda e: [str(p) for p in e.absolute_path]):
        path = ".".join(str(p) for p in e.absolute_path)
        key = ".".join(p for p in (prefix, path) if p) or "<root>"
        msg = e.message
        if e.validator == "additionalProperties":
            allowed = sorted((e.schema.get("properties") or {}).keys())
            msg += f"; allowed keys: {', '.join(allowed)}"
        elif e.validator == "enum":
            msg = f"{e.instance!r} is not one of the valid choices: {', '.join(map(str, e.validator_value))}"
        elif e.validator == "type" and isinstance(e.instance, str) and "object" in _types(e.schema):
            msg += " (a mapping is expected; on the command line: --config '<section>={key: value}')"
        out.append(ConfigError(key, msg, source))
    for path in _nonfinite(instance):  # YAML's .inf / .nan pass every schema bound
        key = ".".join(p for p in (prefix, path) if p) or "<root>"
        out.append(ConfigError(key, "must be a finite number (got inf or nan)", source))
    return out


def _nonfinite(node: Any, path: str = "") -> list[str]:
    """Key paths of the non-finite floats in ``node``."""
    if isinstance(node, float):
        return [] if math.isfinite(node) else [path]
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in _nonfinite(v, f"{path}.{k}" if path else str(k))]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in _nonfinite(v, f"{path}.{i}" if path else str(i))]
    return []


def validate(instance: Any, schema: dict, source: str, prefix: str = "") -> Any:
    """Validate ``instance`` in place (numbers written as strings converted, defaults filled);
    raise ConfigError on the first error."""
    errors = problems(instance, schema, source, prefix)
    if errors:
        raise errors[0]
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
        raise InputError(path, "file does not exist")
    try:
        with open(path) as f:
            data = load_yaml(f)
    except yaml.YAMLError as e:
        raise InputError(path, f"not valid YAML: {' '.join(str(e).split())}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot be read: {e}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(path, f"top level must be a mapping, got {type(data).__name__}")
    return data


def validate_config(cfg: dict, source: str = "config/config.yaml") -> dict:
    """Validate the global config in place (defaults filled) and return it."""
    return validate(cfg, load_schema("config.schema.yaml"), source)


def load_config(path: str | Path | None = None) -> dict:
    path = Path(path) if path else project_root() / "config" / "config.yaml"
    return validate_config(read_yaml(path), str(path))


def origin_of(key: str, layers: list[tuple[str, dict]]) -> str | None:
    """Which config layer sets ``key`` (a dotted path such as ``sim.n_grid``): the name of the
    last of ``layers`` (``[(name, dict)]`` in the order they are applied) that holds it."""
    found = None
    for name, data in layers:
        node, ok = data, True
        for part in key.split("."):
            if isinstance(node, dict) and part in node:
                node = node[part]
            elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
                node = node[int(part)]
            else:
                ok = False
                break
        if ok:
            found = name
    return found


SCENE_NAME = re.compile(r"[A-Za-z0-9_\-]+")  # the workflow's {scene} wildcard


def scenes_dir(cfg: dict) -> Path:
    """The scene folder (``scenes_dir``; relative paths from the repository root)."""
    d = Path(cfg.get("scenes_dir", "config/scenes"))
    return d if d.is_absolute() else project_root() / d


def list_scenes(cfg: dict) -> tuple[list[str], ConfigError | None]:
    """(sorted scene names, None) from the ``*.yaml`` files of ``scenes_dir``, or ([], the
    problem) when the folder is missing, not a folder or holds no scene file. Files whose
    name is not a valid scene name (letters, digits, ``_``, ``-``) are left out
    (:func:`scene_file_problems` reports them)."""
    d = scenes_dir(cfg)
    given = cfg.get("scenes_dir", "config/scenes")
    if not d.exists():
        return [], ConfigError("scenes_dir", f"folder {given!r} ({d}) does not exist; set scenes_dir to a folder of "
                                             "scene files (<name>.yaml), e.g. config/scenes")
    if not d.is_dir():
        return [], ConfigError("scenes_dir", f"{given!r} ({d}) is a file, not a folder of scene files (<name>.yaml)")
    names = sorted(p.stem for p in d.glob("*.yaml") if SCENE_NAME.fullmatch(p.stem))
    if not names:
        others = sorted(p.name for p in d.iterdir())[:5]
        return [], ConfigError("scenes_dir", f"folder {given!r} ({d}) holds no scene file (<name>.yaml with a name of "
                                             f"letters, digits, _ or -); it holds {others or 'nothing'}")
    return names, None


def scene_path(cfg: dict, scene: str) -> Path:
    return scenes_dir(cfg) / f"{scene}.yaml"


def load_scene(cfg: dict, scene: str) -> dict:
    """Read and validate ``config/scenes/<scene>.yaml`` (defaults filled)."""
    path = scene_path(cfg, scene)
    if not path.exists():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ConfigError("scene", f"unknown scene '{scene}': no scene file {path}; known scenes: "
                                   f"{', '.join(known) or '(none)'}")
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
