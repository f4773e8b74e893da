"""Where a small scene's substep goes on the GPU: host time (Python, Taichi's launch), kernel
launches (offloaded tasks) and device time, and what batching the substeps into ``ti.graph``
launches (``MPMSolver.substeps``) leaves of it.

    python benchmarks/bench_substep_launch.py [--run-dir DIR --scene bear] [--substeps N] [--profile]
        [--reps 1 4 8] [--rounds 3]

With ``--run-dir`` the solver is the scene's final simulation as a pipeline run left it (its
particles.h5 and BGDO's last params.json, as benchmarks/bench_scene_substep.py); without it a
bear-sized synthetic scene: 27,648 jelly particles (a 48 x 24 x 24 block at 1/128 spacing,
0.1 m above the ground, grid 32), falling under gravity onto the ground.  After 300 warm-up
substeps it prints, per substep (milliseconds unless marked):

* ``single``: N calls of ``substep`` then one sync (the wall time a substep costs the GPU run);
* ``host``: the Python loop alone over a burst of substeps too short to fill CUDA's launch queue
  (what the host needs per substep; above the device time the GPU waits: launch-bound);
* ``python launch context``: building the substep's launch context in Python (Launcher's
  per-launch work: ~40 ``set_arg`` calls), without launching;
* ``batched R=...`` (a tree with ``MPMSolver.substeps``), per number of substeps a launch R
  (``--reps``, PHYSGS_TI_REPS; default the solver's for the arch), alternating the R values over
  ``--rounds`` rounds, medians: ``wall``, N substeps in calls of 60 (a frame), one sync; ``host``,
  the host time per substep of one call of 64 substeps (min over 20 calls; 64 substeps are 384
  offloaded tasks whatever R, too few to fill CUDA's launch queue); ``first call``: the first
  call with that R, one launch (its kernel's compilation, or its load from Taichi's offline
  cache; R = 1: already loaded); and ``R=... vs single``: 300 substeps from one state, the
  largest difference in x from 300 calls of ``substep``;
* ``frames``: frames of 60 substeps, each followed by ``solver.stats()`` (a host sync and a
  read-back, as run_frames does), with the batched substeps where the tree has them;
* ``per frame``: ``stats()`` and ``save_backup()`` (forward_sim's every frame) alone;
* synthetic kernels through backend.Launcher: per-call time of a kernel with one 1-element loop
  and 1 or 38 ndarray arguments, and with 6 or 9 such loops (offloaded tasks);
* with ``--profile`` (Taichi's kernel profiler; it synchronises after every task): the device
  time of each offloaded task a substep and their count, the same for batched substeps per R,
  and for a ``stats()`` call.

On the GPU: ``python benchmarks/bench_substep_launch.py --reps 1 2 4 8`` (add ``--run-dir
results/bear --scene bear`` for the pipeline's bear).

Both the batched and single substeps run the same compiled kernel; on CUDA their results differ
only by the order of float atomics, which the ``batched vs single`` line bounds.
"""
import argparse
import logging
import os
import sys
import time

ap = argparse.ArgumentParser()
ap.add_argument("--run-dir")
ap.add_argument("--scene", default="bear")
ap.add_argument("--substeps", type=int, default=3000)
ap.add_argument("--arch", default="cuda")
ap.add_argument("--profile", action="store_true")
ap.add_argument("--reps", type=int, nargs="+", help="substeps a launch to compare (PHYSGS_TI_REPS values)")
ap.add_argument("--rounds", type=int, default=3, help="rounds over the --reps values (alternating)")
a = ap.parse_args()
if a.profile:
    os.environ["PHYSGS_TI_PROFILER"] = "1"

import numpy as np  # noqa: E402
import taichi as ti  # noqa: E402

from physgs_steps.mpm import Dynamics, Material, MPMSolver  # noqa: E402
from physgs_steps.mpm import backend as B  # noqa: E402
from physgs_steps.mpm import solver as S  # noqa: E402

