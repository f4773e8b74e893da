"""Sorted particles and run-coarsened P2G (docs/CONTRACTS.md "MPM step", docs/MEASURED.md "Coarsened P2G").

With float atomics (CUDA), P2G costs most of a substep: particles stored sorted by cell make
consecutive threads add into the same 27 grid nodes, and those atomics serialise.  The
``coarsened`` P2G mode removes most of them:

* **Runs.**  A thread takes a range of consecutive particles (``run`` of them on CUDA, or,
  with ``run`` = :data:`CELL`, the slots of one stencil-base cell as the last sort left them;
  one thread's chunk with private CPU grids).  While consecutive particles share a stencil base
  node (``floor(x / dx - 0.5)``, the node the 3x3x3 stencil starts at), their mass and
  momentum contributions are summed in registers (a 27 x 4 accumulator); the thread writes the
  27 nodes once per run of equal bases, instead of once per particle.  Any particle order gives
  the same sums up to float reassociation; sorted particles give long runs.
* **Device counting sort.**  Particles move, so the solver re-sorts them by stencil base every
  ``resort_every`` substeps, on the device: keys and ranks within each cell (one atomic
  increment per particle; serial on the CPU, so that the order and thus the results are
  reproducible there), an exclusive prefix sum over the cells (:func:`exclusive_scan`,
  blocks of :data:`SCAN_BLOCK` summed serially per thread, recursively), then one scatter of
  every per-particle array into a second set of arrays, which then swaps with the first.

Everything here but the warp runs runs on every Taichi backend, so the CPU tests check the
code that runs on the GPU.  ``p2g: atomic`` keeps the one-atomic-per-particle transfer (the
reference); ``auto`` resolves per arch with :data:`AUTO`.

* **Warp runs** (``run_length`` :data:`WARP`, CUDA's default: :data:`RUN_AUTO`): one thread
  per particle; each warp sorts its 32 particles by stencil base (a bitonic sort by shuffles),
  so that the runs which drift has split since the last device sort come together again
  within the warp, and sums each run across its lanes (docs/MEASURED.md "Issue 18, ninth round").
"""

import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from ..errors import ConfigError

