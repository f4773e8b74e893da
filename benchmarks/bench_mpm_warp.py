"""Benchmark: PhysGaussian's warp MPM solver on the particles of bench_mpm.py, as written
(``wp.ScopedTimer(synchronize=True)`` around its kernels: a host synchronisation per kernel)
and with those timers made no-ops (no host synchronisation inside a substep).

PhysGaussian's code is not part of physgs: give the folder of its ``mpm_solver_warp``
(``git clone https://github.com/XPandora/PhysGaussian``) and install ``warp-lang``: a release
that still has ``warp.torch`` and builds a matrix from vectors (1.6.2 runs it; 1.19 does not).

    python benchmarks/bench_mpm_warp.py --physgaussian PhysGaussian/mpm_solver_warp --sizes 300000 1000000

Prints one line per size and variant (particle-substeps/s) and, with ``--emit-rows``, a JSON
line that bench_mpm.py collects (``python benchmarks/bench_mpm.py --warp-solver DIR``).
Material: jelly (PhysGaussian's material 0, fixed corotated), E 1e5 Pa, nu 0.3, 1000 kg/m^3,
gravity, its bounding box (walls), the same grid and dt as bench_mpm.py.
"""
import argparse
import contextlib
import json
import sys
import time

import numpy as np

GRID_FOR = {30_000: 32, 100_000: 48, 300_000: 64, 1_000_000: 96}


class _NoSyncTimer(contextlib.ContextDecorator):
    """Stands in for wp.ScopedTimer: times nothing, synchronises nothing."""

    def __init__(self, *args, **kwargs):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def bench(folder: str, sizes: list, seconds: float) -> list:
    sys.path.insert(0, folder)
    import torch
    import warp as wp

    wp.init()
    import mpm_solver_warp as pg

    E, nu, rho = 1.0e5, 0.3, 1000.0
    c = np.sqrt((E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))) / rho)
    rows = []
    for P in sizes:
        G = GRID_FOR.get(P, 64)
        dt = 0.5 * (1.0 / G) / c
        rng = np.random.default_rng(0)
        x = torch.tensor(0.3 + 0.4 * rng.random((P, 3)), dtype=torch.float32, device="cuda")
        vol = torch.full((P,), 0.4 ** 3 / P, dtype=torch.float32, device="cuda")
        for variant in ("as_written", "no_sync"):
            pg.wp.ScopedTimer = wp.ScopedTimer if variant == "as_written" else _NoSyncTimer
            s = pg.MPM_Simulator_WARP(10)
            s.load_initial_data_from_torch(x, vol, n_grid=G, grid_lim=1.0)
            s.set_parameters_dict({"material": "jelly", "E": E, "nu": nu, "density": rho, "g": [0.0, 0.0, -9.8],
                                   "grid_lim": 1.0, "n_grid": G})
            s.finalize_mu_lam()
            s.add_bounding_box()  # its slip walls 3 cells thick, like the other kernels' boundary
            s.p2g2p(0, dt)  # compile / warm up
            wp.synchronize()
            n, t0 = 0, time.perf_counter()
            while n < 3 or time.perf_counter() - t0 < seconds:
                s.p2g2p(n, dt)
                n += 1
                if n % 20 == 0:
                    wp.synchronize()
            wp.synchronize()
            rate = P * n / (time.perf_counter() - t0)
            rows.append({"arch": "cuda", "particles": P, "n_grid": G, "solver": f"warp_{variant}", "rate": rate,
                         "substeps_measured": n})
            print(f"warp  P={P:>8d} grid {G}^3: PhysGaussian warp solver {variant:10s} {rate:.3g} particle-substeps/s",
                  flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--physgaussian", required=True, help="folder holding PhysGaussian's mpm_solver_warp.py")
    ap.add_argument("--sizes", type=int, nargs="+", default=[300_000, 1_000_000])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--emit-rows", action="store_true")
    a = ap.parse_args()
    rows = bench(a.physgaussian, a.sizes, a.seconds)
    if a.emit_rows:
        print("ROWS " + json.dumps(rows))


if __name__ == "__main__":
    main()
