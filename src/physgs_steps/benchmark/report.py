"""Stages ``benchmark_stages`` and ``benchmark_report``: the benchmark's tables, CSVs, figures
and REPORT.md from the runs listed in the spec's manifest (physgs_steps.benchmark.spec).

``benchmark_stages``  cfg {"scale", "device", "published", "runs": [physgs run records]}
                      outputs {"md": stages.md, "csv": tables/stages.csv, "json": stages.json}
``benchmark_report``  cfg: the manifest (BenchmarkSpec.manifest) plus "stages_json"
                      outputs {"report": REPORT.md, "data": report.json, "tables": [csv...],
                      "figures": figures/ (a folder)}

A value that cannot be computed prints ``n/a [k]``; note [k] at the end of the report says
why. Published numbers are marked "published, RTX A6000" (physgs_steps.benchmark.published).
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from .. import reporting as R
from ..runtime import atomic_path, write_json
from . import figures as FG
from . import published as PUB
from . import readers as RD
from . import tables as T
from .readers import Cell

TABLES = ("comparison", "comparison_scenes", "ablations", "robustness", "fill", "bgdo_change", "stress_vs_E")


# ----------------------------------------------------------------------------------- formatting
class Notes:
    """Numbered footnotes of a report (one number per distinct text)."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def ref(self, text: str) -> str:
        text = " ".join(str(text).split())
        if text not in self.texts:
            self.texts.append(text)
        return f"[{self.texts.index(text) + 1}]"

    def markdown(self) -> str:
        if not self.texts:
            return ""
        return "\n".join(f"[{i + 1}] {t}  " for i, t in enumerate(self.texts)) + "\n"


class Col:
    def __init__(self, key: str, header: str, fmt: str = "{}"):
        self.key, self.header, self.fmt = key, header, fmt


def cell_text(v, fmt: str, notes: Notes) -> str:
    if isinstance(v, Cell):
        if not v.ok:
            return "n/a " + notes.ref(v.reason or "no value")
        text = R.format_value(v.value, fmt)
        if v.note:
            text += f" ({v.note})" if len(v.note) <= 40 else " " + notes.ref(v.note)
        return text
    return R.format_value(v, fmt)


def md_table(rows: list[dict], cols: list[Col], notes: Notes, empty: str = "no rows at this scale") -> str:
    if not rows:
        return f"_({empty})_\n"
    return R.markdown_table([{c.key: cell_text(r.get(c.key), c.fmt, notes) for c in cols} for r in rows],
                            [R.Column(c.key, c.header) for c in cols])


def csv_rows(rows: list[dict], cols: list[Col]) -> tuple[list[dict], list[R.Column]]:
    """Raw values (None for n/a) plus a ``notes`` column with the reasons and qualifiers."""
    out = []
    for r in rows:
        o, notes = {}, []
        for c in cols:
            v = r.get(c.key)
            if isinstance(v, Cell):
                o[c.key] = v.value
                if not v.ok:
                    notes.append(f"{c.key}: n/a ({v.reason})")
                elif v.note:
                    notes.append(f"{c.key}: {v.note}")
            else:
                o[c.key] = v
        o["notes"] = "; ".join(notes) or None
        out.append(o)
    return out, [R.Column(c.key) for c in cols] + [R.Column("notes")]


def write_table(path: str | Path, rows: list[dict], cols: list[Col]) -> None:
    data, columns = csv_rows(rows, cols)
    R.write_csv(path, data, columns)


SCORE_COLS = [Col("CS", "CS", "{:.3f}"), Col("AS", "AS", "{:.2f}"), Col("SA", "SA", "{:.2f}"), Col("PC", "PC", "{:.2f}")]
PHYS_COLS = [Col("stable", "final run stable"), Col("in_domain", "stayed in domain"),
             Col("ground_penetration_mm", "ground pen. (mm)", "{:.1f}"),
             Col("instance_penetration", "inst. pen. (share)", "{:.3f}"),
             Col("J_min", "det F min", "{:.3f}"), Col("J_max", "det F max", "{:.3f}"),
             Col("non_finite", "NaN/inf", "{:.0f}")]
COST_COLS = [Col("memory_gb", "peak RAM (GB)", "{:.2f}"), Col("gpu_gb", "peak GPU (GB)", "{:.2f}"),
             Col("minutes", "minutes", "{:.2f}")]
