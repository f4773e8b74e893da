"""Benchmark: particle-substeps per second of physgs' MLS-MPM solver beside a textbook
single-material MLS-MPM kernel (mpm88/mpm3d structure: fixed-corotated stress from ti.svd in
P2G, float atomics, gravity and slip walls), on the same particles in the same process.

    python benchmarks/bench_mpm.py                      # ti.cpu, and ti.cuda when available
    python benchmarks/bench_mpm.py --arch cuda --sizes 1000000
    python benchmarks/bench_mpm.py --arch cpu --sizes 30000 --seconds 5
    python benchmarks/bench_mpm.py --arch cuda --sizes 300000 1000000 --warp-solver PhysGaussian/mpm_solver_warp
    python benchmarks/bench_mpm.py --arch cuda --sizes 1000000 --profile     # Taichi kernel profiler per pass
    python benchmarks/bench_mpm.py --arch cuda --sizes 300000 1000000 --p2g atomic coarsened coarsened:K=32
    python benchmarks/bench_mpm.py --arch cuda --sizes 1000000 --windows 8 --p2g coarsened:N=16 coarsened:N=8

P2G variants (``--p2g``, src/physgs_steps/mpm/p2g_sorted.py), each measured on its own solver
from the same particles after the default solver: ``atomic`` (one float atomic per particle
and node, the transfer before coarsening) and ``coarsened`` (runs of particles with the same
stencil base summed before one write per run; device re-sort by stencil base; on CUDA by
default warp runs, on the CPU runs of 16 consecutive particles in registers), with
options ``:K=<particles per thread>`` (``K=cell``: a thread per cell of the last sort; ``K=warp``:
a thread per particle, runs summed across a warp's lanes, CUDA only),
``:N=<substeps between re-sorts>``, ``:st=0|1`` (CUDA: G2P's stores staged through shared
memory, the default there, or not; src/physgs_steps/mpm/staged.py), ``:S=1|3|9`` (threads sharing a run's 27 nodes), ``:grid=private|atomic`` (CPU: per-thread grids, the default there, or one grid with atomics
as on CUDA).  A table per size gives each variant's rate and its ratio to ``atomic``.

Particles fill a box in random order (as gaussians come from a .ply); the textbook kernel gets
them in that order and, for reference, sorted by cell as physgs stores them.  The figure is
the ratio physgs / textbook (target: >= 1).  Both use the jelly material (E 1e5 Pa, nu 0.3,
1000 kg/m^3) and the same dt.  Each arch runs in its own process (Taichi has one arch per
process).
"""
import argparse
import functools
import json
import os
import subprocess
import sys
import time

import numpy as np

ROWS = "ROWS "
BATCH = 4  # physgs' substeps per call: MPMSolver.substeps, as the simulation stages advance
GRID_FOR = {30_000: 32, 100_000: 48, 300_000: 64, 1_000_000: 96}
DEFAULT_VARIANTS = ["atomic", "coarsened", "coarsened:K=16", "coarsened:K=8", "coarsened:K=32", "coarsened:K=cell",
                    "coarsened:N=4", "coarsened:N=64"]


def parse_variant(text: str) -> dict:
    """``coarsened:K=32:N=4:grid=atomic`` -> solver keyword arguments (and the label)."""
    from physgs_steps.mpm import p2g_sorted as P2G

    name, *opts = text.split(":")
    if name not in ("atomic", "coarsened"):
        raise SystemExit(f"--p2g {text!r}: the mode must be atomic or coarsened")
    kw = {"p2g": name}  # the solver's defaults (run_length auto: warp runs on CUDA, RESORT_EVERY[_WARP])
    for o in opts:
        key, _, value = o.partition("=")
        if key == "K":
            kw["run_length"] = value if value in ("cell", "warp") else int(value)
        elif key == "N":
            kw["resort_every"] = int(value)
        elif key == "S":
            kw["split"] = int(value)
        elif key == "st" and value in ("0", "1"):
            kw["staged"] = value == "1"
        elif key == "grid" and value in ("private", "atomic"):
            kw["grid_mode"] = value
        else:
            raise SystemExit(f"--p2g {text!r}: unknown option {o!r} (K=<int>, N=<int>, S=1|3|9, st=0|1, grid=private|atomic)")
    return kw