DT = 2e-4  # the time step does not change the cost
FRAME = 60  # substeps a frame (the default bear: 9,238 substeps over 3 x 149 frames)
BURST = 64  # substeps of a host-time call: a multiple of 1, 2, 4, 8, 16


def solver() -> MPMSolver:
    if a.run_dir:
        from physgs_steps import simulate as S

        run = S.load_run(a.run_dir, a.scene)
        return S.build_solver(run["parts"], run["materials"], run["labels"],
                              {"sim": {**run["sim"], "backend": a.arch}, "scene": run["scene"]},
                              logging.getLogger("bench"), run["params"])
    s = 1 / 128
    axes = [np.arange(0.3 + s / 2, 0.3 + 48 * s, s), np.arange(0.4 + s / 2, 0.4 + 24 * s, s),
            np.arange(0.1 + s / 2, 0.1 + 24 * s, s)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    jelly = Material("fixed_corotated", "identity", E=2e5, nu=0.3, density=1000.0, name="jelly")
    dyn = Dynamics.from_config({"ground": {"height": 0.05, "friction": 0.5, "surface": "separate"}}, "bench")
    sol = MPMSolver([jelly], n_grid=32, dynamics=dyn, backend=a.arch)
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    return sol


def ms(seconds: float, n: int) -> str:
    return f"{1e3 * seconds / n:.4f}"


def set_reps(reps: int | None) -> None:
    """PHYSGS_TI_REPS for the next substeps() calls (None: as the caller's environment had it)."""
    if reps is None:
        os.environ.pop("PHYSGS_TI_REPS", None)
        if ENV_REPS is not None:
            os.environ["PHYSGS_TI_REPS"] = ENV_REPS
    else:
        os.environ["PHYSGS_TI_REPS"] = str(reps)


ENV_REPS = os.environ.get("PHYSGS_TI_REPS")
sol = solver()
batched = hasattr(sol, "substeps")
with_reps = hasattr(S, "reps_per_launch")
REPS = (a.reps or [S.reps_per_launch(sol.arch)]) if with_reps else [1]
for _ in range(300):
    sol.substep(DT)
if batched:
    set_reps(1)
    sol.substeps(300, DT)  # builds the one-substep graphs
    set_reps(None)
sol.stats()  # compiled (or loaded) before any timing: a first call's compilation would count
sol.save_backup()
ti.sync()
print(f"scene: {sol.n_particles} particles, grid {sol.n_grid}, arch {B.current_arch()}, p2g {sol.p2g}, "
      f"tree {'with' if batched else 'without'} MPMSolver.substeps", flush=True)
N = a.substeps

if a.profile:
    from collections import defaultdict

    from taichi.profiler.kernel_profiler import get_default_kernel_profiler

    prof = get_default_kernel_profiler()

    def profile(run, n: int, title: str, unit: str = "substep") -> None:
        """``run()`` under the profiler: offloaded tasks and device time per ``n`` units."""
        ti.sync()
        ti.profiler.clear_kernel_profiler_info()
        prof._traced_records.clear()
        run()
        ti.sync()
        prof._update_records()
        per, count = defaultdict(float), defaultdict(int)
        for rec in prof._traced_records:
            per[rec.name] += rec.kernel_time
            count[rec.name] += 1
        print(f"profile of {title}: {sum(count.values()) / n:.1f} offloaded tasks (launches) a {unit}, "
              f"device time {sum(per.values()) / n:.4f} ms a {unit}")
        for name, v in sorted(per.items(), key=lambda kv: -kv[1]):
            print(f"  {v / n:8.4f} ms  x{count[name] / n:.2f}  {name}")

    n = 200
    profile(lambda: [sol.substep(DT) for _ in range(n)], n, "substep(), one substep a launch")
    if batched:
        for R in REPS:
            set_reps(R)
            sol.substeps(n, DT)  # compiled or loaded before the profile
            profile(lambda: sol.substeps(n, DT), n, f"substeps() with R={R}")
        set_reps(None)
    profile(lambda: [sol.stats() for _ in range(20)], 20, "stats()", "call")
    sys.exit(0)

# single substeps
ti.sync()
t = time.perf_counter()
for _ in range(N):
    sol.substep(DT)
ti.sync()
single = time.perf_counter() - t
print(f"single: {ms(single, N)} ms a substep ({N} substeps)", flush=True)

# host time alone, bursts that do not fill the launch queue
hs = []
for _ in range(20):
    ti.sync()
    t = time.perf_counter()
    for _ in range(16):
        sol.substep(DT)
    hs.append(time.perf_counter() - t)
ti.sync()
print(f"host: {ms(min(hs), 16)} ms a substep (min over 20 bursts of 16; median {ms(sorted(hs)[10], 16)})")

# Python's share: building the launch context (no launch)
plan = sol._launch_substep._plan
if plan is not None:
    _arrays, _templates, t_kernel, nd_slots, sc_slots = plan
    args = None
    t = time.perf_counter()
    for _ in range(N):
        ctx = t_kernel.make_launch_context()
        for _i, idx, arr in nd_slots:
            ctx.set_arg_ndarray(idx, arr)
        for _i, idx, kind in sc_slots:
            ctx.set_arg_float(idx, 1.0)
    py = time.perf_counter() - t
    prog = B._current_prog()
    t = time.perf_counter()
    for _ in range(N):
        prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
    look = time.perf_counter() - t
    print(f"python launch context: {ms(py, N)} ms a substep ({len(nd_slots)} ndarrays, {len(sc_slots)} scalars); "
          f"compiled-kernel lookup {ms(look, N)} ms")

def wall_batched() -> float:
    """N substeps in calls of FRAME, one sync: seconds."""
    ti.sync()
    t = time.perf_counter()
    done = 0
    while done < N:
        m = min(FRAME, N - done)
        sol.substeps(m, DT)
        done += m
    ti.sync()
    return time.perf_counter() - t


def host_batched() -> list:
    """Seconds of 20 calls of BURST substeps, each after a sync (the host's time alone)."""
    hb = []
    for _ in range(20):
        ti.sync()
        t = time.perf_counter()
        sol.substeps(BURST, DT)
        hb.append(time.perf_counter() - t)
    ti.sync()
    return hb


R_FRAMES = REPS[-1]  # the R of the frames below
if batched:
    first = {}
    for R in REPS:  # each R's kernel compiled (or loaded from the offline cache), then its graphs built
        set_reps(R)
        ti.sync()
        t = time.perf_counter()
        sol.substeps(R, DT)  # one launch
        ti.sync()
        first[R] = time.perf_counter() - t
        sol.substeps(BURST, DT)
        sol.substeps(FRAME, DT)
    walls, hosts = {R: [] for R in REPS}, {R: [] for R in REPS}
    for _ in range(a.rounds):  # the R values alternate: drifts of the machine touch them alike
        for R in REPS:
            set_reps(R)
            walls[R].append(wall_batched())
            hosts[R].append(min(host_batched()))
    for R in REPS:
        bw, bh = float(np.median(walls[R])), float(np.median(hosts[R]))
        print(f"batched R={R}: wall {ms(bw, N)} ms a substep in calls of {FRAME} ({single / bw:.2f}x single; rounds "
              f"{' '.join(ms(w, N) for w in walls[R])}); host {ms(bh, BURST)} ms a substep (min over 20 calls of "
              f"{BURST}; rounds {' '.join(ms(h, BURST) for h in hosts[R])}); first call {first[R]:.2f} s "
              f"(compilation or offline-cache load)", flush=True)
    bt = float(np.median(walls[R_FRAMES]))
    set_reps(R_FRAMES)

# frames: substeps + stats() (a sync and read-back a frame)
nf = max(1, N // FRAME)
ti.sync()
t = time.perf_counter()
for _ in range(nf):
    if batched:
        sol.substeps(FRAME, DT)
    else:
        for _ in range(FRAME):
            sol.substep(DT)
    sol.stats()
fr = time.perf_counter() - t
print(f"frames: {ms(fr, nf * FRAME)} ms a substep with stats() after every {FRAME} "
      f"({f'batched, R={R_FRAMES}' if batched else 'single'}); stats() {ms(fr - (bt if batched else single) * nf * FRAME / N, nf)} "
      f"ms a frame beyond the substeps")

# the per-frame work alone: stats() (run_frames, every frame), save_backup() (forward_sim, every frame)
ti.sync()
t = time.perf_counter()
for _ in range(200):
    sol.stats()
st_s = time.perf_counter() - t
ti.sync()
t = time.perf_counter()
for _ in range(200):
    sol.save_backup()
ti.sync()
bk_s = time.perf_counter() - t
print(f"per frame: stats() {ms(st_s, 200)} ms a call, save_backup() {ms(bk_s, 200)} ms a call (200 calls each)")

# equivalence on this arch: batched vs single from the same state
if batched:
    st0 = sol.get_state()
    t0 = sol.time
    sol.set_state(st0["x"], st0["v"], st0["C"], st0["F"])
    for _ in range(300):
        sol.substep(DT)
    st1 = sol.get_state()
    moved = float(np.abs(st1["x"] - st0["x"]).max())
    for R in REPS:
        set_reps(R)
        sol.set_state(st0["x"], st0["v"], st0["C"], st0["F"])
        sol.time = t0
        sol.substeps(300, DT)
        st2 = sol.get_state()
        diff = float(np.abs(st1["x"] - st2["x"]).max())
        print(f"batched R={R} vs single, 300 substeps from one state: max |x| difference {diff:.3g} (domain units; "
              f"the particles moved up to {moved:.3g}), bitwise {np.array_equal(st1['x'], st2['x'])}")
    set_reps(None)

# synthetic kernels: per-argument and per-task costs of a launch
V1 = ti.types.ndarray(dtype=ti.f32, ndim=1)


@ti.kernel
def one_arg(a0: V1):
    for i in range(1):
        a0[i] += 1.0


@ti.kernel
def many_args(a0: V1, a1: V1, a2: V1, a3: V1, a4: V1, a5: V1, a6: V1, a7: V1, a8: V1, a9: V1, a10: V1, a11: V1,
              a12: V1, a13: V1, a14: V1, a15: V1, a16: V1, a17: V1, a18: V1, a19: V1, a20: V1, a21: V1, a22: V1,
              a23: V1, a24: V1, a25: V1, a26: V1, a27: V1, a28: V1, a29: V1, f0: ti.f32, f1: ti.f32, f2: ti.f32,
              f3: ti.f32, f4: ti.f32, f5: ti.f32, f6: ti.f32, f7: ti.f32):
    for i in range(1):
        a0[i] += f0


@ti.kernel
def six_tasks(a0: V1):
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0


@ti.kernel
def nine_tasks(a0: V1):
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0
    for i in range(1):
        a0[i] += 1.0


arrs = [ti.ndarray(ti.f32, 8) for _ in range(30)]
for name, kern, args in (("1 ndarray, 1 task", one_arg, (arrs[0],)),
                         ("30 ndarrays + 8 scalars, 1 task", many_args, tuple(arrs) + (1.0,) * 8),
                         ("1 ndarray, 6 tasks", six_tasks, (arrs[0],)),
                         ("1 ndarray, 9 tasks", nine_tasks, (arrs[0],))):
    lau = B.Launcher(kern)
    for _ in range(50):
        lau(*args)
    ti.sync()
    n = 3000
    t = time.perf_counter()
    for _ in range(n):
        lau(*args)
    ti.sync()
    el = time.perf_counter() - t
    print(f"synthetic {name}: {1e6 * el / n:.1f} us a call (Launcher)")
