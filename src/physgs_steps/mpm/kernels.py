"""Taichi kernels of the MLS-MPM step (docs/CONTRACTS.md "MPM step"), mpm88 names.

:func:`build` returns the kernels specialised to a :class:`Spec`: the (elasticity,
plasticity) pairs a scene uses and the counts of its dynamics entries.  Every array is a
kernel argument (``ti.ndarray``), so one compiled kernel serves any particle count and grid
size, and Taichi's offline cache (``runtime.cache_dir("taichi")``) finds it again in the next
process.  Numbers that change between runs (material parameters, collider positions, time)
live in small parameter tables, never in the compiled code.

Arrays (SI units inside the solver: metres, m/s, s, Pa):

    x, v [P] vec3         position, velocity
    C, F, tau [P] mat3    APIC affine matrix, elastic deformation gradient, Kirchhoff stress of F
    p_vol, p_mass [P]     particle volume (m^3) and mass (kg)
    ep [P]                accumulated inelastic strain of tearing materials (materials.Fracture)
    mat [P] int           material (instance) index into mparams / mcombo
    act_bits [P] int      particle-action membership bits (see dynamics.py)
    grid_v [T,G,G,G] vec3 grid momentum, then velocity (in chunk 0)
    grid_m [T,G,G,G]      grid mass
    mparams [K, N_PARAMS] materials.PARAM_COLUMNS (mu, lam, density, yield_stress, ...)
    mcombo [K] int        index of the material's (elasticity, plasticity) pair in Spec.combos
    dyn [R, 12]           dynamics table (dynamics.py)
    err [4] int           err[0] counts particles whose stencil left the grid (clamped)

On the CPU the particles (sorted by cell) are split into T contiguous chunks, one per thread,
and each chunk transfers into its own grid with plain adds; the grid update sums the T grids.
Float atomics (compare-and-swap loops on x86) would otherwise dominate P2G.  The sum order is
then fixed, so CPU runs are bitwise reproducible.  On CUDA, T = 1 and P2G uses atomics.
A particle whose stencil would leave the grid (a blow-up) is clamped onto it and counted in
err[0], so a failing run never reads or writes out of bounds.

``Spec.p2g == "coarsened"`` (p2g_sorted.py): P2G sums runs of consecutive particles with the
same stencil base in registers and writes the 27 nodes once per run (threads take ``Spec.run``
particles each, or, with ``run`` = p2g_sorted.CELL, the slots of one cell of the last device
sort, ``cell_start`` [G^3 + 1]; the CPU's private-grid chunks likewise).  ``cell_start`` is
read only in that case.

The stress of the current F is kept per particle (``tau``): the G2P pass computes it right
after the return map from the SVD it already has, so a substep needs at most one SVD per
particle; ``build_constitutive(...).stress`` recomputes it after ``F`` is set from outside.
"""

import functools
import math
from types import SimpleNamespace
from typing import NamedTuple

import taichi as ti

from . import materials as M
from . import p2g_sorted as P2G

BOUND = 3  # domain wall thickness in grid nodes (CONTRACTS.md)

vec3 = ti.types.vector(3, ti.f32)
mat3 = ti.types.matrix(3, 3, ti.f32)
V1 = ti.types.ndarray(dtype=vec3, ndim=1)
M1 = ti.types.ndarray(dtype=mat3, ndim=1)
S1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
S2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
V4 = ti.types.ndarray(dtype=vec3, ndim=4)
S4 = ti.types.ndarray(dtype=ti.f32, ndim=4)


@ti.func
def _qrow(mparams: ti.template(), m):
    """The parameter row of material ``m`` as a vector (PARAM_COLUMNS order)."""
    return ti.Vector([mparams[m, c] for c in ti.static(range(M.N_PARAMS))], dt=ti.f32)


class Spec(NamedTuple):
    """What a kernel is specialised to (hashable; the build cache key)."""

    combos: tuple        # ((elasticity name, plasticity name, fracture on/off), ...)
    boundary: str        # slip | sticky
    damping: bool        # whether grid damping is applied
    counts: tuple        # (surface, cuboid, acceleration, translation, rotation) dynamics rows
    private_grid: bool   # CPU: one grid per chunk of particles, no atomics; CUDA: one grid, atomics
    p2g: str = "atomic"  # atomic: one add per particle and node; coarsened: one per run of equal bases (p2g_sorted.py)
    run: int = 0         # coarsened P2G on one grid: particles per thread; P2G.CELL: per sorted cell; 0: unused


