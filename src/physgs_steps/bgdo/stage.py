"""Stage ``bgdo_update``: reads forward.h5 key frames and params.json, computes the signals
and writes params.json with the updated E.  Overview: :mod:`physgs_steps.bgdo`."""
from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import ConfigError
from .torch_step import GridSpec, instance_table, log_E_from_instances
from .update import (assemble_frames, bgdo_signals, bgdo_update, first_contact, forward_frames_needed, mark_unloaded,
                     reference_scales, solver_ceiling, static_stress, unstable_run_info)

# ----------------------------------------------------------------------------- key frames & files
def key_frame_indices(key_frames, n_frames: int) -> list[int]:
    """Frame indices of the key frames: ``round(f * (n_frames - 1))`` for every fraction f in
    ``key_frames`` (bgdo.key_frames, default [0, 0.5, 1] = initial, middle and last frame),
    sorted and without duplicates."""
    if n_frames < 1:
        raise ConfigError("sim.n_frames", f"must be >= 1, got {n_frames}")
    out = sorted({int(round(float(f) * (n_frames - 1))) for f in key_frames})
    return out


def read_keyframes_meta(path: str) -> dict:
    """Particles and key-frame index of a forward.h5 (CONTRACTS.md) without loading the states.

    Returns {"label" [P] int64, "vol" [P] f32, "filled" [P] bool or None (files without it),
    "frames": [(group name, frame, time, dt,
    substitute_for)] sorted by frame, "params": dict or None, "sim_config": dict or None,
    "stats": dict or None}. ``substitute_for`` lists the key frames an unstable forward run
    could not reach and for which this (last stable) frame stands in.
    """
    import json

    import h5py

    from ..errors import InputError

    try:
        f = h5py.File(path, "r")
    except (OSError, FileNotFoundError) as e:
        raise InputError(path, f"cannot open as HDF5: {e}") from None
    with f:
        for key in ("particles/label", "particles/vol"):
            if key not in f:
                raise InputError(path, f"missing dataset '{key}' (forward.h5 format, docs/CONTRACTS.md)")
        label = np.asarray(f["particles/label"][...]).astype(np.int64)
        vol = np.asarray(f["particles/vol"][...], dtype=np.float32)
        P = label.shape[0]
        if vol.shape != (P,):
            raise InputError(path, f"particles/vol has shape {vol.shape}, expected ({P},)")
        if not np.all(np.isfinite(vol)) or np.any(vol <= 0):
            raise InputError(path, "particles/vol must be finite and > 0")
        filled = None
        if "particles/filled" in f:
            filled = np.asarray(f["particles/filled"][...]).astype(bool)
            if filled.shape != (P,):
                raise InputError(path, f"particles/filled has shape {filled.shape}, expected ({P},)")
        if "keyframes" not in f or len(f["keyframes"]) == 0:
            raise InputError(path, "has no key frames (group 'keyframes' is missing or empty)")
        frames = []
        for name, g in f["keyframes"].items():
            for key in ("x", "v", "C", "F"):
                if key not in g:
                    raise InputError(path, f"key frame '{name}' lacks dataset '{key}'")
            shapes = {"x": (P, 3), "v": (P, 3), "C": (P, 3, 3), "F": (P, 3, 3)}
            for key, shp in shapes.items():
                if g[key].shape != shp:
                    raise InputError(path, f"keyframes/{name}/{key} has shape {g[key].shape}, expected {shp}")
            for a in ("frame", "time", "dt"):
                if a not in g.attrs:
                    raise InputError(path, f"key frame '{name}' lacks attribute '{a}'")
            dt = float(g.attrs["dt"])
            if not (math.isfinite(dt) and dt > 0):
                raise InputError(path, f"key frame '{name}' has dt = {dt}; expected a positive number of seconds")
            sub = g.attrs.get("substitute_for")
            sub = [] if sub is None else [int(v) for v in np.atleast_1d(sub)]
            frames.append((name, int(g.attrs["frame"]), float(g.attrs["time"]), dt, sub))
        frames.sort(key=lambda t: t[1])
        meta = {"label": label, "vol": vol, "filled": filled, "frames": frames}
        for a in ("params", "sim_config", "stats"):
            raw = f.attrs.get(a)
            try:
                meta[a] = json.loads(raw) if raw is not None else None
            except (TypeError, ValueError):
                raise InputError(path, f"root attribute '{a}' is not valid JSON") from None
    return meta


