"""Where a substep with a free rigid body goes: Taichi's kernel profiler (CUDA) over a rigid block
standing on the ground beside a soft block, grid 64 by default (the benchmark's full scale).

    python benchmarks/bench_rigid_substep.py [cuda|cpu] [n_grid] [substeps]

Prints the milliseconds per substep, particle-substeps/s and, on CUDA, the kernel table.
Measured on one H100 (commit 49b9f22, grid 64, 11,552 rigid + 31,616 soft particles): 20.9 ms a
substep, 2.1e6 particle-substeps/s; the rigid contact solve (rigid.py ``advance``, one thread per
body walking every contact candidate for 12 + 4 iterations) took 18.0 ms of it (96.7 %), every
other kernel together 0.6 ms.  On one H200, base 56b40c2 (one contact per body, obstacle and 2-cell
bin) against the parallel contact solve (rigid.py "Parallel contact solve") in the same call:
4.79 -> 2.51 ms a substep, the contact solve 3.017 ms (``advance``) -> 0.424 ms (``advance_jacobi``,
44 launched tasks) of device time a substep (24 tasks since, not yet timed on a GPU).
The per-kernel summary adds each kernel's offloaded tasks together.
"""
import os, re, sys, time
from collections import defaultdict
os.environ["PHYSGS_TI_PROFILER"] = "1"
import numpy as np
import taichi as ti
from physgs_steps.mpm import Dynamics, MPMSolver, preset
arch = sys.argv[1] if len(sys.argv) > 1 else "cuda"  # the kernel table is CUDA only
G = int(sys.argv[2]) if len(sys.argv) > 2 else 64
n = int(sys.argv[3]) if len(sys.argv) > 3 else 200
s = 1.0 / G / 2
def box(lo, hi):
    ax = [np.arange(l + s / 2, h, s) for l, h in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
h = 0.1
xr = box([0.30, 0.40, h], [0.45, 0.55, h + 0.25])      # a can-sized rigid block standing on the ground
xs = box([0.55, 0.35, h], [0.80, 0.65, h + 0.20])      # a soft block beside it
x = np.r_[xr, xs]
mat = np.r_[np.zeros(len(xr), int), np.ones(len(xs), int)]
stone = preset("stone", rigid=True)
jelly = preset("jelly")
dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}})
sol = MPMSolver([stone, jelly], n_grid=G, dynamics=dyn, backend=arch)
sol.set_particles(x, np.full(len(x), s ** 3), mat)
print(f"{arch}: grid {G}, {len(xr)} rigid + {len(xs)} soft particles, rigid chunks {sol.rigid.part.shape[0]}")
dt = 2e-4
for _ in range(5):
    sol.substep(dt)
sol.stats()
ti.sync()
ti.profiler.clear_kernel_profiler_info()
t = time.perf_counter()
for _ in range(n):
    sol.substep(dt)
ti.sync()
el = time.perf_counter() - t
print(f"{n} substeps in {el:.3f} s: {1e3 * el / n:.2f} ms each, {len(x) * n / el:.3g} particle-substeps/s")
# per kernel (its offloaded tasks together): device milliseconds a substep
from taichi.profiler.kernel_profiler import get_default_kernel_profiler
prof = get_default_kernel_profiler()
prof._update_records()
per = defaultdict(float)
tasks = defaultdict(set)
for rec in prof._traced_records:
    name = re.sub(r"_c\d+_\d+(_kernel_\d+_.*)?$", "", rec.name)
    per[name] += rec.kernel_time
    tasks[name].add(rec.name)
print(f"kernel time {sum(per.values()) / n:.3f} ms a substep; per kernel (ms a substep, tasks):")
for name, t in sorted(per.items(), key=lambda kv: -kv[1]):
    print(f"  {name:<24} {t / n:8.4f} ms  {len(tasks[name]):3d}")
ti.profiler.print_kernel_profiler_info("count")
