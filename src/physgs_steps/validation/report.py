"""results/validation/REPORT.md: error against run time per case (Pareto front, shipped defaults),
the stiff/extreme sweep's counts, and before/after numbers of the fixes.

Inputs are the per-run JSON records (:class:`~.base.RunRecord`), the sweep's per-pair JSON
files and, optionally, a *before* snapshot: the same records measured at an earlier commit
(``src/physgs_steps/validation/data/before.json``; see :func:`snapshot`).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .. import reporting as R
from ..runtime import atomic_path
from .base import DEFAULT, Setting
from .cases import CASES
from .sweep import OUTCOMES


# ============================================================================ fixes (before/after)
@dataclass(frozen=True)
class Fix:
    """One defect the suite exposed and its fix: which measurement shows it."""

    name: str
    what: str           # the defect and the fix, one sentence
    case: str
    variant: str
    setting: str
    metric: str         # "error", "sim_seconds", "substeps" or a key of the record's metrics
    label: str          # what the number is
    snapshot: str | None = None  # label of the before snapshot (None: the file's main one; else one of its "extra")


FIXES = (
    Fix("leapfrog gravity", "gravity was integrated first order (symplectic Euler from v0: drop error = 1/substeps); "
        "velocities are now staggered half a substep (leapfrog), exact for constant body forces",
        "free_fall", "main", "g16-p8-c0.5", "error", "max relative drop error"),
    Fix("leapfrog gravity", "(same, finer grid)", "free_fall", "main", "g32-p8-c0.5", "error", "max relative drop error"),
    Fix("APIC C from the initial velocities", "C = 0 at start lost kinetic energy in the first substep of a "
        "non-uniform velocity field; C is now the velocity gradient the APIC transfer reproduces",
        "rigid_rotation", "main", "g16-p8-c0.5", "ke_ratio_first_frame", "kinetic energy kept after frame 1"),
    Fix("APIC C from the initial velocities", "(same, vibrating bar)", "axial_vibration", "main", "g16-p8-c0.5",
        "amplitude_ratio", "vibration amplitude / exact"),
    Fix("Mohr-Coulomb sand", "the Drucker-Prager cone matched to triaxial compression is a 44 deg Mohr-Coulomb "
        "material in plane strain; sand and snow now use the Mohr-Coulomb surface itself",
        "column_collapse", "a0.5", "g32-p8-c0.5", "runout", "(L_inf - L0)/L0, band 0.6-0.9"),
    Fix("Mohr-Coulomb sand", "(same)", "column_collapse", "a1", "g32-p8-c0.5", "runout", "(L_inf - L0)/L0, band 1.2-1.8"),
    Fix("Mohr-Coulomb sand", "(same)", "column_collapse", "a2", "g32-p8-c0.5", "runout", "(L_inf - L0)/L0, band 2.4-3.6"),
    Fix("Mohr-Coulomb sand", "(same, finer grid)", "column_collapse", "a2", "g48-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 2.4-3.6"),
    Fix("Mohr-Coulomb sand", "(same)", "column_collapse", "a3", "g32-p8-c0.5", "runout", "(L_inf - L0)/L0, band 3.95-5.4"),
    Fix("dam break", "surge front against Martin & Moyce (measured at the surge tip, not the farthest particle)",
        "dam_break", "main", "g16-p8-c0.5", "error", "mean relative front deviation"),
    Fix("dam break", "(default grid)", "dam_break", "main", "g32-p8-c0.5", "error",
        "mean relative front deviation"),
    Fix("dam break", "(finer grid)", "dam_break", "main", "g64-p8-c0.5", "error", "mean relative front deviation"),
    Fix("exact blocks, fluid wave speed", "Scene.block cut a case's block to whole particle spacings (the dam break's "
        "column held 88 % of its water at n_grid 24, 67 % at 16); it now fills its box exactly.  The CFL used the P-wave "
        "speed for the fluid, which has no shear stiffness (1.53x its sound speed, so 1.53x the substeps and the "
        "transfers' smoothing with them); each model's own wave speed now", "dam_break", "main", "g24-p8-c0.5",
        "error", "mean relative front deviation", "b6562d3"),
    Fix("exact blocks, fluid wave speed", "(same; the column 1.4 cells wide: under-resolved)", "dam_break", "main",
        "g16-p8-c0.5", "error", "mean relative front deviation", "b6562d3"),
    Fix("exact blocks, fluid wave speed", "(same, default grid)", "dam_break", "main", "g32-p8-c0.5", "error",
        "mean relative front deviation", "b6562d3"),
    Fix("exact blocks, fluid wave speed", "(same, finer grid: ahead of the raw data, the gate-removal lead)",
        "dam_break", "main", "g48-p8-c0.5", "error", "mean relative front deviation", "b6562d3"),
    Fix("exact blocks, fluid wave speed", "(same)", "dam_break", "main", "g24-p8-c0.5", "substeps", "substeps",
        "b6562d3"),
    Fix("exact blocks", "(the 0.3 m column was cut to 9 particle spacings, 0.28 m, at n_grid 16; the reference used 0.3 m)",
        "self_weight", "main", "g16-p8-c0.5", "error", "relative shortening error", "b6562d3"),
    Fix("exact blocks", "(same)", "self_weight", "main", "g24-p8-c0.5", "error", "relative shortening error",
        "b6562d3"),
    Fix("ghost-row friction", "behind a rough surface the ghost nodes (18-65 % of the reaction) took the mirror's "
        "tangential velocity and charged no friction; they now keep their own less mu times their own push",
        "incline_friction", "slide", "g32-p8-c0.5", "error", "|s - s_ref| / s_ref", "b6562d3"),
    Fix("ghost-row friction", "(same, finer grid)", "incline_friction", "slide", "g48-p8-c0.5", "error",
        "|s - s_ref| / s_ref", "b6562d3"),
    Fix("ghost-row friction", "(same; with exact blocks, whose 1-particle-tall block at 16 hid the defect)",
        "incline_friction", "slide", "g16-p8-c0.5", "error", "|s - s_ref| / s_ref", "b6562d3"),
    Fix("ghost-row friction", "(same)", "incline_friction", "slide", "g24-p8-c0.5", "error", "|s - s_ref| / s_ref",
        "b6562d3"),
    Fix("ghost-row friction", "(same, the block that should stick: creep / free slide)", "incline_friction", "stick",
        "g24-p8-c0.5", "error", "|s| / s_free", "b6562d3"),
    Fix("granular AFLIP", "APIC smoothed the velocity jump across every shear band away once per substep, so a "
        "granular collapse ran out shorter the more substeps it took (its E dependence was only this); the granular "
        "models now add 0.99 x each particle's own deviation from the pre-force grid field (AFLIP, "
        "materials.FLIP_RATIO)", "column_collapse", "a1", "g24-p8-c0.5", "runout", "(L_inf - L0)/L0, band 1.2-1.8",
        "aab9ce8"),
    Fix("granular AFLIP", "(same)", "column_collapse", "a0.5", "g32-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 0.6-0.9", "aab9ce8"),
    Fix("granular AFLIP", "(same, default grid)", "column_collapse", "a1", "g32-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 1.2-1.8", "aab9ce8"),
    Fix("granular AFLIP", "(same)", "column_collapse", "a2", "g32-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 2.4-3.6", "aab9ce8"),
    Fix("granular AFLIP", "(same)", "column_collapse", "a3", "g32-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 3.95-5.4", "aab9ce8"),
    Fix("granular AFLIP", "(same, finer grid)", "column_collapse", "a3", "g48-p8-c0.5", "runout",
        "(L_inf - L0)/L0, band 3.95-5.4", "aab9ce8"),
    Fix("contact at the particles' faces", "contact engaged where a particle's centre came within TOUCH (0.1 cells) "
        "of an obstacle, so material whose face lay on it sank 0.15 cells (half a spacing less TOUCH) before it touched; "
        "a particle now touches when its face, half its volume's cube root in front of its centre, does",
        "resting_block", "main", "g32-p8-c0.5", "error", "largest layer offset / H", "0b071fe"),
    Fix("contact at the particles' faces", "(same, coarse grid)", "resting_block", "main", "g16-p8-c0.5", "error",
        "largest layer offset / H", "0b071fe"),
    Fix("contact at the particles' faces", "(same)", "resting_block", "main", "g24-p8-c0.5", "error",
        "largest layer offset / H", "0b071fe"),
    Fix("contact at the particles' faces", "(same, finer grid)", "resting_block", "main", "g48-p8-c0.5", "error",
        "largest layer offset / H", "0b071fe"),
    Fix("contact at the particles' faces", "(same, 27 per cell)", "resting_block", "main", "g32-p27-c0.5", "error",
        "largest layer offset / H", "0b071fe"),
    Fix("contact at the particles' faces", "(same: the bottom layer's offset in cells)", "resting_block", "main",
        "g32-p8-c0.5", "bottom_offset_cells", "bottom layer offset (cells)", "0b071fe"),
    Fix("contact at the particles' faces", "(same: the block on the incline fell 0.15 cells for a frame, sliding "
        "free, before it touched)", "incline_friction", "slide", "g32-p8-c0.5", "error", "|s - s_ref| / s_ref", "0b071fe"),
    Fix("contact at the particles' faces", "(same, finer grid)", "incline_friction", "slide", "g48-p8-c0.5", "error",
        "|s - s_ref| / s_ref", "0b071fe"),
    Fix("contact at the particles' faces", "(same)", "incline_friction", "slide", "g24-p8-c0.5", "error",
        "|s - s_ref| / s_ref", "0b071fe"),
    Fix("contact at the particles' faces", "(same, the block that should stick)", "incline_friction", "stick",
        "g32-p8-c0.5", "error", "|s| / s_free", "0b071fe"),
    Fix("ghost mirror mass", "with contact at the faces, the 0.8-cell block's ghost row read a mirror in the fringe "
        "above it (0.5 % of a node's mass) and a loop through it lifted the block off (18 mm); obstacle ghost nodes now "
        "read their mirror only where it holds MIRROR_MASS of their own mass, as cuboids' did", "incline_friction",
        "stick", "g16-p8-c0.5", "error", "|s| / s_free", "0b071fe"),
    Fix("contact at the particles' faces", "(side effect: the column's lowest layers no longer sink as a whole; the "
        "local compression at the floor, 0.005 cells between the lowest layers, now shows)", "self_weight", "main",
        "g32-p8-c0.5", "error", "relative shortening error", "0b071fe"),
    Fix("contact at the particles' faces", "(side effect, coarse grid)", "self_weight", "main", "g16-p8-c0.5", "error",
        "relative shortening error", "0b071fe"),
    Fix("contact at the particles' faces", "(side effect: the water column touches floor and back wall from the start "
        "instead of dropping 0.15 cells)", "dam_break", "main", "g24-p8-c0.5", "error", "mean relative front deviation",
        "0b071fe"),
    Fix("contact at the particles' faces", "(side effect, default grid)", "dam_break", "main", "g32-p8-c0.5", "error",
        "mean relative front deviation", "0b071fe"),
    Fix("contact at the particles' faces", "(side effect, finer grid: the front leads by 8 %; with the gate-removal "
        "shift 1.8 %, before 5.9 %)", "dam_break", "main", "g48-p8-c0.5", "error", "mean relative front deviation",
        "0b071fe"),
)


# ============================================================================ loading
def load_records(paths: Sequence[str | Path]) -> list[dict]:
    out = []
    for p in paths:
        with open(p) as f:
            out.append(json.load(f))
    return out


def snapshot(records: Sequence[dict], sweeps: Sequence[dict], label: str, prov: dict) -> dict:
    """A *before* snapshot: records and sweep counts with their provenance (data/before.json)."""
    slim = [{k: r[k] for k in ("case", "variant", "setting", "error", "sim_seconds", "substeps", "stable", "metrics")}
            for r in records]
    return {"label": label, "provenance": prov, "records": slim,
            "sweep": [{"pair": s["pair"], "counts": s["counts"], "scale": s["scale"]} for s in sweeps]}


def _metric(rec: dict | None, metric: str):
    if rec is None:
        return None
    if metric in ("error", "sim_seconds", "substeps"):
        return rec.get(metric)
    return (rec.get("metrics") or {}).get(metric)


# ============================================================================ error vs run time
def case_points(case: str, records: Sequence[dict], scale: str = "cpu") -> list[dict]:
    """One point per setting: the case's error (worst of the variants the scale runs) and run
    time (sum over them)."""
    by_setting: dict[str, list[dict]] = {}
    for r in records:
        if r["case"] == case:
            by_setting.setdefault(r["setting"], []).append(r)
    c = CASES[case]
    pts = []
    for sid, recs in sorted(by_setting.items(), key=lambda kv: Setting.parse(kv[0])):
        s = Setting.parse(sid)
        have = {r["variant"] for r in recs}
        complete = have >= set(c.variants_at(scale))
        errs = [r["error"] for r in recs]
        err = None if (not complete or any(e is None for e in errs)) else max(errs)
        pts.append({"case": case, "setting": sid, "n_grid": s.n_grid, "ppc": s.ppc, "cfl": s.cfl, "error": err,
                    "seconds": sum(r["sim_seconds"] for r in recs), "substeps": sum(r["substeps"] for r in recs),
                    "particles": max(r["n_particles"] for r in recs), "default": s == DEFAULT,
                    "failed": [r["variant"] for r in recs if r["error"] is None]})
    ok = [p for p in pts if p["error"] is not None]
    for p in pts:
        p["pareto"] = p["error"] is not None and not any(
            q is not p and q["seconds"] <= p["seconds"] and q["error"] <= p["error"]
            and (q["seconds"] < p["seconds"] or q["error"] < p["error"]) for q in ok)
    return pts


def convergence_order(pts: Sequence[dict]) -> float | None:
    """Slope of -log(error) against log(n_grid) over the resolution ladder (default ppc and CFL)."""
    lad = [(p["n_grid"], p["error"]) for p in pts if p["ppc"] == DEFAULT.ppc and p["cfl"] == DEFAULT.cfl
           and p["error"] is not None and p["error"] > 0]
    if len(lad) < 3:
        return None
    g, e = np.log([a for a, _ in lad]), np.log([b for _, b in lad])
    return float(-np.polyfit(g, e, 1)[0])


def case_figure(path: Path, case: str, pts: Sequence[dict], device: str) -> None:
    c = CASES[case]
    with R.figure(path, size=(6.4, 4.4)) as (fig, ax):
        ok = [p for p in pts if p["error"] is not None]
        floor = min([p["error"] for p in ok if p["error"] > 0] or [1e-8]) / 10
        for kind, mark, col in (("ppc", "s", "tab:green"), ("cfl", "^", "tab:purple"), ("grid", "o", "tab:blue")):
            sel = [p for p in ok if _kind(p) == kind]
            if sel:
                ax.scatter([p["seconds"] for p in sel], [max(p["error"], floor) for p in sel], marker=mark, c=col,
                           s=36, label={"grid": "n_grid ladder (ppc 8, CFL 0.5)", "ppc": "particles per cell",
                                        "cfl": "CFL number"}[kind], zorder=3)
        for p in ok:
            ax.annotate(p["setting"], (p["seconds"], max(p["error"], floor)), fontsize=6, xytext=(3, 3),
                        textcoords="offset points")
        front = sorted((p for p in ok if p["pareto"]), key=lambda p: p["seconds"])
        if front:
            ax.step([p["seconds"] for p in front], [max(p["error"], floor) for p in front], where="post", c="tab:red",
                    lw=1.5, label="Pareto front", zorder=2)
        d = [p for p in ok if p["default"]]
        if d:
            ax.scatter([d[0]["seconds"]], [max(d[0]["error"], floor)], s=180, facecolors="none", edgecolors="k", lw=1.5,
                       label="shipped defaults (g32-p8-c0.5)", zorder=4)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"simulation wall time (s, {device})")
        ax.set_ylabel("relative error")
        ax.set_title(c.title, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best")


def _kind(p: dict) -> str:
    if p["ppc"] != DEFAULT.ppc:
        return "ppc"
    if p["cfl"] != DEFAULT.cfl:
        return "cfl"
    return "grid"


# ============================================================================ the report
def _fmt_err(e) -> str:
    return R.NA if e is None else f"{100 * e:.3g}%"


def build(records: Sequence[dict], sweeps: Sequence[dict], out_dir: str | Path, *, scale: str, device: str,
          before: dict | None = None, figures: dict[str, str] | None = None) -> dict:
    """Write REPORT.md, the CSVs and the figures into ``out_dir``; return a summary dict."""
    out = Path(out_dir)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    prov = R.provenance(scale=scale, device=device)
    all_pts, summary_rows = [], []
    for name, c in CASES.items():
        pts = case_points(name, records, scale)
        if not pts:
            continue
        all_pts.extend(pts)
        fig = Path(figures[name]) if figures and name in figures else out / "figures" / f"{name}.png"
        case_figure(fig, name, pts, device)
        if c.has_physics_plot:
            with R.figure(out / "figures" / f"{name}_physics.png", size=(6.4, 4.2)) as (_, ax):
                c.physics_plot(ax, [r for r in records if r["case"] == name])
                ax.set_title(c.title, fontsize=10)
        ok = [p for p in pts if p["error"] is not None]
        d = next((p for p in pts if p["default"]), None)
        best = min(ok, key=lambda p: p["error"]) if ok else None
        front = sorted((p for p in ok if p["pareto"]), key=lambda p: p["seconds"])
        order = convergence_order(pts)
        summary_rows.append({
            "case": name, "default_error": d["error"] if d else None, "default_seconds": d["seconds"] if d else None,
            "default_on_front": bool(d and d["pareto"]),
            "best_error": best["error"] if best else None, "best_setting": best["setting"] if best else None,
            "best_seconds": best["seconds"] if best else None,
            "front": ", ".join(f"{p['setting']} ({_fmt_err(p['error'])}, {p['seconds']:.2g} s)" for p in front),
            "order": order, "failed": sum(1 for p in pts if p["error"] is None)})
    run_cols = [R.Column(k) for k in ("case", "variant", "setting", "error", "sim_seconds", "wall_seconds", "substeps",
                                      "n_particles", "stable")]
    flat = [{**{k: r[k] for k in ("case", "variant", "setting", "error", "sim_seconds", "wall_seconds", "substeps",
                                   "n_particles", "stable")}, **{f"m_{k}": v for k, v in (r.get("metrics") or {}).items()
                                                                 if not isinstance(v, (list, dict))}} for r in records]
    R.write_csv(out / "runs.csv", flat)
    R.write_csv(out / "error_vs_time.csv", all_pts, [R.Column(k) for k in (
        "case", "setting", "n_grid", "ppc", "cfl", "error", "seconds", "substeps", "particles", "default", "pareto")])
    R.write_csv(out / "summary.csv", summary_rows)
    sweep_rows = [c for s in sweeps for c in s["cells"]]
    R.write_csv(out / "sweep.csv", sweep_rows, [R.Column(k) for k in (
        "elasticity", "plasticity", "E", "nu", "density", "outcome", "failure", "substeps", "seconds", "message")])

    md = [f"# Physical validation (scale `{scale}`)\n", R.provenance_markdown(prov),
          "Every case runs through the production frame loop (adaptive CFL substeps, stability checks) at several "
          "settings of the accuracy knobs: `n_grid` (sim.n_grid), particles per cell (fill.particles_per_cell; a "
          "k x k x k lattice per cell) and the CFL number (sim.cfl).  Setting ids read `g<n_grid>-p<ppc>-c<cfl>`; "
          "the shipped defaults are `g32-p8-c0.5`.  Times are wall seconds of the substeps (kernel compilation "
          f"excluded) on the machine above ({device}); float64 is not supported (the kernels are f32).  Errors are "
          "relative (0 = exact); a case with variants reports its worst variant.\n",
          "## Error against run time (summary)\n",
          R.markdown_table(summary_rows, [
              R.Column("case"), R.Column("default_error", "error at defaults", "{:.3g}"),
              R.Column("default_seconds", "s at defaults", "{:.3g}"),
              R.Column("default_on_front", "defaults on the Pareto front"),
              R.Column("best_error", "best error", "{:.3g}"), R.Column("best_setting", "best setting"),
              R.Column("order", "observed order in n_grid", "{:.2f}"), R.Column("front", "Pareto front")]),
          "\n`observed order`: slope of -log(error) against log(n_grid) on the ladder (ppc 8, CFL 0.5); near 0 means "
          "the error does not shrink with resolution (see each case's notes).\n"]
    for name, c in CASES.items():
        pts = [p for p in all_pts if p["case"] == name]
        if not pts:
            continue
        recs = [r for r in records if r["case"] == name]
        md += [f"\n## {c.title} (`{name}`)\n", f"**Reference.** {c.reference}\n", f"**Error.** {c.error_doc}.\n",
               f"![{name}](figures/{name}.png)\n",
               *([f"![{name} against its reference](figures/{name}_physics.png)\n"] if c.has_physics_plot else []),
               *([f"**Notes.** {c.notes}\n"] if c.notes else []),
               R.markdown_table(pts, [R.Column("setting"), R.Column("error", "error", "{:.3g}"),
                                      R.Column("seconds", "s", "{:.3g}"), R.Column("substeps"),
                                      R.Column("particles"), R.Column("pareto", "Pareto"), R.Column("default")])]
        keys = sorted({k for r in recs for k, v in (r.get("metrics") or {}).items() if not isinstance(v, (list, dict))})
        if keys:
            rows = [{**r, **{f"m_{k}": v for k, v in (r.get("metrics") or {}).items()}}
                    for r in sorted(recs, key=lambda r: (r["variant"], Setting.parse(r["setting"])))]
            md += ["\nPer run:\n", R.markdown_table(
                rows, [R.Column("variant"), R.Column("setting"), R.Column("error", "error", "{:.3g}")]
                + [R.Column(f"m_{k}", k, "{:.4g}") for k in keys])]
        bad = [r for r in recs if r["error"] is None]
        for r in bad:
            md.append(f"\n- run {r['variant']} {r['setting']} failed: {r.get('message') or 'no measurement'}\n")

    counts = {o: sum(s["counts"][o] for s in sweeps) for o in OUTCOMES}
    md += ["\n## Stiff and extreme sweep\n",
           "A 0.16 m elastic cube dropped 1 cm onto a frictional floor, n_grid 16, 8 particles per cell, the pipeline's "
           "time stepping (CFL 0.5, at most 200 substeps per frame), 15 frames at 30 fps, for every elasticity x "
           "plasticity pair and E in {30, 3e3, 3e5, 3e7, 3e10} Pa, nu in {0, 0.3, 0.49}, density in {10, 1000, 2e4} "
           "kg/m^3 (smoke scale: a corner slice).  von Mises yield stress = 1e-3 E; friction angle 30 deg; j_clamp "
           "[0.6, 1.2].  Outcomes: `stable`; `error` = stopped with a message naming the instance, its parameters "
           "and the change to make; `nan` = a non-finite value handed out or a failure without such a message; "
           "`hang` = over the wall-clock bound.\n",
           f"**Total: {sum(counts.values())} cells: {counts['stable']} stable, {counts['error']} clear error, "
           f"{counts['nan']} NaN, {counts['hang']} hang.**\n",
           R.markdown_table([{"pair": s["pair"], **s["counts"], "seconds": s["seconds"],
                              "substeps": sum(c["substeps"] for c in s["cells"])} for s in sweeps],
                            [R.Column("pair"), *(R.Column(o) for o in OUTCOMES), R.Column("substeps"),
                             R.Column("seconds", "seconds", "{:.3g}")]),
           "\nEvery cell (E, nu, density, outcome, failure kind, substeps, seconds, message): `sweep.csv`.\n"]
    fails = {}
    for c in sweep_rows:
        if c["outcome"] == "error":
            fails[c.get("failure") or "config"] = fails.get(c.get("failure") or "config", 0) + 1
    if fails:
        md.append("Clear errors by kind: " + ", ".join(f"{k} {v}" for k, v in sorted(fails.items())) + ".\n")

    md += ["\n## Fixes: before and after\n"]
    if before is None:
        md.append("No before snapshot given (validation.before).\n")
    else:
        snaps = {None: before, **{e.get("label"): e for e in before.get("extra", [])}}
        for label, snap in snaps.items():
            bp = snap.get("provenance") or {}
            md.append(f"Before{'' if label is None else ' `' + str(label) + '`'} = `{snap.get('label')}`, measured "
                      f"{bp.get('date')} at commit `{bp.get('commit')}` on {(bp.get('machine') or {}).get('cpu')} "
                      f"({(bp.get('machine') or {}).get('cores')} cores).\n")
        md.append("After = this run.\n")
        idx_b = {k: {(r["case"], r["variant"], r["setting"]): r for r in snap.get("records", [])}
                 for k, snap in snaps.items()}
        idx_a = {(r["case"], r["variant"], r["setting"]): r for r in records}
        rows = []
        for f in FIXES:
            key = (f.case, f.variant, f.setting)
            rows.append({"fix": f.name, "what": f.what, "run": f"{f.case} {f.variant} {f.setting}", "measure": f.label,
                         "before at": snaps[f.snapshot].get("label") if f.snapshot in snaps else f.snapshot,
                         "before": _metric(idx_b.get(f.snapshot, {}).get(key), f.metric),
                         "after": _metric(idx_a.get(key), f.metric)})
        md.append(R.markdown_table(rows, [R.Column("fix"), R.Column("run"), R.Column("measure"), R.Column("before at"),
                                          R.Column("before", "before", "{:.4g}"), R.Column("after", "after", "{:.4g}"),
                                          R.Column("what")]))
        bs = {s["pair"]: s["counts"] for s in before.get("sweep", [])}
        if bs:
            tb = {o: sum(c[o] for c in bs.values()) for o in OUTCOMES}
            md.append(f"\nSweep before: {sum(tb.values())} cells ({len(bs)} pairs): " +
                      ", ".join(f"{tb[o]} {o}" for o in OUTCOMES) + ".\n")
        md.append("\n`n/a`: not measured in that snapshot (or at this scale).\n")
    with atomic_path(out / "REPORT.md") as tmp:
        Path(tmp).write_text("\n".join(md))
    return {"cases": len(summary_rows), "runs": len(records), "sweep": counts}
