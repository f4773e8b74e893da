"""Adapters that read what the benchmark's runs wrote, one small function per source.

The formats they read are owned by other stages and change (new metrics, statistics moving
from ``metrics.json`` into ``final.h5``): every read goes through a function here, tolerates
missing files and keys, and gives ``Cell(None, reason)`` for a value it cannot find, never a
made-up number. A change of a format then touches one function.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Cell:
    """A table value: a number (or text), or None with the reason; ``note`` qualifies a value
    (e.g. the rater that produced a score when it is not the paper's)."""

    value: Any = None
    reason: str | None = None
    note: str | None = None

    @property
    def ok(self) -> bool:
        return self.value is not None

    def to_dict(self) -> dict:
        return {k: v for k, v in (("value", self.value), ("reason", self.reason), ("note", self.note)) if v is not None
                or k == "value"}


def missing(reason: str) -> Cell:
    return Cell(None, reason)


def read_json(path: str | Path | None) -> tuple[Any, str | None]:
    """(document, None) or (None, the reason it could not be read)."""
    if path is None:
        return None, "no file"
    p = Path(path)
    if not p.is_file():
        return None, f"{p} does not exist"
    try:
        return json.loads(p.read_text()), None
    except (OSError, ValueError) as e:
        return None, f"{p} is not readable JSON ({e})"


def _get(doc: Any, dotted: str) -> Any:
    cur = doc
    for part in dotted.split("."):
        if not isinstance(cur, dict) or part not in cur:
            return None
        cur = cur[part]
    return cur


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


# ------------------------------------------------------------------------------------ scores
# metrics.json (schema_version 2, physgs_steps.metrics.scores): one key per paper column, each
# {"column", "value" | null, "reason", "backend", "paper_metric", "scale", ...}.
SCORE_KEYS = {"CS": "clip_score", "AS": "aesthetic_score", "SA": "semantic_adherence", "PC": "physical_commonsense"}
SCORE_NAMES = {"CS": "CLIP score", "AS": "aesthetic score", "SA": "VideoPhy2 semantic adherence",
               "PC": "VideoPhy2 physical commonsense"}


def score(metrics: dict | None, name: str, why_missing: str | None = None) -> Cell:
    """One of CS, AS, SA, PC from a metrics.json document.

    An entry is ``{"value": x | null, "reason": ..., "backend": ..., "paper_metric": ...}`` (a
    bare number, as older metrics.json files wrote CS/AS, is read as a value). A value that is
    not the paper's metric (``paper_metric: false``, e.g. the in-process VideoPhy2 stand-in)
    keeps its value and carries the entry's ``label`` (or its backend) in ``note``, so a table
    never shows it as the paper's number.
    """
    if metrics is None:
        return missing(why_missing or "no metrics.json")
    key = SCORE_KEYS[name]
    entry = metrics.get(key) if isinstance(metrics, dict) else None
    if entry is None:
        version = metrics.get("schema_version") if isinstance(metrics, dict) else None
        return missing(f"metrics.json (schema_version {version or 1}) has no '{key}' ({SCORE_NAMES[name]}): "
                       "made by a metrics stage that does not compute it; re-run metrics")
    if _finite(entry):
        return Cell(float(entry))
    if not isinstance(entry, dict):
        return missing(f"metrics.json '{key}' is {entry!r}, not a number")
    value = entry.get("value")
    if _finite(value):
        note = None
        if entry.get("paper_metric") is False:
            note = str(entry.get("label") or f"{entry.get('backend')} (not the paper's metric)")
        return Cell(float(value), note=note)
    return missing(str(entry.get("reason") or f"metrics.json '{key}' has no value"))


# ------------------------------------------------------------------------------------ final.h5
class FinalView:
    """The frames of an open final.h5, whichever layout wrote them.

    * per gaussian (``gaussian_index`` [Nv] rows of scene.ply, ``x`` [T, Nv, 3]);
    * per stored particle (``particle_index`` [M] rows of particles.h5, ``frame_row`` [T]
      -> the stored row of each frame, ``x`` [S, M, 3]: frames held at rest share a row).

    ``index`` are the rows the columns belong to, ``index_of`` what they are rows of
    ("gaussians" or "particles"); ``x(t)`` [n, 3] float64 positions of frame t.
    """

    def __init__(self, h5):
        if "x" not in h5:
            raise KeyError("final.h5 has no 'x' dataset")
        self._x = h5["x"]
        if "frame_row" in h5 and "particle_index" in h5:
            self._row = np.asarray(h5["frame_row"][...], np.int64)
            self.index = np.asarray(h5["particle_index"][...], np.int64)
            self.index_of = "particles"
            self.n_frames = int(self._row.shape[0])
        else:
            self._row = None
            self.index = np.asarray(h5["gaussian_index"][...], np.int64) if "gaussian_index" in h5 else None
            self.index_of = "gaussians"
            self.n_frames = int(self._x.shape[0])

    def x(self, t: int) -> np.ndarray:
        return np.asarray(self._x[t if self._row is None else int(self._row[t])], np.float64)


def final_stats(path: str | Path | None) -> tuple[dict | None, str | None]:
    """The ``stats`` attribute of a final.h5 (the run's stability, substeps, timings, and any
    physical figures final_sim accumulates), or (None, reason)."""
    if path is None or not Path(path).is_file():
        return None, f"{path} does not exist"
    try:
        import h5py

        with h5py.File(path, "r") as f:
            raw = f.attrs.get("stats")
            n_frames = FinalView(f).n_frames if "x" in f else None
    except OSError as e:
        return None, f"{path}: {e}"
    if raw is None:
        return None, f"{path} has no stats attribute"
    try:
        stats = json.loads(raw)
    except (TypeError, ValueError):
        return None, f"{path}: stats attribute is not JSON"
    stats.setdefault("frames_written", n_frames)
    return stats, None


def forward_stats(path: str | Path) -> dict | None:
    """The ``stats`` attribute of a forward.h5 (stability, substeps, solver device memory), or None."""
    if not Path(path).is_file():
        return None
    try:
        import h5py

        with h5py.File(path, "r") as f:
            raw = f.attrs.get("stats")
        return json.loads(raw) if raw is not None else None
    except (OSError, TypeError, ValueError):
        return None


def run_stable(stats: dict | None) -> Cell:
    if stats is None:
        return missing("no final.h5 stats")
    st = stats.get("stable")
    if st is None:
        return missing("final.h5 stats do not say whether the run was stable")
    return Cell(bool(st), note=None if st else _short(stats.get("failure")))


def _short(text: Any, n: int = 160) -> str | None:
    if not text:
        return None
    t = " ".join(str(text).split())
    return t if len(t) <= n else t[: n - 3] + "..."


# ------------------------------------------------------------------------------------ physical
def physical(metrics: dict | None, stats: dict | None) -> dict:
    """The weight-free physical figures of a run: metrics.json ``physical`` overlaid with any
    ``physical`` record in final.h5's stats (where final_sim may accumulate them)."""
    out = {}
    if isinstance(metrics, dict) and isinstance(metrics.get("physical"), dict):
        out.update(metrics["physical"])
    if isinstance(stats, dict) and isinstance(stats.get("physical"), dict):
        out.update(stats["physical"])
    return out


def figure(phys: dict, key: str) -> Cell:
    """A figure ``{"value": x}`` (or a bare number) of :func:`physical`'s dict."""
    e = phys.get(key)
    if e is None:
        return missing(f"no '{key}' among the physical figures")
    if _finite(e) or isinstance(e, bool):
        return Cell(e)
    if isinstance(e, dict):
        if e.get("value") is not None and (_finite(e["value"]) or isinstance(e["value"], bool)):
            return Cell(e["value"])
        return missing(str(e.get("reason") or f"'{key}' has no value"))
    return missing(f"'{key}' is {e!r}")


def check(phys: dict, key: str) -> Cell:
    checks = phys.get("checks") if isinstance(phys.get("checks"), dict) else {}
    if key not in checks:
        return missing(f"no '{key}' check among the physical figures")
    return Cell(bool(checks[key]))


# ------------------------------------------------------------------------------------ params / BGDO
def params_E(params: dict | None) -> dict[int, float]:
    """label -> E of a params.json document."""
    out = {}
    for inst in (params or {}).get("instances") or []:
        if isinstance(inst, dict) and isinstance(inst.get("label"), int) and _finite(inst.get("E")):
            out[inst["label"]] = float(inst["E"])
    return out


def instances(params: dict | None) -> list[dict]:
    """[{label, name, material}] of a params.json document."""
    return [{"label": i.get("label"), "name": i.get("name"), "material": i.get("material")}
            for i in (params or {}).get("instances") or [] if isinstance(i, dict)]


def E_history(params0: dict | None, final_params: dict | None) -> dict[int, list[float]]:
    """label -> [E0, E1, ..., EN]: params_0's E and each BGDO update's ``E_after`` (params.json
    ``history``); without BGDO just [E0]."""
    out = {k: [v] for k, v in params_E(params0).items()}
    for h in (final_params or {}).get("history") or []:
        if not isinstance(h, dict) or h.get("stage") != "bgdo_update":
            continue
        for k, v in (h.get("E_after") or {}).items():
            try:
                lab = int(k)
            except ValueError:
                continue
            if lab in out and _finite(v):
                out[lab].append(float(v))
    return out


def bgdo_record(final_params: dict | None) -> dict[int, dict]:
    """label -> the last BGDO update's per-instance record (band, fate, rule, ...), if any."""
    rec = (final_params or {}).get("bgdo") or {}
    return {r["label"]: r for r in rec.get("instances") or [] if isinstance(r, dict) and isinstance(r.get("label"), int)}


def material_band(material: str | None, kb_path: str | None = None) -> list[float] | None:
    """The knowledge base's E_range of a material (the robustness experiment's band)."""
    if not material:
        return None
    from .. import materials_kb
    from ..errors import PhysGSError

    try:
        return [float(v) for v in materials_kb.get_material(material, materials_kb.load_kb(kb_path))["E_range"]]
    except (PhysGSError, KeyError, TypeError):
        return None


# ------------------------------------------------------------------------------------ fill
def fill_quality(report: dict | None) -> dict:
    """Precision, recall, recall of the gaussians alone, leakage per empty region, filled
    count and seconds of a fill_report.json (Cells)."""
    if report is None:
        r = missing("no fill_report.json")
        return {k: r for k in ("precision", "recall", "recall_gaussians_only", "leakage", "n_filled", "seconds")}
    ev = report.get("evaluation") or {}
    why = ev.get("reason") or "no ground truth (not a built-in scene)"

    def metric(key):
        v = ev.get(key)
        if _finite(v):
            return Cell(float(v))
        if isinstance(v, dict):
            return missing(str(v.get("reason") or why))
        return missing(why)

    leak = ev.get("leakage")
    if isinstance(leak, dict) and leak:
        parts = []
        for name, rec in sorted(leak.items()):
            cov = rec.get("volume_covered")
            parts.append(f"{name} {rec.get('filled_inside')}" + (f" ({float(cov):.0%})" if _finite(cov) else ""))
        leakage = Cell("; ".join(parts))
    elif isinstance(leak, dict):
        leakage = Cell("no empty region in this scene")
    else:
        leakage = missing(why)
    secs = _get(report, "timings.fill.seconds")
    return {"precision": metric("precision"), "recall": metric("recall"),
            "recall_gaussians_only": metric("recall_gaussians_only"), "leakage": leakage,
            "n_filled": Cell(report["n_filled"]) if _finite(report.get("n_filled")) else missing("no n_filled"),
            "seconds": Cell(float(secs)) if _finite(secs) else missing("no timings.fill.seconds")}


# ------------------------------------------------------------------------------------ job time and memory
def job_benchmark(path: str | Path) -> tuple[dict | None, str | None]:
    """Wall seconds and peak RSS (MB) of one job from Snakemake's ``benchmark:`` TSV."""
    p = Path(path)
    if not p.is_file():
        return None, f"{p} does not exist"
    try:
        lines = [l.rstrip("\n").split("\t") for l in p.read_text().splitlines() if l.strip()]
    except OSError as e:
        return None, str(e)
    if len(lines) < 2:
        return None, f"{p} has no measurement"
    row = dict(zip(lines[0], lines[-1]))

    def num(k):
        try:
            v = float(row.get(k, "nan"))
        except ValueError:
            return None
        return v if math.isfinite(v) else None

    return {"seconds": num("s"), "max_rss_mb": num("max_rss")}, None


def stage_summary(log_path: str | Path) -> dict | None:
    """The stage's summary (runtime.run_stage's last line "stage summary: {...}"), or None."""
    from ..runtime import SUMMARY_PREFIX

    p = Path(log_path)
    if not p.is_file():
        return None
    try:
        text = p.read_text(errors="replace")
    except OSError:
        return None
    for line in reversed(text.splitlines()):
        i = line.find(SUMMARY_PREFIX)
        if i >= 0:
            try:
                doc = json.loads(line[i + len(SUMMARY_PREFIX):])
            except ValueError:
                return None
            return doc if isinstance(doc, dict) else None
    return None


def job_record(job: dict) -> dict:
    """One job's figures: {rule, step, seconds (job wall, Snakemake), max_rss_mb, stage_seconds
    (inside the stage, without process start-up), cuda_peak_mb, reason}."""
    bench, why = job_benchmark(job["benchmark"])
    summ = stage_summary(job["log"]) if job.get("log") else None
    rec = {"rule": job["rule"], "step": job.get("step"), "seconds": None, "max_rss_mb": None,
           "stage_seconds": None, "cuda_peak_mb": None, "reason": why}
    if bench:
        rec.update(bench)
    if summ:
        if _finite(summ.get("seconds")):
            rec["stage_seconds"] = float(summ["seconds"])
        if _finite(summ.get("cuda_peak_mb")):
            rec["cuda_peak_mb"] = float(summ["cuda_peak_mb"])
    return rec


def device_memory_mb(stats: dict | None) -> float | None:
    """The simulation's device memory (Taichi fields) from a forward/final run's stats."""
    v = (stats or {}).get("solver_device_mb")
    return float(v) if _finite(v) else None