P2G_MODES = ("auto", "atomic", "coarsened")
AUTO = {"cpu": "atomic", "cuda": "coarsened"}  # what ``auto`` picks per arch
# ``auto`` keeps the atomic transfer below this many particles: with RUN_LENGTH particles per
# thread a small scene launches too few threads to fill a GPU (27k particles: 1.7k threads on
# an H100 with room for 270k).  Measured on one H100: coarsened 1.58x atomic at 300k, 2.58x at
# 1M; the default bear (27k) ran its substeps slower after the switch (docs/MEASURED.md "MPM step").
# Warp runs (CUDA's default run_length) have a thread per particle and beat the atomic transfer
# at 30k (1.20x) and 100k (1.68x) in bench_mpm.py (one H100, 2026-11-28); the threshold stays
# until the default bear's GPU pipeline is measured with them (docs/MEASURED.md "Issue 18, ninth round").
AUTO_MIN_PARTICLES = 200_000
RUN_LENGTH = 16  # particles per thread in coarsened P2G with runs (the CPU's default; CUDA: run_length=16)
CELL = -1  # run_length value: one thread per stencil-base cell of the last sort (its range of slots)
WARP = -2  # run_length value (CUDA): a thread per particle, each warp sorted, runs summed across its lanes
# what run_length "auto" (the solver's default) picks per arch.  Measured on one H100
# (2026-11-28, bench_mpm.py --windows 5, jelly box falling then landed, window means, same
# call): warp runs 1.35e9 particle-substeps/s at 10^6 and 1.04e9 at 300k, against 1.10e9 and
# 8.4e8 for runs of 16 (docs/MEASURED.md "Issue 18, ninth round")
RUN_AUTO = {"cpu": RUN_LENGTH, "cuda": WARP}
# Substeps between device re-sorts in coarsened mode.  What spoils the order is relative motion
# (a block that falls keeps its particles in order; one that bounces and wobbles does not), and
# a spoilt order splits the runs (more atomics).  Measured on one H200 (2026-11-28, jelly cube
# of bench_mpm.py dropping and bouncing, particle-substeps/s in windows of 400 substeps, the
# falling window first, then the mean of all 8): 10^6 particles, every 16 substeps 1.48e9 then
# 1.05-1.13e9 (mean 1.13e9), every 8 1.46e9 then 1.14-1.21e9 (1.22e9), every 4 1.33e9 then
# 1.18-1.27e9 (1.24e9), every 2 1.19e9 mean; 300k: 0.84e9, 0.84e9, 0.88e9 and 0.61e9 means.
# 8 loses 1 % while the order holds and gains 8 % once it does not (docs/MEASURED.md "Issue 18, eighth
# round").  A sort costs about 0.45 ms at 10^6 (mostly the scatter of every particle array;
# 0.452 ms for the scatter alone in Taichi's profiler, one H100; a scatter word by word was
# cheaper at 10^6 but not faster at the default interval, and slower at 300k: docs/MEASURED.md "Issue
# 18, eleventh round").
RESORT_EVERY = 8
# The same for warp runs, which sort each warp's particles themselves: a stale order costs them
# less.  Same H100 call as RUN_AUTO: 10^6 particles 1.35e9 (every 8), 1.37e9 (16), 1.38e9 (32);
# 300k 1.04e9, 1.08e9, 1.10e9.  Again with staged G2P stores (one H100, 2026-11-28, --windows 6,
# window means): 10^6 1.63e9 (8), 1.66e9 (16), 1.65-1.71e9 (32), 1.65e9 (64, 128), 1.66e9 (never);
# 300k faster the less it sorts (1.12-1.16e9 at 32, 1.25e9 never) in that 1.4 s of jelly, which
# does not mix as sand or a fluid does (docs/MEASURED.md "Issue 18, eleventh round").
RESORT_EVERY_WARP = 32
# CUDA: threads per run in coarsened P2G (SPLITS below).  Measured on one H200 (bench_mpm.py,
# jelly, best of 3 interleaved rounds, median in brackets): 300k particles 8.83e8 (7.79e8)
# particle-substeps/s with 1 thread per run, 9.91e8 (8.61e8) with 3, 9.94e8 (8.73e8) with 9;
# 1M: 1.28e9 (1.07e9), 1.34e9 (1.09e9), 1.29e9 (1.04e9).  P2G was 0.36 ms of a 0.74 ms
# substep at 1M, 0.33 ms with 3 (Taichi's profiler; G2P 0.28 ms).
SPLIT = 3
SCAN_BLOCK = 128  # entries each thread sums serially in the prefix sum
# ---- warp runs (run_length WARP, CUDA only: Taichi's warp intrinsics exist there alone)
# One thread per particle, so that a warp's 32 lanes read 32 consecutive particles (coalesced
# loads: the coarsened threads above read a run each, 16 particles apart, and wait on L1).  The
# warp sorts its particles by stencil base (:func:`warp_sort`): between device sorts particles
# cross cells and split the stored runs (Nsight Compute on the landed jelly box of bench_mpm.py:
# 17.7 particles a run after a sort, 2.0 eight substeps later), but they stay near their slot,
# so most of a split run is back together within its warp.  The lanes holding one base in a
# row are then a segment; each node's four sums are reduced over the segment by shuffles (a
# segmented scan down the lanes, five steps), and the segment's first lane adds them to the
# grid: one atomic per run and node, with no 27 x 4 accumulator held across particles.
# Summing the segments through shared memory instead (each lane's node sums written to its
# warp's part of a shared array, the (segment, sum) pairs shared out among the lanes) was
# slower: 1.77e9 (median 1.37e9) against 1.92e9 (1.67e9) particle-substeps/s at 10^6 on one
# H100, same run (docs/MEASURED.md "Issue 18, eleventh round").
WARP_SIZE = 32
FULL_MASK = 0xFFFFFFFF
NO_KEY = 0x7FFFFFFF  # an empty lane's key (past the last particle): sorts last


@ti.func
def warp_sort(key, lane):
    """Bitonic sort of the warp's (key, lane) pairs, ascending by key then lane: returns the
    key and the source lane of this lane's place in that order.  Every lane must call it."""
    mask = ti.u32(FULL_MASK)
    src = lane
    for s1 in ti.static(range(1, 6)):  # blocks of 2, 4, ... 32
        for s2 in ti.static(range(s1 - 1, -1, -1)):  # partner distance 2^s2
            pk = ti.simt.warp.shfl_xor_i32(mask, key, 1 << s2)
            ps = ti.simt.warp.shfl_xor_i32(mask, src, 1 << s2)
            p_less = pk < key or (pk == key and ps < src)
            up = (lane & (1 << s1)) == 0  # this block sorts ascending
            low = (lane & (1 << s2)) == 0  # this lane is the lower of its pair
            take = p_less
            if low != up:
                take = not p_less
            if take:
                key = pk
                src = ps
    return key, src


