"""Pieces of a simulation's particle cloud at a frame of its final.h5 (tearing check).

    PYTHONPATH=src python3 tools/pieces.py results/bread/sim/<sim_id>/<step>/final.h5 [--frame -1] [--link 1.0]

Prints the number of pieces (connected components of the stored particles, edges between
particles closer than ``--link`` grid cells), the sizes of the largest, the share of the
particles in the two largest and the gap between them in grid cells (physical.pieces).
"""
from __future__ import annotations

import argparse
import json

import h5py

from physgs_steps.final_frames import FinalFrames
from physgs_steps.physical import pieces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("final_h5")
    ap.add_argument("--frame", type=int, default=-1, help="frame index (negative: from the end)")
    ap.add_argument("--link", type=float, default=1.0, help="link distance in grid cells (dx)")
    a = ap.parse_args()
    with h5py.File(a.final_h5, "r") as f:
        sim = json.loads(f.attrs["sim_config"])
    dx = 1.0 / int(sim["sim"]["n_grid"])  # grid spacing in domain units (final.h5 positions)
    with FinalFrames(a.final_h5) as fr:
        t = a.frame % fr.n_frames
        x = fr.x(t)
    p = pieces(x, a.link * dx)
    print(f"frame {t}: {len(p['sizes'])} pieces of {len(x)} particles (link {a.link:g} dx), largest {p['sizes'][:4].tolist()}, "
          f"two largest {100 * p['top2']:.1f}%, gap between them {p['gap'] / dx:.2f} dx")


if __name__ == "__main__":
    main()
