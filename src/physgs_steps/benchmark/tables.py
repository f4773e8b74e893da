"""The rows of the benchmark's tables, built from the runs' outputs through :mod:`.readers`.

Every value is a :class:`~.readers.Cell`: a number (or text) or ``None`` with the reason; the
report prints ``n/a`` with the reason as a footnote. Aggregates over scenes use the scenes that
have a value and say so ("k of n scenes") when some have none.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import physical as PH
from . import published as PUB
from . import readers as RD
from .readers import Cell, missing

STAGES = (  # (row, rules): the paper's Table 3 columns plus final sim and render
    ("IPF", ("fill",)),
    ("BGDO forward", ("forward_sim",)),
    ("BGDO backward", ("bgdo_update",)),
    ("final sim", ("final_sim",)),
    ("render", ("render",)),
    ("full", None),
)


# ----------------------------------------------------------------------------------- per run
@dataclass
class RunData:
    """What one run (scene x variant) produced, read once."""

    rec: dict
    metrics: dict | None = None
    metrics_reason: str | None = None
    stats: dict | None = None
    stats_reason: str | None = None
    params: dict | None = None
    params0: dict | None = None
    jobs: list = field(default_factory=list)
    penetration: dict = field(default_factory=dict)
    forward_stats: list = field(default_factory=list)

    @property
    def physical(self) -> dict:
        return RD.physical(self.metrics, self.stats)


def load_run(rec: dict, penetration: bool = True) -> RunData:
    d = RunData(rec)
    if rec.get("render"):
        d.metrics, d.metrics_reason = RD.read_json(rec.get("metrics"))
    d.stats, d.stats_reason = RD.final_stats(rec.get("final"))
    d.params, _ = RD.read_json(rec.get("params"))
    d.params0, _ = RD.read_json(rec.get("params0"))
    d.jobs = [RD.job_record(j) for j in rec.get("jobs") or []]
    d.forward_stats = [RD.forward_stats(p) for p in rec.get("forward") or []]
    if penetration and Path(rec.get("final", "")).is_file():
        d.penetration = PH.penetration(rec["final"], rec.get("labels"), rec.get("ground_height"),
                                       rec.get("domain_size", 1.0), particles_h5=rec.get("particles"))
    return d


def run_minutes(d: RunData) -> Cell:
    """Wall time of every job the run needs (shared upstream jobs included), in minutes."""
    secs = [j["seconds"] for j in d.jobs]
    if not secs:
        return missing("no jobs")
    if any(s is None for s in secs):
        bad = [j["rule"] for j in d.jobs if j["seconds"] is None]
        return missing(f"no benchmark file for {', '.join(sorted(set(bad)))}")
    return Cell(sum(secs) / 60.0)


def run_peak_rss_gb(d: RunData) -> Cell:
    v = [j["max_rss_mb"] for j in d.jobs if j["max_rss_mb"] is not None]
    return Cell(max(v) / 1024.0) if v else missing("no peak memory in the benchmark files")


def run_peak_gpu_gb(d: RunData, device: str) -> Cell:
    v = [j["cuda_peak_mb"] for j in d.jobs if j["cuda_peak_mb"] is not None]
    dev = RD.device_memory_mb(d.stats)
    if dev is not None and (d.stats or {}).get("backend") not in (None, "cpu", "x64", "arm64"):
        v.append(dev)
    if v:
        return Cell(max(v) / 1024.0)
    return missing("no GPU was used (CPU run)" if device != "cuda" else "no stage recorded GPU memory")


def physical_cells(d: RunData) -> dict:
    ph = d.physical
    out = {
        "stable": RD.run_stable(d.stats),
        "in_domain": RD.check(ph, "stayed_in_domain"),
        "finite": RD.check(ph, "finite"),
        "J_min": RD.figure(ph, "det_F_min"),
        "J_max": RD.figure(ph, "det_F_max"),
        "non_finite": RD.figure(ph, "non_finite_count"),
        "max_disp": RD.figure(ph, "max_displacement"),
    }
    if not d.rec.get("render"):
        why = "no metrics for this run (robustness runs are not rendered)"
        out.update({k: missing(why) for k in ("in_domain", "finite", "J_min", "J_max", "non_finite", "max_disp")})
    pen = d.penetration or {}
    for k in ("ground_penetration_mm", "instance_penetration"):
        c = RD.figure(ph, k)  # a future metrics stage may compute it; else ours from final.h5
        out[k] = c if c.ok else pen.get(k, missing("final.h5 not available"))
    if out["stable"].ok and out["stable"].value is False:
        n = (d.stats or {}).get("frames_written")
        out["stable"] = Cell(False, note=f"unstable after {n} frames: {out['stable'].note}" if n else out["stable"].note)
    return out


def scores(d: RunData) -> dict:
    why = d.metrics_reason if d.rec.get("render") else "no metrics for this run"
    return {k: RD.score(d.metrics, k, why) for k in ("CS", "AS", "SA", "PC")}


# ----------------------------------------------------------------------------------- aggregates
def mean_cell(cells: list[Cell]) -> Cell:
    vals = [float(c.value) for c in cells if c.ok and not isinstance(c.value, bool)]
    if not vals:
        reasons = sorted({c.reason for c in cells if c.reason})
        return missing("; ".join(reasons) or "no value")
    note = None if len(vals) == len(cells) else f"{len(vals)} of {len(cells)} scenes"
    notes = sorted({c.note for c in cells if c.ok and c.note})
    if notes:
        note = "; ".join(([note] if note else []) + notes)
    return Cell(float(np.mean(vals)), note=note)


def agg_cell(cells: list[Cell], fn) -> Cell:
    vals = [float(c.value) for c in cells if c.ok and not isinstance(c.value, bool)]
    if not vals:
        reasons = sorted({c.reason for c in cells if c.reason})
        return missing("; ".join(reasons) or "no value")
    note = None if len(vals) == len(cells) else f"{len(vals)} of {len(cells)} scenes"
    return Cell(float(fn(vals)), note=note)


def count_cell(cells: list[Cell]) -> Cell:
    """'k/n' of boolean cells that are True."""
    known = [c for c in cells if c.ok]
    if not known:
        reasons = sorted({c.reason for c in cells if c.reason})
        return missing("; ".join(reasons) or "no value")
    k = sum(bool(c.value) for c in known)
    note = None if len(known) == len(cells) else f"{len(known)} of {len(cells)} known"
    return Cell(f"{k}/{len(known)}", note=note)


def method_row(method: str, source: str, runs: list[RunData], device: str) -> dict:
    """One row of the comparison / ablation table: a variant averaged over scenes."""
    sc = [scores(d) for d in runs]
    ph = [physical_cells(d) for d in runs]
    row = {"method": method, "source": source}
    for k in ("CS", "AS", "SA", "PC"):
        row[k] = mean_cell([s[k] for s in sc])
    row["stable"] = count_cell([p["stable"] for p in ph])
    row["in_domain"] = count_cell([p["in_domain"] for p in ph])
    row["ground_penetration_mm"] = agg_cell([p["ground_penetration_mm"] for p in ph], max)
    row["instance_penetration"] = agg_cell([p["instance_penetration"] for p in ph], max)
    row["J_min"] = agg_cell([p["J_min"] for p in ph], min)
    row["J_max"] = agg_cell([p["J_max"] for p in ph], max)
    row["non_finite"] = agg_cell([p["non_finite"] for p in ph], sum)
    row["memory_gb"] = agg_cell([run_peak_rss_gb(d) for d in runs], max)
    row["gpu_gb"] = agg_cell([run_peak_gpu_gb(d, device) for d in runs], max)
    row["minutes"] = mean_cell([run_minutes(d) for d in runs])
    if row["gpu_gb"].ok:  # the paper's memory column is GPU memory
        row["memory"] = Cell(row["gpu_gb"].value, note="GPU")
    elif row["memory_gb"].ok:
        row["memory"] = Cell(row["memory_gb"].value, note="RAM; no GPU memory recorded")
    else:
        row["memory"] = row["memory_gb"]
    return row


def published_row(p: dict) -> dict:
    nr = missing("not reported in the paper")
    row = {"method": p["method"], "source": PUB.SOURCE}
    for k in ("CS", "AS", "SA", "PC"):
        row[k] = Cell(p[k]) if p.get(k) is not None else nr
    for k in ("stable", "in_domain", "ground_penetration_mm", "instance_penetration", "J_min", "J_max", "non_finite",
              "gpu_gb"):
        row[k] = nr
    row["memory"] = Cell(p["memory_gb"], note="GPU") if p.get("memory_gb") is not None else nr
    row["minutes"] = Cell(p["minutes"]) if p.get("minutes") is not None else nr
    return row


def scene_row(d: RunData, device: str) -> dict:
    sc, ph = scores(d), physical_cells(d)
    return {"scene": d.rec["scene"], "variant": d.rec["variant"], **sc, **ph, "memory_gb": run_peak_rss_gb(d),
            "gpu_gb": run_peak_gpu_gb(d, device), "minutes": run_minutes(d)}


# ----------------------------------------------------------------------------------- stages
def stage_rows(runs: list[RunData], device: str, published: bool) -> tuple[list[dict], list[dict]]:
    """(rows averaged over scenes, per-scene rows) of the stage time and memory table."""
    per_scene = []
    for d in runs:
        for stage, rules in STAGES:
            jobs = [j for j in d.jobs if rules is None or j["rule"] in rules]
            rec = {"scene": d.rec["scene"], "stage": stage, "jobs": len(jobs)}
            if not jobs:
                why = ("bgdo.iterations is 0" if stage.startswith("BGDO") else f"no {stage} job")
                rec.update(seconds=missing(why), stage_seconds=missing(why), rss_gb=missing(why), gpu_gb=missing(why))
            else:
                secs = [j["seconds"] for j in jobs]
                rec["seconds"] = Cell(sum(secs)) if all(s is not None for s in secs) else \
                    missing("a job has no benchmark file")
                ss = [j["stage_seconds"] for j in jobs]
                rec["stage_seconds"] = Cell(sum(ss)) if all(s is not None for s in ss) else \
                    missing("a job's log has no stage summary")
                rss = [j["max_rss_mb"] for j in jobs if j["max_rss_mb"] is not None]
                rec["rss_gb"] = Cell(max(rss) / 1024.0) if rss else missing("no peak memory in the benchmark files")
                gpu = [j["cuda_peak_mb"] for j in jobs if j["cuda_peak_mb"] is not None]
                sims = ([d.stats] if stage in ("final sim", "full") else []) + \
                    (d.forward_stats if stage in ("BGDO forward", "full") else [])
                gpu += [RD.device_memory_mb(st) for st in sims
                        if RD.device_memory_mb(st) is not None and (st or {}).get("backend") == "cuda"]
                rec["gpu_gb"] = Cell(max(gpu) / 1024.0) if gpu else missing(
                    "no GPU was used (CPU run)" if device != "cuda" else "the stage records no GPU memory")
            per_scene.append(rec)
    rows = []
    for stage, _ in STAGES:
        mine = [r for r in per_scene if r["stage"] == stage]
        secs = [r["seconds"] for r in mine]
        row = {"stage": stage, "scenes": len(mine),
               "seconds": mean_cell(secs), "seconds_min": agg_cell(secs, min), "seconds_max": agg_cell(secs, max),
               "stage_seconds": mean_cell([r["stage_seconds"] for r in mine]),
               "rss_gb": agg_cell([r["rss_gb"] for r in mine], max), "gpu_gb": agg_cell([r["gpu_gb"] for r in mine], max)}
        pub = PUB.STAGES.get(stage) if published else None
        nr = missing("not in the paper's Table 3" if published else "benchmark.published is false")
        row["published_time"] = Cell(pub["time"], note=PUB.SOURCE) if pub else nr
        row["published_memory"] = Cell(pub["memory"], note=PUB.SOURCE) if pub else nr
        rows.append(row)
    return rows, per_scene


# ----------------------------------------------------------------------------------- robustness
def robustness_rows(by_key: dict, scenes: list[str], E0s: list[float], kb_path: str | None = None) -> list[dict]:
    """Per scene, instance and start: band, E0 -> E1 -> ... , in band, final stable with and
    without BGDO. ``by_key``: (scene, variant) -> RunData."""
    rows = []
    for s in scenes:
        starts = [("KB", by_key.get((s, "physgs")), by_key.get((s, "no_bgdo")))]
        starts += [(f"{e:g}", by_key.get((s, f"e0_{_tag(e)}")), by_key.get((s, f"e0_{_tag(e)}_no_bgdo"))) for e in E0s]
        base = by_key.get((s, "physgs"))
        insts = RD.instances(base.params0 if base else None)
        for start, with_b, without_b in starts:
            if with_b is None:
                continue
            hist = RD.E_history(with_b.params0, with_b.params)
            recs = RD.bgdo_record(with_b.params)
            stable = RD.run_stable(with_b.stats)
            no_b = RD.run_stable(without_b.stats) if without_b else missing("robustness.without_bgdo is false")
            for inst in insts:
                k = inst["label"]
                band = (recs.get(k) or {}).get("band") or RD.material_band(inst.get("material"), kb_path)
                chain = hist.get(k) or []
                E_last = chain[-1] if chain else None
                rows.append({
                    "scene": s, "instance": f"{inst.get('name')} ({inst.get('material')})", "start": start,
                    "band": Cell(f"{band[0]:.0e}-{band[1]:.0e}") if band else missing("material not in the knowledge base"),
                    "E_chain": Cell(" -> ".join(f"{e:.3g}" for e in chain)) if chain else missing("no params.json"),
                    "E_final": Cell(E_last) if E_last is not None else missing("no params.json"),
                    "in_band": Cell(bool(band[0] <= E_last <= band[1])) if band and E_last is not None else
                    missing("no band or no E"),
                    "fate": _fate(recs.get(k)),
                    "stable": stable, "stable_without_bgdo": no_b,
                })
    return rows


def _fate(rec: dict | None) -> Cell:
    """The last BGDO update's fate and rule of an instance (ok / exploded / broken, and how E was set)."""
    if not rec:
        return missing("no BGDO update (bgdo.iterations 0)")
    fate, rule = str(rec.get("fate")), str(rec.get("rule") or "")
    if rule == "rigid":  # a rigid body or static geometry: its E does not enter the simulation
        return Cell("rigid: skipped by BGDO")
    if rule.startswith(fate + ":"):
        rule = rule.split(":", 1)[1].strip()
    text = f"{fate} ({rule})" if rule else fate
    if rec.get("capped_by_ceiling"):
        text += " (solver ceiling)"
    return Cell(text)