@ti.func
def warp_segments(key, lane):
    """For a warp whose lanes hold sort keys ``key``: whether this lane
    starts a segment of equal keys in a row, and [5] flags ``ok[s]``: lane + 2^s is in this
    lane's segment (the steps of :func:`warp_sum`).  Every lane of the warp must call it."""
    mask = ti.u32(FULL_MASK)
    prev = ti.simt.warp.shfl_up_i32(mask, key, 1)
    head = 0
    if lane == 0 or prev != key:
        head = 1
    seg = head  # inclusive scan of the heads: the segment's number within the warp
    for s in ti.static(range(5)):
        o = ti.simt.warp.shfl_up_i32(mask, seg, 1 << s)
        if lane >= (1 << s):
            seg += o
    ok = ti.Vector([0, 0, 0, 0, 0])
    for s in ti.static(range(5)):
        o = ti.simt.warp.shfl_down_i32(mask, seg, 1 << s)
        if lane + (1 << s) < WARP_SIZE and o == seg:
            ok[s] = 1
    return head, ok


@ti.func
def warp_sum(val, ok):
    """The sum of ``val`` over this lane and the rest of its segment below it (the segment's
    first lane gets the whole segment's): a segmented suffix scan.  Every lane must call it."""
    mask = ti.u32(FULL_MASK)
    for s in ti.static(range(5)):
        o = ti.simt.warp.shfl_down_f32(mask, val, 1 << s)
        if ok[s] == 1:
            val += o
    return val

vec3 = ti.types.vector(3, ti.f32)
mat3 = ti.types.matrix(3, 3, ti.f32)
V1 = ti.types.ndarray(dtype=vec3, ndim=1)
M1 = ti.types.ndarray(dtype=mat3, ndim=1)
S1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)


def resolve(mode: str, arch: str, n_particles: int | None = None) -> str:
    """``atomic`` or ``coarsened`` for the config value ``mode`` (auto | atomic | coarsened);
    ``auto`` also looks at the particle count when it is known (:data:`AUTO_MIN_PARTICLES`)."""
    if mode not in P2G_MODES:
        raise ConfigError("sim.p2g", f"must be one of {', '.join(P2G_MODES)}, got {mode!r}")
    if mode != "auto":
        return mode
    if n_particles is not None and n_particles < AUTO_MIN_PARTICLES:
        return "atomic"
    return AUTO[arch]


# ---------------------------------------------------------------------------- run accumulator
# A run's 27 stencil nodes may be shared out among ``split`` threads (1, 3 or 9): thread ``s``
# of a run sums the nodes of x slab ``s`` (split 3: 9 nodes) or of (x, y) column ``s // 3,
# s % 3`` (split 9: 3 nodes), so each thread holds 27 / split x 4 sums in registers instead of
# 108 (more threads in flight on a GPU; every thread of a run reads the same particles).
SPLITS = (1, 3, 9)


@ti.func
def _slab_offsets(split: ti.template(), s):
    """The stencil offsets (sx, sy) thread ``s`` of a run starts from (0, 0 with split 1)."""
    sx = 0
    sy = 0
    if ti.static(split == 3):
        sx = s
    elif ti.static(split == 9):
        sx = s // 3
        sy = s % 3
    return sx, sy


@ti.func
def _pick(a, b, c, i):
    """(a, b, c)[i] for a runtime i in 0..2."""
    return ti.select(i == 0, a, ti.select(i == 1, b, c))


@ti.func
def bspline(fx):
    """The quadratic B-spline weights of a particle ``fx`` [3] cells from its stencil base node:
    (w0, w1, w2), one [3] vector per offset (docs/CONTRACTS.md "MPM step")."""
    return 0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2