def iter_keyframes(path: str, frames: list):
    """Yield key-frame dicts {"frame", "time", "dt", "x", "v", "C", "F"} (and "ep" when stored:
    tearing materials) one at a time."""
    import h5py

    for name, frame, time_, dt, _ in frames:
        with h5py.File(path, "r") as f:
            g = f["keyframes"][name]
            yield {"frame": frame, "time": time_, "dt": dt, **{k: g[k][...] for k in ("x", "v", "C", "F", "ep") if k in g}}


def resolve_device(cfg: dict) -> str:
    """'cpu' or 'cuda' from bgdo.device (null = the top-level ``device``; auto = CUDA if present)."""
    want = cfg.get("bgdo", {}).get("device") or cfg.get("device") or "auto"
    if want == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if want == "cuda" and not torch.cuda.is_available():
        raise ConfigError("bgdo.device", "is 'cuda' but torch finds no CUDA device; use 'cpu' or 'auto'")
    if want not in ("cpu", "cuda"):
        raise ConfigError("bgdo.device", f"must be auto, cpu or cuda, got {want!r}")
    return want


def grid_from_config(cfg: dict, sim_config: dict | None = None) -> GridSpec:
    """GridSpec from the forward simulation's recorded config (``sim_config`` of forward.h5:
    {"sim": {...}, "dynamics": {...}}, preferred) or cfg["sim"] and cfg["scene"]["dynamics"]:
    n_grid, domain size, gravity and domain walls (dynamics schema defaults filled)."""
    import copy

    from .. import config as C

    sim = dict(cfg.get("sim") or {})
    rec = dict(sim_config or {})
    rec_sim = rec.get("sim") if isinstance(rec.get("sim"), dict) else rec  # forward.h5 nests the sim section
    n_grid = rec_sim.get("n_grid", sim.get("n_grid"))
    L = rec_sim.get("domain_size", sim.get("domain_size", 1.0))
    if not isinstance(n_grid, int) or n_grid < 8:
        raise ConfigError("sim.n_grid", f"must be an integer >= 8, got {n_grid!r}")
    if not isinstance(L, (int, float)) or not L > 0:
        raise ConfigError("sim.domain_size", f"must be a positive number of metres, got {L!r}")
    dyn = rec.get("dynamics") if isinstance(rec.get("dynamics"), dict) else (cfg.get("scene") or {}).get("dynamics")
    dyn = C.validate(copy.deepcopy(dyn or {}), C.load_schema("scene_dynamics.schema.yaml"), "scene", "dynamics")
    return GridSpec(n_grid=int(n_grid), domain_size=float(L), gravity=tuple(float(g) for g in dyn["gravity"]),
                    boundary=dyn["boundary"], wall_margin=float(dyn["wall_margin"]))


# ----------------------------------------------------------------------------- the stage
def _read_params(path: str) -> dict:
    from ..errors import InputError
    from ..runtime import read_json_input

    params = read_json_input(path, "params file")
    if not isinstance(params, dict) or not isinstance(params.get("instances"), list) or not params["instances"]:
        raise InputError(path, "expected an object with a non-empty 'instances' list (params.json, docs/CONTRACTS.md)")
    return params


def _check_same_E(params: dict, used: dict | None, path_kf: str, path_params: str) -> None:
    """The key frames must come from a simulation with exactly these moduli."""
    from ..errors import InputError

    if not used or not isinstance(used.get("instances"), list):
        return
    mine = {int(i["label"]): float(i["E"]) for i in params["instances"]}
    theirs = {int(i["label"]): float(i["E"]) for i in used["instances"] if "label" in i and "E" in i}
    for k, E in mine.items():
        if k in theirs and not math.isclose(theirs[k], E, rel_tol=1e-6):
            raise InputError(path_kf, f"key frames were simulated with E = {theirs[k]:.6g} Pa for instance {k}, "
                                      f"but {path_params} has E = {E:.6g} Pa (stale forward simulation?)")


