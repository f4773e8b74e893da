"""final.h5 layouts: bytes, write time and one streaming read, on real simulated frames;
final_sim's per-frame host work (writer + physical figures), inline against the writer thread.

    python benchmarks/bench_final_h5.py results/bear/sim/<sim_id>/<step>/final.h5 [--repeat 3]
    python benchmarks/bench_final_h5.py --callback [--particles 5000 60000] [--frames 150]
                                        [--substep-ms 6] [--final-sim 5000] [--backend cpu]

``--callback``: synthetic frames (a drifting, deforming block) through ``FrameSink`` at each
particle count, once inline (``PHYSGS_FINAL_WRITER_THREAD=0``) and once with the writer thread,
with the main thread between frames doing ``--substep-ms`` of stand-in substep work of three
kinds: ``python`` (a Python loop: Taichi's launch overhead), ``gil-wait`` (a C call that waits
holding the GIL, as Taichi's device synchronisation does), ``sleep`` (a wait that releases the
GIL: final_sim's wait for the GPU through ``runner.gil_free_device_wait``).
Per frame it prints the callback ms (the main thread's time handing the frame over, waiting
for a full queue and, spread over the frames, the final drain: what ``stats.write_seconds``
counts), the writer's busy ms (the work itself, wherever it ran) and the wall ms (substep
stand-in + callback: the overlap shows as wall < substep + busy). ``--final-sim N``: then the
final_sim stage end to end on a tiny scene of N stored particles (two blocks, ``--sim-frames``
frames on ``--backend``): inline, threaded and (CUDA) threaded without the GIL-free device
wait, ``--rounds`` alternating rounds in one process after a run that compiles the kernels.

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
import ctypes
import os
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


def _stand_in(kind: str, ms: float) -> None:
    """ms of the main thread's substep work between two frames (module docstring)."""
    if ms <= 0:
        return
    if kind == "sleep":
        time.sleep(ms / 1e3)
    elif kind == "gil-wait":
        _LIBC.usleep(int(ms * 1e3))   # ctypes.PyDLL: the call keeps the GIL
    else:
        end = time.perf_counter() + ms / 1e3
        n = 0
        while time.perf_counter() < end:
            n += 1


_LIBC = ctypes.PyDLL(None)


def callback_bench(m: int, frames: int, substep_ms: float, kind: str, thread: bool) -> dict:
    """One pass of ``frames`` synthetic frames of m particles through FrameSink; ms per frame."""
    from physgs_steps.final_frames import FinalWriter, FrameSink
    from physgs_steps.physical import PhysicalFigures

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.3, 0.7, (m, 3)).astype(np.float32)
    v = rng.normal(0.0, 0.002, (m, 3)).astype(np.float32)
    A = rng.normal(0.0, 0.01, (m, 3, 3)).astype(np.float32)
    eye = np.eye(3, dtype=np.float32)
    with tempfile.TemporaryDirectory() as d:
        with h5py.File(Path(d) / "final.h5", "w") as h:
            writer = FinalWriter(h, np.arange(m), np.arange(frames) / 30.0)
            figures = PhysicalFigures(frames)
            sink = FrameSink(writer, figures, thread=thread)
            cb = sub = 0.0
            t_all = time.perf_counter()
            try:
                for k in range(frames):
                    if k:
                        t0 = time.perf_counter()
                        _stand_in(kind, substep_ms)
                        sub += time.perf_counter() - t0
                    xs, Fs = x0 + np.float32(k) * v, eye + np.float32(k / frames) * A   # fresh arrays, as gather_rows
                    t0 = time.perf_counter()
                    sink.frame(k, xs, Fs)
                    cb += time.perf_counter() - t0
                t0 = time.perf_counter()
                sink.close()
                cb += time.perf_counter() - t0
            finally:
                sink.abort()
            wall = time.perf_counter() - t_all
            writer.finish({"physical": figures.result(np.arange(frames) / 30.0)})
    return {"callback": cb / frames * 1e3, "busy": sink.busy_seconds / frames * 1e3,
            "substep": sub / frames * 1e3, "wall": wall / frames * 1e3}


def final_sim_bench(n: int, backend: str, frames: int = 30, rounds: int = 2) -> None:
    """final_sim end to end on two blocks of n/2 stored particles each, inline and threaded."""
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
        print(f"{'run':<26} {'stage s':>8} {'substeps s':>10} {'write s':>8} {'writer busy s':>13}")
        # thread without the GIL-free device wait (PHYSGS_GIL_FREE_WAIT=0) only differs on CUDA
        modes = [("inline", "0", "1"), ("thread", "1", "1")] + ([("thread, no GIL-free wait", "1", "0")]
                                                                if backend == "cuda" else [])
        for name, thread, gil_free in [("warm-up", "0", "1")] + modes * rounds:
            os.environ["PHYSGS_FINAL_WRITER_THREAD"], os.environ["PHYSGS_GIL_FREE_WAIT"] = thread, gil_free
            out = d / "final.h5"
            t0 = time.perf_counter()
            simulate.run_final(inputs, {"frames": str(out)}, cfg, log)
            wall = time.perf_counter() - t0
            with h5py.File(out) as f:
                st = json.loads(f.attrs["stats"])
            print(f"{name:<26} {wall:8.2f} {st['simulate_seconds']:10.2f} {st['write_seconds']:8.3f} "
                  f"{st.get('writer_busy_seconds', float('nan')):13.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("final_h5", nargs="?")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--callback", action="store_true", help="final_sim's per-frame host work, inline vs thread")
    ap.add_argument("--particles", type=int, nargs="*", default=[5000, 60000])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--substep-ms", type=float, default=6.0,
                    help="stand-in substep work per frame (H100, bear: 0.87 s / 150 frames)")
    ap.add_argument("--kinds", nargs="+", default=["python", "gil-wait", "sleep"])
    ap.add_argument("--final-sim", type=int, default=0, metavar="N", help="then final_sim end to end, N stored particles")
    ap.add_argument("--backend", default="cpu")
    ap.add_argument("--sim-frames", type=int, default=30, help="frames of the --final-sim runs")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds of the --final-sim modes")
    args = ap.parse_args()
    if args.callback:
        print(f"per frame, ms ({args.frames} frames; best of --repeat {args.repeat} by wall)")
        print(f"{'particles':>9} {'stand-in':<9} {'mode':<7} {'callback':>9} {'busy':>7} {'substep':>8} {'wall':>7}")
        for m in args.particles:
            for kind in args.kinds:
                for thread in (False, True):
                    r = min((callback_bench(m, args.frames, args.substep_ms, kind, thread) for _ in range(args.repeat)),
                            key=lambda r: r["wall"])
                    print(f"{m:9d} {kind:<9} {'thread' if thread else 'inline':<7} {r['callback']:9.2f} "
                          f"{r['busy']:7.2f} {r['substep']:8.2f} {r['wall']:7.2f}")
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