@functools.lru_cache(maxsize=None)
def _textbook():
    """The textbook kernel (defined here so that it compiles only when benchmarked)."""
    import taichi as ti

    vec3 = ti.types.vector(3, ti.f32)
    mat3 = ti.types.matrix(3, 3, ti.f32)

    @ti.kernel
    def substep(x: ti.types.ndarray(dtype=vec3, ndim=1), v: ti.types.ndarray(dtype=vec3, ndim=1),
                C: ti.types.ndarray(dtype=mat3, ndim=1), F: ti.types.ndarray(dtype=mat3, ndim=1),
                grid_v: ti.types.ndarray(dtype=vec3, ndim=3), grid_m: ti.types.ndarray(dtype=ti.f32, ndim=3),
                dt: ti.f32, dx: ti.f32, p_vol: ti.f32, p_mass: ti.f32, mu: ti.f32, lam: ti.f32):
        inv_dx = 1.0 / dx
        G = grid_m.shape[0]
        for I in ti.grouped(grid_m):
            grid_v[I] = ti.Vector.zero(ti.f32, 3)
            grid_m[I] = 0.0
        for p in x:
            base = ti.cast(x[p] * inv_dx - 0.5, ti.i32)
            fx = x[p] * inv_dx - ti.cast(base, ti.f32)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            F[p] = (ti.Matrix.identity(ti.f32, 3) + dt * C[p]) @ F[p]
            U, sig, V = ti.svd(F[p])
            J = sig[0, 0] * sig[1, 1] * sig[2, 2]
            stress = 2.0 * mu * (F[p] - U @ V.transpose()) @ F[p].transpose() + \
                ti.Matrix.identity(ti.f32, 3) * lam * J * (J - 1.0)
            affine = (-dt * p_vol * 4.0 * inv_dx * inv_dx) * stress + p_mass * C[p]
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                offset = ti.Vector([i, j, k])
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                weight = w[i][0] * w[j][1] * w[k][2]
                grid_v[base + offset] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + offset] += weight * p_mass
        for I in ti.grouped(grid_m):
            if grid_m[I] > 0:
                gv = grid_v[I] / grid_m[I]
                gv[2] -= dt * 9.8
                for d in ti.static(range(3)):
                    if I[d] < 3 and gv[d] < 0:
                        gv[d] = 0.0
                    if I[d] > G - 3 and gv[d] > 0:
                        gv[d] = 0.0
                grid_v[I] = gv
        for p in x:
            base = ti.cast(x[p] * inv_dx - 0.5, ti.i32)
            fx = x[p] * inv_dx - ti.cast(base, ti.f32)
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(ti.f32, 3)
            new_C = ti.Matrix.zero(ti.f32, 3, 3)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                dpos = (ti.Vector([i, j, k]).cast(ti.f32) - fx) * dx
                g_v = grid_v[base + ti.Vector([i, j, k])]
                weight = w[i][0] * w[j][1] * w[k][2]
                new_v += weight * g_v
                new_C += 4.0 * inv_dx * inv_dx * weight * g_v.outer_product(dpos)
            v[p] = new_v
            x[p] += dt * new_v
            C[p] = new_C

    class Textbook:
        def __init__(self, x_m: np.ndarray, G: int, L: float, mu: float, lam: float, p_vol: float, p_mass: float):
            P = len(x_m)
            self.x = ti.ndarray(vec3, P)
            self.x.from_numpy(x_m.astype(np.float32))
            self.v, self.C, self.F = ti.ndarray(vec3, P), ti.ndarray(mat3, P), ti.ndarray(mat3, P)
            self.v.from_numpy(np.zeros((P, 3), np.float32))
            self.C.from_numpy(np.zeros((P, 3, 3), np.float32))
            self.F.from_numpy(np.tile(np.eye(3, dtype=np.float32), (P, 1, 1)))
            self.gv, self.gm = ti.ndarray(vec3, (G, G, G)), ti.ndarray(ti.f32, (G, G, G))
            self.args = (L / G, p_vol, p_mass, mu, lam)

        def substep(self, dt: float) -> None:
            substep(self.x, self.v, self.C, self.F, self.gv, self.gm, dt, *self.args)

    return Textbook


def _particles(P: int, seed: int = 0) -> np.ndarray:
    """[P, 3] random points in a box of the unit domain (random order, like gaussians)."""
    rng = np.random.default_rng(seed)
    return (0.3 + 0.4 * rng.random((P, 3))).astype(np.float64)


