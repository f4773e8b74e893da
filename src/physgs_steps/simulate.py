"""Stages forward_sim and final_sim: the MLS-MPM simulation of the filled scene.

Both read ``particles.h5`` (fill stage) and ``params.json`` (vlm_params / bgdo_update) and
simulate with :mod:`physgs_steps.mpm` under ``cfg["sim"]`` (sim.schema.yaml) and the scene's
``dynamics`` (scene_dynamics.schema.yaml).  Formats: docs/CONTRACTS.md.

* ``run_forward`` (gradient-free forward run for BGDO) writes ``forward.h5`` with the key
  frames ``round(f (T - 1))`` for ``f`` in ``bgdo.key_frames`` over ``T = bgdo.forward_frames``
  (null: ``sim.n_frames``) frames: x, v, C, F of every particle in domain units.  If the run
  becomes unstable it does NOT fail: the state of the last stable frame is stored as the last
  key frame (attribute ``substitute_for`` lists the key frames it stands for), key frames
  after it are left out, and ``stats`` records ``stable: false`` with the reason.  BGDO then
  sees the parameters that broke the run (a too stiff E for the substep cap shows up as huge
  stresses, a too soft one as large deformation) and corrects them.
* ``run_final`` writes ``final.h5`` (:mod:`physgs_steps.final_frames`): positions and
  deformation gradients of the particles that carry the visible gaussians (particles.h5
  ``driver``) for every frame, frames held at rest stored once, and the physical
  plausibility figures accumulated on the way (:mod:`physgs_steps.physical`).  An unstable
  run stops with a :class:`SimulationError` naming the instance, its material and
  parameters and what to change; no output is written. With ``sim.on_unstable: keep`` it
  writes the stable frames instead (fewer than ``n_frames``) with ``stats.stable = false`` and
  the failure message (the benchmark's expected failures).

Both detect rest (``sim.rest``, :mod:`physgs_steps.mpm.rest`): once everything has stopped
moving and no force or enforced motion acts, no more substeps until the dynamics' schedule
changes.
"""
from __future__ import annotations

import logging
from pathlib import Path

import h5py
import numpy as np

from .errors import ConfigError, InputError, SimulationError
from .runtime import atomic_path, json_text, peak_rss_mb, read_json_input
from .mpm.colliders import StaticGeometry, face_half_width
from .mpm.dynamics import Dynamics, describe_counts
from .mpm.materials import Material
from .mpm.rest import RestPolicy
from .mpm.runner import RunResult, run_frames
from .mpm.solver import MPMSolver
from .mpm.stability import Thresholds, cfl_note
from .mpm.timestep import TimeStepper

DEFAULT_KEY_FRAMES = (0.0, 0.5, 1.0)
RIGID_PARTICLES_PER_CELL = 1  # sim.rigid_particles_per_cell's default (sim.schema.yaml)
CLEARANCE_CELLS = 1.0  # static collider points this close (grid cells) to material touching them are left out


