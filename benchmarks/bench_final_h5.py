"""final.h5 layouts: bytes, write time and one streaming read, on real simulated frames;
final_sim's per-frame host work (writer + physical figures).

    python benchmarks/bench_final_h5.py results/bear/sim/<sim_id>/<step>/final.h5 [--repeat 3]
    python benchmarks/bench_final_h5.py --callback [--particles 5000 60000] [--frames 150]
                                        [--final-sim 5000] [--backend cpu]

``--callback``: synthetic frames (a drifting, deforming block) at each particle count, handed
to a ``FinalWriter`` and a ``PhysicalFigures`` as final_sim's frame callback does (the figures
take F - I from the writer); prints ms per frame in the writer, in the figures and both
(best of ``--repeat``). ``--final-sim N``: then the final_sim stage end to end on a tiny scene
of N stored particles (two blocks, ``--sim-frames`` frames on ``--backend``), ``--rounds``
runs in one process after a run that compiles the kernels; prints the stage's seconds, its
substeps, ``stats.write_seconds`` (the frame callbacks: device copy, writer and figures) and
``stats.writer_busy_seconds`` (writer and figures alone).

Reads the frames of a final.h5 (format physgs-final/2, written by final_sim) and writes them
again in each layout, one frame per chunk as the renderer reads them:

* ``f32 gzip1``: float32 x and F, gzip level 1 with byte shuffling (format 1, before #16);
* ``f32 none``: float32 x and F, no filter;
* ``f16 none``: float32 x, float16 F - I, no filter (format 2, the default);
* ``f16 gzip1``: the same with gzip 1 + shuffle;
* ``f16 lz4``: the same with Blosc LZ4 + shuffle (only when hdf5plugin is importable).

Prints MiB, write and read seconds per layout (best of --repeat), and the largest float16
error of F against the float32 frames. Timings on a shared machine are noisy: compare the
rows of one run. (The float16 error bound is stated in physgs_steps/final_frames.py and
checked in tests/test_carrier.py.)
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from physgs_steps.final_frames import FinalFrames, codec_options


def layouts() -> dict:
    out = {"f32 gzip1": ("f32", codec_options("gzip", 1)), "f32 none": ("f32", {}),
           "f16 none": ("f16", {}), "f16 gzip1": ("f16", codec_options("gzip", 1))}
    try:
        out["f16 lz4"] = ("f16", codec_options("lz4", 1))
    except Exception as e:  # noqa: BLE001 - hdf5plugin missing
        print(f"(f16 lz4 left out: {e})")
    return out


def write(path: Path, xs: list, Fs: list, kind: str, codec: dict) -> float:
    t0 = time.perf_counter()
    m = xs[0].shape[0]
    with h5py.File(path, "w") as h:
        dx = h.create_dataset("x", (len(xs), m, 3), np.float32, chunks=(1, m, 3), **codec)
        dt = np.float32 if kind == "f32" else np.float16
        dF = h.create_dataset("F", (len(xs), m, 3, 3), dt, chunks=(1, m, 3, 3), **codec)
        eye = np.eye(3, dtype=np.float32)
        for k, (x, F) in enumerate(zip(xs, Fs)):
            dx[k] = x
            dF[k] = F if kind == "f32" else (F - eye).astype(np.float16)
    return time.perf_counter() - t0


def read(path: Path, kind: str) -> float:
    t0 = time.perf_counter()
    with h5py.File(path, "r") as h:
        eye = np.eye(3, dtype=np.float32)
        for k in range(h["x"].shape[0]):
            np.asarray(h["x"][k])
            F = np.asarray(h["F"][k], np.float32)
            if kind == "f16":
                F = F + eye
    return time.perf_counter() - t0


def callback_bench(m: int, frames: int) -> dict:
    """``frames`` synthetic frames of m particles through the writer and the figures; ms per frame."""
    from physgs_steps.final_frames import FinalWriter
    from physgs_steps.physical import PhysicalFigures

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.3, 0.7, (m, 3)).astype(np.float32)
    v = rng.normal(0.0, 0.002, (m, 3)).astype(np.float32)
    A = rng.normal(0.0, 0.01, (m, 3, 3)).astype(np.float32)
    eye = np.eye(3, dtype=np.float32)
    t_w = t_f = 0.0
    with tempfile.TemporaryDirectory() as d:
        with h5py.File(Path(d) / "final.h5", "w") as h:
            writer = FinalWriter(h, np.arange(m), np.arange(frames) / 30.0)
            figures = PhysicalFigures(frames)
            for k in range(frames):
                xs, Fs = x0 + np.float32(k) * v, eye + np.float32(k / frames) * A   # fresh arrays, as gather_rows
                t0 = time.perf_counter()
                dev = writer.frame(k, xs, Fs)
                t1 = time.perf_counter()
                figures.add(k, xs, Fs, f_minus_i=dev)
                t_w, t_f = t_w + t1 - t0, t_f + time.perf_counter() - t1
            writer.finish({"physical": figures.result(np.arange(frames) / 30.0)})
    return {"writer": t_w / frames * 1e3, "figures": t_f / frames * 1e3, "total": (t_w + t_f) / frames * 1e3}


def final_sim_bench(n: int, backend: str, frames: int = 30, rounds: int = 2) -> None:
    """final_sim end to end on two blocks of n/2 stored particles each, ``rounds`` runs after a warm-up."""
    import copy
    import json
    import logging

    from physgs_steps import simulate
    from physgs_steps.config import section_defaults
    from physgs_steps.runtime import write_json

    log = logging.getLogger("bench_final_h5")
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        rng = np.random.default_rng(0)
        xs, labels, filled = [], [], []
        for lab, lo, hi in ((0, (0.3, 0.35, 0.3), (0.5, 0.6, 0.5)), (1, (0.55, 0.4, 0.3), (0.7, 0.55, 0.45))):
            lo, hi = np.asarray(lo), np.asarray(hi)
            for is_filled, count in ((False, n // 2), (True, n // 4)):
                xs.append(lo + (hi - lo) * rng.random((count, 3)))
                labels.append(np.full(count, lab))
                filled.append(np.full(count, is_filled))
        x, label, fl = np.concatenate(xs), np.concatenate(labels).astype(np.int32), np.concatenate(filled)
        order = np.r_[np.flatnonzero(~fl), np.flatnonzero(fl)]
        x, label, fl = x[order], label[order], fl[order]
        with h5py.File(d / "particles.h5", "w") as f:
            f["x"], f["label"], f["filled"] = x.astype(np.float32), label, fl
            f["vol"] = np.full(len(x), 0.2 * 0.25 * 0.2 / len(x), np.float32)
            f.attrs["n_gaussians"] = int((~fl).sum())
        inst = {"elasticity": "fixed_corotated", "plasticity": "identity", "nu": 0.3, "plasticity_params": {},
                "velocity": [0.3, 0.0, 0.0]}
        write_json(d / "params.json", {"instances": [
            {**inst, "label": 0, "name": "bear", "material": "jelly", "E": 5.0e4, "density": 1050.0},
            {**inst, "label": 1, "name": "can", "material": "jelly", "E": 2.0e5, "density": 1200.0}],
            "backend": "prior", "prompt": "bench", "history": []})
        sim = copy.deepcopy(section_defaults("sim"))
        sim.update({"n_grid": 32, "n_frames": frames, "backend": backend})
        cfg = {"sim": sim, "scene": {"dynamics": {"ground": {"height": 0.1}}}, "device": backend}
        inputs = {"particles": str(d / "particles.h5"), "params": str(d / "params.json")}
        print(f"\nfinal_sim end to end: {int((~fl).sum())} stored of {len(x)} particles, {frames} frames, "
              f"grid 32^3, backend {backend}")
        print(f"{'run':<8} {'stage s':>8} {'substeps s':>10} {'write s':>8} {'writer busy s':>13}")
        for name in ["warm-up"] + [f"run {i + 1}" for i in range(rounds)]:
            out = d / "final.h5"
            t0 = time.perf_counter()
            simulate.run_final(inputs, {"frames": str(out)}, cfg, log)
            wall = time.perf_counter() - t0
            with h5py.File(out) as f:
                st = json.loads(f.attrs["stats"])
            print(f"{name:<8} {wall:8.2f} {st['simulate_seconds']:10.2f} {st['write_seconds']:8.3f} "
                  f"{st['writer_busy_seconds']:13.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("final_h5", nargs="?")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--callback", action="store_true", help="final_sim's per-frame host work (writer + figures)")
    ap.add_argument("--particles", type=int, nargs="*", default=[5000, 60000])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--final-sim", type=int, default=0, metavar="N", help="then final_sim end to end, N stored particles")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--sim-frames", type=int, default=30, help="frames of the --final-sim runs")
    ap.add_argument("--rounds", type=int, default=2, help="runs of final_sim after the warm-up run")
    args = ap.parse_args()
    if args.callback:
        print(f"per frame, ms ({args.frames} frames; best of --repeat {args.repeat} by total)")
        print(f"{'particles':>9} {'writer':>7} {'figures':>8} {'total':>7}")
        for m in args.particles:
            r = min((callback_bench(m, args.frames) for _ in range(args.repeat)), key=lambda r: r["total"])
            print(f"{m:9d} {r['writer']:7.2f} {r['figures']:8.2f} {r['total']:7.2f}")
        if args.final_sim:
            final_sim_bench(args.final_sim, args.backend, args.sim_frames, args.rounds)
        return
    if not args.final_h5:
        ap.error("give a final.h5 (or --callback)")
    with FinalFrames(args.final_h5) as fr:
        rows = sorted(set(fr.frame_row.tolist()))
        xs = [np.asarray(fr.h5["x"][r], np.float32) for r in rows]
        Fs = [np.asarray(fr.h5["F_minus_I"][r], np.float32) + np.eye(3, dtype=np.float32) for r in rows]
    m = xs[0].shape[0]
    print(f"{args.final_h5}: {len(xs)} stored frames x {m} particles")
    print(f"{'layout':<11} {'MiB':>8} {'write s':>8} {'read s':>8}")
    with tempfile.TemporaryDirectory() as d:
        for name, (kind, codec) in layouts().items():
            p = Path(d) / f"{name.replace(' ', '_')}.h5"
            w = min(write(p, xs, Fs, kind, codec) for _ in range(args.repeat))
            r = min(read(p, kind) for _ in range(args.repeat))
            print(f"{name:<11} {p.stat().st_size / 2**20:8.2f} {w:8.3f} {r:8.3f}")


if __name__ == "__main__":
    main()
