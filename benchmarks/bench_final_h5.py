"""final.h5 layouts: bytes, write time and one streaming read, on real simulated frames.

    python benchmarks/bench_final_h5.py results/bear/sim/<sim_id>/<step>/final.h5 [--repeat 3]

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("final_h5")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
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
