"""Benchmark of the cluster and fill stages: wall time and peak memory at 30k, 100k and 300k
gaussians (built-in scene, default ``bear_can``), for each filling method.

    python benchmarks/bench_fill.py [--scene bear_can] [--sizes 30000 100000 300000]
                                    [--methods paper no_mcis surface global] [--out DIR]

Each stage runs in a fresh process (spawn), so "rss MiB" is that process's peak resident
set (imports included, about 200 MiB of it); "alloc MiB" is the stage's own peak of
Python/numpy allocations (tracemalloc). The scene is built and normalised by the prepare
stage once per size, outside the measured stages.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import tempfile
import time
from pathlib import Path

METHODS = {
    "paper": {"method": "ipf", "occupancy": "hull", "mcis": True},
    "no_mcis": {"method": "ipf", "occupancy": "hull", "mcis": False},
    "surface": {"method": "ipf", "occupancy": "surface", "mcis": False},
    "global": {"method": "global", "mcis": False},
}


def _quiet_logger():
    import logging

    log = logging.getLogger("bench_fill")
    log.handlers[:] = [logging.NullHandler()]
    log.propagate = False
    return log


def _stage(args) -> dict:
    """Run one stage in this (child) process; returns seconds and peak memory."""
    stage, inputs, outputs, cfg = args
    import json

    from physgs_steps import cluster, fill

    log = _quiet_logger()
    t0 = time.perf_counter()
    if stage == "cluster":
        cluster.run(inputs, outputs, cfg, log)
        rec = json.loads(Path(outputs["clusters"]).read_text())
        alloc, extra = rec["peak_alloc_mb"], f"K={rec['n_instances']} ({rec.get('algorithm', rec['method'])})"
    else:
        fill.run(inputs, outputs, cfg, log)
        rec = json.loads(Path(outputs["report"]).read_text())
        alloc, extra = rec["timings"]["fill"]["peak_alloc_mb"], f"filled={rec['n_filled']}"
        if rec["evaluation"].get("available"):
            # the evaluation against the ground truth is part of fill.run but not of the filling
            alloc_s = rec["timings"]["evaluation"]["seconds"]
            return {"seconds": time.perf_counter() - t0 - alloc_s, "alloc": alloc,
                    "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "extra": extra}
    return {"seconds": time.perf_counter() - t0, "alloc": alloc,
            "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "extra": extra}


def _child(args, queue) -> None:
    try:
        queue.put(_stage(args))
    except Exception as e:  # report the failure to the parent instead of hanging it
        queue.put({"error": f"{type(e).__name__}: {e}"})


def _in_child(ctx, args) -> dict:
    """Run a stage in a fresh (non-daemon) process, so its peak RSS is its own."""
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(args, queue))
    proc.start()
    out = queue.get()
    proc.join()
    if "error" in out:
        raise RuntimeError(f"stage {args[0]} failed: {out['error']}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bear_can")
    ap.add_argument("--sizes", type=int, nargs="+", default=[30000, 100000, 300000])
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--n-grid", type=int, default=32)
    ap.add_argument("--out", default=None, help="keep the artifacts here (default: a temporary folder)")
    a = ap.parse_args(argv)

    from physgs_steps import config, prepare

    ctx = mp.get_context("spawn")
    tmp = tempfile.TemporaryDirectory() if a.out is None else None
    root = Path(a.out or tmp.name)
    rows = []
    for n in a.sizes:
        d = root / f"{a.scene}_{n}"
        scene = {"source": f"builtin:{a.scene}", "builtin": {"n_gaussians": n, "seed": 0}, "instances": []}
        t0 = time.perf_counter()
        prepare.run({}, {"scene": str(d / "scene.ply"), "transform": str(d / "transform.json")},
                    {"scene": scene, "prepare": config.section_defaults("prepare")}, _quiet_logger())
        print(f"[{a.scene} n={n}] scene built and prepared in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        cfg = {"scene": scene, "cluster": config.section_defaults("cluster")}
        r = _in_child(ctx, ("cluster", {"scene": str(d / "scene.ply")},
                            {"labels": str(d / "labels.npz"), "clusters": str(d / "clusters.json")}, cfg))
        rows.append((n, "cluster", "-", r))
        for m in a.methods:
            fcfg = dict(config.section_defaults("fill"), n_grid=a.n_grid, **METHODS[m])
            cfg = {"scene": scene, "fill": fcfg}
            r = _in_child(ctx, ("fill", {"scene": str(d / "scene.ply"), "labels": str(d / "labels.npz"),
                                         "transform": str(d / "transform.json")},
                                {"particles": str(d / f"particles_{m}.h5"), "report": str(d / f"fill_report_{m}.json")},
                                cfg))
            rows.append((n, "fill", m, r))
    print(f"\nscene builtin:{a.scene}, n_grid {a.n_grid}, {mp.cpu_count()} CPU cores\n")
    print("| gaussians | stage | method | seconds | alloc MiB | rss MiB | result |")
    print("|---:|---|---|---:|---:|---:|---|")
    for n, stage, m, r in rows:
        print(f"| {n} | {stage} | {m} | {r['seconds']:.2f} | {r['alloc']:.0f} | {r['rss']:.0f} | {r['extra']} |")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