# ============================================================================ inputs
def load_particles(path: str | Path) -> dict:
    """Read particles.h5: {"x" [P,3] f32, "label" [P] int32, "filled" [P] bool, "vol" [P] f32,
    "driver" [P] bool, "static_x" [S,3] f32, "static_label" [S] int32, "n_gaussians"}.  ``driver`` (the particles whose states final.h5 stores)
    defaults to the non-filled rows when the file has none.  Raises InputError on a
    missing/malformed file."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "particles file does not exist")
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in ("x", "label", "filled", "vol") if k not in f]
            if missing:
                raise InputError(path, f"missing datasets {missing}")
            out = {"x": f["x"][()], "label": f["label"][()], "filled": f["filled"][()].astype(bool), "vol": f["vol"][()]}
            out["driver"] = f["driver"][()].astype(bool) if "driver" in f else ~out["filled"]
            out["static_x"] = f["static_x"][()].reshape(-1, 3) if "static_x" in f else np.zeros((0, 3), np.float32)
            out["static_label"] = (f["static_label"][()] if "static_label" in f
                                   else np.full(len(out["static_x"]), -1, np.int32))
            n_g = f.attrs.get("n_gaussians")
    except OSError as e:
        raise InputError(path, f"not a readable HDF5 file: {e}") from None
    P = len(out["x"])
    if out["x"].ndim != 2 or out["x"].shape[1] != 3 or P == 0:
        raise InputError(path, f"x must have shape [P, 3] with P > 0, got {out['x'].shape}")
    for k in ("label", "filled", "vol", "driver"):
        if out[k].shape != (P,):
            raise InputError(path, f"{k} must have shape [{P}], got {out[k].shape}")
    for k in ("x", "vol"):
        if not np.all(np.isfinite(out[k])):
            raise InputError(path, f"{k} has {int((~np.isfinite(out[k])).sum())} non-finite values")
    if np.any(out["vol"] <= 0):
        raise InputError(path, "vol must be > 0 for every particle")
    if out["static_label"].shape != (len(out["static_x"]),):
        raise InputError(path, f"static_label must have shape [{len(out['static_x'])}] (one per static_x row), "
                               f"got {out['static_label'].shape}")
    if not np.all(np.isfinite(out["static_x"])):
        raise InputError(path, "static_x has non-finite values")
    out["n_gaussians"] = int(n_g) if n_g is not None else int((~out["filled"]).sum())
    return out


def load_materials(path: str | Path, labels_present: np.ndarray) -> tuple[dict, list[Material], list[int]]:
    """Read params.json; return (params dict, materials, labels) for the labels present in the
    particles, in label order.  Raises InputError naming the file and entry."""
    path = Path(path)
    params = read_json_input(path, "params file")
    if not isinstance(params, dict) or not isinstance(params.get("instances"), list):
        raise InputError(path, "must be an object with an 'instances' list")
    by_label = {}
    for i, e in enumerate(params["instances"]):
        if not isinstance(e, dict) or not isinstance(e.get("label"), int) or isinstance(e.get("label"), bool):
            raise InputError(path, f"instances[{i}] needs an integer 'label'")
        try:
            by_label[e["label"]] = Material.from_params(e, f"instances[{i}]")
        except ConfigError as err:
            raise InputError(path, str(err)) from None
    labels = sorted(int(l) for l in np.unique(labels_present))
    missing = [l for l in labels if l not in by_label]
    if missing:
        raise InputError(path, f"no material for particle label(s) {missing}; entries exist for {sorted(by_label)}")
    return params, [by_label[l] for l in labels], labels


def load_run(run_dir: str | Path, scene_name: str) -> dict:
    """The inputs of a finished pipeline run's final simulation, for tools that rebuild its solver
    (benchmarks/bench_scene_substep.py, bench_rigid_proxies.py): ``run_dir`` is where snakemake
    ran (``results/<scene>/fill/*/particles.h5`` and ``results/<scene>/sim/*/it<k>*/params.json``
    below it), the config is ``config/`` of the working directory.  Returns ``sim`` and
    ``scene`` (the effective sections), ``parts``, ``params``, ``materials`` and ``labels``, from
    the last fill and the highest BGDO iteration's params.  Raises InputError when the run has
    none of them."""
    import re

    from . import config as C

    cfg = C.load_config()
    scene = C.load_scene(cfg, scene_name)
    res = Path(run_dir) / "results" / scene_name
    fills = sorted(res.glob("fill/*/particles.h5"))
    its = sorted(res.glob("sim/*/it*/params.json"),
                 key=lambda p: (int(re.match(r"it(\d+)", p.parent.name).group(1)), str(p)))
    if not fills or not its:
        raise InputError(res, "no fill/*/particles.h5 or sim/*/it*/params.json: run the pipeline for "
                              f"{scene_name!r} in {run_dir} first")
    parts = load_particles(fills[-1])
    params, materials, labels = load_materials(its[-1], parts["label"])
    return dict(sim=C.effective_section(cfg, scene, "sim"), scene=scene, parts=parts, params=params,
                materials=materials, labels=labels)


def _backend(cfg: dict) -> str:
    b = cfg["sim"].get("backend", "auto")
    if b == "auto" and cfg.get("device") in ("cpu", "cuda"):
        return cfg["device"]
    return b


def _key_frames(cfg: dict, n_frames: int) -> list[int]:
    fracs = (cfg.get("bgdo") or {}).get("key_frames") or DEFAULT_KEY_FRAMES
    frames = []
    for f in fracs:
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0.0 <= f <= 1.0:
            raise ConfigError("bgdo.key_frames", f"entries are fractions in [0, 1], got {f!r}")
        frames.append(int(round(f * (n_frames - 1))))
    return sorted(set(frames))


def _forward_frames(cfg: dict) -> int:
    n = (cfg.get("bgdo") or {}).get("forward_frames")
    n = cfg["sim"]["n_frames"] if n is None else n
    if isinstance(n, bool) or not isinstance(n, int) or n < 2:
        raise ConfigError("bgdo.forward_frames", f"must be an integer >= 2 or null, got {n!r}")
    return n


# ============================================================================ set-up
def build_solver(parts: dict, materials: list[Material], labels: list[int], cfg: dict, log: logging.Logger,
                 params: dict | None = None) -> MPMSolver:
    """A loaded MPMSolver for the particles, materials and cfg (sim + scene dynamics); the static
    instances and surroundings (particles.h5 ``static_x``) are its colliders
    (:func:`static_colliders`) unless ``sim.static_colliders`` is false."""
    sim = cfg["sim"]
    scene = cfg.get("scene") or {}
    dyn = Dynamics.from_config(scene.get("dynamics"), source=str(scene.get("_path", "scene file")))
    materials = rigid_setting(materials, sim)
    static = static_colliders(parts, params, cfg, log) if sim.get("static_colliders", True) else []
    solver = MPMSolver(materials, n_grid=int(sim["n_grid"]), domain_size=float(sim["domain_size"]), dynamics=dyn,
                       backend=_backend(cfg), labels=labels, sort_particles=bool(sim.get("sort_particles", True)),
                       p2g=str(sim.get("p2g", "auto")), static=static,
                       rigid_particles_per_cell=sim.get("rigid_particles_per_cell", RIGID_PARTICLES_PER_CELL))
    index = {l: i for i, l in enumerate(labels)}
    material = np.array([index[int(l)] for l in parts["label"]], np.int64)
    # contact starts at each particle's face (colliders.py "Boundary placement"): half its side in
    # front of a filled (lattice) particle's centre, at the centre of a gaussian (on the surface);
    # particles without a "filled" flag are all material samples (the lattice rule)
    surface = ~np.asarray(parts["filled"], bool) if "filled" in parts else None
    solver.set_particles(parts["x"], parts["vol"], material, face=face_half_width(parts["vol"], surface))
    counts = np.bincount(material, minlength=len(materials))
    L3 = float(sim["domain_size"]) ** 3
    for k, (m, n) in enumerate(zip(materials, counts)):
        if m.fixed:
            log.info("instance %s: %d particles -> FIXED: static geometry (a level-set collider), not simulated",
                     m.describe(), n)
        elif m.rigid:
            mass = float(parts["vol"][material == k].sum()) * L3 * m.density
            proxies = solver.proxy_count(k)
            log.info("instance %s: %d particles -> RIGID: one free rigid body of %.4g kg (density x volume), "
                     "no stress, no time-step limit; %s", m.describe(), n, mass,
                     f"simulated with {proxies} proxy particles (sim.rigid_particles_per_cell "
                     f"{solver.rigid_particles_per_cell:g}), the others follow its motion" if proxies is not None
                     else "every particle simulated")
        else:
            log.info("instance %s: %d particles -> SIMULATED (deformable), wave speed %.3g m/s", m.describe(), n,
                     m.wave_speed)
    n_static = int(sum(n for m, n in zip(materials, counts) if m.fixed))
    n_proxied = solver.n_input - n_static - solver.n_particles + solver.proxy_total()
    log.info("MPM: %d particles simulated (%d of them proxies for %d rigid-body particles), %d static, grid %d^3 "
             "(dx %.4g m), backend %s, %s", solver.n_particles, solver.proxy_total(), n_proxied, n_static,
             solver.n_grid, solver.dx, solver.arch, describe_counts(solver.bound))
    return solver


def static_colliders(parts: dict, params: dict | None, cfg: dict, log: logging.Logger) -> list[StaticGeometry]:
    """The static instances and static surroundings as level-set colliders (colliders.py).

    They have no particles (fill gives them none); particles.h5 ``static_x`` holds their points
    inside the domain, ``static_label`` the instance each belongs to (-1: the surroundings).
    One StaticGeometry per static instance (surface kind and friction of its params.json entry
    when it has one) and one for the surroundings (``separate``, friction 0.5).  Where the
    material touches the static geometry at the start (a simulated particle within one point
    spacing of a static point: a ball on its seat), the static points within one grid cell
    (:data:`CLEARANCE_CELLS`) of the touching particles are left out: the collider's surface
    (half a spacing beyond its points) and its reaction band (one cell in front of it) would
    lie in the material and squeeze it (the winter fountain's ball: J fell to 0.003 in 66
    frames when only the points within one spacing were left out; with one cell it comes to
    rest on its seat).  Material that starts clear of the static geometry (an object above
    a table) leaves it whole.
    Their cost per substep is the grid's boundary treatment only (no particles)."""
    from scipy.spatial import cKDTree

    from .mpm.colliders import estimate_spacing

    sx, sl = np.asarray(parts.get("static_x", np.zeros((0, 3))), np.float64), np.asarray(parts.get("static_label", []))
    if len(sx) == 0:
        return []
    entries = {e.get("label"): e for e in ((params or {}).get("instances") or []) if isinstance(e, dict)}
    names = {l: str(e.get("name") or f"instance {l}") for l, e in entries.items()}
    spacing = estimate_spacing(sx)
    clearance = max(spacing, CLEARANCE_CELLS / float(cfg["sim"]["n_grid"]))  # domain units
    x = np.asarray(parts["x"], np.float64)
    d, _ = cKDTree(sx).query(x, distance_upper_bound=spacing)
    touching = x[np.isfinite(d)]  # [T, 3] simulated particles in contact with static points at the start
    clear = np.ones(len(sx), bool)
    if len(touching):
        d, _ = cKDTree(touching).query(sx, distance_upper_bound=clearance)
        clear = ~np.isfinite(d)
    out = []
    for lab in np.unique(sl):
        sel = sl == lab
        keep = sel & clear
        name = "static surroundings" if lab < 0 else f"static instance {names.get(int(lab), f'label {int(lab)}')}"
        if keep.sum() < 1:
            log.info("%s: all %d points touch simulated particles, no collider", name, int(sel.sum()))
            continue
        e = entries.get(int(lab), {})
        surface, friction = str(e.get("surface") or "separate"), float(e.get("friction", 0.5))
        out.append(StaticGeometry(sx[keep], spacing=spacing, surface=surface, friction=friction, name=name))
        lo, hi = sx[keep].min(0), sx[keep].max(0)
        log.info("%s (label %d): STATIC COLLIDER (level set, not simulated) from %d points (%d next to the simulated "
                 "material left out), %s, friction %g, box [%s]..[%s] (domain units)", name, int(lab), int(keep.sum()),
                 int((sel & ~clear).sum()), surface, friction, ", ".join(f"{v:.3f}" for v in lo),
                 ", ".join(f"{v:.3f}" for v in hi))
    return out


