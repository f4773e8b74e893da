"""``physgs check``: every problem of the global config and of every scene file, at once.

The workflow stops at the first problem of the target it builds (one line, naming the file
and the key); this lists them all without running anything, so that a folder of twenty
captures can be fixed in one pass. Checked, without reading any gaussian data:

* the global config (``config/config.yaml`` or ``--config``): every schema violation, every
  ablation's overlay, ``scenes_dir``, the material knowledge base;
* each ``<scenes_dir>/*.yaml``: the file name (it is the scene name in ``results/<name>/``),
  YAML syntax, every schema violation, the ``config:`` overrides merged with the global
  config and with every ablation, the source (``builtin:<name>`` exists; a ``.ply`` /
  ``.splat`` exists and its header and size are consistent), the transform, the dynamics,
  the instances' pinned materials and values, the camera's ``cameras.json``; finally the
  artifact plan of every target of the scene.

Each problem is one line ``<file>: <problem>``; the exit status is 1 when there is any.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

from . import config as C
from .errors import ConfigError, InputError, PhysGSError


@dataclass
class Problem:
    file: str
    message: str

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


def _msg(e: PhysGSError) -> str:
    """The error without the scene/config file it names (each line starts with that file)."""
    if isinstance(e, ConfigError):
        return f"{e.key}: {e.problem}"
    return str(e)


def check_config(path: str | Path | None = None) -> tuple[dict | None, list[Problem]]:
    """(the validated global config or None, its problems)."""
    path = Path(path) if path else C.project_root() / "config" / "config.yaml"
    name = str(path)
    try:
        raw = C.read_yaml(path)
    except PhysGSError as e:
        return None, [Problem(name, e.problem if isinstance(e, InputError) else str(e))]
    cfg = copy.deepcopy(raw)
    out = [Problem(name, _msg(e)) for e in C.problems(cfg, C.load_schema("config.schema.yaml"), name)]
    if out:
        return None, out
    empty_scene = {"_path": name}
    for abl in sorted(cfg.get("ablations") or {}):
        for section in C.SECTIONS:
            try:
                C.effective_section(cfg, empty_scene, section, abl)
            except PhysGSError as e:
                out.append(Problem(name, f"ablation '{abl}': {_msg(e)}"))
    try:
        from . import materials_kb

        materials_kb.load_kb(cfg["materials"].get("kb_path") or None)
    except PhysGSError as e:
        out.append(Problem(name, f"materials.kb_path: {e}"))
    _, why = C.list_scenes(cfg)
    if why is not None:
        out.append(Problem(name, _msg(why)))
    return cfg, out


def check_scene_file(cfg: dict, path: Path) -> list[Problem]:
    """Every problem of one scene file (``cfg``: the validated global config)."""
    name = str(path)
    if not C.SCENE_NAME.fullmatch(path.stem):
        return [Problem(name, f"'{path.stem}' is not a valid scene name (letters, digits, _ and - only; it names "
                              "results/<scene>/): rename the file")]
    try:
        data = C.read_yaml(path)
    except PhysGSError as e:
        return [Problem(name, e.problem if isinstance(e, InputError) else str(e))]
    out = [Problem(name, _msg(e)) for e in C.problems(data, C.load_schema("scene.schema.yaml"), name)]
    if out:  # the checks below need a valid file
        return out
    data["_name"], data["_path"] = path.stem, name
    for section in data.get("config") or {}:
        if section not in C.SECTIONS:
            out.append(Problem(name, f"config.{section}: unknown section; allowed: {', '.join(C.SECTIONS)}"))
    seen = set()
    for abl in [None, *sorted(cfg.get("ablations") or {})]:
        for section in C.SECTIONS:
            try:
                C.effective_section(cfg, data, section, abl)
            except PhysGSError as e:
                if _msg(e) not in seen:  # an ablation's own problem, not the scene's again
                    seen.add(_msg(e))
                    out.append(Problem(name, f"config.{_msg(e)}" + (f" (with ablation '{abl}')" if abl else "")))
    out += [Problem(name, m) for m in _source_problems(data)]
    out += [Problem(name, m) for m in _scene_key_problems(cfg, data)]
    if not out:
        from . import plan as P

        for abl in [None, *sorted(cfg.get("ablations") or {})]:
            try:
                P.make_plan(cfg, path.stem, abl)
            except PhysGSError as e:
                out.append(Problem(name, _msg(e) + (f" (ablation '{abl}')" if abl else "")))
                break
    return out


def _source_problems(data: dict) -> list[str]:
    src = data["source"]
    if src.startswith("builtin:"):
        from .builtin_names import BUILTIN_SCENES  # light: no geometry libraries

        if src[len("builtin:"):] not in BUILTIN_SCENES:
            return [f"source: unknown built-in scene '{src}'; valid: "
                    + ", ".join(f"builtin:{s}" for s in BUILTIN_SCENES)]
        return []
    from .scene_io import probe

    _, p = C.resolve_source(data)
    try:
        probe(p)
    except InputError as e:
        return [f"source: {e}"]
    return []


def _scene_key_problems(cfg: dict, data: dict) -> list[str]:
    out = []
    src = data["_path"]
    try:
        from .prepare import transform_config

        transform_config(data)
    except PhysGSError as e:
        out.append(_msg(e))
    try:
        from .mpm.dynamics import Dynamics

        Dynamics.from_config(data.get("dynamics"), src)
    except PhysGSError as e:
        out.append(_msg(e))
    try:
        from . import materials_kb
        from .params.validate import check_pins, check_velocity

        kb = materials_kb.load_kb(cfg["materials"].get("kb_path") or None)
        for i, entry in enumerate(data.get("instances") or []):
            for fn in (lambda: check_pins(entry, i, kb, src), lambda: check_velocity(entry, i)):
                try:
                    fn()
                except PhysGSError as e:
                    out.append(_msg(e))
    except PhysGSError as e:
        out.append(f"materials knowledge base: {e}")
    cam = data.get("camera") or {}
    if cam.get("mode") == "cameras_json":
        if not cam.get("cameras_json"):
            out.append("camera.cameras_json: mode is cameras_json but no cameras.json path is given")
        else:
            p = C.resolve_path(cam["cameras_json"])
            if not p.is_file():
                out.append(f"camera.cameras_json: {p} does not exist")
    return out


def check_all(config_path: str | Path | None = None) -> tuple[list[Problem], int]:
    """(every problem, number of scene files checked)."""
    cfg, problems = check_config(config_path)
    if cfg is None:
        return problems, 0
    d = C.scenes_dir(cfg)
    files = sorted(d.glob("*.yaml")) if d.is_dir() else []
    for f in files:
        problems += check_scene_file(cfg, f)
    return problems, len(files)