PAPER_COLS = [Col("method", "method"), Col("source", "source"), *SCORE_COLS, Col("memory", "memory (GB)", "{:.2f}"),
              Col("minutes", "time (min)", "{:.2f}")]
METHOD_COLS = [Col("method", "method"), *PHYS_COLS, *COST_COLS]
SCENE_COLS = [Col("scene", "scene"), Col("variant", "variant"), *SCORE_COLS, *PHYS_COLS, *COST_COLS]
STAGE_COLS = [Col("stage", "stage"), Col("scenes", "scenes"), Col("seconds", "time (s)", "{:.1f}"),
              Col("seconds_min", "min (s)", "{:.1f}"), Col("seconds_max", "max (s)", "{:.1f}"),
              Col("stage_seconds", "in stage (s)", "{:.1f}"), Col("rss_gb", "peak RAM (GB)", "{:.2f}"),
              Col("gpu_gb", "peak GPU (GB)", "{:.2f}"), Col("published_time", "time, published"),
              Col("published_memory", "memory, published")]
ROBUST_COLS = [Col("scene", "scene"), Col("instance", "instance (material)"), Col("band", "band (Pa)"),
               Col("start", "start E0 (Pa)"), Col("E_chain", "E0 -> E1 -> ... (Pa)"), Col("in_band", "in band"),
               Col("fate", "last BGDO update: fate (rule)"), Col("stable", "final stable (BGDO)"),
               Col("stable_without_bgdo", "final stable (no BGDO)")]
FILL_COLS = [Col("scene", "scene"), Col("method", "method"), Col("n_filled", "filled", "{:.0f}"),
             Col("precision", "precision", "{:.3f}"), Col("recall", "recall", "{:.3f}"),
             Col("recall_gaussians_only", "recall, gaussians only", "{:.3f}"), Col("leakage", "leakage"),
             Col("seconds", "seconds", "{:.2f}")]
CHANGE_COLS = [Col("scene", "scene"), Col("E_kb", "E without BGDO (Pa)"), Col("E_bgdo", "E with BGDO (Pa)"),
               Col("frame", "frame"), Col("diff_mean_mm", "mean difference (mm)", "{:.2f}"),
               Col("diff_max_mm", "max difference (mm)", "{:.2f}"), Col("disp_mean_mm", "mean displacement (mm)", "{:.2f}"),
               Col("ratio", "difference / displacement", "{:.3f}")]
STRESS_COLS = [Col("E", "initial E (Pa)", "{:.3g}"), Col("forward", "forward run"), Col("fate", "fate"),
               Col("E_after", "E after BGDO (Pa)", "{:.3g}"), Col("G", "G", "{:.3f}"), Col("delta", "delta", "{:.4f}"),
               Col("stress_median", "stress median (Pa)", "{:.3g}"), Col("stress_p10", "p10 (Pa)", "{:.3g}"),
               Col("stress_p90", "p90 (Pa)", "{:.3g}"), Col("seconds", "seconds", "{:.1f}")]


def _provenance(cfg: dict) -> dict:
    s = cfg.get("sizes") or {}
    return R.provenance(scale=cfg.get("scale"), device=cfg.get("device"),
                        sizes=f"{s.get('n_gaussians') or 'scene default'} gaussians per built-in scene, grid "
                              f"{s.get('n_grid')}, {s.get('n_frames')} frames, {s.get('bgdo_iterations')} BGDO "
                              f"iteration(s), video {'x'.join(str(v) for v in s.get('render') or [])}" if s else None)