def rigid_setting(materials: list[Material], sim: dict) -> list[Material]:
    """The materials as simulated under ``sim.rigid_bodies``: with false (the ``no_rigid``
    ablation) every free rigid instance is deformable with its material's models and
    simulation-effective E; fixed instances stay static geometry."""
    if sim.get("rigid_bodies", True):
        return list(materials)
    return [m if m.fixed else m.with_(rigid=False) for m in materials]


def _prepare(inputs: dict, cfg: dict, log: logging.Logger):
    if "sim" not in cfg:
        raise ConfigError("sim", "the stage config has no 'sim' section")
    import time

    from .mpm.backend import counters

    t0 = time.perf_counter()
    before = counters()
    parts = load_particles(inputs["particles"])
    params, materials, labels = load_materials(inputs["params"], parts["label"])
    stepper = TimeStepper.from_config(cfg["sim"])
    th = Thresholds.from_config(cfg["sim"].get("stability"))
    solver = build_solver(parts, materials, labels, cfg, log, params)
    note = cfl_note(materials, stepper, solver.dx)
    if note:
        log.warning("%s", note)
    rest = RestPolicy.from_config(cfg["sim"].get("rest"), solver.dynamics)
    after = counters()
    solver.startup = {"taichi_init": round(after["init_seconds"], 3) if after["inits"] > before["inits"] else 0.0,
                      "setup": round(time.perf_counter() - t0, 3), "kernels_before": before["kernels"]}
    return parts, params, solver, stepper, th, rest


