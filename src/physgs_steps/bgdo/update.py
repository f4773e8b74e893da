"""The BGDO signals and update rule (FastPhysGS Sec. 4.2, Appendix B.3-B.5, Algorithm 1):
reference scales, solver and load limits, per-key-frame signals from the pseudo step, the
handling of unstable forward runs and the log E update.  Overview: :mod:`physgs_steps.bgdo`."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .. import materials_kb
from ..errors import ConfigError, SimulationError
from ..mpm.material import wave_modulus
from .torch_step import GridSpec, InstanceTable, pseudo_step, svd3

G_REF = 9.81       # m/s^2: the gravity of the per-material delta_target (whatever the scene's gravity)
DELTA_FLOOR = 1e-4  # log_ratio: delta is taken as at least 1e-4 delta_target (log ratio >= -9.2)


# ----------------------------------------------------------------------------- reference scales
@dataclass
class Scales:
    """Reference scales that make the BGDO signals dimensionless (module docs, "Units").

    pressure  # [K] Pa: E and the stress gradient are divided by it (E_hat, g_hat)
    modulus  # [K] Pa: the reference modulus E_ref the pressure was derived from
    deformation  # [K] or scalar: s_delta, delta is divided by it (deformation_signal difference)
    source: per instance, where E_ref came from; band: per instance the material's KB
    ``E_range`` [lo, hi] in Pa, or None when the material is not in the knowledge base.
    target  # [K] delta_target per instance (None: 0.1 for every instance)
    """

    pressure: np.ndarray
    modulus: np.ndarray
    deformation: np.ndarray | float
    source: list
    band: list
    target: np.ndarray | None = None

    def s_delta(self, k: int) -> float:
        return float(np.broadcast_to(np.asarray(self.deformation, np.float64), self.pressure.shape)[k])

    def delta_target(self, k: int) -> float:
        return 0.1 if self.target is None else float(self.target[k])


def reference_scales(instances: list[dict], bcfg: dict) -> Scales:
    """The reference scales of every instance (ordered by label) for config ``bcfg`` (section bgdo).

    delta_target per instance: ``bgdo.delta_target`` if it is a number, else (null, default)
    ``rho g h_ref / E_ref``: the strain that its own weight causes in an object of the
    reference height h_ref (``bgdo.reference_height``, 0.3 m) of this material at the material's
    reference modulus (h_ref 0.3 m: jelly 0.044, bread 0.010, rubber 0.010, stone 3.4e-4)."""

    by_label = {int(i["label"]): i for i in instances}
    K = len(by_label)
    fixed_target = bcfg.get("delta_target")
    ref_strain = float(bcfg.get("reference_strain", 0.1))
    h_ref = float(bcfg.get("reference_height", 0.3))
    modulus, pressure, source, band, target = [], [], [], [], []
    for k in range(K):
        inst = by_label[k]
        name = inst.get("material")
        entry = None
        if isinstance(name, str) and name.strip():
            try:
                entry = materials_kb.get_material(name)
            except ConfigError:
                entry = None
        band.append(list(entry["E_range"]) if entry else None)
        if bcfg["scaling"] == "si":
            modulus.append(1.0)
            pressure.append(1.0)
            target.append(0.1 if fixed_target is None else float(fixed_target))
            source.append("si: signals in Pa, literal reading of the paper")
            continue
        if entry is not None:
            lo, hi = entry["E_range"]
            e_ref = math.sqrt(lo * hi)
            src = f"knowledge base '{entry['name']}': geometric mean of E_range [{lo:.3g}, {hi:.3g}] Pa"
        else:
            e_ref = float(bcfg["reference_modulus"])
            src = f"bgdo.reference_modulus ({e_ref:.3g} Pa): material {name!r} is not in the knowledge base"
        p = bcfg.get("reference_pressure")
        modulus.append(e_ref)
        if p is None:
            pressure.append(ref_strain * e_ref)
        else:
            pressure.append(float(p))
            src += f"; pressure fixed by bgdo.reference_pressure = {float(p):.3g} Pa"
        if fixed_target is None:
            t = float(inst["density"]) * G_REF * h_ref / e_ref
            target.append(t)
            src += f"; delta_target = rho g h_ref / E_ref = {t:.3g}"
        else:
            target.append(float(fixed_target))
        source.append(src)
    target = np.asarray(target, np.float64)
    if bcfg["scaling"] == "si":
        sdelta = np.ones(K)
    else:
        sd = bcfg.get("deformation_scale")
        sdelta = target.copy() if sd is None else np.full(K, float(sd))
    return Scales(np.asarray(pressure, np.float64), np.asarray(modulus, np.float64), sdelta, source, band, target)


# ----------------------------------------------------------------------------- solver and load limits
def solver_ceiling(instances: list[dict], sim: dict, grid: "GridSpec") -> np.ndarray:
    """The largest E per instance (Pa, label order)  # [K] that the forward/final solver integrates
    at its own CFL number: the P-wave speed sqrt((lam + 2 mu) / rho) reaches sim.cfl * dx / dt at
    the smallest substep the config allows (frame_dt / sim.max_substeps, or sim.substep_dt in
    fixed mode). Above it the substep cap binds and the explicit step runs over its CFL number;
    from about twice the wave speed (4x this E) it explodes.

        E_cap = rho (cfl dx / dt_min)^2 (1 + nu)(1 - 2 nu) / (1 - nu)
    """
    from ..mpm.timestep import TimeStepper

    stepper = TimeStepper.from_config(sim or {})
    n_max = stepper.fixed_substeps if stepper.mode == "fixed" else int(stepper.max_substeps)
    dt_min = stepper.frame_dt / n_max
    dx = grid.domain_size / grid.n_grid
    c_cap = stepper.cfl * dx / dt_min
    by_label = {int(i["label"]): i for i in instances}
    out = []
    for k in range(len(by_label)):
        i = by_label[k]
        nu, rho = float(i["nu"]), float(i["density"])
        out.append(rho * c_cap ** 2 * (1 + nu) * (1 - 2 * nu) / (1 - nu))
    return np.asarray(out, np.float64)


def static_stress(x0, label, instances: list[dict], grid: "GridSpec") -> np.ndarray:
    """The static stress rho |g| H_k (Pa) at the base of each instance under gravity  # [K]

    x0  # [P, 3] particle positions (domain units) at the first key frame; label  # [P].
    H_k is the extent of instance k along gravity in metres. With no gravity it is 0.
    The strain this stress causes at modulus E, rho |g| H / E, is the deformation BGDO assumes
    for an instance whose forward run failed (module docs, "Unstable forward runs")."""
    g = np.asarray(grid.gravity, np.float64)
    gn = float(np.linalg.norm(g))
    by_label = {int(i["label"]): i for i in instances}
    K = len(by_label)
    out = np.zeros(K)
    if gn == 0.0:
        return out
    x0 = np.asarray(x0, np.float64)
    label = np.asarray(label)
    ok = np.isfinite(x0).all(axis=1)
    h = x0[ok] @ (g / gn) * grid.domain_size
    lab = label[ok]
    for k in range(K):
        hk = h[lab == k]
        if hk.size:
            out[k] = float(by_label[k]["density"]) * gn * float(hk.max() - hk.min())
    return out


# ----------------------------------------------------------------------------- signals
def _finite_rows(*arrays: torch.Tensor) -> torch.Tensor:
    ok = None
    for a in arrays:
        r = torch.isfinite(a.reshape(a.shape[0], -1)).all(dim=1)
        ok = r if ok is None else ok & r
    return ok


def frame_signals(keyframe: dict, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec, scales: Scales,
                  device="cpu", dtype=torch.float32, measure: str = "stretch") -> list[dict]:
    """BGDO signals of one key frame: one pseudo step with log E as the leaf, per instance.

    keyframe: {"frame", "time", "dt", "x" [P, 3], "v" [P, 3], "C" [P, 3, 3], "F" [P, 3, 3]} (domain
    units, numpy or torch). log_E  # [K]. Returns one dict per instance (label order) with
    n_particles, n_exploded, tau_norm (mean ||tau|| Pa), stress_grad (mean d||tau_p||/dlogE Pa),
    stress_grad_hat (the same in units of the reference pressure, mean), g_tilde (mean over
    particles of log(1 + |g_hat_p|)) and delta, the mean deformation of the stepped F' by
    ``measure``: "stretch" ||F' - R'||_F = ||sigma' - 1|| (rotation removed) or "frobenius"
    ||F' - I||_F (both are recorded, as delta_stretch and delta_frobenius).

    A particle whose stored state is not finite or lies outside the domain [0, 1]^3 is "exploded":
    it takes no part in the step, its stress signal is +inf (so a frame with exploded particles
    asks for the largest allowed decrease of E), and it is left out of delta.
    """
    st = {k: torch.as_tensor(np.asarray(keyframe[k]), dtype=dtype, device=device) for k in ("x", "v", "C", "F", "ep")
          if k in keyframe}
    ok = _finite_rows(st["x"], st["v"], st["C"], st["F"])
    ok &= ((st["x"] >= 0) & (st["x"] <= 1)).all(dim=1) if ok.numel() else ok
    idx = torch.nonzero(ok, as_tuple=True)[0]
    sub = table.select(idx)
    out = None
    if idx.numel():
        out = _step_signals({k: v[idx] for k, v in st.items()}, float(keyframe["dt"]), log_E, sub, grid, measure)
    head = {"frame": int(keyframe["frame"]), "time": float(keyframe["time"]), "dt": float(keyframe["dt"])}
    return [{**head, **_instance_signals(k, table, sub, out, float(scales.pressure[k]))}
            for k in range(table.n_instances)]


def _step_signals(st: dict, dt: float, log_E: torch.Tensor, sub: InstanceTable, grid: GridSpec, measure: str) -> dict:
    """Per-particle signals of one pseudo step from the finite particles ``st`` (each [P', ...]):
    g  # [P'] d||tau_p||/dlog E, tau  # [P'] ||tau_p||, delta_frobenius, delta_stretch  # [P'] and
    delta (the one ``measure`` names). The graph is freed before returning."""
    leaf = log_E.detach().to(device=st["x"].device, dtype=torch.float64).clone().requires_grad_(True)
    res = pseudo_step(st, dt, leaf, sub, grid)
    s_p = res["tau"].flatten(1).norm(dim=1)  # ||tau_p||_F (Pa)
    g_p, = torch.autograd.grad(s_p.sum(), [res["log_E_p"]])  # d||tau_p|| / d log E_k(p)
    Fn = res["F"].detach()
    d_frob = (Fn - torch.eye(3, dtype=Fn.dtype, device=Fn.device)).flatten(1).norm(dim=1)
    d_str = torch.full_like(d_frob, math.nan)
    fin = torch.isfinite(Fn.flatten(1)).all(dim=1)
    if bool(fin.any()):
        _, sig, _ = svd3(Fn[fin])
        d_str[fin] = (sig - 1.0).norm(dim=1)
    return {"g": g_p.detach(), "tau": s_p.detach(), "delta_frobenius": d_frob, "delta_stretch": d_str,
            "delta": d_str if measure == "stretch" else d_frob}


def _instance_signals(k: int, table: InstanceTable, sub: InstanceTable, out: dict | None, p_ref: float) -> dict:
    """Instance k's means of the per-particle signals ``out`` (particles of ``sub``)."""
    none = dict(tau_norm=None, stress_grad=None, delta=None, delta_frobenius=None, delta_stretch=None)
    n_all = int((table.label == k).sum())
    if n_all == 0:
        return {"n_particles": 0, "n_exploded": 0, "stress_grad_hat": None, "g_tilde": None, **none}
    fin = torch.zeros(0, dtype=torch.bool)
    if out is not None:
        mk = sub.label == k
        sel = {name: v[mk] for name, v in out.items()}
        fin = torch.isfinite(sel["g"]) & torch.isfinite(sel["delta"])
    n_exploded = n_all - int(fin.sum())
    rec = {"n_particles": n_all, "n_exploded": n_exploded}
    if int(fin.sum()):
        ghat = sel["g"][fin].double().abs() / p_ref
        rec.update(tau_norm=float(sel["tau"][fin].double().mean()), stress_grad=float(sel["g"][fin].double().mean()),
                   **{name: float(sel[name][fin].double().mean()) for name in ("delta", "delta_frobenius", "delta_stretch")})
        ghat_mean, gt_mean = float(ghat.mean()), float(torch.log1p(ghat).mean())
    else:
        rec.update(none)
        ghat_mean, gt_mean = 0.0, 0.0
    if n_exploded:  # log(1 + inf) = inf: the mean over particles is +inf
        ghat_mean, gt_mean = math.inf, math.inf
    rec["stress_grad_hat"] = ghat_mean
    rec["g_tilde"] = gt_mean
    return rec


def bgdo_signals(keyframes, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec, scales: Scales,
                 device="cpu", dtype=torch.float32, log=None, measure: str = "stretch") -> list[list[dict]]:
    """Signals of every key frame; ``keyframes`` is an iterable of key-frame dicts (see
    :func:`frame_signals`) consumed one at a time, so only one frame and one step's graph are
    in memory. Returns ``[frame][instance]`` records."""
    frames = []
    for kf in keyframes:
        rows = frame_signals(kf, log_E, table, grid, scales, device=device, dtype=dtype, measure=measure)
        frames.append(rows)
        if log is not None:
            log.info("key frame %d: %s", rows[0]["frame"] if rows else -1,
                     "; ".join(f"[{k}] g~={r['g_tilde']:.4g} delta={r['delta'] if r['delta'] is None else round(r['delta'], 5)} "
                               f"exploded={r['n_exploded']}" for k, r in enumerate(rows) if r["g_tilde"] is not None))
    return frames


def wave_speeds(instances: list[dict], rigid: list | None = None) -> np.ndarray:
    """Wave speed sqrt(M / rho) in m/s per instance (label order)  # [K], M the modulus of its
    elasticity model's fastest wave (``mpm.material.wave_modulus``: P-wave, or the sound of a
    fluid or volume model); 0 for the instances flagged in ``rigid`` (no elastic waves)."""
    by_label = {int(i["label"]): i for i in instances}
    out = []
    for k in range(len(by_label)):
        i = by_label[k]
        if rigid is not None and rigid[k]:
            out.append(0.0)
            continue
        E, nu, rho = float(i["E"]), float(i["nu"]), float(i["density"])
        out.append(math.sqrt(wave_modulus(str(i.get("elasticity", "")), E, nu) / rho))
    return np.asarray(out)


def failing_instances(message, names: list) -> list | None:
    """Indices of the instances a forward run's failure message names, or None if it names none.

    The forward stage records the failure as text (physgs_steps.mpm.stability.explain:
    "... in instance '<name>' (...) (also affected: '<a>', '<b>')")."""
    import re

    if not isinstance(message, str):
        return None
    found = re.findall(r"in instance '([^']+)'", message)
    also = re.search(r"\(also affected: ([^)]*)\)", message)
    if also:
        found += re.findall(r"'([^']+)'", also.group(1))
    idx = sorted({k for k, n in enumerate(names) if n in found})
    return idx or None


def unstable_run_info(meta: dict, instances: list[dict], grid: GridSpec, cfl_limit: float,
                      rigid: list | None = None) -> dict:
    """What an unstable forward run says about each instance.

    The forward stage stops at the first unstable frame and stores the last stable frame in
    place of the key frames it could not reach (``substitute_for``). Returns {"stable",
    "missing": those key frames, "cfl": [K] CFL number c_k dt / dx of each instance in the
    failing frame (None if unknown), "fate": [K] "ok" | "exploded" | "broken",
    "delta_broken": the deformation of a broken state}. An instance is "exploded" when its CFL
    number exceeded ``cfl_limit`` (the explicit step was unstable for its stiffness: too stiff
    for the substep cap); otherwise, when the failure names it (collapse J < j_min, tearing,
    splashing out), it is "broken": it could not carry the load (too soft). ``delta_broken`` =
    sqrt(3) (1 - j_min^(1/3)) is the deformation ||sigma - 1|| of an isotropic collapse to the
    forward run's stability limit J = sim.stability.j_min, the least deformation it calls a
    collapse.
    """
    stats = meta.get("stats") or {}
    stored = [fr[1] for fr in meta["frames"]]
    missing = sorted({m for fr in meta["frames"] for m in fr[4]} - set(stored))
    K = len(instances)
    sim_cfg = meta.get("sim_config") or {}
    j_min = ((sim_cfg.get("sim") or {}).get("stability") or {}).get("j_min", 0.05)
    info = {"stable": stats.get("stable", True) is not False, "missing": missing, "cfl": None,
            "fate": ["ok"] * K, "delta_broken": math.sqrt(3.0) * (1.0 - float(j_min) ** (1.0 / 3.0)),
            "failure": stats.get("failure")}
    if info["stable"]:
        return info
    dts = stats.get("dt_per_frame") or []
    dx = sim_cfg.get("dx") or grid.domain_size / grid.n_grid
    if dts:
        cfl = wave_speeds(instances, rigid) * float(dts[-1]) / float(dx)
        info["cfl"] = [float(c) for c in cfl]
        info["fate"] = ["exploded" if c > cfl_limit else "ok" for c in cfl]
    by_label = {int(i["label"]): i for i in instances}
    names = [str(by_label[k].get("name", "")) for k in range(K)]
    failing = failing_instances(stats.get("failure"), names)
    if failing is None:  # the message names no instance: every instance not blamed on the CFL limit
        failing = list(range(K))
    for k in failing:
        if info["fate"][k] == "ok":
            info["fate"][k] = "broken"
    return info


def assemble_frames(frames: list[list[dict]], meta: dict, info: dict) -> list[list[dict]]:
    """Weight the per-frame records and add the key frames an unstable run never reached.

    Every stored key frame that was requested counts once (the last stable frame an unstable
    run stores in place of the missing ones counts only if it was requested itself). For an
    "exploded" instance every missing key frame is an exploded state: all particles diverged,
    the compressed stress signal is +inf (the paper's log(1 + |g|) of a diverged stress) and the
    deformation undefined. For a "broken" instance every missing key frame is a collapsed state
    with the last stable frame's stress signal and the deformation max(``info["delta_broken"]``,
    the static strain ``info["static_delta"][k]`` = rho |g| H / E when given): a collapse shows
    at least the collapse deformation, and an object far too soft to carry its own weight
    would have deformed by its static strain had the run not stopped. An instance the failure
    did not involve ("ok" in an unstable run) gets nothing for the missing key frames: the run
    ended before they could show its behaviour (the last stable frame of a run that broke at
    impact shows an object still falling); if it is left with no stored key frame after frame 0
    (the rest state), it is "broken" too when its static strain exceeds the collapse
    deformation (it cannot carry its own weight; ``info["fate"]`` is updated), else it has no
    evidence and :func:`bgdo_update` leaves its E unchanged (``no_evidence``). Returns
    ``[frame][instance]`` records with a ``weight``."""
    stats = meta.get("stats") or {}
    requested = stats.get("key_frames_requested")
    fate = info["fate"]
    out = []
    last = {}
    for fr, rows in zip(meta["frames"], frames):
        frame, subs = fr[1], fr[4]
        own = 1 if (requested is None or frame in requested or not subs) else 0
        new_rows = []
        for k, r in enumerate(rows):
            new_rows.append({**r, "frame": frame, "weight": own, "substitute_for": list(subs)})
            last[k] = r
        out.append(new_rows)
    static = info.get("static_delta")
    if not info["stable"]:
        for k, f in enumerate(fate):
            informative = [rows[k] for rows in out if rows[k]["weight"] > 0 and rows[k]["frame"] > 0]
            if f == "ok" and not informative:
                if static is not None and static[k] > info["delta_broken"]:
                    # it cannot carry its own weight: the static strain alone is beyond a collapse
                    fate[k] = "broken"
                    info.setdefault("fate_reason", {})[k] = (
                        f"static strain rho |g| H / E = {static[k]:.3g} > collapse deformation {info['delta_broken']:.3g}")
                    continue
                for rows in out:
                    rows[k]["no_evidence"] = True
    if any(f != "ok" for f in fate):
        for m in info["missing"]:
            rows = []
            for k, f in enumerate(fate):
                r = last[k]
                base = {"frame": m, "time": None, "dt": None, "n_particles": r["n_particles"], "tau_norm": None,
                        "stress_grad": None, "delta_frobenius": None, "delta_stretch": None, "substitute_for": [],
                        "missing": f}
                if f == "exploded":
                    rows.append({**base, "n_exploded": r["n_particles"], "stress_grad_hat": math.inf,
                                 "g_tilde": math.inf, "delta": None, "weight": 1})
                elif f == "broken":
                    d = max(info["delta_broken"], 0.0 if r["delta"] is None else r["delta"],
                            0.0 if static is None else float(static[k]))
                    rows.append({**base, "n_exploded": 0, "stress_grad_hat": r["stress_grad_hat"],
                                 "g_tilde": r["g_tilde"], "delta": d, "weight": 1})
                else:
                    rows.append({**base, "n_exploded": 0, "stress_grad_hat": None, "g_tilde": None, "delta": None,
                                 "weight": 0, "no_evidence": bool(out[0][k].get("no_evidence"))})
            out.append(rows)
    return out


# ----------------------------------------------------------------------------- key frames without load
def mark_unloaded(frames: list[list[dict]], static: np.ndarray, scales: Scales, min_load: float) -> list[int]:
    """Mark the key frames after frame 0 in which an instance is not loaded (``unloaded``).

    An instance is loaded in a key frame when its mean ||tau|| is at least ``min_load`` x its
    static stress rho |g| H (``static`` [K], Pa), or its mean deformation at least ``min_load``
    x its delta_target (a collapsed, far too soft object is barely stressed but very deformed),
    or when it has exploded particles. An unloaded frame (the object still falling or flying:
    stress and deformation both about 1e-6 of those scales) carries no information about E and
    is left out of that instance's update. Returns the instances that have key frames after frame 0 but no loaded
    one: :func:`bgdo_update` leaves their E unchanged (rule ``no_signal``)."""
    silent = []
    K = len(frames[0]) if frames else 0
    for k in range(K):
        later = [rows[k] for rows in frames if rows[k]["frame"] > 0 and rows[k].get("weight", 1) > 0]
        for r in later:
            if r.get("n_exploded") or r.get("tau_norm") is None:
                continue  # exploded (a signal: too stiff) or a state the failure rules supply
            ref = float(static[k]) if static is not None else 0.0
            stressed = ref > 0 and r["tau_norm"] >= min_load * ref
            deformed = r["delta"] is not None and r["delta"] >= min_load * scales.delta_target(k)
            if not (stressed or deformed):
                r["unloaded"] = True
        if later and all(r.get("unloaded") for r in later):
            silent.append(k)
    return silent


def first_contact(x0, v0, label, k: int, grid: "GridSpec", floor: float) -> dict | None:
    """When instance ``k`` first touches what lies below it, from its state at frame 0.

    x0, v0  # [P, 3] positions (domain units) and velocities (domain units/s) at frame 0;
    label  # [P]; ``floor``: height of the floor in domain units (the ground collider, or the
    domain's bottom wall). The support is the floor or the top of another instance under it
    (overlapping boxes in x and y). Free fall along -z from the lowest point with the mean
    vertical velocity. Returns {"height_m", "support", "time_s"} or None (gravity not along -z,
    no particles, or the instance rises away)."""
    g = np.asarray(grid.gravity, np.float64)
    gz = -g[2]
    if gz <= 0 or np.linalg.norm(g[:2]) > 1e-6 * gz:
        return None
    x0, v0, label = np.asarray(x0, np.float64), np.asarray(v0, np.float64), np.asarray(label)
    ok = np.isfinite(x0).all(axis=1) & np.isfinite(v0).all(axis=1)
    mine = ok & (label == k)
    if not mine.any():
        return None
    lo, hi = x0[mine].min(axis=0), x0[mine].max(axis=0)
    support, what = floor, "the floor"
    for j in np.unique(label[ok & (label != k)]):
        o = x0[ok & (label == j)]
        olo, ohi = o.min(axis=0), o.max(axis=0)
        if (olo[:2] <= hi[:2]).all() and (ohi[:2] >= lo[:2]).all() and ohi[2] <= lo[2] and ohi[2] > support:
            support, what = float(ohi[2]), f"instance {int(j)}"
    L = grid.domain_size
    h = max(float(lo[2] - support), 0.0) * L
    vz = float(v0[mine, 2].mean()) * L
    disc = vz * vz + 2.0 * gz * h
    t = (vz + math.sqrt(disc)) / gz
    return {"height_m": h, "support": what, "time_s": t}


def forward_frames_needed(t_contact: float, fps: float, key_frames) -> int:
    """Forward frames T for which the first key frame after frame 0 (fraction f of T - 1) comes
    0.05 s after ``t_contact`` (the load builds within a few frames of the impact)."""
    fracs = [float(f) for f in key_frames if float(f) > 0]
    f = min(fracs) if fracs else 1.0
    return int(math.ceil((t_contact + 0.05) * fps / f)) + 1


# ----------------------------------------------------------------------------- update
def eta_value(E: float, pressure: float, bcfg: dict) -> tuple[float, float]:
    """(eta, E_hat): the guidance weight for modulus E (Pa) and reference pressure (Pa)."""
    E_hat = E / pressure
    if bcfg["eta_rule"] == "constant":
        return float(bcfg["eta_constant"]), E_hat
    return min(1.0, float(bcfg["eta_coefficient"]) * math.log1p(E_hat)), E_hat


def _instance_step(frames_k: list[dict], eta: float, bcfg: dict, sdelta: float, target: float) -> tuple[float, list]:
    """(G, per-frame terms) for one instance from its per-frame records."""
    usable = [r for r in frames_k if r["g_tilde"] is not None and r.get("weight", 1) > 0 and not r.get("unloaded")]
    if not usable or any(r.get("no_evidence") for r in frames_k):
        return math.nan, []
    if any(r.get("unloaded") for r in frames_k) and not any(r["frame"] > 0 for r in usable):
        return math.nan, []  # no key frame after the rest state carries a load
    W = float(sum(r.get("weight", 1) for r in usable))

    def stress_term(x):  # eta * x with eta * inf = inf for eta > 0
        return math.inf if math.isinf(x) and eta > 0 else eta * x

    if bcfg["variant"] == "main_text":
        g_tau = sum(r.get("weight", 1) * r["stress_grad_hat"] for r in usable) / W
        dl = [(r.get("weight", 1), r["delta"]) for r in usable if r["delta"] is not None]
        d_F = (sum(w * d for w, d in dl) / sum(w for w, _ in dl)) / sdelta if dl else 0.0
        G = stress_term(math.log1p(g_tau)) - (1.0 - eta) * d_F
        return G, [{"frame": r["frame"], "weight": r.get("weight", 1)} for r in usable]
    if bcfg.get("deformation_signal", "log_ratio") == "difference":
        terms = []
        for r in usable:
            dterm = 0.0 if r["delta"] is None else (1.0 - eta) * (r["delta"] - target) / sdelta
            terms.append({"frame": r["frame"], "weight": r.get("weight", 1), "term": stress_term(r["g_tilde"]) - dterm})
        return sum(t["weight"] * t["term"] for t in terms) / W, terms
    # log_ratio: the stress term averaged over all key frames, the deformation term
    # log(delta / delta_target) over the key frames after the rest state (frame 0: F = I)
    floor = target * DELTA_FLOOR
    terms = [{"frame": r["frame"], "weight": r.get("weight", 1), "stress": stress_term(r["g_tilde"]),
              "log_ratio": (math.log(max(r["delta"], floor) / target)
                            if r["delta"] is not None and r["frame"] > 0 else None)} for r in usable]
    S = sum(t["weight"] * t["stress"] for t in terms) / W
    dfr = [t for t in terms if t["log_ratio"] is not None]
    Wd = float(sum(t["weight"] for t in dfr))
    D = sum(t["weight"] * t["log_ratio"] for t in dfr) / Wd if Wd > 0 else 0.0
    return S - (1.0 - eta) * D, terms


def bgdo_update(log_E, frames: list[list[dict]], scales: Scales, bcfg: dict,
                limits: dict | None = None) -> tuple[np.ndarray, list[dict]]:
    """One BGDO update of log E per instance from the key-frame signals.

    log_E  # [K] natural log of E (Pa); frames: ``[frame][instance]`` records of
    :func:`bgdo_signals` (after :func:`assemble_frames`). limits (optional): {"ceiling"  # [K]
    :func:`solver_ceiling` (Pa), "static_stress"  # [K] :func:`static_stress` (Pa), "fate": [K]
    of :func:`unstable_run_info`}. Returns (new log E  # [K], one record per instance with the
    signals, eta, E_hat, the step G, E before and after, and which rule set E).

    With ``failure_rule: static_load`` (default) an "exploded" instance goes to
    min(E_cap, static_stress / delta_target): the stiffest modulus the solver integrates, or
    the one at which its own weight strains it by the target, whichever is lower. With
    ``ceiling: true`` (default) no update raises E above max(E, E_cap).
    """
    log_E = np.asarray(torch.as_tensor(log_E).detach().cpu().double().numpy(), dtype=np.float64).reshape(-1)
    K = log_E.shape[0]
    max_step = bcfg.get("max_step")
    limits = limits or {}
    ceiling = limits.get("ceiling")
    sstress = limits.get("static_stress")
    fates = limits.get("fate") or ["ok"] * K
    rigid = limits.get("rigid") or [False] * K
    new = log_E.copy()
    records = []
    for k in range(K):
        E = float(math.exp(log_E[k]))
        eta, E_hat = eta_value(E, float(scales.pressure[k]), bcfg)
        fk = [fr[k] for fr in frames]
        target = scales.delta_target(k)
        G, terms = _instance_step(fk, eta, bcfg, scales.s_delta(k), target)
        cap = None if ceiling is None else float(ceiling[k])
        rec = {"label": k, "E_before": E, "log_E_before": float(log_E[k]), "eta": eta, "E_hat": E_hat,
               "reference_pressure": float(scales.pressure[k]), "reference_modulus": float(scales.modulus[k]),
               "deformation_scale": scales.s_delta(k), "delta_target": target, "reference_source": scales.source[k],
               "band": scales.band[k], "fate": fates[k], "ceiling": cap,
               "static_stress": None if sstress is None else float(sstress[k]), "frames": fk, "terms": terms,
               "capped_by_ceiling": False, "rule": "signals"}
        if rigid[k]:
            rec.update(G=None, G_unclipped=None, clipped=False, E_after=E, log_E_after=float(log_E[k]), rule="rigid",
                       note="rigid instance (a rigid body or static geometry): its E does not enter the simulation; "
                            "left unchanged")
        elif math.isnan(G):
            unloaded = any(r.get("unloaded") for r in fk)
            why = ("no key frame after frame 0 carries a load (bgdo.min_load): the object had not touched anything "
                   "yet" if unloaded else
                   "the forward run became unstable (other instances) before any key frame after frame 0"
                   if any(r.get("no_evidence") for r in fk) else "no particle of this instance in any key frame")
            rec.update(G=None, G_unclipped=None, clipped=False, E_after=E, log_E_after=float(log_E[k]),
                       note=f"{why}: E left unchanged", rule="no_signal" if unloaded else "unchanged")
        elif (fates[k] == "exploded" and bcfg.get("failure_rule", "static_load") == "static_load"
              and cap is not None and cap < E):
            s = 0.0 if sstress is None else float(sstress[k])
            E_new = cap if s <= 0 else min(cap, s / target)
            new[k] = math.log(E_new)
            rec.update(G=float(log_E[k] - new[k]), G_unclipped=None, clipped=False, E_after=E_new,
                       log_E_after=float(new[k]), rule=("exploded: min(E_cap, static stress / delta_target)"
                                                         if s > 0 else "exploded: E_cap"))
        else:
            if max_step is None and not math.isfinite(G):
                raise SimulationError(f"instance {k}: the forward simulation exploded (infinite stress signal) and "
                                      "bgdo.max_step is null, so the update of log E would be infinite; set "
                                      "bgdo.max_step (default ln 10000)")
            Gc = G if max_step is None else max(-float(max_step), min(float(max_step), G))
            new[k] = log_E[k] - Gc
            rec.update(G=Gc, G_unclipped=(None if math.isinf(G) else G), clipped=bool(Gc != G))
            if bcfg.get("ceiling", True) and cap is not None and new[k] > log_E[k] and new[k] > math.log(cap):
                new[k] = max(float(log_E[k]), math.log(cap))
                rec.update(capped_by_ceiling=True, G=float(log_E[k] - new[k]))
            rec.update(E_after=float(math.exp(new[k])), log_E_after=float(new[k]))
        band = scales.band[k]
        rec["in_band_before"] = None if band is None else bool(band[0] <= E <= band[1])
        rec["in_band_after"] = None if band is None else bool(band[0] <= rec["E_after"] <= band[1])
        records.append(rec)
    return new, records

