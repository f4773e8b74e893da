"""Proxy particles of free rigid bodies (sim.rigid_particles_per_cell, rigid.py "Proxy particles")
against the full particle set, on a real scene: the particles of a pipeline run's final
simulation (its particles.h5 and BGDO's last params.json) simulated for a few frames with the
frame loop of final_sim (run_frames: adaptive substeps, rest hold), once per setting.

    python benchmarks/bench_rigid_proxies.py RUN_DIR SCENE [frames] [--ppc none jitter 1 2] [--threads N]

RUN_DIR is the directory snakemake ran in (results/SCENE/fill/*/particles.h5,
results/SCENE/sim/*/it*/params.json); the scene's config comes from config/ here.  Prints per
setting the simulated particles, substeps and seconds of substepping (one thread unless
--threads), and against the first setting (the reference, ``none``: every particle; ``jitter``
is every particle too, with every position moved by a random 1e-6 domain units (3e-5 cells at
grid 32), which shows how far the scene itself amplifies a rounding-size change): the
largest difference over the frames of each rigid body's centre (grid cells) and rotation
(degrees), the deformable instances' final state (mean and largest particle displacement
difference, cells), and the contact between each deformable and each rigid instance: the 20
smallest distances from a deformable particle to the body's particles (mean, cells) at the
end, smaller = sunk in further.
"""
import argparse
import logging
import os
import sys
import time

ap = argparse.ArgumentParser()
ap.add_argument("run_dir")
ap.add_argument("scene")
ap.add_argument("frames", nargs="?", type=int, default=60)
ap.add_argument("--ppc", nargs="+", default=["none", "1"])
ap.add_argument("--threads", type=int, default=1)
a = ap.parse_args()
if a.threads:
    os.cpu_count = lambda: a.threads  # backend.py and the solver's chunks read it

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from physgs_steps import simulate as S  # noqa: E402
from physgs_steps.errors import InputError  # noqa: E402
from physgs_steps.mpm.rest import RestPolicy  # noqa: E402
from physgs_steps.mpm.runner import run_frames  # noqa: E402
from physgs_steps.mpm.stability import Thresholds  # noqa: E402
from physgs_steps.mpm.timestep import TimeStepper  # noqa: E402

try:
    run = S.load_run(a.run_dir, a.scene)
except InputError as e:
    sys.exit(str(e))
sim, scene, parts = run["sim"], run["scene"], run["parts"]
par, mats, labels = run["params"], run["materials"], run["labels"]
log = logging.getLogger("bench")
runs = {}
for ppc in a.ppc:
    value = None if ppc in ("none", "jitter") else float(ppc)
    p_run = dict(parts)
    if ppc == "jitter":
        p_run["x"] = (parts["x"] + np.random.default_rng(0).uniform(-1e-6, 1e-6, parts["x"].shape)).astype(np.float32)
    sol = S.build_solver(p_run, mats, labels, {"sim": {**sim, "rigid_particles_per_cell": value}, "scene": scene},
                         log, par)
    stepper = TimeStepper.from_config(sim)
    rest = RestPolicy.from_config(sim.get("rest"), sol.dynamics)
    index = {l: i for i, l in enumerate(labels)}
    mat = np.array([index[int(l)] for l in parts["label"]])
    free = sol._rigid_k
    track = {"c": [], "R": []}

    def on_frame(k, t, dt_next):
        if sol.rigid is not None:
            st = sol.rigid.state()
            track["c"].append(st["c"] / sol.dx)
            track["R"].append(st["R"])

    t0 = time.perf_counter()
    res = run_frames(sol, a.frames, stepper, Thresholds.from_config(sim.get("stability")), on_frame, log, rest=rest,
                     stage="bench")
    wall = time.perf_counter() - t0
    st = sol.get_state()
    runs[ppc] = dict(c=np.array(track["c"]), R=np.array(track["R"]), x=st["x"].astype(np.float64) * sol.n_grid,
                     n=sol.n_particles, substeps=int(sum(res.substeps)), secs=res.step_seconds, wall=wall,
                     stable=res.stable, held=res.held_frames)
    print(f"{a.scene} ppc {ppc:>4}: {sol.n_particles} particles simulated, {runs[ppc]['substeps']} substeps, "
          f"substepping {res.step_seconds:.1f} s ({1e3 * res.step_seconds / max(runs[ppc]['substeps'], 1):.2f} ms "
          f"a substep), {res.held_frames} frames held at rest, stable {res.stable}", flush=True)

soft = [k for k, m in enumerate(mats) if not m.rigid and not m.fixed]
rig = [k for k, m in enumerate(mats) if m.rigid and not m.fixed and (S.rigid_setting(mats, sim)[k].rigid)]


def contact(x, ks, kr):
    d, _ = cKDTree(x[mat == kr]).query(x[mat == ks], k=1)
    return float(np.sort(d)[:20].mean())


ref = runs[a.ppc[0]]
for ppc in a.ppc:
    r = runs[ppc]
    out = [f"{a.scene} ppc {ppc:>4} vs {a.ppc[0]}:"]
    n = min(len(r["c"]), len(ref["c"]))
    for b, k in enumerate(rig):
        if n:
            dc = np.abs(r["c"][:n, b] - ref["c"][:n, b]).max()
            ang = max(np.degrees(np.arccos(np.clip((np.trace(Ra @ Rb.T) - 1) / 2, -1, 1)))
                      for Ra, Rb in zip(r["R"][:n, b], ref["R"][:n, b]))
            moved = np.abs(ref["c"][:n, b] - ref["c"][0, b]).max()
            out.append(f"body {mats[k].name}: centre diff max {dc:.3f} cells (it moved {moved:.2f}), rotation diff "
                       f"max {ang:.3f} deg;")
    for k in soft:
        d = np.linalg.norm(r["x"][mat == k] - ref["x"][mat == k], axis=1)
        out.append(f"{mats[k].name} final: mean diff {d.mean():.3f}, max {d.max():.3f} cells;")
        for kr in rig:
            out.append(f"{mats[k].name}-{mats[kr].name} contact {contact(r['x'], k, kr):.3f} cells "
                       f"(reference {contact(ref['x'], k, kr):.3f});")
    print(" ".join(out))