def _timings(solver: MPMSolver, res: RunResult, log: logging.Logger, **extra) -> dict:
    """The stage's fixed costs (summary ``timings``): Taichi start (0 when this process had it
    running), set-up (reading, solver, fields, including the start), the first substep (kernel
    compilation or offline-cache loading and code generation), the kernel instances this stage
    materialised and the runtime's total, plus ``extra`` (e.g. writing)."""
    from .mpm.backend import counters

    st = dict(solver.startup)
    k = counters()["kernels"]
    t = {"taichi_init": st["taichi_init"], "setup": st["setup"],
         "first_substep": round(res.first_substep_seconds, 3), "substeps": round(res.step_seconds, 3),
         "kernels_new": None if k is None or st["kernels_before"] is None else k - st["kernels_before"],
         "kernels_total": k, **extra}
    log.info("fixed costs: Taichi start %.2f s, set-up %.2f s, first substep %.2f s (%s kernel instances "
             "compiled or loaded here, %s in this process)", t["taichi_init"], t["setup"], t["first_substep"],
             t["kernels_new"], t["kernels_total"])
    return t


def _stats(res: RunResult, solver: MPMSolver, extra: dict) -> dict:
    out = res.summary(solver.n_particles)
    out.update({
        "n_particles": solver.n_particles, "n_grid": solver.n_grid, "backend": solver.arch,
        "peak_rss_mb": round(peak_rss_mb(), 1), "solver_device_mb": round(solver.device_bytes() / 2**20, 1),
    })
    out.update(extra)
    return out