def _tag(e: float) -> str:
    from .spec import e0_tag

    return e0_tag(e)


# ----------------------------------------------------------------------------------- fill
def fill_rows(runs: list[RunData]) -> list[dict]:
    """Per scene and filling method (every distinct fill of the scene's runs)."""
    rows, seen = [], set()
    for d in runs:
        key = (d.rec["scene"], d.rec["fill_id"])
        if key in seen:
            continue
        seen.add(key)
        rep, why = RD.read_json(d.rec.get("fill_report"))
        q = RD.fill_quality(rep)
        rows.append({"scene": d.rec["scene"], "method": d.rec["fill_label"], **q})
    return rows


# ----------------------------------------------------------------------------------- BGDO change
def bgdo_change_row(scene: str, with_b: RunData | None, without_b: RunData | None) -> dict:
    """Final-frame difference between the BGDO and the no-BGDO run of a scene."""
    row = {"scene": scene}
    if with_b is None or without_b is None:
        r = missing("the physgs or the no_bgdo run is missing")
        return {**row, **{k: r for k in ("E_kb", "E_bgdo", "diff_mean_mm", "diff_max_mm", "disp_mean_mm", "ratio",
                                          "frame")}}
    E0, E1 = RD.params_E(without_b.params), RD.params_E(with_b.params)
    row["E_kb"] = Cell(", ".join(f"{E0[k]:.3g}" for k in sorted(E0))) if E0 else missing("no params.json")
    row["E_bgdo"] = Cell(", ".join(f"{E1[k]:.3g}" for k in sorted(E1))) if E1 else missing("no params.json")
    diff = final_difference(with_b.rec["final"], without_b.rec["final"], with_b.rec.get("domain_size", 1.0))
    row.update(diff)
    return row


