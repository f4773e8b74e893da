"""Rigid bodies on soft material: how far does a rigid ball sink into jelly?  (prints figures)

The ball_jelly scene's geometry (issue #15): a steel ball (radius 0.06 m, 7850 kg/m^3, a free
rigid body) resting on a jelly slab (0.5 x 0.36 x 0.16 m, fixed corotated, nu 0.3, 1050 kg/m^3)
on the ground, settled with grid damping.  Printed per grid resolution and jelly E: the sink
depth (the ball's lowest point below the slab's top surface far from the ball) against Hertz'
estimate for a rigid sphere on an elastic half-space,

    delta = (9 W^2 / (16 E*^2 R))^(1/3),   E* = E / (1 - nu^2),   W = m g,

and delta / R (Hertz assumes delta << R and a slab much thicker than the contact radius
sqrt(R delta): a thin slab is stiffer, so it sinks less than Hertz says).  The MPM grid smears
contact over about a cell, so the measured depth is meaningful where it spans several cells.
The sinking speed over the last 0.5 s shows whether the ball has come to rest (before the
grid coupling of rigid.py, "Coupling", it kept sinking at about 1 cm/s).

A second measurement has an exact answer: a steel plate (0.25 x 0.25 x 0.0625 m) resting on a
jelly column (0.25 m tall, nu = 0, on a frictionless ground). With nu = 0 the fixed-corotated
column is in uniaxial stress, Cauchy sigma = E (lambda - 1), so between its bottom and top
particle layers (s/2 and h - s/2 above the base) it shortens by
[(h - s) p + rho g ((h - s/2)^2 - (s/2)^2) / 2] / E, p = the plate's weight per area. Printed
for the column alone, with the plate as a free rigid body and with the plate deformable
(E 5e5): the shortening against that value, and the gap between the plate's lowest layer and
the column's top layer at 0.5 s and at the end (one particle spacing when the plate sits on
it; a shrinking gap is the plate creeping into the column).

    PYTHONPATH=src python benchmarks/bench_rigid.py [--grids 24 32] [--E 5e4 2e4] [--column-seconds 1.0] [--column-E 5e4]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from physgs_steps.mpm import Dynamics, Material, MPMSolver

R_BALL, RHO_BALL = 0.06, 7850.0
SLAB = (0.5, 0.36, 0.16)
RHO_JELLY, NU = 1050.0, 0.3
GROUND = 0.1
G_ACC = 9.8


def lattice(lo, hi, s):
    axes = [np.arange(a + s / 2, b - 1e-9, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def hertz_depth(E: float, nu: float, mass: float, R: float) -> float:
    """Hertz' indentation depth (m) of a rigid sphere of ``mass`` kg and radius R on an elastic
    half-space of modulus E (Pa) and Poisson ratio nu, under gravity."""
    W = mass * G_ACC
    Es = E / (1.0 - nu * nu)
    return (9.0 * W * W / (16.0 * Es * Es * R)) ** (1.0 / 3.0)


def sink_depth(G: int, E: float) -> tuple[float, float, float]:
    """(measured sink depth, ball mass, sinking speed over the last 0.5 s in m/s) of the ball
    settled on the slab at grid ``G`` (2 s)."""
    s = 0.5 / G
    lo = np.array([0.5 - SLAB[0] / 2, 0.5 - SLAB[1] / 2, GROUND])
    xj = lattice(lo, lo + np.array(SLAB), s)
    top0 = GROUND + SLAB[2]
    c = np.array([0.5, 0.5, top0 + R_BALL + 0.5 * s])
    cube = lattice(c - R_BALL, c + R_BALL, s)
    xb = cube[np.linalg.norm(cube - c, axis=1) <= R_BALL]
    x = np.r_[xj, xb]
    mat = np.r_[np.zeros(len(xj), int), np.ones(len(xb), int)]
    jelly = Material("fixed_corotated", "identity", E=E, nu=NU, density=RHO_JELLY, name="jelly")
    ball = Material("fixed_corotated", "identity", E=2e7, nu=0.3, density=RHO_BALL, name="ball", rigid=True)
    dyn = Dynamics.from_config({"ground": {"height": GROUND, "friction": 0.5, "surface": "separate"}, "damping": 6.0})
    sol = MPMSolver([jelly, ball], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    dt = 0.4 * (1.0 / G) / jelly.wave_speed
    far = np.linalg.norm(xj[:, :2] - 0.5, axis=1) > 0.15
    top = far & (xj[:, 2] > xj[:, 2].max() - s / 2)

    def depth() -> float:
        xs = sol.get_state()["x"].astype(np.float64)
        surface = xs[mat == 0][top, 2].mean() + s / 2   # the slab's face: half a spacing above the top layer
        lowest = xs[mat == 1, 2].min() - s / 2          # the ball's face below its lowest particle layer
        return float(surface - lowest)

    for _ in range(int(1.5 / dt)):
        sol.substep(dt)
    d1 = depth()
    for _ in range(int(0.5 / dt)):
        sol.substep(dt)
    d2 = depth()
    return d2, float(sol.rigid.mass[0]), (d2 - d1) / 0.5


def column(plate: str, seconds: float, E: float = 5.0e4, G: int = 32) -> tuple[float, float, float, float]:
    """(shortening, analytic shortening, gap at 0.5 s, gap at the end) in m of the jelly column
    under the steel plate (``plate``: none | rigid | deformable)."""
    s = 0.5 / G
    g0, h, t, w = 0.125, 0.25, 0.0625, 0.25
    lo = [0.5 - w / 2, 0.5 - w / 2]
    xj = lattice(lo + [g0], [0.5 + w / 2, 0.5 + w / 2, g0 + h], s)
    xp = lattice(lo + [g0 + h], [0.5 + w / 2, 0.5 + w / 2, g0 + h + t], s) if plate != "none" else np.zeros((0, 3))
    x = np.r_[xj, xp]
    mat = np.r_[np.zeros(len(xj), int), np.ones(len(xp), int)]
    jelly = Material("fixed_corotated", "identity", E=E, nu=0.0, density=1000.0, name="column")
    steel = Material("fixed_corotated", "identity", E=5.0e5, nu=0.0, density=7850.0, name="plate",
                     rigid=plate == "rigid")
    dyn = Dynamics.from_config({"ground": {"height": g0, "friction": 0.0, "surface": "separate"}, "damping": 8.0})
    sol = MPMSolver([jelly, steel] if plate != "none" else [jelly], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    dt = 0.4 * (1.0 / G) / max(jelly.wave_speed, steel.cfl_speed if plate != "none" else 0.0)
    z0 = xj[:, 2]
    bot, top = z0 < z0.min() + s / 2, z0 > z0.max() - s / 2

    def gap():
        if plate == "none":
            return float("nan")
        z = sol.get_state()["x"][:, 2].astype(np.float64)
        return float(z[mat == 1].min() - z[mat == 0][top].mean())

    n = int(seconds / dt)
    g_half = float("nan")
    for k in range(n):
        sol.substep(dt)
        if k == int(0.5 / dt):
            g_half = gap()
    zj = sol.get_state()["x"][mat == 0, 2].astype(np.float64)
    short = (z0[top].mean() - z0[bot].mean()) - (zj[top].mean() - zj[bot].mean())
    p = steel.density * G_ACC * t if plate != "none" else 0.0
    pred = ((h - s) * p + jelly.density * G_ACC * ((h - s / 2) ** 2 - (s / 2) ** 2) / 2) / jelly.E
    return float(short), float(pred), g_half, gap()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grids", type=int, nargs="+", default=[24, 32])
    ap.add_argument("--E", type=float, nargs="+", default=[5.0e4, 2.0e4])
    ap.add_argument("--column-seconds", type=float, default=1.0)
    ap.add_argument("--column-E", type=float, default=5.0e4)
    a = ap.parse_args()
    t0 = time.perf_counter()
    print(f"jelly column (E {a.column_E:.3g} Pa, nu 0, 0.25 m) under a steel plate, n_grid 32: shortening vs the exact value")
    for plate in ("none", "rigid", "deformable"):
        short, pred, g1, g2 = column(plate, a.column_seconds, a.column_E)
        print(f"  plate {plate:10s}: shortening {1e3 * short:5.1f} mm, exact {1e3 * pred:5.1f} mm (ratio "
              f"{short / pred:.2f}); plate gap {1e3 * g1:5.1f} mm at 0.5 s, {1e3 * g2:5.1f} mm at "
              f"{a.column_seconds:g} s (one spacing: {1e3 * 0.5 / 32:.1f} mm)")
    print("rigid steel ball (R 0.06 m) settled on a jelly slab 0.16 m thick: sink depth vs Hertz")
    for E in a.E:
        for G in a.grids:
            d, m, rate = sink_depth(G, E)
            h = hertz_depth(E, NU, m, R_BALL)
            print(f"  E {E:.3g} Pa, n_grid {G} (dx {1e3 / G:.1f} mm): sink {1e3 * d:6.1f} mm ({d * G:.2f} dx) at 2 s, "
                  f"still sinking {1e3 * rate:+.2f} mm/s, "
                  f"Hertz {1e3 * h:6.1f} mm (delta/R {h / R_BALL:.2f}, contact radius {1e3 * math.sqrt(R_BALL * h):.0f} mm), "
                  f"ratio {d / h:.2f}")
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