def _sim_config(cfg: dict, solver: MPMSolver, stepper: TimeStepper) -> dict:
    scene = cfg.get("scene") or {}
    return {"sim": cfg["sim"], "dynamics": scene.get("dynamics"), "backend": solver.arch,
            "frame_dt": stepper.frame_dt, "dx": solver.dx}


# ============================================================================ forward
def run_forward(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Stage forward_sim: key-frame snapshots for BGDO (see the module docstring)."""
    parts, params, solver, stepper, th, rest = _prepare(inputs, cfg, log)
    n_frames = _forward_frames(cfg)
    keys = _key_frames(cfg, n_frames)
    log.info("forward run: %d frames at %g fps, key frames %s", n_frames, stepper.fps, keys)
    snaps: dict[int, dict] = {}

    def on_frame(k: int, t: float, dt_next: float) -> None:
        if k in keys:
            snaps[k] = {**solver.get_state(), "time": t, "dt": dt_next}

    res = run_frames(solver, n_frames, stepper, th, on_frame, log, keep_backup=True, stage="forward_sim",
                     rest=rest)
    missing = [k for k in keys if k not in snaps]
    substitute = None
    if missing:
        k = res.last_stable_frame
        if k not in snaps:
            c_max = float(np.max(solver.wave_speeds()))
            plan = stepper.plan(solver.dx, c_max, float(np.max(solver.stats()["speed_max"])))
            snaps[k] = {**solver.get_state(), "time": k * stepper.frame_dt, "dt": plan.dt}
        substitute = (k, missing)
        log.warning("forward run unstable: key frames %s replaced by the last stable frame %d", missing, k)
    stats = _stats(res, solver, {"key_frames_requested": keys, "key_frames_written": sorted(snaps),
                                 "forward_frames": n_frames})
    tears = any(m.fractures for m in solver.materials)  # ep is stored for tearing materials only
    with atomic_path(outputs["keyframes"]) as tmp:
        with h5py.File(tmp, "w") as f:
            g = f.create_group("particles")
            g.create_dataset("label", data=parts["label"].astype(np.int32))
            g.create_dataset("filled", data=parts["filled"])
            g.create_dataset("vol", data=parts["vol"].astype(np.float32))
            kf = f.create_group("keyframes")
            for k in sorted(snaps):
                s = snaps[k]
                h = kf.create_group(str(k))
                for name in ("x", "v", "C", "F") + (("ep",) if tears else ()):
                    h.create_dataset(name, data=s[name].astype(np.float32))
                h.attrs["frame"] = k
                h.attrs["time"] = float(s["time"])
                h.attrs["dt"] = float(s["dt"])
                if substitute and k == substitute[0]:
                    h.attrs["substitute_for"] = np.array(substitute[1], np.int64)
            f.attrs["params"] = json_text(params)
            f.attrs["sim_config"] = json_text(_sim_config(cfg, solver, stepper), default=str)
            f.attrs["stats"] = json_text(stats)
    log.info("forward_sim: %s, %d substeps in %.1f s (+%.1f s first substep); key frames %s -> %s",
             "stable" if res.stable else "UNSTABLE", stats["substeps_total"], res.step_seconds,
             res.first_substep_seconds, sorted(snaps), outputs["keyframes"])
    return {"stable": res.stable, "substeps_total": stats["substeps_total"], "simulate_seconds": stats["simulate_seconds"],
            "key_frames": sorted(snaps), "timings": _timings(solver, res, log)}


# ============================================================================ final
def run_final(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Stage final_sim: per-frame positions and F of the carrier particles (final.h5).

    inputs: ``particles``, ``params``, optional ``transform`` (transform.json: the motion box
    the render camera is fitted to is then recorded in the capture's frame)."""
    from .final_frames import FinalWriter, codec_options
    from .physical import PhysicalFigures

    parts, params, solver, stepper, th, rest = _prepare(inputs, cfg, log)
    n_frames = int(cfg["sim"]["n_frames"])
    rows = np.flatnonzero(parts["driver"]).astype(np.int64)
    if len(rows) == 0:
        raise InputError(inputs["particles"], "no particle carries a visible gaussian ('driver' is empty)")
    codec = codec_options(cfg["sim"].get("compression", "none"), int(cfg["sim"].get("compression_level", 1)))
    times = np.arange(n_frames, dtype=np.float64) * stepper.frame_dt
    figures = PhysicalFigures(n_frames)
    to_source = None
    if inputs.get("transform"):
        from .prepare import load_transform

        to_source = load_transform(inputs["transform"]).to_source
    import time

    with atomic_path(outputs["frames"]) as tmp:
        with h5py.File(tmp, "w") as f:
            writer = FinalWriter(f, rows, times, codec, to_source)
            busy = 0.0   # seconds in the writer and the figures (within the frame callbacks)

            def on_frame(k: int, t: float, dt_next: float) -> None:
                nonlocal busy
                xs, Fs = solver.gather_rows(rows)
                t0 = time.perf_counter()
                dev = writer.frame(k, xs, Fs)   # F - I when F is finite: the figures reuse it
                figures.add(k, xs, Fs, f_minus_i=dev)
                busy += time.perf_counter() - t0

            def on_hold(k: int, t: float) -> None:
                nonlocal busy
                t0 = time.perf_counter()
                writer.hold(k)
                figures.repeat(k)
                busy += time.perf_counter() - t0

            log.info("final run: %d frames at %g fps, %d particles stored (of %d; they carry the %s gaussians)",
                     n_frames, stepper.fps, len(rows), solver.n_particles, "visible")
            res = run_frames(solver, n_frames, stepper, th, on_frame, log, stage="final_sim", rest=rest,
                             on_hold=on_hold)
            if not res.stable:
                if cfg["sim"].get("on_unstable", "error") != "keep" or res.frames_done < 1:
                    raise SimulationError(res.message)
                # sim.on_unstable: keep -> the stable frames stay, the failure goes into the stats
                writer.truncate(res.frames_done)
                times = times[: res.frames_done]
                log.warning("final_sim unstable after frame %d: keeping frames 0..%d (sim.on_unstable: keep)",
                            res.last_stable_frame, res.last_stable_frame)
            # write_seconds: the stage's time on frames outside the substeps (the frame callbacks:
            # the device -> host copy, the writer and the figures); writer_busy_seconds: the
            # writer and the figures alone
            write_s = res.callback_seconds
            stats = _stats(res, solver, {"n_frames": n_frames, "n_stored": len(rows), "rows_stored": writer.rows,
                                         "frames_written": res.frames_done,
                                         "write_seconds": round(write_s, 3),
                                         "writer_busy_seconds": round(busy, 3)})
            writer.finish({"stats": stats, "params": params, "sim_config": _sim_config(cfg, solver, stepper),
                           "physical": figures.result(times)})
    log.info("final_sim: %d frames%s (%d held at rest, %d rows stored), %d substeps in %.1f s (+%.1f s first substep, "
             "%.2f s in the frame callbacks, of which writer and figures %.2f s) -> %s",
             res.frames_done, "" if res.stable else " (UNSTABLE, kept)", res.held_frames, writer.rows,
             stats["substeps_total"], res.step_seconds, res.first_substep_seconds, write_s, busy, outputs["frames"])
    return {"stable": res.stable, "substeps_total": stats["substeps_total"], "simulate_seconds": stats["simulate_seconds"],
            "held_frames": res.held_frames, "particle_substeps_per_second": stats["particle_substeps_per_second"],
            "timings": _timings(solver, res, log, write=round(write_s, 3), writer_busy=round(busy, 3))}