@functools.lru_cache(maxsize=None)
def build(spec: Spec) -> SimpleNamespace:
    """The kernels for ``spec`` (built once per process and spec)."""
    updates = [_make_update(M.ELASTICITY[e], M.PLASTICITY[p], f) for e, p, f in spec.combos]
    n_combo = len(updates)
    any_fracture = any(f for _, _, f in spec.combos)
    n_surf, n_cub, n_acc, n_tra, n_rot = spec.counts
    r_cub = n_surf
    r_acc = r_cub + n_cub
    r_tra = r_acc + n_acc
    r_rot = r_tra + n_tra
    has_actions = (n_acc + n_tra + n_rot) > 0
    sticky = spec.boundary == "sticky"
    damping = spec.damping
    private_grid = spec.private_grid
    coarsened = spec.p2g == "coarsened"
    run = spec.run
    flush = P2G.make_flush(private_grid)
    two_pi = 2.0 * math.pi

    @ti.func
    def _vrow(dyn: ti.template(), r, c):
        return ti.Vector([dyn[r, c], dyn[r, c + 1], dyn[r, c + 2]], dt=ti.f32)

    @ti.func
    def _stencil(xp, inv_dx, G, err: ti.template()):
        base = ti.cast(ti.floor(xp * inv_dx - 0.5), ti.i32)
        if base.min() < 0 or base.max() > G - 3:
            ti.atomic_add(err[0], 1)
            base = ti.min(ti.max(base, 0), G - 3)
        fx = xp * inv_dx - ti.cast(base, ti.f32)
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
        return base, fx, w

    @ti.func
    def _particle_actions(b, xp, vp, t, dt, dyn: ti.template()):
        for a in ti.static(range(n_acc)):
            r = r_acc + a
            if (b >> a) & 1 and t >= dyn[r, 8] and t < dyn[r, 9]:
                ph = two_pi * dyn[r, 6] * (t - dyn[r, 8]) + dyn[r, 7]
                vp += dt * (_vrow(dyn, r, 0) + _vrow(dyn, r, 3) * ti.sin(ph))
        for k in ti.static(range(n_tra)):
            r = r_tra + k
            if (b >> (n_acc + k)) & 1 and t >= dyn[r, 3] and t < dyn[r, 4]:
                vp = _vrow(dyn, r, 0)
        for k in ti.static(range(n_rot)):
            r = r_rot + k
            if (b >> (n_acc + n_tra + k)) & 1 and t >= dyn[r, 8] and t < dyn[r, 9]:
                n = _vrow(dyn, r, 3)
                vp = dyn[r, 6] * n.cross(xp - _vrow(dyn, r, 0)) + dyn[r, 7] * n
        return vp

    @ti.func
    def _grid_actions(I, gv, dx, t, dyn: ti.template()):
        xn = ti.cast(I, ti.f32) * dx
        for s in ti.static(range(n_surf)):
            r = s
            if t >= dyn[r, 8] and t < dyn[r, 9]:
                n = _vrow(dyn, r, 3)
                if (xn - _vrow(dyn, r, 0)).dot(n) < 0.0:
                    kind = dyn[r, 6]
                    if kind < 0.5:
                        gv = ti.Vector.zero(ti.f32, 3)
                    else:
                        vn = gv.dot(n)
                        if kind < 1.5 or vn < 0.0:
                            gv -= vn * n
                        if vn < 0.0:
                            vt = gv.norm()
                            if vt > 1e-20:
                                gv *= ti.max(0.0, vt + vn * dyn[r, 7]) / vt
        for c in ti.static(range(n_cub)):
            r = r_cub + c
            if t >= dyn[r, 9] and t < dyn[r, 10]:
                vel = _vrow(dyn, r, 6)
                centre = _vrow(dyn, r, 0) + vel * (t - dyn[r, 9])
                d = ti.abs(xn - centre)
                if d[0] < dyn[r, 3] and d[1] < dyn[r, 4] and d[2] < dyn[r, 5]:
                    gv = vel
        return gv

    @ti.func
    def _p2g_prepare(p, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                     p_vol: ti.template(), p_mass: ti.template(), act_bits: ti.template(), dyn: ti.template(),
                     err: ti.template(), dt, t, dx, inv_dx, G):
        """Particle p's stencil (base, fx, w) and what it transfers: momentum mv, APIC affine
        matrix (stress and C terms), mass."""
        xp = x[p]
        base, fx, w = _stencil(xp, inv_dx, G, err)
        vp = v[p]
        if ti.static(has_actions):
            b = act_bits[p]
            if b != 0:
                vp = _particle_actions(b, xp, vp, t, dt, dyn)
        mass = p_mass[p]
        affine = (-dt * p_vol[p] * 4.0 * inv_dx * inv_dx) * tau[p] + mass * C[p]
        mv = mass * vp
        return base, fx, w, mv, affine, mass

    @ti.func
    def _p2g_particle(p, c, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                      p_vol: ti.template(), p_mass: ti.template(), act_bits: ti.template(), grid_v: ti.template(),
                      grid_m: ti.template(), dyn: ti.template(), err: ti.template(), dt, t, dx, inv_dx, G):
        base, fx, w, mv, affine, mass = _p2g_prepare(p, x, v, C, tau, p_vol, p_mass, act_bits, dyn, err,
                                                     dt, t, dx, inv_dx, G)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, ti.f32) - fx) * dx
            weight = w[i][0] * w[j][1] * w[k][2]
            node = base + offset
            if ti.static(private_grid):
                # this chunk's own grid: a plain read-modify-write, no atomic needed
                grid_v[c, node[0], node[1], node[2]] = grid_v[c, node[0], node[1], node[2]] + weight * (mv + affine @ dpos)
                grid_m[c, node[0], node[1], node[2]] = grid_m[c, node[0], node[1], node[2]] + weight * mass
            else:
                grid_v[0, node[0], node[1], node[2]] += weight * (mv + affine @ dpos)
                grid_m[0, node[0], node[1], node[2]] += weight * mass

    @ti.func
    def _p2g_runs(p0, p1, c, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                  p_vol: ti.template(), p_mass: ti.template(), act_bits: ti.template(), grid_v: ti.template(),
                  grid_m: ti.template(), dyn: ti.template(), err: ti.template(), dt, t, dx, inv_dx, G):
        """Coarsened P2G of particles p0..p1-1 (p2g_sorted.py): sums in registers while the
        stencil base stays the same, one write of the 27 nodes per run."""
        acc = P2G.acc_zero()
        cur = ti.Vector([-1, -1, -1])  # the run's base (none yet)
        for p in range(p0, p1 + 1):  # p1: past the end, closes the last run (one flush site: less code)
            base = ti.Vector([-2, -2, -2])
            fx = ti.Vector.zero(ti.f32, 3)
            mv = ti.Vector.zero(ti.f32, 3)
            affine = ti.Matrix.zero(ti.f32, 3, 3)
            mass = 0.0
            if p < p1:
                base, fx, _, mv, affine, mass = _p2g_prepare(p, x, v, C, tau, p_vol, p_mass, act_bits, dyn, err,
                                                             dt, t, dx, inv_dx, G)
            if not P2G.same_base(base, cur):
                if cur[0] >= 0:
                    flush(acc, cur, c, grid_v, grid_m)
                    acc = P2G.acc_zero()
                cur = base
            if p < p1:
                P2G.acc_add(acc, fx, dx, mv, affine, mass)

    @ti.kernel
    def substep(x: V1, v: V1, C: M1, F: M1, tau: M1, ep: S1, p_vol: S1, p_mass: S1, mat: I1, act_bits: I1,
                grid_v: V4, grid_m: S4, mparams: S2, mcombo: I1, dyn: S2, err: I1,
                dt: ti.f32, t: ti.f32, dx: ti.f32, gx: ti.f32, gy: ti.f32, gz: ti.f32, damp: ti.f32,
                cell_start: I1):
        inv_dx = 1.0 / dx
        n_chunks = grid_m.shape[0]
        G = grid_m.shape[1]
        P = x.shape[0]
        for I in ti.grouped(grid_m):
            grid_v[I] = ti.Vector.zero(ti.f32, 3)
            grid_m[I] = 0.0
        # P2G
        if ti.static(coarsened and private_grid):
            for c in range(n_chunks):  # parallel over chunks, runs of equal bases inside a chunk
                _p2g_runs(c * P // n_chunks, (c + 1) * P // n_chunks, c, x, v, C, tau, p_vol, p_mass, act_bits,
                          grid_v, grid_m, dyn, err, dt, t, dx, inv_dx, G)
        elif ti.static(coarsened and run == P2G.CELL):
            for k in range(cell_start.shape[0] - 1):  # one thread per cell of the last sort
                p0 = cell_start[k]
                p1 = cell_start[k + 1]
                if p1 > p0:
                    _p2g_runs(p0, p1, 0, x, v, C, tau, p_vol, p_mass, act_bits, grid_v, grid_m, dyn, err,
                              dt, t, dx, inv_dx, G)
        elif ti.static(coarsened):
            for r in range((P + run - 1) // run):  # one thread per `run` consecutive particles
                _p2g_runs(r * run, ti.min((r + 1) * run, P), 0, x, v, C, tau, p_vol, p_mass, act_bits,
                          grid_v, grid_m, dyn, err, dt, t, dx, inv_dx, G)
        elif ti.static(private_grid):
            for c in range(n_chunks):  # parallel over chunks, serial inside a chunk
                for p in range(c * P // n_chunks, (c + 1) * P // n_chunks):
                    _p2g_particle(p, c, x, v, C, tau, p_vol, p_mass, act_bits, grid_v, grid_m, dyn, err,
                                  dt, t, dx, inv_dx, G)
        else:
            for p in range(P):
                _p2g_particle(p, 0, x, v, C, tau, p_vol, p_mass, act_bits, grid_v, grid_m, dyn, err,
                              dt, t, dx, inv_dx, G)
        # grid update (the chunks' grids are summed into chunk 0)
        for i, j, k in ti.ndrange(G, G, G):
            m = grid_m[0, i, j, k]
            mom = grid_v[0, i, j, k]
            if ti.static(private_grid):
                for c in range(1, n_chunks):
                    m += grid_m[c, i, j, k]
                    mom += grid_v[c, i, j, k]
            if m > 0.0:
                I = ti.Vector([i, j, k])
                gv = mom / m
                gv += dt * ti.Vector([gx, gy, gz], dt=ti.f32)
                if ti.static(damping):
                    gv *= damp
                if ti.static(n_surf + n_cub > 0):
                    gv = _grid_actions(I, gv, dx, t, dyn)
                for d in ti.static(range(3)):
                    if I[d] < BOUND:
                        if ti.static(sticky):
                            gv = ti.Vector.zero(ti.f32, 3)
                        elif gv[d] < 0.0:
                            gv[d] = 0.0
                    if I[d] > G - BOUND:
                        if ti.static(sticky):
                            gv = ti.Vector.zero(ti.f32, 3)
                        elif gv[d] > 0.0:
                            gv[d] = 0.0
                grid_v[0, i, j, k] = gv
            else:
                grid_v[0, i, j, k] = ti.Vector.zero(ti.f32, 3)
        # G2P, F update, return map, stress of the new F
        for p in x:
            xp = x[p]
            base, fx, w = _stencil(xp, inv_dx, G, err)
            new_v = ti.Vector.zero(ti.f32, 3)
            new_C = ti.Matrix.zero(ti.f32, 3, 3)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                offset = ti.Vector([i, j, k])
                dpos = (ti.cast(offset, ti.f32) - fx) * dx
                node = base + offset
                g_v = grid_v[0, node[0], node[1], node[2]]
                weight = w[i][0] * w[j][1] * w[k][2]
                new_v += weight * g_v
                new_C += (4.0 * inv_dx * inv_dx * weight) * g_v.outer_product(dpos)
            v[p] = new_v
            C[p] = new_C
            x[p] = xp + dt * new_v
            F_trial = (ti.Matrix.identity(ti.f32, 3) + dt * new_C) @ F[p]
            m = mat[p]
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            F_new = F_trial
            tau_new = ti.Matrix.zero(ti.f32, 3, 3)
            ep_p = 0.0
            if ti.static(any_fracture):
                ep_p = ep[p]
            for ci in ti.static(range(n_combo)):
                if cid == ci:
                    F_new, tau_new, ep_p = updates[ci](F_trial, q, ep_p)
            F[p] = F_new
            tau[p] = tau_new
            if ti.static(any_fracture):
                ep[p] = ep_p

    return SimpleNamespace(substep=substep, spec=spec)


@functools.lru_cache(maxsize=None)
def build_constitutive(combos: tuple) -> SimpleNamespace:
    """Kernels of the constitutive models alone (no grid): ``stress(F, mat, mparams, mcombo,
    ep, tau)`` and ``update(F_trial, mat, mparams, mcombo, ep, F_out, tau_out)`` (return map,
    then the stress of the returned F, exactly as in G2P; ``ep`` is updated in place)."""
    updates = [_make_update(M.ELASTICITY[e], M.PLASTICITY[p], f) for e, p, f in combos]
    stresses = [_make_stress(M.ELASTICITY[e], f) for e, _, f in combos]
    n_combo = len(updates)

    @ti.kernel
    def stress(F: M1, mat: I1, mparams: S2, mcombo: I1, ep: S1, tau: M1):
        for p in F:
            m = mat[p]
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            tau_new = ti.Matrix.zero(ti.f32, 3, 3)
            for ci in ti.static(range(n_combo)):
                if cid == ci:
                    tau_new = stresses[ci](F[p], q, ep[p])
            tau[p] = tau_new

    @ti.kernel
    def update(F_trial: M1, mat: I1, mparams: S2, mcombo: I1, ep: S1, F_out: M1, tau_out: M1):
        for p in F_trial:
            m = mat[p]
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            F_new = F_trial[p]
            tau_new = ti.Matrix.zero(ti.f32, 3, 3)
            ep_p = ep[p]
            for ci in ti.static(range(n_combo)):
                if cid == ci:
                    F_new, tau_new, ep_p = updates[ci](F_trial[p], q, ep_p)
            F_out[p] = F_new
            tau_out[p] = tau_new
            ep[p] = ep_p

    return SimpleNamespace(stress=stress, update=update)


def _make_update(el: type, pl: type, fracture: bool = False):
    """ti.func (F_trial, q, ep) -> (F, tau, ep): return map (then tearing, when the material
    fractures) and the stress of the returned F."""
    svd_first = M.svd_before_return_map(el, pl) or fracture
    svd_ok = M.svd_available(el, pl) or fracture

    @ti.func
    def update(F_trial, q, ep):
        mu = q[0]
        lam = q[1]
        U = ti.Matrix.identity(ti.f32, 3)
        V = ti.Matrix.identity(ti.f32, 3)
        sig = ti.Vector([1.0, 1.0, 1.0], dt=ti.f32)
        if ti.static(svd_first):
            U, S, V = ti.svd(F_trial)
            sig = ti.Vector([S[0, 0], S[1, 1], S[2, 2]], dt=ti.f32)
        F_new, U2, sig2, V2 = pl.return_map(F_trial, U, sig, V, mu, lam, q)
        d = 0.0
        ep_out = ep
        if ti.static(fracture):
            F_new, sig2, ep_out, d = M.Fracture.update(U2, sig2, V2, ep, q)
        J = 0.0
        if ti.static(svd_ok):
            J = sig2[0] * sig2[1] * sig2[2]
        else:
            J = F_new.determinant()
        tau = ti.Matrix.zero(ti.f32, 3, 3)
        if ti.static(svd_ok and M.takes_svd(el)):
            tau = el.kirchhoff_svd(F_new, U2, sig2, V2, J, mu, lam)
        else:
            tau = el.kirchhoff(F_new, J, mu, lam)
        if ti.static(fracture):
            tau = M.Fracture.degrade(tau, U2, d)
        return F_new, tau, ep_out

    return update


def _make_stress(el: type, fracture: bool = False):
    """ti.func (F, q, ep) -> tau of the given F (no return map), degraded by the damage of ep."""

    @ti.func
    def stress(F, q, ep):
        mu = q[0]
        lam = q[1]
        U = ti.Matrix.identity(ti.f32, 3)
        V = ti.Matrix.identity(ti.f32, 3)
        sig = ti.Vector([1.0, 1.0, 1.0], dt=ti.f32)
        J = 0.0
        tau = ti.Matrix.zero(ti.f32, 3, 3)
        if ti.static(el.needs_svd or fracture):
            U, S, V = ti.svd(F)
            sig = ti.Vector([S[0, 0], S[1, 1], S[2, 2]], dt=ti.f32)
            J = sig[0] * sig[1] * sig[2]
            if ti.static(M.takes_svd(el)):
                tau = el.kirchhoff_svd(F, U, sig, V, J, mu, lam)
            else:
                tau = el.kirchhoff(F, J, mu, lam)
        else:
            J = F.determinant()
            tau = el.kirchhoff(F, J, mu, lam)
        if ti.static(fracture):
            tau = M.Fracture.degrade(tau, U, M.Fracture.damage(ep, q))
        return tau

    return stress


@ti.func
def _stencil_clamped(xp, inv_dx, G):
    """Quadratic B-spline stencil (base node, fx, weights) with the base clamped onto the grid."""
    base = ti.cast(ti.floor(xp * inv_dx - 0.5), ti.i32)
    base = ti.min(ti.max(base, 0), G - 3)
    fx = xp * inv_dx - ti.cast(base, ti.f32)
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    return base, fx, w


@ti.kernel
def affine_transfer(x: V1, v: V1, C: M1, p_mass: S1, grid_v: V4, grid_m: S4, dx: ti.f32):
    """One APIC round trip of the particle velocity field at fixed positions: P2G of the
    momenta ``m (v + C dpos)`` into chunk 0 of the grid, then ``C = 4 / dx^2 sum w v_i dpos^T``.
    ``v`` is left unchanged.  Repeated, C converges to the velocity gradient the APIC transfer
    reproduces (exact for affine velocity fields: Jiang et al. 2015)."""
    inv_dx = 1.0 / dx
    G = grid_m.shape[1]
    for I in ti.grouped(grid_m):
        grid_v[I] = ti.Vector.zero(ti.f32, 3)
        grid_m[I] = 0.0
    for p in x:
        base, fx, w = _stencil_clamped(x[p], inv_dx, G)
        mass = p_mass[p]
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, ti.f32) - fx) * dx
            weight = w[i][0] * w[j][1] * w[k][2]
            node = base + offset
            grid_v[0, node[0], node[1], node[2]] += weight * mass * (v[p] + C[p] @ dpos)
            grid_m[0, node[0], node[1], node[2]] += weight * mass
    for i, j, k in ti.ndrange(G, G, G):
        m = grid_m[0, i, j, k]
        if m > 0.0:
            grid_v[0, i, j, k] = grid_v[0, i, j, k] / m
    for p in x:
        base, fx, w = _stencil_clamped(x[p], inv_dx, G)
        new_C = ti.Matrix.zero(ti.f32, 3, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, ti.f32) - fx) * dx
            weight = w[i][0] * w[j][1] * w[k][2]
            node = base + offset
            new_C += (4.0 * inv_dx * inv_dx * weight) * grid_v[0, node[0], node[1], node[2]].outer_product(dpos)
        C[p] = new_C


