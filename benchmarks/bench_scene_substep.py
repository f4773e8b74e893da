"""Where a substep of a real scene goes: the solver of a pipeline run's final simulation (its
particles.h5 and BGDO's last params.json), timed on its own.

    python benchmarks/bench_scene_substep.py RUN_DIR SCENE [substeps] [--profile] [--threads N]

RUN_DIR is the directory snakemake ran in (it holds results/SCENE/fill/*/particles.h5 and
results/SCENE/sim/*/it*/params.json); the scene's config comes from config/ here.  After 400
warm-up substeps (kernel compilation, the start of the motion) it times ``substeps`` substeps
(default 300) at the final run's time step of duck_stone (4.12e-4 s; the time step does not
change the cost).  Prints milliseconds a substep and particle-substeps/s; with ``--profile``
Taichi's kernel profiler (it synchronises after every task, so the wall time grows) lists the
tasks of every kernel a substep and the wall time not spent in kernels (the host: Python and
launches).  ``--threads N`` runs Taichi and the private P2G grids on N threads.  It also prints
the process CPU time a substep (all threads): on a loaded machine the wall time follows the
other load, the CPU time mostly the work (compare before/after with it, alternating runs).

Measured on the 2-core CPU machine (duck_stone: 4,306 particles, 2,684 of them one free rigid
body), one thread, base b6562d3 / branch cpu_substep in one session: kernels 7.81 / 5.95 ms a
substep, wall 9.9 / 7.0 ms (docs/MEASURED.md, CPU substep).
"""
import argparse
import logging
import os
import sys
import time
from collections import defaultdict

ap = argparse.ArgumentParser()
ap.add_argument("run_dir")
ap.add_argument("scene")
ap.add_argument("substeps", nargs="?", type=int, default=300)
ap.add_argument("--profile", action="store_true")
ap.add_argument("--threads", type=int, default=0)
a = ap.parse_args()
if a.threads:
    os.cpu_count = lambda: a.threads  # backend.py and the solver's chunks read it
if a.profile:
    os.environ["PHYSGS_TI_PROFILER"] = "1"

import taichi as ti  # noqa: E402

from physgs_steps import simulate as S  # noqa: E402
from physgs_steps.errors import InputError  # noqa: E402

try:
    run = S.load_run(a.run_dir, a.scene)
except InputError as e:
    sys.exit(str(e))
sim, scene, parts = run["sim"], run["scene"], run["parts"]
par, mats, labels = run["params"], run["materials"], run["labels"]
sol = S.build_solver(parts, mats, labels, {"sim": sim, "scene": scene}, logging.getLogger("bench"), par)
dt = 4.12e-4
for _ in range(400):
    sol.substep(dt)
sol.stats()
ti.sync()
if a.profile:
    ti.profiler.clear_kernel_profiler_info()
t = time.perf_counter()
c = time.process_time()
for _ in range(a.substeps):
    sol.substep(dt)
ti.sync()
el = time.perf_counter() - t
cpu = time.process_time() - c
n = a.substeps
print(f"{a.scene}: {sol.n_particles} particles ({sol.rigid.n_particles if sol.rigid else 0} rigid), grid {sol.n_grid}, "
      f"{sol.n_chunks} thread(s): {n} substeps {1e3 * el / n:.3f} ms each, {sol.n_particles * n / el:.3g} "
      f"particle-substeps/s; CPU time {1e3 * cpu / n:.3f} ms each (all threads: the work, less sensitive than the "
      f"wall time to other load on a shared machine)")
if a.profile:
    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    prof = get_default_kernel_profiler()
    prof._update_records()
    per = defaultdict(float)
    for rec in prof._traced_records:
        per[rec.name] += rec.kernel_time
    total = sum(per.values()) / n
    for name, v in sorted(per.items(), key=lambda kv: -kv[1]):
        if v / n >= 0.005:
            print(f"  {v / n:8.3f} ms  {name}")
    print(f"kernels {total:.3f} ms a substep, host (Python, launches) {1e3 * el / n - total:.3f} ms")
