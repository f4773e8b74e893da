"""Where do the boundaries sit?  Boundary placement against grid resolution (prints figures).

Two measurements at n_grid 16, 32 and 64 (particles on a lattice of spacing dx / 2, 8 per cell):

* **Ground**: an elastic block (E 2e5 Pa, 1000 kg/m^3, 0.12 x 0.12 x 0.08 m, static strain
  0.4 %) released 2 mm above the ground plane settles (damping 8/s).  Printed: the height of
  its material's face (the lowest particle layer less half a particle spacing) above the plane
  in mm and in cells.  Where the boundary sits where the user put it, the face rests on the
  plane: contact starts when a particle's face comes within ``colliders.TOUCH`` = 0.1 cells of
  it, so it rests within 0.1 cells above it at every resolution (the error falls with dx), and
  the material above is held at the plane, not piled onto it.  (Before contact engaged at the
  faces, the lowest centres rested 0.1 cells above the plane: the face 0.15 cells below it.  Measured
  after, grids 16 / 32: +1.96 / +1.98 mm, +0.03 / +0.06 dx: the 2 mm gap it was released with,
  which is within TOUCH, so contact engaged at once and the block never closed it.)  Run for two plane
  heights (on a node plane at every n_grid, and 0.4 cells of n_grid 32 above it) to expose the
  dependence on where the plane falls between nodes.
* **Clamp**: a bar (nu = 0, c = sqrt(E / rho) = 14 m/s) whose first 0.125 m is held by a
  fixed ``cuboid`` (its face on a boundary between particle cells at every resolution) vibrates in its first axial mode.  A free-free bar of twice the free length has
  the same period (its middle is a node), so the ratio of the two periods measured at the same
  resolution is the clamp's effective free length over the true one, independent of the
  solver's own dispersion.  Printed: L_eff / L - 1 in percent.

    PYTHONPATH=src python benchmarks/bench_boundaries.py [--grids 16 32 64]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from physgs_steps.mpm import Dynamics, Material, MPMSolver

E, RHO = 2.0e5, 1000.0


def lattice(lo, hi, s):
    axes = [np.arange(a + s / 2, b - 1e-9, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def ground_rest(G: int, h: float) -> float:
    """Height (m) of the lowest particle layer above a ground plane at ``h`` after settling."""
    s = 0.5 / G
    x = lattice([0.44, 0.44, h + 0.002], [0.56, 0.56, h + 0.082], s)
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.3, "surface": "separate"}, "damping": 8.0})
    m = Material("fixed_corotated", "identity", E=E, nu=0.3, density=RHO, name="block")
    sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    dt = 0.4 * (1.0 / G) / m.wave_speed
    for _ in range(int(0.8 / dt)):
        sol.substep(dt)
    z = sol.get_state()["x"][:, 2]
    bottom = z < z.min() + s / 2
    return float(z[bottom].mean() - h)


def axial_period(G: int, clamped: bool) -> float:
    """Period (s) of the first axial mode of a clamped-free bar (free length 0.25 m, clamp 0.125 m)
    or of a free-free bar 0.5 m long, from the zero crossings of its end's displacement."""
    s = 0.5 / G
    c = math.sqrt(E / RHO)
    L = 0.25
    y0, z0, w = 0.47, 0.47, 0.06
    if clamped:
        x0 = 0.2  # clamp [0.2, 0.325], free part [0.325, 0.575]: the face on a particle cell boundary
        lc = 0.125
        x = lattice([x0, y0, z0], [x0 + lc + L, y0 + w, z0 + w], s)
        face = x0 + lc
        v = np.where(x[:, 0] > face, np.sin(np.pi * (x[:, 0] - face) / (2 * L)), 0.0)
        bcs = [{"type": "cuboid", "point": [x0 - 0.05 + (lc + 0.05) / 2, y0 + w / 2, z0 + w / 2],
                "size": [(lc + 0.05) / 2, 0.1, 0.1], "velocity": [0, 0, 0]}]
        tip = x[:, 0] > x[:, 0].max() - s / 2
    else:
        x0 = 0.25
        x = lattice([x0, y0, z0], [x0 + 2 * L, y0 + w, z0 + w], s)
        v = np.sin(np.pi * (x[:, 0] - x0 - L) / (2 * L))
        bcs = []
        tip = x[:, 0] > x[:, 0].max() - s / 2
    dyn = Dynamics.from_config({"gravity": [0, 0, 0], "ground": None, "boundary_conditions": bcs})
    m = Material("fixed_corotated", "identity", E=E, nu=0.0, density=RHO, name="bar")
    sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
    vel = np.zeros_like(x)
    vel[:, 0] = 0.02 * v
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int), velocity=vel)
    dt = 0.3 * (1.0 / G) / c
    T_ref = 4 * L / c
    n = int(1.6 * T_ref / dt)
    u = np.empty(n)
    x_tip0 = x[tip, 0].mean()
    rows = np.flatnonzero(tip)
    for k in range(n):
        sol.substep(dt)
        u[k] = sol.gather_rows(rows)[0][:, 0].mean() - x_tip0
    t = dt * np.arange(1, n + 1)
    u -= 0.5 * (u.max() + u.min())
    cross = [t[k] - u[k] * (t[k + 1] - t[k]) / (u[k + 1] - u[k]) for k in range(n - 1) if u[k] > 0 >= u[k + 1]]
    up = [t[k] - u[k] * (t[k + 1] - t[k]) / (u[k + 1] - u[k]) for k in range(n - 1) if u[k] < 0 <= u[k + 1]]
    if len(cross) >= 1 and len(up) >= 1:
        return 2.0 * abs(up[0] - cross[0]) if len(cross) < 2 else cross[1] - cross[0]
    return float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grids", type=int, nargs="+", default=[16, 32, 64])
    a = ap.parse_args()
    t0 = time.perf_counter()
    print("ground: the material's face (lowest particle layer less half a spacing) above the plane after settling (mm, cells)")
    for h in (0.125, 0.1375):
        row = []
        for G in a.grids:
            d = ground_rest(G, h) - 0.25 / G  # particles on a lattice of spacing dx / 2
            row.append(f"n_grid {G}: {1e3 * d:+6.2f} mm ({d * G:+.2f} dx)")
        print(f"  plane at z = {h}: " + ", ".join(row))
    print("clamp: effective free length of a bar clamped by a fixed cuboid, L_eff / L - 1")
    row = []
    for G in a.grids:
        Tc, Tf = axial_period(G, True), axial_period(G, False)
        row.append(f"n_grid {G}: {100 * (Tc / Tf - 1):+5.1f} % (periods {Tc * 1e3:.1f} / {Tf * 1e3:.1f} ms)")
    print("  " + ", ".join(row))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
