"""Per-stage time and peak memory of one target, from Snakemake's ``benchmark:`` files.

Snakemake writes one TSV per job (wall seconds ``s``, peak resident memory ``max_rss`` in MB,
...). This collects the jobs that made a target's video (``Plan.jobs``) into one table. A job
whose artifact was reused from cache has the benchmark of the run that made it.
"""
from __future__ import annotations

from pathlib import Path

import pandas as pd

from .runtime import atomic_path

COLUMNS = ["rule", "step", "seconds", "max_rss_mb", "benchmark"]


def collect(jobs: list[tuple[str, str | None, str]]) -> pd.DataFrame:
    """jobs: (rule, step, benchmark path) -> one row each (NaN where the file is missing)."""
    rows = []
    for rule, step, path in jobs:
        row = {"rule": rule, "step": step or "", "seconds": float("nan"), "max_rss_mb": float("nan"), "benchmark": path}
        if Path(path).exists():
            b = pd.read_csv(path, sep="\t")
            row["seconds"] = float(b["s"].iloc[-1])
            if "max_rss" in b and pd.notna(b["max_rss"].iloc[-1]):
                row["max_rss_mb"] = float(b["max_rss"].iloc[-1])
        rows.append(row)
    return pd.DataFrame(rows, columns=COLUMNS)


def run(inputs: dict, outputs: dict, cfg: dict, log) -> dict:
    jobs = [(j["rule"], j["step"], j["benchmark"]) for j in cfg["jobs"]]
    table = collect(jobs)
    with atomic_path(outputs["table"]) as tmp:
        table.to_csv(tmp, sep="\t", index=False, float_format="%.3f")
    total = float(table["seconds"].sum())
    log.info("stage times and peak memory:\n%s\ntotal %.1f s", table.drop(columns="benchmark").to_string(index=False), total)
    missing = table[table["seconds"].isna()]["rule"].tolist()
    if missing:
        log.warning("no benchmark file for: %s", ", ".join(missing))
    return {"total_seconds": round(total, 2), "peak_rss_mb_max": float(table["max_rss_mb"].max())}
