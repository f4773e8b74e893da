"""Shared plumbing of the generated reports (benchmark, validation): where and with what a
report was made, Markdown tables, CSV files and matplotlib figures.

    from physgs_steps import reporting as R
    prov = R.provenance(scale="smoke")                  # commit, versions, device, date
    cols = [R.Column("scene"), R.Column("E", "E (Pa)", "{:.3g}")]
    md = R.markdown_table(rows, cols)                   # rows: list of dicts; None -> "n/a"
    R.write_csv("results/benchmark/fill.csv", rows, cols)
    with R.figure("results/benchmark/stress_vs_E.png") as (fig, ax):
        ax.loglog(E, tau)

A value that could not be computed is ``None`` in a row and prints as ``n/a`` (a footnote
says why); nothing here invents a number.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import importlib.metadata as _md
import os
import platform
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

from .runtime import atomic_path, project_root

NA = "n/a"
VERSIONED = ("physgs-steps", "numpy", "scipy", "torch", "taichi", "snakemake", "h5py", "scikit-learn", "trimesh",
             "transformers", "gsplat", "matplotlib")


@dataclass(frozen=True)
class Column:
    """One column of a table: the row key, its header and a format for numbers."""

    key: str
    header: str | None = None
    fmt: str = "{}"

    @property
    def title(self) -> str:
        return self.header if self.header is not None else self.key

    def cell(self, row: dict) -> str:
        return format_value(row.get(self.key), self.fmt)


def format_value(v: Any, fmt: str = "{}") -> str:
    """``fmt`` applied to ``v``; None, NaN and missing values print as ``n/a``."""
    if v is None:
        return NA
    if isinstance(v, float) and v != v:
        return NA
    if isinstance(v, bool):
        return "yes" if v else "no"
    try:
        return fmt.format(v)
    except (ValueError, TypeError):
        return str(v)


def markdown_table(rows: Sequence[dict], columns: Sequence[Column]) -> str:
    """A GitHub Markdown table of ``rows`` (pipes inside cells escaped)."""
    def esc(s: str) -> str:
        return s.replace("|", "\\|").replace("\n", " ")

    head = "| " + " | ".join(esc(c.title) for c in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(esc(c.cell(r)) for c in columns) + " |" for r in rows]
    return "\n".join([head, rule, *body]) + "\n"


def write_csv(path: str | os.PathLike, rows: Sequence[dict], columns: Sequence[Column] | None = None) -> None:
    """Rows as CSV (raw values, empty cell for None), atomically; ``columns`` picks and orders keys."""
    import csv

    keys = [c.key for c in columns] if columns is not None else list(dict.fromkeys(k for r in rows for k in r))
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(keys)
            for r in rows:
                w.writerow(["" if r.get(k) is None else r.get(k) for k in keys])


@contextlib.contextmanager
def figure(path: str | os.PathLike, size=(6.4, 4.2), dpi: int = 120, **subplots: Any) -> Iterator[tuple]:
    """``(fig, ax)`` of a new matplotlib figure (Agg, no display), saved atomically to ``path`` (PNG).
    ``subplots`` go to ``plt.subplots`` (e.g. ``nrows=2, sharex=True``: ``ax`` is then the array of axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=size, **subplots)
    try:
        yield fig, ax
        fig.tight_layout()
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)


def git_commit(root: str | os.PathLike | None = None) -> dict:
    """{"commit": sha or None, "dirty": bool or None} of the repository at ``root``."""
    root = Path(root) if root else project_root()
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return {"commit": None, "dirty": None}
        st = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True,
                            text=True, timeout=10)
        return {"commit": sha.stdout.strip(), "dirty": bool(st.stdout.strip()) if st.returncode == 0 else None}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def versions(names: Sequence[str] = VERSIONED) -> dict:
    """Installed versions (package metadata only: nothing is imported); None when absent."""
    out = {"python": platform.python_version()}
    for n in names:
        try:
            out[n] = _md.version(n)
        except _md.PackageNotFoundError:
            out[n] = None
    return out


def device_info() -> dict:
    """The CPU (model, cores) and, when torch is already imported and sees CUDA, the GPU."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info = {"cpu": cpu, "cores": cores, "gpu": None}
    torch = sys.modules.get("torch")
    try:
        if torch is not None and torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except Exception:  # pragma: no cover - a broken CUDA install
        pass
    if info["gpu"] is None and shutil.which("nvidia-smi"):
        # report jobs do not import torch: ask the driver (no CUDA context is made)
        try:
            p = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                               text=True, timeout=10)
            names = [n.strip() for n in p.stdout.splitlines() if n.strip()] if p.returncode == 0 else []
            if names:
                info["gpu"] = names[0] if len(names) == 1 else f"{len(names)} x {names[0]}"
        except (OSError, subprocess.SubprocessError):
            pass
    return info


def provenance(**extra: Any) -> dict:
    """What a report was made with: date, git commit, versions, machine, plus ``extra``
    (e.g. ``scale="cpu"``, ``device="cuda"``)."""
    return {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), **git_commit(),
            "versions": versions(), "machine": device_info(), **extra}


def provenance_markdown(prov: dict) -> str:
    """A short Markdown block of :func:`provenance`'s dict."""
    v = prov.get("versions") or {}
    m = prov.get("machine") or {}
    commit = prov.get("commit") or "unknown"
    if prov.get("dirty"):
        commit += " (with uncommitted changes)"
    lines = [f"- made {prov.get('date')} from commit `{commit}`"]
    for k in sorted(set(prov) - {"date", "commit", "dirty", "versions", "machine"}):
        lines.append(f"- {k}: {format_value(prov[k])}")
    gpu = m.get("gpu")
    lines.append(f"- machine: {m.get('cpu')} ({m.get('cores')} cores){'; GPU ' + gpu if gpu else '; no GPU found'} (the machine that made this report)")
    lines.append("- versions: " + ", ".join(f"{k} {val}" for k, val in v.items() if val is not None))
    return "\n".join(lines) + "\n"