def _rate(step, P: int, seconds: float):
    import taichi as ti

    step()  # compile / warm up
    ti.sync()
    n, t0 = 0, time.perf_counter()
    while n < 3 or time.perf_counter() - t0 < seconds:
        step()
        n += 1
        if n % 5 == 0:
            ti.sync()
    ti.sync()
    return P * n / (time.perf_counter() - t0), n


def _profile(step, title: str) -> None:
    """Taichi's kernel profiler over 20 substeps (when --profile)."""
    if os.environ.get("PHYSGS_TI_PROFILER") != "1":
        return
    import taichi as ti

    ti.profiler.clear_kernel_profiler_info()
    for _ in range(20):
        step()
    ti.sync()
    print(f"--- Taichi kernel profiler, {title}, 20 substeps (offloaded tasks):", flush=True)
    ti.profiler.print_kernel_profiler_info("count")
    ti.profiler.clear_kernel_profiler_info()


def bench_variants(arch: str, x: np.ndarray, G: int, m, dt: float, variants: list, seconds: float,
                   textbook_sorted: float, rounds: int = 3) -> list:
    """Rates of the P2G variants on the particles ``x`` (a solver each, all loaded first), measured
    in ``rounds`` interleaved rounds of ``seconds / rounds`` each (so that a machine's load or
    clock changes hit every variant alike); the best round counts.  Prints a table."""
    from physgs_steps.mpm import Dynamics, MPMSolver
    from physgs_steps.mpm import p2g_sorted as P2G

    P = len(x)
    solvers = []
    for text in variants:
        s = MPMSolver([m], n_grid=G, dynamics=Dynamics.free(), backend=arch, **parse_variant(text))
        s.set_particles(x, np.full(P, 0.4 ** 3 / P), np.zeros(P, int))
        s.substep(dt)  # compile / warm up
        solvers.append(s)
    rates = [[] for _ in solvers]
    counts = [0] * len(solvers)
    for _ in range(max(1, rounds)):
        for i, s in enumerate(solvers):
            rate, n = _rate(lambda: s.substeps(BATCH, dt), BATCH * P, seconds / max(1, rounds))
            rates[i].append(rate)
            counts[i] += n
    rows = []
    for text, s, rs, n in zip(variants, solvers, rates, counts):
        _profile(lambda: s.substep(dt), f"p2g {text}, P={P}")
        rows.append({"arch": s.arch, "particles": P, "n_grid": G, "variant": text, "p2g": s.p2g,
                     "run_length": ({P2G.CELL: "cell", P2G.WARP: "warp"}.get(s.run_length, s.run_length))
                     if s.p2g == "coarsened" and not s.private_grid else None,
                     "resort_every": s.resort_every if s.p2g == "coarsened" else None,
                     "grid_mode": "private" if s.private_grid else "atomic", "rate": max(rs),
                     "rate_median": float(np.median(rs)), "rates": rs, "resorts": s.sort_generation,
                     "split": s.split if s.p2g == "coarsened" and not s.private_grid else None,
                     "substeps_measured": BATCH * n})
    del solvers, s
    ref = {r["grid_mode"]: r["rate"] for r in rows if r["p2g"] == "atomic"}  # per grid mode
    print(f"P2G variants, {arch} P={P} grid {G}^3, particle-substeps/s, best of {rounds} interleaved rounds "
          f"(vs atomic: against the atomic variant of the same grid mode):", flush=True)
    print(f"  {'variant':28s} {'grid':8s} {'K':>4s} {'N':>4s} {'S':>2s} {'rate':>10s} {'median':>10s} {'vs atomic':>10s} "
          f"{'vs textbook':>12s}")
    for r in rows:
        r["vs_atomic"] = r["rate"] / ref[r["grid_mode"]] if r["grid_mode"] in ref else None
        r["vs_textbook_sorted"] = r["rate"] / textbook_sorted
        print(f"  {r['variant']:28s} {r['grid_mode']:8s} {r['run_length'] or '-':>4} {r['resort_every'] or '-':>4} {r['split'] or '-':>2} "
              f"{r['rate']:10.3g} {r['rate_median']:10.3g} {r['vs_atomic'] or float('nan'):10.2f} "
              f"{r['vs_textbook_sorted']:12.2f}",
              flush=True)
    return rows


