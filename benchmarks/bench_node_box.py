"""Cost that follows the scene: milliseconds per substep of a small object at several grid sizes
(CPU). The substep kernel's grid passes run over the box of nodes the particles reach
(kernels.py "Node box"), so with the same particles a finer grid costs little more.

    python benchmarks/bench_node_box.py [grid ...]      # default: 32 48 64

Rows: a small jelly block (600 particles at two per cell at grid 32), the same beside a free rigid
block (rigid coupling passes), a large jelly block (8,800 particles); the particles are the same
at every grid size (spacing 1/64 of the domain), resting on a ground plane.
"""
import sys
import time

import numpy as np
import taichi as ti

from physgs_steps.mpm import Dynamics, MPMSolver, preset

GRIDS = [int(a) for a in sys.argv[1:]] or [32, 48, 64]
S = 1.0 / 64
H = 0.1


def box(lo, hi):
    ax = [np.arange(a + S / 2, b, S) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


def ms_per_substep(G, blocks, mats, n=200):
    x = np.concatenate(blocks)
    mat = np.concatenate([np.full(len(b), i) for i, b in enumerate(blocks)])
    dyn = Dynamics.from_config({"ground": {"height": H, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver(mats, n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), S ** 3), mat)
    for _ in range(5):
        sol.substep(2e-4)
    sol.stats()
    t = time.perf_counter()
    for _ in range(n):
        sol.substep(2e-4)
    sol.stats()
    ti.sync()
    return (time.perf_counter() - t) / n * 1e3, len(x)


small = box([0.40, 0.40, H], [0.55, 0.55, H + 0.1])
beside = box([0.60, 0.40, H], [0.75, 0.55, H + 0.1])
large = box([0.3, 0.3, H], [0.7, 0.7, H + 0.2])
cases = [("small jelly", [small], [preset("jelly")]),
         ("small jelly + free rigid", [small, beside], [preset("jelly"), preset("stone", rigid=True)]),
         ("large jelly", [large], [preset("jelly")])]
print(f"{'case':<26}{'particles':>10}" + "".join(f"{'grid ' + str(G):>12}" for G in GRIDS) + "   (ms per substep)")
for name, blocks, mats in cases:
    row = [ms_per_substep(G, blocks, mats) for G in GRIDS]
    print(f"{name:<26}{row[0][1]:>10}" + "".join(f"{r[0]:>12.2f}" for r in row), flush=True)