# ----------------------------------------------------------------------------------- stage table
def run_stages(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    runs = [T.load_run(r, penetration=False) for r in cfg["runs"]]
    rows, per_scene = T.stage_rows(runs, cfg.get("device", "auto"), bool(cfg.get("published", True)))
    notes = Notes()
    prov = _provenance(cfg)
    prov.update(backends_used(runs))
    md = [f"# Stage time and memory (scale: {cfg['scale']})\n", R.provenance_markdown(prov),
          "Averaged over the scenes' physgs runs (min/max over scenes); time = wall seconds of the stage's "
          "job(s) from Snakemake's benchmark files (process start-up included), in stage = inside the stage "
          "function (start-up excluded); BGDO forward/backward sum their iterations; full = every job of the "
          "run. Jobs that ran side by side (`--cores` > 1) slow each other down.\n",
          md_table(rows, STAGE_COLS, notes), "\n", notes.markdown()]
    with atomic_path(outputs["md"]) as tmp:
        tmp.write_text("\n".join(md))
    write_table(outputs["csv"], rows, STAGE_COLS)
    write_json(outputs["json"], {"provenance": prov, "rows": [_plain(r) for r in rows],
                                 "per_scene": [_plain(r) for r in per_scene]})
    log.info("stage table of %d scenes -> %s", len(runs), outputs["md"])
    return {"scenes": len(runs)}


def _plain(row: dict) -> dict:
    return {k: (v.to_dict() if isinstance(v, Cell) else v) for k, v in row.items()}


def _cells(row: dict) -> dict:
    return {k: (Cell(v.get("value"), v.get("reason"), v.get("note")) if isinstance(v, dict) and "value" in v else v)
            for k, v in row.items()}


# ----------------------------------------------------------------------------------- the report
def run_report(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    t0 = time.perf_counter()
    out_dir = Path(outputs["report"]).parent
    fig_dir = Path(outputs["figures"])
    fig_dir.mkdir(parents=True, exist_ok=True)
    tables_dir = out_dir / "tables"
    device = cfg.get("device", "auto")
    data = {(r["scene"], r["variant"]): T.load_run(r) for r in cfg["runs"]}
    log.info("read %d runs in %.1f s", len(data), time.perf_counter() - t0)
    variants = cfg["variants"]
    scenes = cfg["scenes"]
    notes = Notes()
    prov = _provenance(cfg)
    prov.update(backends_used(data.values()))
    pub = bool(cfg.get("published", True))
    md = [f"# physgs benchmark (scale: {cfg['scale']})\n",
          "The paper's tables and figures regenerated by `snakemake benchmark` "
          f"(`--config benchmark='{{scale: {cfg['scale']}}}'`) from cached workflow runs under "
          f"`runs/`. Published numbers are quoted from the paper and marked \"{PUB.SOURCE}\"; ours are measured "
          "by this run. `n/a [k]`: not computed, note [k] at the end says why.\n",
          R.provenance_markdown(prov)]
    rows_out: dict[str, list] = {}

    def runs_of(variant: str) -> list:
        return [data[(s, variant)] for s in scenes if (s, variant) in data]

    # 1. comparison
    src = f"ours, {cfg['scale']}, {len(scenes)} scene(s)"
    ours = [T.method_row(v["label"], src, runs_of(v["name"]), device) for v in variants
            if v["role"] in ("physgs", "baseline")]
    comp = ([T.published_row(p) for p in PUB.COMPARISON] if pub else []) + ours
    rows_out["comparison"] = comp
    md += ["## 1. Comparison (paper Table 1)\n",
           "Rows marked published are quoted from the paper (other methods' results as the paper reports them); "
           "ours are this engine's physgs pipeline and a PhysGaussian-style configuration of it (global filling, "
           "knowledge-base parameters, no BGDO), averaged over the scenes. CS/AS/SA/PC need metric weights "
           "(README \"Regenerating the benchmark\"). Memory: the paper's is GPU memory; ours is the peak GPU "
           "memory a stage recorded, or the peak RAM of the run's jobs on a CPU run. Time: the summed wall time "
           "of every job the run needs (shared upstream jobs included), from Snakemake's benchmark files.\n",
           md_table(comp, PAPER_COLS, notes), "\n",
           "### 1b. Weight-free physical figures (ours)\n",
           "Final run stable; stayed in the domain; deepest ground penetration; largest share of an instance's "
           "gaussians that entered another instance's convex hull (beyond the share at frame 0); det F range "
           "(volume change); NaN/inf count; peak RAM and GPU memory; minutes.\n",
           md_table(ours, METHOD_COLS, notes), "\n"]
    per_scene = [T.scene_row(data[(s, v["name"])], device) for s in scenes for v in variants
                 if v["render"] and (s, v["name"]) in data]
    rows_out["comparison_scenes"] = per_scene
    md += ["### 1c. Every scene and variant\n", md_table(per_scene, SCENE_COLS, notes), "\n"]

    # 2. stages
    stages = json.loads(Path(inputs["stages"]).read_text())
    st_rows = [_cells(r) for r in stages["rows"]]
    md += ["## 2. Stage time and memory (paper Table 3)\n",
           "physgs runs, averaged over scenes with min/max; time = job wall seconds (process start-up "
           "included), in stage = inside the stage function. Also `stages.md` / `tables/stages.csv` "
           "(`snakemake benchmark_stages`).\n", md_table(st_rows, STAGE_COLS, notes), "\n"]

    # 3. ablations
    ours = [T.method_row(v["label"] if v["role"] != "physgs" else "full (physgs)", src, runs_of(v["name"]), device)
            for v in variants if v["role"] in ("ablation", "ablation_extra", "physgs")]
    abl = ([T.published_row(p) for p in PUB.ABLATIONS] if pub else []) + ours
    rows_out["ablations"] = abl
    md += ["## 3. Ablations (paper Table 4)\n",
           "Each of our rows changes one thing of the full pipeline (the `ablations` of config/config.yaml). The "
           "paper's \"w/o BGDO\" row starts from corrupted moduli; ours keeps the knowledge-base E (the corrupted "
           "starts are section 4).\n", md_table(abl, PAPER_COLS, notes), "\n",
           "### 3b. Weight-free physical figures of the ablations (ours)\n", md_table(ours, METHOD_COLS, notes), "\n"]

    # 4. robustness + stress figure
    rob = T.robustness_rows(data, cfg["robustness_scenes"], cfg["E0"])
    rows_out["robustness"] = rob
    n_in = sum(1 for r in rob if r["in_band"].ok and r["in_band"].value)
    n_st = sum(1 for r in rob if r["stable"].ok and r["stable"].value)
    md += ["## 4. BGDO robustness (paper Sec. 5.3, \"W/o BGDO\")\n",
           f"Every built-in scene started from E0 = {', '.join(f'{e:g}' for e in cfg['E0'])} Pa (every instance) "
           "and from its knowledge-base E (KB), then BGDO; band = the material's E_range in the knowledge base. "
           f"{n_in} of {len(rob)} instance starts end in their band, {n_st} of {len(rob)} final runs are stable "
           "with BGDO. A run that failed is a row saying so (`sim.on_unstable: keep`).\n",
           md_table(rob, ROBUST_COLS, notes, "no built-in scene at this scale"), "\n"]
    stress_docs = [json.loads(Path(p).read_text()) for p in inputs.get("stress") or []]
    srows = T.stress_rows(stress_docs)
    rows_out["stress_vs_E"] = srows
    st = cfg["stress"]
    band = next((d.get("band") for d in stress_docs if d.get("band")), None)
    mat = next((d.get("material") for d in stress_docs if d.get("material")), None)
    fig = fig_dir / "stress_vs_E.png"
    FG.stress_plot(stress_docs, band, fig, f"{st['scene']} ({mat}), {len(stress_docs)} runs, E {st['E_min']:g}-"
                   f"{st['E_max']:g} Pa, scale {cfg['scale']} (the paper: 60 runs)")
    md += [f"### 4b. Stress against initial E ({len(stress_docs)} runs; the paper plots 60)\n",
           f"Only E changes (scene {st['scene']}): one forward simulation and one BGDO step each. Top: "
           "per-particle stress signal |d||tau||/dlog E| of the key frames after frame 0; bottom: BGDO's step of "
           "log E and the key-frame deformation; shaded: the material's band.\n",
           f"![stress vs E](figures/{fig.name})\n", md_table(srows, STRESS_COLS, notes), "\n"]

    # 5. fill
    frows = T.fill_rows([data[(s, v["name"])] for s in scenes for v in variants if (s, v["name"]) in data])
    rows_out["fill"] = frows
    md += ["## 5. Filling quality\n",
           "Every filling method the runs use, against the built-in scenes' ground-truth solids "
           "(fill_report.json): precision = share of filled particles inside their own instance's solid, recall = "
           "share of the solids' volume covered (filled + gaussians), leakage = filled particles inside regions "
           "that must stay empty (share of the region covered), seconds = the fill itself.\n",
           md_table(frows, FILL_COLS, notes), "\n"]

    # 6. does BGDO change the result?
    th = cfg.get("thumbnails") or {}
    nf, size = int(th.get("frames", 4)), int(th.get("size", 96))
    crow = []
    md6 = []
    for s in scenes:
        a, b = data.get((s, "physgs")), data.get((s, "no_bgdo"))
        crow.append(T.bgdo_change_row(s, a, b))
        if a and b and a.rec.get("video") and b.rec.get("video"):
            path = fig_dir / f"bgdo_change_{s}.png"
            _bgdo_sheet(a, b, path, nf, size)
            md6.append(f"![{s}: BGDO vs no BGDO](figures/{path.name})\n")
    rows_out["bgdo_change"] = crow
    md += ["## 6. Does BGDO change the result?\n",
           "Per scene, the same gaussians at the last frame of the run with BGDO and of the run without it "
           "(knowledge-base E): mean and max distance, and the mean displacement of the BGDO run from its first "
           "frame for scale. Sheets: BGDO, no BGDO, and their pixel difference (x4, white = equal).\n",
           md_table(crow, CHANGE_COLS, notes), "\n", *md6]

    # 7. contact sheets
    md += ["## 7. Contact sheets\n", f"{nf} frames of each scene x variant video, first to last.\n"]
    for s in scenes:
        rows = []
        for v in variants:
            d = data.get((s, v["name"]))
            if d is None or not v["render"]:
                continue
            rows.append(_strip(d, v["label"], nf))
        path = fig_dir / f"sheet_{s}.png"
        FG.strip_sheet(rows, path, size, caption=f"{s} (scale {cfg['scale']})")
        md.append(f"![{s}](figures/{path.name})\n")

    md += ["## Notes\n", notes.markdown() or "none\n"]
    with atomic_path(outputs["report"]) as tmp:
        tmp.write_text("\n".join(md))
    full = PAPER_COLS + METHOD_COLS[1:]
    cols = {"comparison": full, "comparison_scenes": SCENE_COLS, "ablations": full,
            "robustness": ROBUST_COLS, "fill": FILL_COLS, "bgdo_change": CHANGE_COLS, "stress_vs_E": STRESS_COLS}
    wanted = {Path(p).stem: p for p in outputs["tables"]}
    for name in TABLES:
        if name in wanted:
            write_table(wanted[name], rows_out[name], cols[name])
    write_json(outputs["data"], {"provenance": prov, "notes": notes.texts, "stages": stages["rows"],
                                 **{k: [_plain(r) for r in v] for k, v in rows_out.items()}})
    log.info("benchmark report (%d runs, %d notes) in %.1f s -> %s", len(data), len(notes.texts),
             time.perf_counter() - t0, outputs["report"])
    return {"runs": len(data), "notes": len(notes.texts)}


def backends_used(runs) -> dict:
    """The simulation and render backends the runs actually used (the config may say auto)."""
    sim, ren = set(), set()
    for d in runs:
        if d.stats and d.stats.get("backend"):
            sim.add(str(d.stats["backend"]))
        rep, _ = RD.read_json(d.rec.get("render_report")) if d.rec.get("render_report") else (None, None)
        if isinstance(rep, dict) and rep.get("backend"):
            ren.add(f"{rep['backend']} ({rep.get('device')})" if rep.get("device") else str(rep["backend"]))
    return {"simulation backend": ", ".join(sorted(sim)) or None, "render backend": ", ".join(sorted(ren)) or None}


def _strip(d: T.RunData, label: str, n: int):
    video = d.rec.get("video")
    if not video or not Path(video).is_file():
        return (label, None, "no video")
    frames, idx, total = FG.video_frames(video, n)
    st = RD.run_stable(d.stats)
    note = None if not st.ok or st.value else "unstable: frames up to the failure"
    return (f"{label} (frames {idx[0]}-{idx[-1]} of {total})", frames, note)


def _bgdo_sheet(a: T.RunData, b: T.RunData, path: Path, n: int, size: int) -> None:
    fa, ia, _ = FG.video_frames(a.rec["video"], n)
    fb, ib, _ = FG.video_frames(b.rec["video"], n)
    def label(d: T.RunData, what: str) -> str:
        E = RD.params_E(d.params)
        return f"{what} (E = {', '.join(f'{E[k]:.3g}' for k in sorted(E))} Pa)" if E else what

    rows = [(label(a, "with BGDO"), fa, None), (label(b, "without BGDO"), fb, None)]
    if ia == ib:
        rows.append(("difference x4", FG.difference_frames(fa, fb), None))
    FG.strip_sheet(rows, path, size, caption=f"{a.rec['scene']}: BGDO vs no BGDO")