@ti.kernel
def add_velocity(v: V1, dvx: ti.f32, dvy: ti.f32, dvz: ti.f32):
    """v[p] += (dvx, dvy, dvz) for every particle (the leapfrog re-staggering)."""
    for p in v:
        v[p] = v[p] + ti.Vector([dvx, dvy, dvz], dt=ti.f32)


@ti.func
def _bits_bad(a) -> ti.i32:
    """1 when the f32 ``a`` is NaN or Inf (exponent bits all set; safe under fast math)."""
    return ti.cast((ti.bit_cast(a, ti.i32) & 0x7F800000) == 0x7F800000, ti.i32)


@ti.func
def _vec_bad(a) -> ti.i32:
    bad = 0
    for i in ti.static(range(3)):
        bad |= _bits_bad(a[i])
    return bad


@ti.func
def _mat_bad(a) -> ti.i32:
    bad = 0
    for i, j in ti.static(ti.ndrange(3, 3)):
        bad |= _bits_bad(a[i, j])
    return bad


@ti.kernel
def frame_stats(x: V1, v: V1, F: M1, mat: I1, out: S2, dx: ti.f32, G: ti.i32):
    """Per material k: out[k] = [non-finite count, J min, J max, speed max, outside count].
    ``out`` must be reset by the caller to [0, +big, -big, 0, 0]."""
    inv_dx = 1.0 / dx
    for p in x:
        m = mat[p]
        xp = x[p]
        vp = v[p]
        Fp = F[p]
        if _vec_bad(xp) | _vec_bad(vp) | _mat_bad(Fp):
            ti.atomic_add(out[m, 0], 1.0)
        else:
            J = Fp.determinant()
            ti.atomic_min(out[m, 1], J)
            ti.atomic_max(out[m, 2], J)
            ti.atomic_max(out[m, 3], vp.norm())
            g = xp * inv_dx
            if g.min() < 0.5 or g.max() >= ti.cast(G, ti.f32) - 1.5:
                ti.atomic_add(out[m, 4], 1.0)


@ti.kernel
def gather(idx: ti.types.ndarray(dtype=ti.i64, ndim=1), x: V1, F: M1, out_x: V1, out_F: M1, scale: ti.f32):
    """out_x[j] = scale * x[idx[j]], out_F[j] = F[idx[j]] (visible particles, original order)."""
    for j in idx:
        i = idx[j]
        out_x[j] = scale * x[i]
        out_F[j] = F[i]