def bench_windows(arch: str, x: np.ndarray, G: int, m, dt: float, variants: list, n_windows: int,
                  window: int = 400) -> list:
    """Rates of the P2G variants window by window: a fresh solver per variant from the same
    particles, then ``n_windows`` windows of ``window`` substeps each.  The jelly box falls,
    lands and bounces, so the windows show how a variant's rate follows the state (the stored
    order holds while the box falls as a block and not once it wobbles).  Prints a line per
    variant."""
    import taichi as ti

    from physgs_steps.mpm import Dynamics, MPMSolver

    P = len(x)
    calls = max(1, window // BATCH)
    rows = []
    for text in variants:
        s = MPMSolver([m], n_grid=G, dynamics=Dynamics.free(), backend=arch, **parse_variant(text))
        s.set_particles(x, np.full(P, 0.4 ** 3 / P), np.zeros(P, int))
        for _ in range(10):  # compile / warm up: 40 substeps
            s.substeps(BATCH, dt)
        ti.sync()
        rates = []
        for _ in range(n_windows):
            t0 = time.perf_counter()
            for i in range(calls):
                s.substeps(BATCH, dt)
                if i % 5 == 4:
                    ti.sync()
            ti.sync()
            rates.append(BATCH * calls * P / (time.perf_counter() - t0))
        t_end = dt * BATCH * (10 + calls * n_windows)
        print(f"windows {s.arch:5s} P={P:>8d} {text:24s} {BATCH * calls} substeps each, simulated time "
              f"{dt * BATCH * 10:.2f}-{t_end:.2f} s: " + " ".join(f"{r:.3g}" for r in rates) +
              f"  mean {np.mean(rates):.3g}", flush=True)
        rows.append({"arch": s.arch, "particles": P, "n_grid": G, "variant": text, "window_substeps": BATCH * calls,
                     "window_rates": rates, "rate": float(np.mean(rates)), "rate_mean": float(np.mean(rates))})
        del s
    return rows


def bench_arch(arch: str, sizes: list, seconds: float, variants: list | None = None, rounds: int = 3,
               windows: int = 0) -> list:
    from physgs_steps.mpm import Dynamics, Material, MPMSolver

    m = Material("fixed_corotated", "identity", E=1.0e5, nu=0.3, density=1000.0, name="jelly")
    out = []
    for P in sizes:
        G = GRID_FOR.get(P, 64)
        x = _particles(P)
        vol = np.full(P, 0.4 ** 3 / P)
        dt = 0.5 * (1.0 / G) / m.wave_speed
        s = MPMSolver([m], n_grid=G, dynamics=Dynamics.free(), backend=arch)
        s.set_particles(x, vol, np.zeros(P, int))
        Textbook = _textbook()
        p_vol = 0.4 ** 3 / P
        tb = Textbook(x, G, 1.0, m.mu, m.lam, p_vol, p_vol * m.density)
        tbs = Textbook(x[s._perm], G, 1.0, m.mu, m.lam, p_vol, p_vol * m.density)
        r_ours, n_ours = _rate(lambda: s.substeps(BATCH, dt), BATCH * P, seconds)
        _profile(lambda: s.substep(dt), f"physgs substep (p2g {s.p2g}), P={P}")
        r_tb, _ = _rate(lambda: tb.substep(dt), P, seconds)
        r_tbs, _ = _rate(lambda: tbs.substep(dt), P, seconds)
        row = {"arch": s.arch, "particles": P, "n_grid": G, "physgs": r_ours, "textbook": r_tb,
               "textbook_sorted": r_tbs, "ratio": r_ours / r_tb, "ratio_vs_sorted": r_ours / r_tbs,
               "p2g": s.p2g, "substeps_measured": BATCH * n_ours, "threads": os.cpu_count()}
        print(f"{s.arch:5s} P={P:>8d} grid {G}^3: physgs (p2g {s.p2g}) {r_ours:.3g}  textbook {r_tb:.3g} "
              f"(sorted input {r_tbs:.3g}) particle-substeps/s  ratio {row['ratio']:.2f} "
              f"({row['ratio_vs_sorted']:.2f} vs sorted)", flush=True)
        out.append(row)
        del s, tb, tbs
        if variants and windows > 0:
            out += bench_windows(arch, x, G, m, dt, variants, windows)
        elif variants:
            out += bench_variants(arch, x, G, m, dt, variants, seconds, r_tbs, rounds)
    return out


def _cuda_available() -> bool:
    try:
        import torch

        return bool(torch.cuda.is_available())
    except Exception:  # torch missing: ask Taichi in a subprocess instead
        code = "import taichi as ti; ti.init(arch=ti.cuda); from taichi.lang import impl; print(impl.current_cfg().arch == ti.cuda)"
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        return r.stdout.strip().endswith("True")


def _summary(rows: list) -> None:
    """One line per size: physgs, textbook and the warp solver's variants (CUDA, same run)."""
    by_size: dict = {}
    for r in rows:
        if r.get("arch") != "cuda":
            continue
        d = by_size.setdefault(r["particles"], {})
        if "solver" in r:
            d[r["solver"]] = r["rate"]
        elif "variant" in r:
            d[f"p2g {r['variant']}"] = r["rate"]
        else:
            d.update(physgs=r["physgs"], textbook=r["textbook"], textbook_sorted=r["textbook_sorted"])
    for P, d in sorted(by_size.items()):
        line = f"SUMMARY cuda P={P}: " + ", ".join(f"{k} {v:.3g}" for k, v in d.items())
        if "warp_no_sync" in d and "physgs" in d:
            line += f"; physgs / warp no-sync {d['physgs'] / d['warp_no_sync']:.2f}"
            best = max((k for k in d if k.startswith("p2g ")), key=d.get, default=None)
            if best:
                line += f"; best variant ({best[4:]}) / warp no-sync {d[best] / d['warp_no_sync']:.2f}"
        print(line, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", choices=["cpu", "cuda", "all"], default="all")
    ap.add_argument("--sizes", type=int, nargs="+", default=[30_000, 300_000, 1_000_000])
    ap.add_argument("--seconds", type=float, default=3.0, help="measuring time per kernel and size")
    ap.add_argument("--json", help="also write the rows to this JSON file")
    ap.add_argument("--profile", action="store_true",
                    help="also print Taichi's kernel profiler for the physgs substep (per offloaded task; the "
                         "profiler synchronises per task, so rates are measured before it)")
    ap.add_argument("--warp-solver", metavar="DIR",
                    help="also run PhysGaussian's warp solver from DIR (its mpm_solver_warp folder) on CUDA, "
                         "as written and without host syncs (benchmarks/bench_mpm_warp.py; needs warp-lang)")
    ap.add_argument("--p2g", nargs="*", metavar="VARIANT", default=DEFAULT_VARIANTS,
                    help="P2G variants measured after the default solver, each on a fresh solver: atomic | "
                         "coarsened, with options :K=<run length> :N=<substeps between re-sorts> "
                         ":grid=private|atomic (default: %(default)s; none: --p2g with no value)")
    ap.add_argument("--rounds", type=int, default=3,
                    help="interleaved rounds of the --p2g variants (each gets --seconds in all; best round counts)")
    ap.add_argument("--windows", type=int, default=0, metavar="N",
                    help="measure the --p2g variants in N windows of 400 substeps each from a fresh solver "
                         "(the box falls, lands and bounces: rates as the state changes) instead of rounds")
    ap.add_argument("--emit-rows", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.profile:
        os.environ["PHYSGS_TI_PROFILER"] = "1"  # read by physgs_steps.mpm.backend (child processes too)
    if a.arch == "all":
        rows = []
        for arch in ["cpu"] + (["cuda"] if _cuda_available() else []):
            cmd = [sys.executable, __file__, "--arch", arch, "--seconds", str(a.seconds), "--sizes",
                   *map(str, a.sizes), "--emit-rows", "--rounds", str(a.rounds), "--windows", str(a.windows),
                   "--p2g", *a.p2g]
            r = subprocess.run(cmd, capture_output=True, text=True)
            for line in r.stdout.splitlines():
                if line.startswith(ROWS):
                    rows += json.loads(line[len(ROWS):])
                elif line.strip():
                    print(line, flush=True)
            if r.returncode != 0:
                print(r.stderr[-3000:], file=sys.stderr)
        if "cuda" not in {r["arch"] for r in rows}:
            print("ti.cuda: not available on this machine")
    else:
        rows = bench_arch(a.arch, a.sizes, a.seconds, a.p2g, a.rounds, a.windows)
        if a.emit_rows:
            print(ROWS + json.dumps(rows))
            return
    if a.warp_solver and not a.emit_rows:
        cmd = [sys.executable, os.path.join(os.path.dirname(__file__), "bench_mpm_warp.py"), "--physgaussian",
               a.warp_solver, "--seconds", str(a.seconds), "--sizes", *map(str, a.sizes), "--emit-rows"]
        r = subprocess.run(cmd, capture_output=True, text=True)
        for line in r.stdout.splitlines():
            if line.startswith(ROWS):
                rows += json.loads(line[len(ROWS):])
            elif line.strip():
                print(line, flush=True)
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
    _summary(rows)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