def run(inputs: dict, outputs: dict, cfg: dict, log) -> dict:
    """Stage bgdo_update: params_i + forward.h5 (key frames) -> params_{i+1}.

    inputs: {"keyframes": forward.h5, "params": params.json}; outputs: {"params": params.json}.
    cfg: {"bgdo": {...}, "sim": {...}, "scene": {...}, "device": ...}. Writes params.json with E
    updated, each instance's provenance set to bgdo, a record under "bgdo" and one appended to
    "history"; returns a summary (E before/after per instance, seconds per part, peak memory).
    """
    import copy
    import time

    from .. import runtime

    t0 = time.perf_counter()
    bcfg = cfg["bgdo"]
    _check_config(bcfg)
    device = resolve_device(cfg)
    cuda_start = runtime.cuda_start_seconds(torch) if device == "cuda" else None  # apart from the work below
    dtype = torch.float64 if bcfg.get("dtype") == "float64" else torch.float32
    params = _read_params(inputs["params"])
    meta = read_keyframes_meta(inputs["keyframes"])
    rec_sim0 = (meta.get("sim_config") or {}).get("sim") or cfg.get("sim") or {}
    # the gaussians' faces at their centres, the filled particles' half their side in front (wall
    # contact, as the forward run's solver: simulate.build_solver)
    full = instance_table(params["instances"], meta["label"], meta["vol"], dtype=dtype, device=device,
                          source=inputs["params"], rigid_bodies=bool(rec_sim0.get("rigid_bodies", True)),
                          filled=meta["filled"])
    # fixed instances are static geometry: not in the MPM, so not in the pseudo step either
    fixed_k = [k for k in range(full.n_instances) if full.fixed and full.fixed[k]]
    keep = np.flatnonzero(~np.isin(meta["label"], fixed_k))
    table = full.select(torch.as_tensor(keep, device=device)) if fixed_k else full
    rigid = [full.is_rigid(k) for k in range(full.n_instances)]
    if any(rigid):
        log.info("rigid instances %s (%s): skipped by BGDO, their E does not enter the simulation",
                 [k for k in range(len(rigid)) if rigid[k]], ", ".join(
                     f"{full.names[k]}: {'fixed' if fixed_k and k in fixed_k else 'free'}" for k in range(len(rigid))
                     if rigid[k]))
    _check_same_E(params, meta.get("params"), inputs["keyframes"], inputs["params"])
    grid = grid_from_config(cfg, meta.get("sim_config"))
    scales = reference_scales(params["instances"], bcfg)
    log_E = log_E_from_instances(params["instances"], device=device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    log.info("BGDO on %s: %d particles, %d instances, %d key frames %s, variant %s, scaling %s",
             device, table.label.shape[0], table.n_instances, len(meta["frames"]),
             [fr[1] for fr in meta["frames"]], bcfg["variant"], bcfg["scaling"])
    t1 = time.perf_counter()
    first = {}  # x of the first key frame (the rest state), kept for the static load

    def keep_first(frames_):
        for kf in frames_:
            first.setdefault("x", kf["x"])
            first.setdefault("v", kf["v"])
            yield {**kf, **{q: kf[q][keep] for q in ("x", "v", "C", "F")}} if fixed_k else kf

    frames = bgdo_signals(keep_first(iter_keyframes(inputs["keyframes"], meta["frames"])), log_E, table, grid, scales,
                          device=device, dtype=dtype, log=log, measure=bcfg["deformation_measure"])
    info = unstable_run_info(meta, params["instances"], grid, float(bcfg["cfl_limit"]), rigid)
    sstress = static_stress(first["x"], meta["label"], params["instances"], grid)
    E_now = np.exp(log_E.detach().cpu().double().numpy())
    info["static_delta"] = [float(s_ / e_) for s_, e_ in zip(sstress, E_now)]
    rec_sim = (meta.get("sim_config") or {}).get("sim") or cfg.get("sim") or {}
    ceiling = solver_ceiling(params["instances"], rec_sim, grid)
    log.info("static stress rho|g|H per instance %s Pa (static strain %s); solver ceiling E_cap %s Pa",
             [f"{v:.3g}" for v in sstress], [f"{v:.3g}" for v in info["static_delta"]], [f"{v:.3g}" for v in ceiling])
    if not info["stable"]:
        log.warning("the forward run was unstable (key frames %s not reached; CFL number per instance %s, "
                    "bgdo.cfl_limit %g): instance fates %s (exploded: too stiff for the substep cap; broken: "
                    "collapsed under its load; missing key frames count as such states)", info["missing"],
                    info["cfl"], float(bcfg["cfl_limit"]), info["fate"])
    frames = assemble_frames(frames, meta, info)
    silent = [k for k in mark_unloaded(frames, sstress, scales, float(bcfg.get("min_load", 0.01))) if not rigid[k]]
    contact = _warn_no_signal(silent, first, meta, params["instances"], grid, cfg, log)
    t2 = time.perf_counter()
    new_log_E, records = bgdo_update(log_E, frames, scales, bcfg,
                                     limits={"ceiling": ceiling, "static_stress": sstress, "fate": info["fate"],
                                             "rigid": rigid})
    iteration = 1 + sum(1 for h in params.get("history") or [] if isinstance(h, dict) and h.get("stage") == "bgdo_update")
    out = copy.deepcopy(params)
    by_label = {int(i["label"]): i for i in out["instances"]}
    for rec in records:
        inst = by_label[rec["label"]]
        rec["E_before"] = float(inst["E"])  # exactly as read, not exp(log E)
        if rec["G"] is None:
            rec["E_after"] = rec["E_before"]
        rec["name"] = inst.get("name")
        rec["material"] = inst.get("material")
        inst["E"] = rec["E_after"]
        inst["provenance"] = {"source": "bgdo", "iteration": iteration, "E_before": rec["E_before"],
                              "E_after": rec["E_after"], "G": rec["G"], "previous": inst.get("provenance")}
        log.info("instance %d (%s, %s): E %.4g -> %.4g Pa (G = %s, eta = %.3f, E_hat = %.4g, delta_target %.3g, "
                 "rule: %s)%s%s", rec["label"], rec["name"], rec["material"], rec["E_before"], rec["E_after"],
                 "n/a" if rec["G"] is None else f"{rec['G']:.4f}", rec["eta"], rec["E_hat"], rec["delta_target"],
                 rec["rule"], " [clipped to max_step]" if rec["clipped"] else "",
                 " [held at the solver ceiling]" if rec["capped_by_ceiling"] else "")
    for rec in records:
        if rec.get("in_band_after") is False and rec.get("in_band_before") is not False:
            lo, hi = rec["band"]
            why = (f"the forward run exploded and the solver integrates at most E_cap = {rec['ceiling']:.3g} Pa at "
                   f"this resolution (sim.max_substeps = {rec_sim.get('max_substeps')}, grid spacing dx = "
                   f"{grid.domain_size / grid.n_grid:.3g} m): raise sim.max_substeps or lower sim.n_grid to keep "
                   "the material's stiffness" if str(rec["rule"]).startswith("exploded") or rec["capped_by_ceiling"]
                   else "check the scene's loads and the material choice")
            log.warning("instance %d (%s): E %.4g -> %.4g Pa leaves %s's range [%.3g, %.3g] Pa: %s", rec["label"],
                        rec["name"], rec["E_before"], rec["E_after"], rec["material"], lo, hi, why)
    cuda_peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
    seconds = {"read": round(t1 - t0, 4), "signals": round(t2 - t1, 4), "total": round(time.perf_counter() - t0, 4)}
    from .torch_step import svd3_method

    timings = {"cuda_start": cuda_start, "read": seconds["read"], "signals": seconds["signals"],
               "update": round(time.perf_counter() - t2, 4),
               "svd": svd3_method(torch.device(device))}
    log.info("fixed costs: first CUDA call %s s, reading %.2f s (includes the CUDA start), signals %.2f s "
             "(pseudo steps and gradients; 3x3 SVD by %s)", cuda_start, timings["read"], timings["signals"],
             timings["svd"])
    record = {
        "iteration": iteration, "variant": bcfg["variant"], "scaling": bcfg["scaling"],
        "delta_target": bcfg["delta_target"], "deformation_measure": bcfg["deformation_measure"],
        "deformation_signal": bcfg.get("deformation_signal"), "failure_rule": bcfg.get("failure_rule"),
        "ceiling": bcfg.get("ceiling"), "eta_rule": bcfg["eta_rule"], "max_step": bcfg.get("max_step"),
        "static_stress": [float(v) for v in sstress], "static_delta": info["static_delta"],
        "solver_ceiling": [float(v) for v in ceiling], "fate_reason": {str(k): v for k, v in (info.get("fate_reason") or {}).items()},
        "device": device, "dtype": str(dtype).replace("torch.", ""),
        "forward_stable": info["stable"], "missing_key_frames": info["missing"], "forward_cfl": info["cfl"],
        "instance_fates": info["fate"], "delta_broken": info["delta_broken"],
        "rigid_skipped": [records[k]["name"] for k in range(len(rigid)) if rigid[k]],
        "min_load": bcfg.get("min_load", 0.01), "no_signal": {str(k): v for k, v in contact.items()},
        "key_frames": [fr[1] for fr in meta["frames"]], "grid": {"n_grid": grid.n_grid, "domain_size": grid.domain_size,
                                                                  "gravity": list(grid.gravity), "boundary": grid.boundary},
        "instances": records, "seconds": seconds,
        "peak_rss_mb": round(runtime.peak_rss_mb(), 1), "cuda_peak_mb": None if cuda_peak is None else round(cuda_peak, 1),
        "forward_stats": meta.get("stats"),
    }
    out["bgdo"] = record
    out.setdefault("history", [])
    out["history"].append({"stage": "bgdo_update", "iteration": iteration, "keyframes": str(inputs["keyframes"]),
                           "E_before": {str(r["label"]): r["E_before"] for r in records},
                           "E_after": {str(r["label"]): r["E_after"] for r in records},
                           "G": {str(r["label"]): r["G"] for r in records}})
    runtime.write_json(outputs["params"], out)
    log.info("wrote %s (BGDO iteration %d, %.2f s, peak RSS %.0f MiB%s)", outputs["params"], iteration,
             seconds["total"], record["peak_rss_mb"], "" if cuda_peak is None else f", CUDA peak {cuda_peak:.0f} MiB")
    return {"iteration": iteration, "E_before": [r["E_before"] for r in records],
            "E_after": [r["E_after"] for r in records], "seconds_parts": seconds,
            "cuda_peak_mb": record["cuda_peak_mb"], "timings": timings}


def _warn_no_signal(silent: list[int], first: dict, meta: dict, instances: list[dict], grid, cfg: dict, log) -> dict:
    """WARNING per instance whose key frames carry no load (E stays), with the estimated time of
    its first contact and the forward frames that would reach it. Returns {k: record}."""
    import copy

    from .. import config as C

    out = {}
    if not silent:
        return out
    rec = meta.get("sim_config") or {}
    sim = rec.get("sim") if isinstance(rec.get("sim"), dict) else (cfg.get("sim") or {})
    dyn = rec.get("dynamics") if isinstance(rec.get("dynamics"), dict) else (cfg.get("scene") or {}).get("dynamics")
    dyn = C.validate(copy.deepcopy(dyn or {}), C.load_schema("scene_dynamics.schema.yaml"), "scene", "dynamics")
    floor = max(float((dyn.get("ground") or {}).get("height", 0.0)), 3.0 / grid.n_grid)
    fps = float(sim.get("fps", 30.0))
    stored = [fr for fr in meta["frames"] if fr[1] > 0]
    times = ", ".join(f"{fr[2]:.3g}" for fr in stored)
    n_forward = (meta.get("stats") or {}).get("forward_frames")
    by_label = {int(i["label"]): i for i in instances}
    for k in silent:
        inst = by_label[k]
        c = first_contact(first.get("x"), first.get("v"), meta["label"], k, grid, floor)
        r = {"key_frame_times_s": [fr[2] for fr in stored], "contact": c}
        hint = ""
        if c is not None:
            need = forward_frames_needed(c["time_s"], fps, cfg["bgdo"].get("key_frames", [0.0, 0.5, 1.0]))
            r["forward_frames_needed"] = need
            hint = (f"; it is {c['height_m']:.3g} m above {c['support']} and reaches it after about {c['time_s']:.3g} s: "
                    f"set bgdo.forward_frames to at least {need} (now {n_forward}), or null (= sim.n_frames)")
        else:
            hint = "; give the forward simulation more frames (bgdo.forward_frames, null = sim.n_frames)"
        log.warning("instance %d (%s): no key frame after frame 0 (t = %s s) carries a load (mean stress below "
                    "bgdo.min_load = %g of its static stress): the object has not touched anything yet, so the key "
                    "frames say nothing about its stiffness; E is left unchanged (%.4g Pa)%s", k, inst.get("name"),
                    times, float(cfg["bgdo"].get("min_load", 0.01)), float(inst["E"]), hint)
        out[k] = r
    return out


def _check_config(bcfg: dict) -> None:
    """Range checks beyond the schema (the schema has already filled defaults)."""
    for key in ("variant", "scaling", "eta_rule", "delta_target", "eta_coefficient", "reference_modulus", "cfl_limit",
                "deformation_measure", "max_step"):
        if key not in bcfg:
            raise ConfigError(f"bgdo.{key}", "missing (pass the section through config.section_defaults('bgdo'))")
    if bcfg["variant"] not in ("algorithm1", "main_text"):
        raise ConfigError("bgdo.variant", f"must be algorithm1 or main_text, got {bcfg['variant']!r}")
    if bcfg["scaling"] not in ("reference", "si"):
        raise ConfigError("bgdo.scaling", f"must be reference or si, got {bcfg['scaling']!r}")
    if bcfg.get("deformation_measure") not in ("stretch", "frobenius"):
        raise ConfigError("bgdo.deformation_measure", f"must be stretch or frobenius, got {bcfg.get('deformation_measure')!r}")
    if bcfg["eta_rule"] not in ("paper", "constant"):
        raise ConfigError("bgdo.eta_rule", f"must be paper or constant, got {bcfg['eta_rule']!r}")
    if bcfg.get("deformation_signal", "log_ratio") not in ("log_ratio", "difference"):
        raise ConfigError("bgdo.deformation_signal", f"must be log_ratio or difference, got {bcfg.get('deformation_signal')!r}")
    if bcfg.get("failure_rule", "static_load") not in ("static_load", "max_step"):
        raise ConfigError("bgdo.failure_rule", f"must be static_load or max_step, got {bcfg.get('failure_rule')!r}")
    if not isinstance(bcfg.get("ceiling", True), bool):
        raise ConfigError("bgdo.ceiling", f"must be true or false, got {bcfg.get('ceiling')!r}")
    for key in ("eta_coefficient", "reference_modulus", "cfl_limit", "reference_strain", "reference_height"):
        if key not in bcfg:
            continue
        v = bcfg[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ConfigError(f"bgdo.{key}", f"must be a positive number, got {v!r}")
    for key in ("reference_pressure", "deformation_scale", "max_step", "delta_target"):
        v = bcfg.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0):
            raise ConfigError(f"bgdo.{key}", f"must be a positive number or null, got {v!r}")
    ec = bcfg.get("eta_constant", 0.5)
    if isinstance(ec, bool) or not isinstance(ec, (int, float)) or not 0 <= ec <= 1:
        raise ConfigError("bgdo.eta_constant", f"must lie in [0, 1], got {ec!r}")
