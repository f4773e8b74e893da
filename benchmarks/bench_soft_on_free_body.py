"""A soft block dropped on a free rigid block lying on the ground, against the same block fixed
(static geometry) and against the ground itself: when the soft block comes to rest and how far
above the support it rests (issue #15, "the duck dropped on the stone rests on it").

    python benchmarks/bench_soft_on_free_body.py [free,fixed,ground] [n_grid] [seconds]

No damping (as the built-in scenes).  Per variant it prints, every 0.2 s, the soft block's
kinetic energy (total and about its centre of mass; the stored velocity is staggered by
-g dt/2, added back), its largest particle speed and the gap between its lowest particles and
the support's highest ones (cells), then the first time after which every particle stayed
below 0.01 m/s (sim.rest.speed) and the mean gap over the last second.  A resting contact of
two sampled surfaces has a gap of one particle spacing between the particle layers (0.5 cells
at 2 particles per cell and axis); the ground's plane sits at the block's first particle layer
height minus half a spacing.

Measured on the 2-core machine (grid 16, 3 s; rest15 branch): before (base 73e9aee, the
soft material glued to the body's covered nodes) free block: at rest from 1.47 s, layer gap
0.971 cells; fixed block: 0.53 s, 0.341; ground: 0.90 s, 0.349 (plane + half a spacing).  With
the soft-body contact of rigid.py "Coupling" the free block: at rest from 0.77 s, gap 0.348.
"""
import sys
import time

import numpy as np

from physgs_steps.mpm import Dynamics, Material, MPMSolver

REST_SPEED = 0.01


def box(lo, hi, s):
    axes = [np.arange(a + s / 2, b - 1e-9, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def run(variant: str, G: int = 16, T: float = 3.0, E: float = 1e5, drop: float = 0.03) -> dict:
    s = 1 / (2 * G)
    h = 0.125
    top = h + 0.125
    xs = box([0.25, 0.25, h], [0.75, 0.75, top], s)                      # the support: 0.5 x 0.5 x 0.125 m
    xj = box([0.375, 0.375, top + drop], [0.625, 0.625, top + drop + 0.1875], s)  # soft block 3 cm above it
    soft = Material("fixed_corotated", "identity", E=E, nu=0.4, density=1100.0, name="soft")
    block = Material("fixed_corotated", "identity", E=2e7, nu=0.25, density=2600.0, name="block", rigid=True,
                     friction=0.5)
    if variant == "ground":
        x, mat, mats, ground = xj, np.zeros(len(xj), int), [soft], top
    else:
        x = np.r_[xs, xj]
        mat = np.r_[np.zeros(len(xs), int), np.ones(len(xj), int)]
        mats, ground = [block.with_(fixed=(variant == "fixed")), soft], h
    dyn = Dynamics.from_config({"ground": {"height": ground, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver(mats, n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    js = mat == (0 if variant == "ground" else 1)
    m = soft.density * s ** 3
    dt = 0.4 * (1 / G) / soft.wave_speed
    n = int(np.ceil(1 / 30 / dt))
    dt = 1 / 30 / n
    rows = []
    t0 = time.perf_counter()
    for f in range(int(round(T * 30))):
        for _ in range(n):
            sol.substep(dt)
        st = sol.get_state()
        v = st["v"][js].astype(np.float64) + np.array([0.0, 0.0, 9.8 * dt / 2])
        ke = 0.5 * m * (v ** 2).sum()
        vc = v.mean(0)
        support = st["x"][~js, 2].max() if variant == "free" else (top if variant == "ground" else xs[:, 2].max())
        gap = (st["x"][js, 2].min() - support) * G
        if variant == "ground":
            gap += 0.5 * s * G  # the plane: half a spacing above a support's top particle layer
        rows.append(((f + 1) / 30, ke, ke - 0.5 * m * js.sum() * (vc ** 2).sum(), np.linalg.norm(v, axis=1).max(), gap))
    a = np.array(rows)
    moving = np.flatnonzero(a[:, 3] >= REST_SPEED)
    rest = float(a[moving[-1] + 1, 0]) if len(moving) and moving[-1] + 1 < len(a) else (0.0 if not len(moving) else None)
    return {"rows": a, "rest_from": rest, "gap": float(a[-30:, 4].mean()), "seconds": time.perf_counter() - t0}


if __name__ == "__main__":
    variants = (sys.argv[1] if len(sys.argv) > 1 else "free,fixed,ground").split(",")
    G = int(sys.argv[2]) if len(sys.argv) > 2 else 16
    T = float(sys.argv[3]) if len(sys.argv) > 3 else 3.0
    for v in variants:
        r = run(v, G, T)
        print(f"{v}: grid {G}, {T:g} s in {r['seconds']:.1f} s wall")
        for t, ke, kei, vmax, gap in r["rows"][5::6]:
            print(f"  t {t:.2f} s  KE {ke:.2e} J (internal {kei:.1e})  v_max {vmax:.4f} m/s  gap {gap:+.3f} cells")
        rest = "never" if r["rest_from"] is None else f"{r['rest_from']:.2f} s"
        print(f"  -> every particle below {REST_SPEED} m/s from {rest}; gap over the last second {r['gap']:.3f} cells")