@ti.func
def acc_zero(split: ti.template()):
    """The accumulator of one run (or of its part ``split``): [27 / split, 4] (momentum xyz,
    mass) per stencil node of the part, node n = 9i + 3j + k of its own offsets."""
    return ti.Matrix.zero(ti.f32, 27 // split, 4)


@ti.func
def acc_add(acc: ti.template(), split: ti.template(), s, fx, dx, mv, affine, mass):
    """Add one particle's APIC contributions (stencil offset ``fx`` [3] in cells from the base
    node, momentum ``mv``, affine matrix ``affine``, ``mass``) to the part ``s`` of ``split`` of
    the run accumulator ``acc`` [27 / split, 4] in place."""
    w = bspline(fx)
    sx, sy = _slab_offsets(split, s)
    # the part's own nodes: all 27 (split 1), one x slab (3), one (x, y) column (9)
    for i, j, k in ti.static(ti.ndrange(3 if split == 1 else 1, 1 if split == 9 else 3, 3)):
        n = ti.static(9 * i + 3 * j + k)
        wx = w[i][0]
        if ti.static(split != 1):
            wx = _pick(w[0][0], w[1][0], w[2][0], sx)
        wy = w[j][1]
        if ti.static(split == 9):
            wy = _pick(w[0][1], w[1][1], w[2][1], sy)
        dpos = (ti.Vector([sx + i, sy + j, k], dt=ti.f32) - fx) * dx
        weight = wx * wy * w[k][2]
        mom = weight * (mv + affine @ dpos)
        acc[n, 0] += mom[0]
        acc[n, 1] += mom[1]
        acc[n, 2] += mom[2]
        acc[n, 3] += weight * mass


def make_flush(private_grid: bool, split: int = 1):
    """ti.func flush(acc, base, s, c, grid_v, grid_m): add a run's sums (part ``s`` of
    ``split``) to its nodes from ``base`` of grid chunk ``c`` (plain adds into a thread's
    private grid, else atomics); and mark(base, s, c, grid_c): set its nodes' touch flag."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")

    @ti.func
    def _node(base, s, n: ti.template()):
        """Node n of part s (numbered 9i + 3j + k from the part's first offsets, as acc_add)."""
        sx, sy = _slab_offsets(split, s)
        return base + ti.Vector([sx + n // 9, sy + (n // 3) % 3, n % 3])

    @ti.func
    def flush(acc: ti.template(), base, s, c, grid_v: ti.template(), grid_m: ti.template()):
        for n in ti.static(range(27 // split)):
            node = _node(base, s, n)
            mom = ti.Vector([acc[n, 0], acc[n, 1], acc[n, 2]], dt=ti.f32)
            if ti.static(private_grid):
                grid_v[c, node[0], node[1], node[2]] = grid_v[c, node[0], node[1], node[2]] + mom
                grid_m[c, node[0], node[1], node[2]] = grid_m[c, node[0], node[1], node[2]] + acc[n, 3]
            else:
                ti.atomic_add(grid_v[0, node[0], node[1], node[2]], mom)
                ti.atomic_add(grid_m[0, node[0], node[1], node[2]], acc[n, 3])

    @ti.func
    def mark(base, s, c, grid_c: ti.template()):
        for n in ti.static(range(27 // split)):
            node = _node(base, s, n)
            grid_c[c, node[0], node[1], node[2]] = 1.0

    return SimpleNamespace(flush=flush, mark=mark)


@ti.func
def same_base(a, b):
    return a[0] == b[0] and a[1] == b[1] and a[2] == b[2]


# ---------------------------------------------------------------------------- device sort
@ti.func
def base_key(xp, inv_dx, G):
    """Row-major index of the stencil base node of position ``xp`` (clamped onto the grid)."""
    base = ti.cast(ti.floor(xp * inv_dx - 0.5), ti.i32)
    base = ti.min(ti.max(base, 0), G - 3)
    return (base[0] * G + base[1]) * G + base[2]


@functools.lru_cache(maxsize=None)
def _key_kernel(serial: bool):
    @ti.kernel
    def keys(x: V1, key: I1, rank: I1, count: I1, dx: ti.f32, G: ti.i32):
        """key[p] = stencil base index of particle p; rank[p] = its slot within that cell
        (count[] must be zero; holds the per-cell counts after)."""
        inv_dx = 1.0 / dx
        ti.loop_config(serialize=serial)
        for p in range(x.shape[0]):
            k = base_key(x[p], inv_dx, G)
            key[p] = k
            rank[p] = ti.atomic_add(count[k], 1)

    return keys


@ti.kernel
def _block_sums(a: I1, n: ti.i32, B: ti.i32, sums: I1):
    for b in range((n + B - 1) // B):
        s = 0
        for i in range(b * B, ti.min((b + 1) * B, n)):
            s += a[i]
        sums[b] = s


@ti.kernel
def _block_scan(a: I1, n: ti.i32, B: ti.i32, offs: I1):
    """In place: a[i] = offs[block of i] + the sum of the entries before i in its block."""
    for b in range((n + B - 1) // B):
        s = offs[b]
        for i in range(b * B, ti.min((b + 1) * B, n)):
            v = a[i]
            a[i] = s
            s += v


class Scan:
    """In-place exclusive prefix sum of an int32 ndarray of length ``n`` (buffers kept)."""

    def __init__(self, n: int, block: int = SCAN_BLOCK):
        self.n, self.B = int(n), int(block)
        self.levels = []  # block sums per level
        m = self.n
        while m > self.B:
            m = (m + self.B - 1) // self.B
            self.levels.append(ti.ndarray(ti.i32, m))
        self.zero = ti.ndarray(ti.i32, 1)
        self.zero.fill(0)

    def __call__(self, a) -> None:
        arrays = [a] + self.levels
        sizes = [self.n] + [arr.shape[0] for arr in self.levels]
        for lvl in range(len(self.levels)):
            _block_sums(arrays[lvl], sizes[lvl], self.B, arrays[lvl + 1])
        _block_scan(arrays[-1], sizes[-1], max(self.B, sizes[-1]), self.zero)
        for lvl in reversed(range(len(self.levels))):
            _block_scan(arrays[lvl], sizes[lvl], self.B, arrays[lvl + 1])


def exclusive_scan(a) -> None:
    """In-place exclusive prefix sum of the int32 ndarray ``a`` (one-off; :class:`Scan` keeps buffers)."""
    Scan(a.shape[0])(a)


@ti.kernel
def _scatter(dest: I1, key: I1, start: I1,
             x: V1, v: V1, C: M1, F: M1, tau: M1, ep: S1, p_vol: S1, p_face: S1, p_mass: S1, mat: I1, act_bits: I1,
             order: I1, x2: V1, v2: V1, C2: M1, F2: M1, tau2: M1, ep2: S1, p_vol2: S1, p_face2: S1, p_mass2: S1,
             mat2: I1, act_bits2: I1, order2: I1):
    """Particle p goes to slot start[key[p]] + dest[p] (dest holds its rank within the cell)."""
    for p in range(x.shape[0]):
        q = start[key[p]] + dest[p]
        x2[q] = x[p]
        v2[q] = v[p]
        C2[q] = C[p]
        F2[q] = F[p]
        tau2[q] = tau[p]
        ep2[q] = ep[p]
        p_vol2[q] = p_vol[p]
        p_face2[q] = p_face[p]
        p_mass2[q] = p_mass[p]
        mat2[q] = mat[p]
        act_bits2[q] = act_bits[p]
        order2[q] = order[p]


# the per-particle arrays the sort permutes (MPMSolver attribute names), in _scatter's order
PERMUTED = ("x", "v", "C", "F", "tau", "ep", "_p_vol", "_p_face", "_p_mass", "_mat", "_act_bits", "_order")
PERMUTED_TYPES = (vec3, vec3, mat3, mat3, mat3, ti.f32, ti.f32, ti.f32, ti.f32, ti.i32, ti.i32, ti.i32)


class DeviceSort:
    """Counting sort of a solver's particles by stencil base node, on the device.

    ``sort(solver)`` permutes the arrays named in :data:`PERMUTED` (the solver's ``_order``
    [P] i32 holds each storage slot's row in the caller's order and is permuted with them).
    Buffers: keys, ranks [P], counts [G^3], and a second set of the permuted arrays.
    """

    def __init__(self, P: int, G: int, arch: str):
        self.P, self.G = int(P), int(G)
        self.key = ti.ndarray(ti.i32, P)
        self.rank = ti.ndarray(ti.i32, P)
        self.count = ti.ndarray(ti.i32, G ** 3 + 1)  # counts, then the first slot of each cell (+ P at the end)
        self.scan = Scan(G ** 3 + 1)
        self.keys = _key_kernel(arch == "cpu")  # serial on the CPU: a reproducible order
        self.spare = None

    def _spares(self) -> dict:
        if self.spare is None:
            self.spare = {n: ti.ndarray(t, self.P) for n, t in zip(PERMUTED, PERMUTED_TYPES)}
        return self.spare

    def sort(self, solver) -> None:
        self.count.fill(0)
        self.keys(solver.x, self.key, self.rank, self.count, float(solver.dx), self.G)
        self.scan(self.count)
        spare = self._spares()
        cur = [getattr(solver, n) for n in PERMUTED]
        new = [spare[n] for n in PERMUTED]
        _scatter(self.rank, self.key, self.count, *cur, *new)
        for n, a, b in zip(PERMUTED, cur, new):
            setattr(solver, n, b)
            spare[n] = a

    def nbytes(self) -> int:
        return 4 * (2 * self.P + self.G ** 3 + 1) + (4 * 40 * self.P if self.spare is not None else 0)


def sorted_by_base(x: np.ndarray, dx: float, G: int) -> bool:
    """Whether positions ``x`` [P, 3] (metres) are in non-decreasing stencil-base order."""
    base = np.clip(np.floor(x / dx - 0.5).astype(np.int64), 0, G - 3)
    key = (base[:, 0] * G + base[:, 1]) * G + base[:, 2]
    return bool(np.all(np.diff(key) >= 0))