def final_difference(a: str, b: str, domain_size: float) -> dict:
    """Mean and max distance (mm) between the same gaussians (or stored particles) in two
    final.h5 at their last common frame, and the mean displacement of run ``a`` from its first
    frame (mm)."""
    import h5py

    out = {}
    try:
        with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
            va, vb = RD.FinalView(fa), RD.FinalView(fb)
            if va.index is None or vb.index is None or va.index_of != vb.index_of:
                r = missing("the two final.h5 do not say which gaussians or particles they hold")
                return {k: r for k in ("diff_mean_mm", "diff_max_mm", "disp_mean_mm", "ratio", "frame")}
            common, pa, pb = np.intersect1d(va.index, vb.index, return_indices=True)
            if common.size == 0:
                r = missing(f"the two runs share no {va.index_of[:-1]}")
                return {k: r for k in ("diff_mean_mm", "diff_max_mm", "disp_mean_mm", "ratio", "frame")}
            t = min(va.n_frames, vb.n_frames) - 1
            xa, xb = va.x(t)[pa], vb.x(t)[pb]
            x0 = va.x(0)[pa]
    except (OSError, KeyError) as e:
        r = missing(f"cannot read final.h5: {e}")
        return {k: r for k in ("diff_mean_mm", "diff_max_mm", "disp_mean_mm", "ratio", "frame")}
    d = np.linalg.norm(xa - xb, axis=1)
    disp = np.linalg.norm(xa - x0, axis=1)
    ok = np.isfinite(d) & np.isfinite(disp)
    if not ok.any():
        r = missing("no finite position at the compared frame")
        return {k: r for k in ("diff_mean_mm", "diff_max_mm", "disp_mean_mm", "ratio", "frame")}
    scale = domain_size * 1000.0
    out["diff_mean_mm"] = Cell(float(d[ok].mean()) * scale)
    out["diff_max_mm"] = Cell(float(d[ok].max()) * scale)
    out["disp_mean_mm"] = Cell(float(disp[ok].mean()) * scale)
    m = float(disp[ok].mean())
    out["ratio"] = Cell(float(d[ok].mean()) / m) if m > 0 else missing("the BGDO run does not move")
    out["frame"] = Cell(int(t))
    return out


# ----------------------------------------------------------------------------------- stress
def stress_rows(docs: list[dict]) -> list[dict]:
    rows = []
    for r in sorted(docs, key=lambda r: r.get("E", math.inf)):
        st = r.get("stress") or {}
        none = missing(st.get("reason") or "no stress sample")
        rows.append({
            "E": Cell(r.get("E")), "forward": Cell("stable" if r.get("stable") else "unstable"),
            "fate": Cell(r.get("fate")) if r.get("fate") else missing("no fate recorded"),
            "E_after": Cell(r["E_after"]) if r.get("E_after") is not None else missing("no BGDO result"),
            "G": Cell(r["G"]) if r.get("G") is not None else missing("no BGDO step (G undefined)"),
            "delta": Cell(r["delta"]) if r.get("delta") is not None else missing("no key frame after frame 0"),
            "stress_median": Cell(st["median"]) if st.get("n") else none,
            "stress_p10": Cell(st["p10"]) if st.get("n") else none,
            "stress_p90": Cell(st["p90"]) if st.get("n") else none,
            "seconds": Cell(sum((r.get("seconds") or {}).values())) if r.get("seconds") else missing("no timing"),
        })
    return rows
