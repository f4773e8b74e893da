"""Resource requests of the workflow's jobs (``mem_mb``, ``runtime``): what the configured
backend and the scene's size need, from the config section ``resources``.

    mem_mb  = base + per_million_gaussians[rule] x N / 1e6      (rounded up to 100 MB)
    base    = resources.stages.<rule>.mem_mb, else for vlm_params
              resources.backends.<materials.backend>.mem_mb, else resources.default.mem_mb
    runtime = resources.stages.<rule>.runtime, else for vlm_params
              resources.backends.<backend>.runtime, else resources.default.runtime

N is the scene's gaussian count, known before anything runs: ``builtin.n_gaussians`` of a
built-in scene, or the vertex count in the header of a ``.ply`` (the size of a ``.splat``).
The defaults (``workflow/schemas/config.schema.yaml``) are measured peaks with head room:
on the CPU at 20k and 100k gaussians (grid 32) the largest peaks were bgdo_update 394 / 714
MB, render 391 / 476 MB, forward_sim 168 / 222 MB; the ``prior`` backend peaks at 40 MB, a
Qwen3-VL 8B model needs about 20 GB of host memory to load.
"""
from __future__ import annotations

import functools
import math

from . import config as C


@functools.lru_cache(maxsize=256)
def _count_file(path: str) -> int | None:
    from .scene_io import probe

    try:
        return int(probe(path)["n"])
    except Exception:  # a bad file is the prepare stage's to report, with its message
        return None


def scene_gaussians(scene_cfg: dict) -> int | None:
    """The gaussian count of a scene (its validated scene dict), or None when unknown."""
    src = scene_cfg.get("source") or ""
    if src.startswith("builtin:"):
        from .builtin_names import DEFAULT_N_GAUSSIANS  # light: no geometry libraries

        n = (scene_cfg.get("builtin") or {}).get("n_gaussians")
        return int(n) if n is not None else DEFAULT_N_GAUSSIANS.get(src[len("builtin:"):])
    kind, path = C.resolve_source(scene_cfg)
    return _count_file(str(path)) if path is not None else None


@functools.lru_cache(maxsize=1)
def _schema_defaults() -> dict:
    return C.load_schema("config.schema.yaml")["properties"]["resources"]["properties"]


def _merged(res_cfg: dict, key: str, name: str | None) -> dict | float:
    """Entry ``name`` of ``resources.<key>``: the configured entry over the schema default's
    (a config that sets one backend's runtime keeps that backend's default memory)."""
    default = (_schema_defaults()[key].get("default") or {}).get(name)
    given = (res_cfg.get(key) or {}).get(name)
    if key == "per_million_gaussians":
        return float(given if given is not None else (default or 0))
    return {**(default or {}), **(given or {})}


def request(res_cfg: dict, rule: str, n_gaussians: int | None = None, backend: str | None = None) -> dict:
    """{"mem_mb": int, "runtime": int (minutes)} of one job of ``rule`` (see the module docs).

    res_cfg: the validated ``resources`` section; n_gaussians: the scene's size (None: 0);
    backend: ``materials.backend`` of the job's scene (vlm_params only). Entries of ``stages``,
    ``backends`` and ``per_million_gaussians`` are merged key by key over the schema defaults."""
    stage = _merged(res_cfg, "stages", rule)
    by_backend = _merged(res_cfg, "backends", backend) if rule == "vlm_params" else {}
    default = res_cfg["default"]
    base = stage.get("mem_mb", by_backend.get("mem_mb", default["mem_mb"]))
    per_m = float(_merged(res_cfg, "per_million_gaussians", rule))
    mem = base + per_m * (n_gaussians or 0) / 1e6
    runtime = stage.get("runtime", by_backend.get("runtime", default["runtime"]))
    return {"mem_mb": int(math.ceil(mem / 100.0) * 100), "runtime": int(runtime)}
