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
    p_face [P]            how far in front of its centre the particle's face lies (m; colliders.face_half_width)
    ep [P]                accumulated inelastic strain of tearing materials (materials.Fracture)
    mat [P] int           material (instance) index into mparams / mcombo
    act_bits [P] int      particle-action membership bits (see dynamics.py)
    grid_v [T,G,G,G] vec3 grid momentum, then velocity (in chunk 0)
    grid_m [T,G,G,G]      grid mass
    grid_o [T,G,G,G] vec3 FLIP materials only: the pre-force momenta (summed into chunk 0)
    mparams [K, N_PARAMS] materials.PARAM_COLUMNS (mu, lam, density, yield_stress, ...)
    mcombo [K] int        index of the material's (elasticity, plasticity) pair in Spec.combos
    dyn [R, 12]           dynamics table (dynamics.py)
    err [4] int           err[0] counts particles whose stencil left the grid (clamped)
    box [3 + T, 6] int    node boxes (lo i, j, k, hi i, j, k; hi exclusive): rows current,
                          previous, their union, then one per chunk (see "Node box")

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

Node box.  On the CPU the grid passes (clear, update, rigid coupling, boundaries) run only over
the box of nodes this substep's particles reach (their stencils' bases, min to max + 3),
computed per chunk at the start of the substep; the clear runs over the union with the last
substep's box, so every node outside the current box is zero (the boundary rules' mirror
samples read zeros there, as before).  A node outside the box has no mass, and the passes do
nothing at a node without mass, so results are those of the full-grid loops.  Each pass runs in
parallel over the box's (x, y) columns and along z inside (``_box_runs``/``_box_run``; on CUDA
one node per thread, which fills a GPU): a
node index computed per node (three integer divisions) made the passes cost more than twice as much
(duck_stone, one thread, kernel profiler: clear, update, rigid field and boundaries 1.25 ms
of a 7.8 ms substep, 0.48 with columns).  Cost that
follows the scene: a small object in a 32^3 grid used to pay for all 32,768 nodes every
substep (benchmarks/bench_node_box.py).  ``solver._box_full`` marks the whole
grid dirty after another kernel (``affine_transfer``) wrote it.  On CUDA the box is the grid
(a per-substep reduction over a million particles would cost more than the grid loops).

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
from . import staged as ST

from .colliders import FRINGE_SOFT, FRONT_BAND, GHOST_BAND, HELD_REACH, MIRROR_MASS, TOUCH

from .p2g_sorted import I1, M1, S1, V1, mat3, vec3  # noqa: E402,F401  (per-particle types, defined once there; K.mat3 is used by solver and rigid)

S2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
I2 = ti.types.ndarray(dtype=ti.i32, ndim=2)
V3 = ti.types.ndarray(dtype=vec3, ndim=3)
V4 = ti.types.ndarray(dtype=vec3, ndim=4)
S3 = ti.types.ndarray(dtype=ti.f32, ndim=3)
I3 = ti.types.ndarray(dtype=ti.i32, ndim=3)
I4 = ti.types.ndarray(dtype=ti.i32, ndim=4)
D2 = ti.types.ndarray(dtype=ti.f64, ndim=2)
D3 = ti.types.ndarray(dtype=ti.f64, ndim=3)
V1d = ti.types.ndarray(dtype=ti.types.vector(3, ti.f64), ndim=1)
M1d = ti.types.ndarray(dtype=ti.types.matrix(3, 3, ti.f64), ndim=1)
N_GSUM = 16  # per body on the grid: m, m x (3), m v (3), m x × v (3), m x x^T (6)
S4 = ti.types.ndarray(dtype=ti.f32, ndim=4)


@ti.func
def _qrow(mparams: ti.template(), m):
    """The parameter row of material ``m`` as a vector (PARAM_COLUMNS order)."""
    return ti.Vector([mparams[m, c] for c in ti.static(range(M.N_PARAMS))], dt=ti.f32)


class Spec(NamedTuple):
    """What a kernel is specialised to (hashable; the build cache key)."""

    combos: tuple        # ((elasticity name, plasticity name, fracture on/off), ...)
    boundary: str        # slip | sticky (domain walls)
    damping: bool        # whether grid damping is applied
    counts: tuple        # (surface, cuboid, acceleration, translation, rotation) dynamics rows
    static: bool         # whether there are level-set colliders (static geometry)
    private_grid: bool   # CPU: one grid per chunk of particles, no atomics; CUDA: one grid, atomics
    p2g: str = "atomic"  # atomic: one add per particle and node; coarsened: one per run of equal bases (p2g_sorted.py)
    run: int = 0         # coarsened P2G on one grid: particles per thread; P2G.CELL: per sorted cell; 0: unused
    split: int = 1       # coarsened P2G with `run` particles per thread: threads per run (P2G.SPLITS), each its share of the 27 nodes
    staged: bool = False  # CUDA without rigid bodies: G2P stores the new state through shared memory (staged.py)


@ti.func
def _trilinear(corners, fr):
    """Trilinear value and gradient (per cell, unnormalised) of a cell's 8 corner values
    ``corners`` [8] (corner (i, j, k) at 4i + 2j + k) at the fraction ``fr`` [3] of the cell."""
    phi = 0.0
    grad = ti.Vector.zero(ti.f32, 3)
    for i, j, k in ti.static(ti.ndrange(2, 2, 2)):
        v = corners[ti.static(4 * i + 2 * j + k)]
        wx = fr[0] if i else 1.0 - fr[0]
        wy = fr[1] if j else 1.0 - fr[1]
        wz = fr[2] if k else 1.0 - fr[2]
        phi += wx * wy * wz * v
        grad += v * ti.Vector([(1.0 if i else -1.0) * wy * wz, (1.0 if j else -1.0) * wx * wz,
                               (1.0 if k else -1.0) * wx * wy], dt=ti.f32)
    return phi, grad


@ti.func
def _box_sdf(xp, centre, half):
    """Signed distance (positive outside) of point ``xp`` to the box centre +- half."""
    q = ti.abs(xp - centre) - half
    return ti.max(q, 0.0).norm() + ti.min(q.max(), 0.0)


@ti.func
def _box_normal(xp, centre, half):
    """Outward unit normal of the box at ``xp`` (the gradient of :func:`_box_sdf`)."""
    rel = xp - centre
    q = ti.abs(rel) - half
    sgn = ti.Vector([1.0 if rel[a] >= 0.0 else -1.0 for a in ti.static(range(3))], dt=ti.f32)
    n = ti.Vector.zero(ti.f32, 3)
    if q.max() > 0.0:
        n = ti.max(q, 0.0) * sgn
        n /= ti.max(n.norm(), 1e-20)
    else:
        a = 0
        if q[1] > q[a]:
            a = 1
        if q[2] > q[a]:
            a = 2
        n[a] = sgn[a]
    return n


def collider_funcs(counts: tuple, boundary: str, static: bool) -> SimpleNamespace:
    """ti.funcs evaluating the boundaries (colliders.py, "Boundary placement").

    Slots, in order: the 6 domain walls, the surface colliders, the level set (if ``static``)
    (obstacles: material stays on their free side), then the cuboids (holding regions).
    ``slot(k, x, t, dx, wall, dyn, lvl_phi, lvl_id, lvl_rows)`` -> (active, phi, n, v_c, kind,
    friction) at a position x (m); the level set is interpolated trilinearly from its nodes.
    ``node_slot`` is the same at grid node I (level set: the node's own value, central
    differences for n).
    """
    n_surf, n_cub = counts[0], counts[1]
    r_cub = n_surf
    n_obst = 6 + n_surf + (1 if static else 0)
    n_slots = n_obst + n_cub
    wall_kind = 0.0 if boundary == "sticky" else 2.0  # slip walls remove only the outward velocity

    @ti.func
    def _vrow(dyn: ti.template(), r, c):
        return ti.Vector([dyn[r, c], dyn[r, c + 1], dyn[r, c + 2]], dt=ti.f32)

    @ti.func
    def _lvl_at(xp, dx, lvl_phi: ti.template(), lvl_id: ti.template(), lvl_rows: ti.template()):
        G = lvl_phi.shape[0]
        g = xp / dx
        base = ti.min(ti.max(ti.cast(ti.floor(g), ti.i32), 0), G - 2)
        fr = ti.min(ti.max(g - ti.cast(base, ti.f32), 0.0), 1.0)
        corners = ti.Vector.zero(ti.f32, 8)
        for i, j, k in ti.static(ti.ndrange(2, 2, 2)):
            corners[ti.static(4 * i + 2 * j + k)] = lvl_phi[base[0] + i, base[1] + j, base[2] + k]
        phi, grad = _trilinear(corners, fr)
        near = ti.min(ti.max(ti.cast(ti.round(g), ti.i32), 0), G - 1)
        o = lvl_id[near[0], near[1], near[2]]
        return phi, grad / ti.max(grad.norm(), 1e-20), lvl_rows[o, 0], lvl_rows[o, 1]

    @ti.func
    def _lvl_node(I, lvl_phi: ti.template(), lvl_id: ti.template(), lvl_rows: ti.template()):
        G = lvl_phi.shape[0]
        grad = ti.Vector.zero(ti.f32, 3)
        for a in ti.static(range(3)):
            e = ti.Vector.unit(3, a, ti.i32)
            hi = ti.min(I + e, G - 1)
            lo = ti.max(I - e, 0)
            grad[a] = lvl_phi[hi[0], hi[1], hi[2]] - lvl_phi[lo[0], lo[1], lo[2]]
        o = lvl_id[I[0], I[1], I[2]]
        return lvl_phi[I[0], I[1], I[2]], grad / ti.max(grad.norm(), 1e-20), lvl_rows[o, 0], lvl_rows[o, 1]

    @ti.func
    def _slot(k, xp, I, at_node: ti.template(), t, dx, L, wall, dyn: ti.template(),
              lvl_phi: ti.template(), lvl_id: ti.template(), lvl_rows: ti.template()):
        """Slot ``k`` (a runtime index: one copy of the code serves all slots)."""
        active = 1
        phi = 1.0e30
        n = ti.Vector([0.0, 0.0, 1.0], dt=ti.f32)
        vc = ti.Vector.zero(ti.f32, 3)
        kind = 0.0
        fric = 0.0
        if k < 6:  # domain wall: axis k // 2, lower (even k) or upper side
            a = k // 2
            sgn = 1.0 if k % 2 == 0 else -1.0
            n = ti.Vector([1.0 if a == 0 else 0.0, 1.0 if a == 1 else 0.0, 1.0 if a == 2 else 0.0], dt=ti.f32) * sgn
            xa = xp[0] if a == 0 else (xp[1] if a == 1 else xp[2])
            phi = xa - wall if k % 2 == 0 else L - wall - xa
            kind = wall_kind
        elif k < 6 + n_surf:
            r = k - 6
            active = 1 if (t >= dyn[r, 8] and t < dyn[r, 9]) else 0
            n = _vrow(dyn, r, 3)
            phi = (xp - _vrow(dyn, r, 0)).dot(n)
            kind = dyn[r, 6]
            fric = dyn[r, 7]
        elif k < n_obst:
            if ti.static(static):
                if ti.static(at_node):
                    phi, n, kind, fric = _lvl_node(I, lvl_phi, lvl_id, lvl_rows)
                else:
                    phi, n, kind, fric = _lvl_at(xp, dx, lvl_phi, lvl_id, lvl_rows)
        else:  # cuboid (holding region, sticky)
            r = r_cub + k - n_obst
            active = 1 if (t >= dyn[r, 9] and t < dyn[r, 10]) else 0
            vc = _vrow(dyn, r, 6)
            centre = _vrow(dyn, r, 0) + vc * (t - dyn[r, 9])
            half = _vrow(dyn, r, 3)
            phi = _box_sdf(xp, centre, half)
            n = _box_normal(xp, centre, half)
        return active, phi, n, vc, kind, fric

    @ti.func
    def node_rule(gv, n, vc, kind, fric):
        """The plain node condition: sticky -> v_c; slip -> no normal relative velocity;
        separate -> no inward normal relative velocity; friction on the tangential part."""
        out = vc
        if kind >= 0.5:
            u = gv - vc
            un = u.dot(n)
            if kind < 1.5 or un < 0.0:
                u -= un * n
            if un < 0.0:
                vt = u.norm()
                if vt > 1e-20:
                    u *= ti.max(0.0, vt + un * fric) / vt
            out = vc + u
        return out

    @ti.func
    def ghost(xn, gv, gv0, pushed, phi, n, vc, kind, fric, dx, band, m_min, grid_v: ti.template(),
              grid_m: ti.template(), grid_r: ti.template(), bodies: ti.template()):
        """The node velocity near a boundary (colliders.py, "Boundary placement"): behind it
        (phi < 0) the linear extrapolation across the surface of the velocity at the mirror
        point ``d = (band + |n|_1) dx`` in front of the surface; in front of it (0 <= phi <
        band dx: nodes whose kernel support holds the surface) the normal velocity on the same
        line, which gives these nodes the surface's reaction; else (or where the mirror's mean
        node mass is below ``m_min``) the plain node rule.

        ``gv`` is the node's velocity after the boundaries before this one, ``gv0`` before any
        boundary; ``pushed`` [3] the normal pushes that earlier obstacles at this node have
        already turned into friction.  A front node's Coulomb friction is ``fric`` times this
        obstacle's own push on the node's velocity before any boundary, less what an earlier
        frictional obstacle already charged along the same normal (overlapping bands: a
        frictionless wall pushing first does not take the floor's friction away, two coincident
        frictional surfaces do not brake twice).  Returns (velocity, pushed).

        With free rigid bodies (``bodies``, compile-time) the mirror leaves out the nodes a body
        covers (``grid_r`` > 0): they move with the body's field, which is not the material
        touching this obstacle.  A layer thinner than the mirror's distance (2 cells), squeezed
        between a free body and the ground, had the body's velocity extrapolated behind the
        ground: ghost nodes moving out of the ground, into the layer, while it pressed on them,
        so the ground did work on it (basket_mat: the basket's first landing on the 1.6-cell mat
        gained 0.66 J, rebound 1.19 times the impact speed; rigid.py "Coupling")."""
        G = grid_m.shape[1]
        out = gv
        pushed_out = pushed
        done = 0
        if phi > -GHOST_BAND * dx:
            dm = dx * (band + ti.abs(n[0]) + ti.abs(n[1]) + ti.abs(n[2]))  # the mirror's trilinear cube lies beyond the band
            xm = xn + (dm - phi) * n
            g = xm / dx
            base = ti.cast(ti.floor(g), ti.i32)
            fr = g - ti.cast(base, ti.f32)
            acc = ti.Vector.zero(ti.f32, 3)
            wsum = 0.0
            msum = 0.0
            for i, j, k in ti.static(ti.ndrange(2, 2, 2)):
                node = base + ti.Vector([i, j, k])
                if node.min() >= 0 and node.max() < G:
                    use = grid_m[0, node[0], node[1], node[2]] > 0.0
                    if ti.static(bodies):
                        if grid_r[0, node[0], node[1], node[2]] > 0:
                            use = False
                    if use:
                        w = (fr[0] if i else 1.0 - fr[0]) * (fr[1] if j else 1.0 - fr[1]) * (fr[2] if k else 1.0 - fr[2])
                        acc += w * grid_v[0, node[0], node[1], node[2]]
                        wsum += w
                        msum += w * grid_m[0, node[0], node[1], node[2]]
            if wsum > 1e-6 and msum >= m_min * wsum:
                vm = acc / wsum
                u = vm - vc
                q = phi / dm
                un = u.dot(n)
                if phi >= 0.0:  # in front: the normal part on the line through v_c and the mirror's
                    own = gv - vc
                    own_n = own.dot(n)
                    if kind < 0.5:
                        out = vc + q * u
                    else:
                        target = q * un
                        if kind >= 1.5:  # separate: it only pushes, and only against approaching material
                            target = q * ti.min(un, 0.0)
                        dn = target - own_n
                        ot = own - own_n * n
                        if kind < 1.5 or dn > 0.0:
                            out = vc + ot + target * n
                        # Coulomb friction of this obstacle's own push (on the velocity before
                        # any boundary; an earlier push along n that already braked is not counted twice)
                        dn_own = target - (gv0 - vc).dot(n)
                        if dn_own > 0.0 and fric > 0.0:
                            dn_f = ti.max(0.0, dn_own - ti.max(pushed.dot(n), 0.0))
                            vt = ot.norm()
                            if vt > 1e-20 and dn_f > 0.0:
                                out -= ot * (1.0 - ti.max(0.0, vt - fric * dn_f) / vt)
                            pushed_out = pushed + dn_f * n
                elif kind < 0.5:
                    out = vc + q * u
                else:
                    # behind a slip/separate surface: the normal part on the line through v_c and
                    # the mirror's (separate, mirror leaving: the mirror's own normal velocity)
                    target = q * un
                    if kind >= 1.5 and un >= 0.0:
                        # leaving: no faster than the node's own normal velocity (before any
                        # boundary).  Material still pressing on the surface pushes its ghost nodes
                        # into it; with the mirror's velocity (2 cells away: under a thin layer, the
                        # body rising off it) they moved out of the surface into the layer and the
                        # surface did work on it (test_rigid_block_on_a_thin_layer_on_the_ground_...)
                        target = ti.min(un, ti.max((gv0 - vc).dot(n), 0.0))
                    if fric > 0.0:
                        # rough: the node keeps its own tangential velocity less mu times its own
                        # push, as a front node does.  The ghost row carries 18-65 % of the
                        # surface's reaction (B-spline stress transfer of the lowest layers); with
                        # the mirror's tangential velocity (2 cells into a sheared body, faster
                        # than the contact) it charged no friction for it, or drove the body
                        # (validation incline_friction notes)
                        own = gv0 - vc
                        own_n = own.dot(n)
                        ot = own - own_n * n
                        dn_own = target - own_n
                        vt = ot.norm()
                        if dn_own > 0.0 and vt > 1e-20:
                            ot *= ti.max(0.0, vt - fric * dn_own) / vt
                        out = vc + ot + target * n
                    else:
                        out = vc + (u - un * n) + target * n
                done = 1
        if done == 0:
            out = node_rule(gv, n, vc, kind, fric)
        return out, pushed_out

    return SimpleNamespace(slot=_slot, node_rule=node_rule, ghost=ghost, n_obst=n_obst, n_slots=n_slots)


def uses_flip(combos: tuple) -> bool:
    """Whether a deformable (elasticity, plasticity, fracture) pair of ``combos`` blends FLIP
    into its G2P (materials.FLIP_RATIO): the substep then needs ``grid_o``."""
    return any(M.FLIP_RATIO.get(c[1], 0.0) > 0.0 for c in combos if c != M.RIGID_KEY)


@functools.lru_cache(maxsize=None)
def build(spec: Spec) -> SimpleNamespace:
    """The kernels for ``spec`` (built once per process and spec)."""
    update = make_dispatch(spec.combos)
    n_combo = len(spec.combos)
    any_fracture = any(f for _, _, f in spec.combos)
    rigid_cid = spec.combos.index(M.RIGID_KEY) if M.RIGID_KEY in spec.combos else -1
    any_flip = uses_flip(spec.combos)
    q_flip = M.COL["flip"]
    n_surf, n_cub, n_acc, n_tra, n_rot = spec.counts
    r_acc = n_surf + n_cub
    r_tra = r_acc + n_acc
    r_rot = r_tra + n_tra
    has_actions = (n_acc + n_tra + n_rot) > 0
    damping = spec.damping
    private_grid = spec.private_grid
    coarsened = spec.p2g == "coarsened"
    run = spec.run
    split = spec.split
    if split != 1 and not (coarsened and not private_grid and run > 0):
        raise ValueError(f"Spec.split {split} needs coarsened P2G with run > 0 on one grid")
    runfl = P2G.make_flush(private_grid, split)
    staged = spec.staged
    if staged and (private_grid or rigid_cid >= 0):
        raise ValueError("Spec.staged needs one grid (CUDA) and no rigid material")
    two_pi = 2.0 * math.pi
    col = collider_funcs(spec.counts, spec.boundary, spec.static)
    n_obst, n_slots = col.n_obst, col.n_slots

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
        w = P2G.bspline(fx)
        return base, fx, w

    @ti.func
    def _box_lo_n(box: ti.template(), r):
        """Row r of the node box (module docs "Node box"): its low corner and its extents."""
        lo = ti.Vector([box[r, 0], box[r, 1], box[r, 2]])
        return lo, ti.max(ti.Vector([box[r, 3], box[r, 4], box[r, 5]]) - lo, 0)

    @ti.func
    def _box_columns(box: ti.template(), r):
        """The (x, y) columns of the node box in row r (one division per column, not three per
        node: with the index of a node computed per node, the passes cost 0.15-0.3 ms each on the
        2-core CPU for a 3,500-node box)."""
        _, n = _box_lo_n(box, r)
        return n[0] * n[1]

    @ti.func
    def _box_column(box: ti.template(), r, qc):
        """Column qc (row-major, y fastest) of the node box in row r: its i, j and z range."""
        lo, n = _box_lo_n(box, r)
        return lo[0] + qc // n[1], lo[1] + qc % n[1], lo[2], lo[2] + n[2]

    @ti.func
    def _box_runs(box: ti.template(), r):
        """The runs of nodes a node pass hands to one thread: the box's (x, y) columns on the CPU
        (``_box_columns``), single nodes on CUDA (one grid, ``private_grid`` off): 4,096 columns
        of 64 nodes leave a GPU mostly idle (the H200's substep kernel took 0.63 instead of 0.37
        ms a substep at grid 64 with columns).  Only for passes whose nodes are independent; the
        rigid column sums need whole columns (``_box_columns``)."""
        res = _box_columns(box, r)
        if ti.static(not private_grid):
            _, n = _box_lo_n(box, r)
            res *= n[2]
        return res

    @ti.func
    def _box_run(box: ti.template(), r, qc):
        """Run qc of ``_box_runs``: its i, j and z range (on CUDA node qc, row-major with z
        fastest, as a range of one)."""
        i, j, k0, k1 = _box_column(box, r, qc)
        if ti.static(not private_grid):
            lo, n = _box_lo_n(box, r)
            i, j, k0 = lo[0] + qc // (n[1] * n[2]), lo[1] + (qc // n[2]) % n[1], lo[2] + qc % n[2]
            k1 = k0 + 1
        return i, j, k0, k1

    @ti.func
    def _body_field(b, I, dx, gbody: ti.template()):
        """The grid velocity field of rigid body b at node I: V + omega x (x_I - c) (f32)."""
        c0 = ti.Vector([gbody[b, 0], gbody[b, 1], gbody[b, 2]], dt=ti.f64)
        V = ti.Vector([gbody[b, 3], gbody[b, 4], gbody[b, 5]], dt=ti.f64)
        w = ti.Vector([gbody[b, 6], gbody[b, 7], gbody[b, 8]], dt=ti.f64)
        xn = ti.cast(I, ti.f64) * ti.cast(dx, ti.f64)
        return ti.cast(V + w.cross(xn - c0), ti.f32)

    @ti.func
    def _body_phi(b, xn, bphi: ti.template(), body_c: ti.template(), body_R: ti.template(), gbody: ti.template(),
                  dx):
        """Signed distance (m, > 0 outside) and outward normal of free body b at the point xn (m):
        its level set bphi[b] (built from its particles in its initial pose, on the simulation
        grid's nodes) read at the point's place in that pose, c_init + R^T (x - c), trilinearly."""
        Gb = bphi.shape[1]
        R = body_R[b]
        c_init = ti.Vector([gbody[b, 24], gbody[b, 25], gbody[b, 26]], dt=ti.f64)
        y = c_init + R.transpose() @ (ti.cast(xn, ti.f64) - body_c[b])
        g = ti.cast(y, ti.f32) / dx
        base = ti.min(ti.max(ti.cast(ti.floor(g), ti.i32), 0), Gb - 2)
        fr = ti.min(ti.max(g - ti.cast(base, ti.f32), 0.0), 1.0)
        corners = ti.Vector.zero(ti.f32, 8)
        for i, j, k in ti.static(ti.ndrange(2, 2, 2)):
            corners[ti.static(4 * i + 2 * j + k)] = bphi[b, base[0] + i, base[1] + j, base[2] + k]
        phi, grad = _trilinear(corners, fr)
        n = ti.cast(R @ ti.cast(grad, ti.f64), ti.f32)
        return phi, n / ti.max(n.norm(), 1e-20)

    @ti.func
    def _body_contact(I, xn, gv, dx, grid_v: ti.template(), grid_m: ti.template(), grid_c: ti.template(),
                      grid_r: ti.template(),
                      grid_rm: ti.template(), grid_rv: ti.template(), gbody: ti.template(), bphi: ti.template(),
                      body_c: ti.template(), body_R: ti.template()):
        """Soft material on a free body's nodes meets the body as a moving obstacle (rigid.py
        "Coupling"): the body's level set (:func:`_body_phi`), the body's solved field as the
        obstacle's velocity, a separating surface with the body's friction, the ground's node rule
        (colliders.ghost: behind the surface and, where the soft material touches it, in front).
        The reaction, the soft material's momentum change, is left in grid_rv for the reaction
        sums (the body takes it before its contact solve after G2P).  Returns (velocity, pushed)."""
        G = grid_m.shape[1]
        o = grid_r[0, I[0], I[1], I[2]]
        m = grid_m[0, I[0], I[1], I[2]]
        pushed = ti.Vector.zero(ti.f32, 3)
        out = gv
        if o != 0:
            rm = grid_rm[0, I[0], I[1], I[2]]
            dp = ti.Vector.zero(ti.f32, 3)
            if m - rm > FRINGE_SOFT * m:
                b = ti.abs(o) - 1
                phi, n = _body_phi(b, xn, bphi, body_c, body_R, gbody, dx)
                if phi < FRONT_BAND * dx:
                    vb = _body_field(b, I, dx, gbody)
                    # where soft material touches the surface (grid_c: a particle within TOUCH of an
                    # obstacle or of a body's surface), behind and in front of it, as for the ground
                    if grid_c[0, I[0], I[1], I[2]] > 0.0:
                        out, pushed = col.ghost(xn, gv, gv, pushed, phi, n, vb, 2.0, ti.cast(gbody[b, 17], ti.f32), dx,
                                                FRONT_BAND, 0.0, grid_v, grid_m, grid_r, True)
                dp = (m - rm) * (out - gv)
            grid_rv[0, I[0], I[1], I[2]] = dp
        return out, pushed

    @ti.func
    def _slab_sums(gpart: ti.template(), box: ti.template(), B, G, nq: ti.template()):
        """The rigid bodies' per-column partial sums gpart[i G + j, b, q] (q < nq) summed over y into
        gpart[G^2 + i, b, q], per x slab of the node box (a parallel loop at the kernel's top level;
        a fixed order, so the sums are reproducible)."""
        for i in range(box[0, 0], box[0, 3]):
            for b in range(B):
                for q in ti.static(range(nq)):
                    acc_s = ti.cast(0.0, ti.f64)
                    for j in range(box[0, 1], box[0, 4]):
                        acc_s += gpart[i * G + j, b, q]
                    gpart[G * G + i, b, q] = acc_s

    @ti.func
    def _is_rigid(m, mcombo: ti.template()):
        r = 0
        if ti.static(rigid_cid >= 0):
            if ti.static(n_combo == 1):
                r = 1
            elif mcombo[m] == rigid_cid:
                r = 1
        return r

    @ti.func
    def _held(xp, t, dyn: ti.template()):
        """(1, velocity) when xp lies inside an active cuboid (a holding region), else (0, 0)."""
        held = 0
        vel = ti.Vector.zero(ti.f32, 3)
        for c in ti.static(range(n_cub)):
            r = n_surf + c
            if t >= dyn[r, 9] and t < dyn[r, 10]:
                v_c = _vrow(dyn, r, 6)
                if _box_sdf(xp, _vrow(dyn, r, 0) + v_c * (t - dyn[r, 9]), _vrow(dyn, r, 3)) < 0.0:
                    held = 1
                    vel = v_c
        return held, vel

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
    def _touching(xp, half, t, dx, L, wall, dyn: ti.template(), lvl_phi: ti.template(), lvl_id: ti.template(),
                  lvl_rows: ti.template()):
        """1 when the particle at xp, whose face lies ``half`` in front of its centre (p_face:
        half its volume's cube root for lattice material, 0 for surface carriers), touches (or
        is behind) an active obstacle: its face within TOUCH cells of it (colliders.py
        "Boundary placement")."""
        touch = 0
        for s in range(n_obst):
            active, phi, n, vc, kind, fric = col.slot(s, xp, ti.Vector([0, 0, 0]), False, t, dx, L, wall, dyn,
                                                      lvl_phi, lvl_id, lvl_rows)
            if active == 1 and phi - half < TOUCH * dx:
                touch = 1
        return touch

    @ti.func
    def _p2g_prepare(p, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                     p_vol: ti.template(), p_face: ti.template(), p_mass: ti.template(), mat: ti.template(), mcombo: ti.template(),
                     act_bits: ti.template(), mbody: ti.template(), dyn: ti.template(), lvl_phi: ti.template(),
                     lvl_id: ti.template(), lvl_rows: ti.template(), err: ti.template(), dt, t, dx, inv_dx, G, L,
                     wall, gbody: ti.template(), bphi: ti.template(), body_c: ti.template(), body_R: ti.template()):
        """Particle p's stencil (base, fx, w) and what it transfers: momentum mv, APIC affine
        matrix (stress and C terms), mass; touch = 1 when it touches an obstacle (grid_c);
        owner = 1 + the rigid body it belongs to (0: deformable)."""
        xp = x[p]
        held = 0
        rigid = _is_rigid(mat[p], mcombo)
        owner = 0  # 1 + the rigid body this particle belongs to (0: deformable)
        if ti.static(rigid_cid >= 0):
            if rigid == 1:
                owner = mbody[mat[p]] + 1
        if ti.static(n_cub > 0):
            if rigid == 0:
                held, _ = _held(xp, t, dyn)
        touch = 0
        if rigid == 0 and held == 0:
            touch = _touching(xp, p_face[p], t, dx, L, wall, dyn, lvl_phi, lvl_id, lvl_rows)
            if ti.static(rigid_cid >= 0):
                if bphi.shape[1] > 1:  # free bodies: their surfaces (_body_phi) are obstacles too
                    # (at the soft particle's centre, not its face as for the other obstacles: with
                    # the face the ball of test_rigid_ball_on_jelly... sinks 14.9 mm against Hertz'
                    # 25.2 mm, with the centre 23.0 mm; which is right is open, README #15)
                    for b in range(gbody.shape[0]):
                        phi_b, _n = _body_phi(b, xp, bphi, body_c, body_R, gbody, dx)
                        if phi_b < TOUCH * dx:
                            touch = 1
        base, fx, w = _stencil(xp, inv_dx, G, err)
        vp = v[p]
        if ti.static(has_actions):
            b = act_bits[p]
            if b != 0 and held == 0:  # a holding region absorbs the forces on what it holds
                vp = _particle_actions(b, xp, vp, t, dt, dyn)
        mass = p_mass[p]
        affine = mass * C[p]
        if rigid == 0:  # a rigid particle's tau is 0 (materials.Rigid, rigid.py scatter): the same sum
            affine = (-dt * p_vol[p] * 4.0 * inv_dx * inv_dx) * tau[p] + mass * C[p]
        mv = mass * vp
        return base, fx, w, mv, affine, mass, touch, owner

    @ti.func
    def _p2g_particle(p, c, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                      p_vol: ti.template(), p_face: ti.template(), p_mass: ti.template(), mat: ti.template(), mcombo: ti.template(),
                      act_bits: ti.template(), grid_v: ti.template(), grid_m: ti.template(), grid_c: ti.template(),
                      grid_r: ti.template(), grid_rm: ti.template(), grid_rv: ti.template(), mbody: ti.template(),
                      dyn: ti.template(), lvl_phi: ti.template(), lvl_id: ti.template(), lvl_rows: ti.template(),
                      err: ti.template(), dt, t, dx, inv_dx, G, L, wall, gbody: ti.template(), bphi: ti.template(),
                      body_c: ti.template(), body_R: ti.template()):
        base, fx, w, mv, affine, mass, touch, owner = _p2g_prepare(p, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo,
                                                                   act_bits, mbody, dyn, lvl_phi, lvl_id, lvl_rows,
                                                                   err, dt, t, dx, inv_dx, G, L, wall, gbody, bphi,
                                                                   body_c, body_R)
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
            if touch == 1:
                grid_c[c, node[0], node[1], node[2]] = 1.0
            if ti.static(rigid_cid >= 0):
                if owner > 0:  # the body's mass at the node (the highest index owns it where bodies meet)
                    if ti.static(private_grid):
                        grid_r[c, node[0], node[1], node[2]] = ti.max(grid_r[c, node[0], node[1], node[2]], owner)
                        grid_rm[c, node[0], node[1], node[2]] = grid_rm[c, node[0], node[1], node[2]] + weight * mass
                        grid_rv[c, node[0], node[1], node[2]] = grid_rv[c, node[0], node[1], node[2]] + weight * (mv + affine @ dpos)
                    else:
                        ti.atomic_max(grid_r[0, node[0], node[1], node[2]], owner)
                        grid_rm[0, node[0], node[1], node[2]] += weight * mass
                        grid_rv[0, node[0], node[1], node[2]] += weight * (mv + affine @ dpos)

    @ti.func
    def _p2g_runs(p0, p1, c, s, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                  p_vol: ti.template(), p_face: ti.template(), p_mass: ti.template(), mat: ti.template(), mcombo: ti.template(),
                  act_bits: ti.template(), grid_v: ti.template(), grid_m: ti.template(), grid_c: ti.template(),
                  mbody: ti.template(), dyn: ti.template(), lvl_phi: ti.template(), lvl_id: ti.template(),
                  lvl_rows: ti.template(), err: ti.template(), dt, t, dx, inv_dx, G, L, wall, gbody: ti.template(),
                  bphi: ti.template(), body_c: ti.template(), body_R: ti.template()):
        """Coarsened P2G of particles p0..p1-1 (p2g_sorted.py): sums in registers while the
        stencil base stays the same, one write of the 27 nodes per run (and of grid_c when a
        particle of the run touches an obstacle: the same nodes); with Spec.split > 1 only the
        nodes of this thread's part ``s`` of the run."""
        acc = P2G.acc_zero(split)
        cur = ti.Vector([-1, -1, -1])  # the run's base (none yet)
        touch_run = 0
        for p in range(p0, p1 + 1):  # p1: past the end, closes the last run (one flush site: less code)
            base = ti.Vector([-2, -2, -2])
            fx = ti.Vector.zero(ti.f32, 3)
            mv = ti.Vector.zero(ti.f32, 3)
            affine = ti.Matrix.zero(ti.f32, 3, 3)
            mass = 0.0
            touch = 0
            if p < p1:
                # no rigid bodies here (the solver uses the atomic transfer with them): owner is 0
                base, fx, _w, mv, affine, mass, touch, _owner = _p2g_prepare(p, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo,
                                                                       act_bits, mbody, dyn, lvl_phi, lvl_id,
                                                                       lvl_rows, err, dt, t, dx, inv_dx, G, L, wall,
                                                                       gbody, bphi, body_c, body_R)
            if not P2G.same_base(base, cur):
                if cur[0] >= 0:
                    runfl.flush(acc, cur, s, c, grid_v, grid_m)
                    if touch_run == 1:
                        runfl.mark(cur, s, c, grid_c)
                    acc = P2G.acc_zero(split)
                    touch_run = 0
                cur = base
            if p < p1:
                P2G.acc_add(acc, split, s, fx, dx, mv, affine, mass)
                touch_run = ti.max(touch_run, touch)

    @ti.func
    def _p2g_warp(p, x: ti.template(), v: ti.template(), C: ti.template(), tau: ti.template(),
                  p_vol: ti.template(), p_face: ti.template(), p_mass: ti.template(), mat: ti.template(), mcombo: ti.template(),
                  act_bits: ti.template(), grid_v: ti.template(), grid_m: ti.template(), grid_c: ti.template(),
                  mbody: ti.template(), dyn: ti.template(), lvl_phi: ti.template(), lvl_id: ti.template(),
                  lvl_rows: ti.template(), err: ti.template(), dt, t, dx, inv_dx, G, L, wall,
                  gbody: ti.template(), bphi: ti.template(), body_c: ti.template(), body_R: ti.template()):
        """Warp-sorted P2G (p2g_sorted.py "warp runs", CUDA): slot ``p`` (past the particles:
        an empty lane); the loop over slots is a whole number of warps, lane = p % 32.  Each
        lane prepares its slot's particle; the warp sorts its 32 particles by stencil base
        (p2g_sorted.warp_sort) and hands each lane the particle of its sorted place, so the
        runs the stored order has split come together again; each run's node sums are reduced
        over its lanes and its first lane adds them to the grid."""
        lane = p % P2G.WARP_SIZE
        key = P2G.NO_KEY
        fx = ti.Vector.zero(ti.f32, 3)
        mv = ti.Vector.zero(ti.f32, 3)
        affine = ti.Matrix.zero(ti.f32, 3, 3)
        mass = 0.0
        touch = 0
        if p < x.shape[0]:
            # no rigid bodies here (the solver uses the atomic transfer with them): owner is 0
            base, fx, _w, mv, affine, mass, touch, _owner = _p2g_prepare(p, x, v, C, tau, p_vol, p_face, p_mass,
                                                                       mat, mcombo, act_bits, mbody, dyn, lvl_phi, lvl_id,
                                                                       lvl_rows, err, dt, t, dx, inv_dx, G, L, wall,
                                                                       gbody, bphi, body_c, body_R)
            key = (base[0] * G + base[1]) * G + base[2]
            if touch == 1:  # (plain stores: any order)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    grid_c[0, base[0] + i, base[1] + j, base[2] + k] = 1.0
        key, src = P2G.warp_sort(key, lane)
        # this lane's particle is now lane src's: its stencil offset, momentum, affine matrix, mass
        mask = ti.u32(P2G.FULL_MASK)
        for a in ti.static(range(3)):
            fx[a] = ti.simt.warp.shfl_sync_f32(mask, fx[a], src)
            mv[a] = ti.simt.warp.shfl_sync_f32(mask, mv[a], src)
        for a, b in ti.static(ti.ndrange(3, 3)):
            affine[a, b] = ti.simt.warp.shfl_sync_f32(mask, affine[a, b], src)
        mass = ti.simt.warp.shfl_sync_f32(mask, mass, src)
        head, ok = P2G.warp_segments(key, lane)
        base = ti.Vector([key // (G * G), (key // G) % G, key % G])
        w = P2G.bspline(fx)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            dpos = (ti.Vector([i, j, k], dt=ti.f32) - fx) * dx
            weight = w[i][0] * w[j][1] * w[k][2]
            mom = weight * (mv + affine @ dpos)
            sx = P2G.warp_sum(mom[0], ok)
            sy = P2G.warp_sum(mom[1], ok)
            sz = P2G.warp_sum(mom[2], ok)
            sm = P2G.warp_sum(weight * mass, ok)
            if head == 1 and key != P2G.NO_KEY:
                ti.atomic_add(grid_v[0, base[0] + i, base[1] + j, base[2] + k], ti.Vector([sx, sy, sz]))
                ti.atomic_add(grid_m[0, base[0] + i, base[1] + j, base[2] + k], sm)

    @ti.func
    def _flip_momentum(p, c, x: ti.template(), v: ti.template(), C: ti.template(), p_mass: ti.template(),
                       grid_o: ti.template(), err: ti.template(), dx, inv_dx, G):
        """FLIP materials' P2G of particle p's momentum m (v + C dpos) alone into grid_o[c]."""
        base, fx, w = _stencil(x[p], inv_dx, G, err)
        mass = p_mass[p]
        mv = mass * v[p]
        mC = mass * C[p]
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, ti.f32) - fx) * dx
            node = base + offset
            if ti.static(private_grid):  # this chunk's own grid: no atomic needed
                grid_o[c, node[0], node[1], node[2]] = grid_o[c, node[0], node[1], node[2]] + \
                    (w[i][0] * w[j][1] * w[k][2]) * (mv + mC @ dpos)
            else:
                grid_o[0, node[0], node[1], node[2]] += (w[i][0] * w[j][1] * w[k][2]) * (mv + mC @ dpos)

    @ti.func
    def _g2p_particle(p, x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), tau: ti.template(),
                      ep: ti.template(), mat: ti.template(), store: ti.template(),
                      grid_v: ti.template(), grid_m: ti.template(), grid_b: ti.template(), grid_o: ti.template(),
                      grid_r: ti.template(), gbody: ti.template(), bphi: ti.template(), body_c: ti.template(),
                      body_R: ti.template(), mparams: ti.template(), mcombo: ti.template(), dyn: ti.template(),
                      lvl_phi: ti.template(), lvl_id: ti.template(), lvl_rows: ti.template(), err: ti.template(), dt, t,
                      dx, inv_dx, G, L, wall):
        """G2P of particle p (reads the grid's boundary field grid_b): its new position, velocity,
        C, F after the return map and the stress of that F, and its tearing strain.  With
        ``store`` (compile-time) it also stores them into x, v, C, F, tau, ep (F, tau and ep
        not for a rigid particle: rigid.py's scatter sets them); the staged G2P stores them
        itself (staged.py)."""
        xp = x[p]
        m = mat[p]
        rigid = _is_rigid(m, mcombo)
        held = 0
        hv = ti.Vector.zero(ti.f32, 3)
        if ti.static(n_cub > 0):
            if rigid == 0:
                held, hv = _held(xp, t, dyn)
        base, fx, w = _stencil(xp, inv_dx, G, err)
        new_v = ti.Vector.zero(ti.f32, 3)
        new_C = ti.Matrix.zero(ti.f32, 3, 3)
        for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
            offset = ti.Vector([i, j, k])
            dpos = (ti.cast(offset, ti.f32) - fx) * dx
            node = base + offset
            g_v = grid_b[node[0], node[1], node[2]]
            if ti.static(rigid_cid >= 0):
                if rigid == 1:  # the field of the body owning the node (boundaries: rigid.py)
                    o = grid_r[0, node[0], node[1], node[2]]
                    if o != 0:
                        g_v = _body_field(ti.abs(o) - 1, node, dx, gbody)
                    else:
                        g_v = grid_v[0, node[0], node[1], node[2]]
            weight = w[i][0] * w[j][1] * w[k][2]
            new_v += weight * g_v
            new_C += (4.0 * inv_dx * inv_dx * weight) * g_v.outer_product(dpos)
        x_new = xp + dt * new_v
        if ti.static(any_flip):
            fr = mparams[m, q_flip]
            if rigid == 0 and fr > 0.0:
                # AFLIP (Fei et al. 2021): the APIC velocity plus the particle's own deviation
                # from the pre-force grid field (materials.FLIP_RATIO); the particle still
                # moves with, and strains by, the grid field
                v_old = ti.Vector.zero(ti.f32, 3)
                for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                    node = base + ti.Vector([i, j, k])
                    mn = grid_m[0, node[0], node[1], node[2]]
                    if mn > 0.0:
                        v_old += (w[i][0] * w[j][1] * w[k][2] / mn) * grid_o[0, node[0], node[1], node[2]]
                new_v += fr * (v[p] - v_old)
        if held == 1:
            # inside a cuboid: the particle stays with the cuboid, but carries the field the
            # ghost nodes extend into it (so stress and momentum stay continuous at the face)
            x_new = xp + dt * hv
        elif rigid == 0:  # obstacles: back onto the surface, no inward velocity
            for s in range(n_obst):
                active, phi, n, vc, kind, fric = col.slot(s, x_new, ti.Vector([0, 0, 0]), False, t, dx, L,
                                                          wall, dyn, lvl_phi, lvl_id, lvl_rows)
                if active == 1 and phi < 0.0:
                    x_new -= phi * n
                    if kind < 0.5:
                        new_v = vc
                    else:
                        un = (new_v - vc).dot(n)
                        if un < 0.0:
                            new_v -= un * n
            if ti.static(rigid_cid >= 0):
                if bphi.shape[1] > 1:  # free bodies' surfaces (separating), as the obstacles'
                    for b in range(gbody.shape[0]):
                        phi_b, n_b = _body_phi(b, x_new, bphi, body_c, body_R, gbody, dx)
                        if phi_b < 0.0:
                            x_new -= phi_b * n_b
                            c0 = ti.Vector([gbody[b, 0], gbody[b, 1], gbody[b, 2]], dt=ti.f64)
                            Vb = ti.Vector([gbody[b, 3], gbody[b, 4], gbody[b, 5]], dt=ti.f64)
                            wb = ti.Vector([gbody[b, 6], gbody[b, 7], gbody[b, 8]], dt=ti.f64)
                            vc = ti.cast(Vb + wb.cross(ti.cast(x_new, ti.f64) - c0), ti.f32)
                            un = (new_v - vc).dot(n_b)
                            if un < 0.0:
                                new_v -= un * n_b
        F_trial = (ti.Matrix.identity(ti.f32, 3) + dt * new_C) @ F[p]
        if held == 1:
            # a held particle strains with the field the ghost nodes extend into the box (its
            # stress keeps the stress continuous across the face) but transfers the holder's
            # motion, so its momentum does not feed back into the ghost nodes' mirror samples
            new_v = hv
            new_C = ti.Matrix.zero(ti.f32, 3, 3)
        F_new = F_trial
        tau_new = ti.Matrix.zero(ti.f32, 3, 3)
        ep_p = 0.0
        if ti.static(store):
            v[p] = new_v
            C[p] = new_C
            x[p] = x_new
        if rigid == 0:  # a rigid particle's F and tau are set by rigid.py's scatter after this kernel
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            if ti.static(any_fracture):
                ep_p = ep[p]
            F_new, tau_new, ep_p = update(F_trial, cid, q, ep_p)
            if ti.static(store):
                F[p] = F_new
                tau[p] = tau_new
                if ti.static(any_fracture):
                    ep[p] = ep_p
        return x_new, new_v, new_C, F_new, tau_new, ep_p

    @ti.func
    def _substep(x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), tau: ti.template(),
                 ep: ti.template(), p_vol: ti.template(), p_face: ti.template(), p_mass: ti.template(),
                 mat: ti.template(), act_bits: ti.template(), grid_v: ti.template(), grid_m: ti.template(),
                 grid_c: ti.template(), grid_b: ti.template(), grid_o: ti.template(), grid_r: ti.template(),
                 grid_rm: ti.template(), grid_rv: ti.template(), mbody: ti.template(), gpart: ti.template(),
                 gbody: ti.template(), bphi: ti.template(), body_c: ti.template(), body_R: ti.template(),
                 mparams: ti.template(), mcombo: ti.template(), dyn: ti.template(), lvl_phi: ti.template(),
                 lvl_id: ti.template(), lvl_rows: ti.template(), err: ti.template(), box: ti.template(), dt: ti.template(),
                 t: ti.template(), dx: ti.template(), wall: ti.template(), gx: ti.template(), gy: ti.template(),
                 gz: ti.template(), damp: ti.template(), cell_start: ti.template(), part: ti.template()):
        """One substep at time ``t``: the body of the kernels ``substep`` (one substep a launch)
        and ``substep_reps(R)`` (R a launch), inlined where it is called; its top-level loops
        are the launch's offloaded tasks.  Every argument is a template, so the body reads the
        kernel's own arguments as when it was the kernel itself (the same compiled code: the
        same state bit for bit, the same offloaded tasks); with the scalars passed by value
        (copied into locals) the CPU state after 11 substeps differed in its last bits."""
        # part (compile-time): 0 the whole substep; with free rigid bodies it runs as two launches
        # around their contact solve on the grid (rigid.py "Coupling"): 1 up to the bodies' grid
        # fields (P2G, grid update part 1, gbody), 2 the rest (covered nodes <- the fields after the
        # contact solve, boundaries, G2P)
        # the rigid bodies' grid projection (1-element when no instance is rigid): grid_r
        # [T,G,G,G] i32 owner (1 + body; + covered, - fringe), grid_rm [T,G,G,G] and grid_rv
        # [T,G,G,G] vec3 the rigid particles' mass and momentum (then velocity), mbody [K] i32
        # body of each material (-1: none), gpart [G^2 + G, B, N_GSUM] f64 per-column and per-slab sums, gbody
        # [B, 17] f64 per body: centre, V, omega of its grid field, covering mass (input), the field's
        # mass and inertia about its centre (xx, yy, zz, xy, xz, yz)
        inv_dx = 1.0 / dx
        n_chunks = grid_m.shape[0]
        G = grid_m.shape[1]
        L = dx * ti.cast(G, ti.f32)
        P = x.shape[0]
        if ti.static(part != 2):
            # node box (module docs "Node box"): row 0 the nodes this substep's particles reach (every node loop
            # below runs over it), row 1 last substep's, row 2 their union (cleared); CUDA: the grid
            if ti.static(private_grid):
                for c in range(n_chunks):  # per chunk of particles, rows 3 + c
                    lo = ti.Vector([G, G, G])
                    hi = ti.Vector([-1, -1, -1])
                    for p in range(c * P // n_chunks, (c + 1) * P // n_chunks):
                        base = ti.min(ti.max(ti.cast(ti.floor(x[p] * inv_dx - 0.5), ti.i32), 0), G - 3)
                        lo = ti.min(lo, base)
                        hi = ti.max(hi, base)
                    for a in ti.static(range(3)):
                        box[3 + c, a] = lo[a]
                        box[3 + c, 3 + a] = hi[a] + 3
            ti.loop_config(serialize=True)
            for a in range(3):
                box[1, a] = box[0, a]
                box[1, 3 + a] = box[0, 3 + a]
                lo = 0
                hi = G
                if ti.static(private_grid):
                    lo = G
                    hi = 0
                    for c in range(n_chunks):
                        lo = ti.min(lo, box[3 + c, a])
                        hi = ti.max(hi, box[3 + c, 3 + a])
                    hi = ti.max(hi, lo)
                box[0, a] = lo
                box[0, 3 + a] = hi
                box[2, a] = ti.min(lo, box[1, a])
                box[2, 3 + a] = ti.max(hi, box[1, 3 + a])
        # the node passes' run count, read from the box once per launch, before the first loop: a
        # loop bound computed between two loops costs Taichi a serial task of its own (on CUDA
        # one more launch a substep)
        n_nodes = _box_runs(box, 0)
        if ti.static(part != 2):
            for qc in range(n_chunks * _box_runs(box, 2)):  # per chunk, the union box's columns (CUDA: nodes)
                c = qc // _box_runs(box, 2)
                i, j, k0, k1 = _box_run(box, 2, qc % _box_runs(box, 2))
                for k in range(k0, k1):
                    grid_v[c, i, j, k] = ti.Vector.zero(ti.f32, 3)
                    grid_m[c, i, j, k] = 0.0
                    grid_c[c, i, j, k] = 0.0
                    if ti.static(any_flip):
                        grid_o[c, i, j, k] = ti.Vector.zero(ti.f32, 3)
                    if ti.static(rigid_cid >= 0):
                        grid_r[c, i, j, k] = 0
                        grid_rm[c, i, j, k] = 0.0
                        grid_rv[c, i, j, k] = ti.Vector.zero(ti.f32, 3)
            # P2G
            if ti.static(coarsened and private_grid):
                for c in range(n_chunks):  # parallel over chunks, runs of equal bases inside a chunk
                    _p2g_runs(c * P // n_chunks, (c + 1) * P // n_chunks, c, 0, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo,
                              act_bits, grid_v, grid_m, grid_c, mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx,
                              inv_dx, G, L, wall, gbody, bphi, body_c,
                                  body_R)
            elif ti.static(coarsened and run == P2G.WARP):
                ti.loop_config(block_dim=128)  # whole warps: lane = slot % 32
                for p in range((P + P2G.WARP_SIZE - 1) // P2G.WARP_SIZE * P2G.WARP_SIZE):
                    _p2g_warp(p, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo, act_bits, grid_v, grid_m, grid_c,
                              mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx, G, L, wall, gbody, bphi,
                              body_c, body_R)
            elif ti.static(coarsened and run == P2G.CELL):
                for k in range(cell_start.shape[0] - 1):  # one thread per cell of the last sort
                    p0 = cell_start[k]
                    p1 = cell_start[k + 1]
                    if p1 > p0:
                        _p2g_runs(p0, p1, 0, 0, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo, act_bits, grid_v, grid_m, grid_c,
                                  mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx, G, L, wall, gbody, bphi, body_c,
                                  body_R)
            elif ti.static(coarsened):
                for rs in range((P + run - 1) // run * split):  # `split` threads per `run` consecutive particles
                    r = rs // split
                    _p2g_runs(r * run, ti.min((r + 1) * run, P), 0, rs % split, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo,
                              act_bits, grid_v, grid_m, grid_c, mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx,
                              inv_dx, G, L, wall, gbody, bphi, body_c,
                                  body_R)
            elif ti.static(private_grid):
                for c in range(n_chunks):  # parallel over chunks, serial inside a chunk
                    for p in range(c * P // n_chunks, (c + 1) * P // n_chunks):
                        _p2g_particle(p, c, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo, act_bits, grid_v, grid_m, grid_c,
                                      grid_r, grid_rm, grid_rv, mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx, G, L, wall, gbody, bphi, body_c,
                                  body_R)
            else:
                for p in range(P):
                    _p2g_particle(p, 0, x, v, C, tau, p_vol, p_face, p_mass, mat, mcombo, act_bits, grid_v, grid_m, grid_c,
                                  grid_r, grid_rm, grid_rv, mbody, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx, G, L, wall, gbody, bphi, body_c,
                                  body_R)
            if ti.static(any_flip):
                # FLIP materials (materials.FLIP_RATIO): the momenta m (v + C dpos) alone, before the
                # stress and body-force impulses, so that G2P can tell each particle's own deviation
                # from the field the grid had before this substep's forces; on the CPU into each
                # chunk's own grid, summed in the grid update as the momenta are (a fixed order:
                # one grid for all threads gave different sums in every run)
                if ti.static(private_grid):
                    for c in range(n_chunks):
                        for p in range(c * P // n_chunks, (c + 1) * P // n_chunks):
                            _flip_momentum(p, c, x, v, C, p_mass, grid_o, err, dx, inv_dx, G)
                else:
                    for p in range(P):
                        _flip_momentum(p, 0, x, v, C, p_mass, grid_o, err, dx, inv_dx, G)
            # grid update, part 1: the chunks' grids summed into chunk 0, velocity, gravity, damping
            for qc in range(n_nodes):  # the box's (x, y) columns, z inside (CUDA: nodes; module docs)
                i, j, k0, k1 = _box_run(box, 0, qc)
                for k in range(k0, k1):
                    m = grid_m[0, i, j, k]
                    mom = grid_v[0, i, j, k]
                    touch = grid_c[0, i, j, k]
                    if ti.static(private_grid):
                        for c in range(1, n_chunks):
                            m += grid_m[c, i, j, k]
                            mom += grid_v[c, i, j, k]
                            touch += grid_c[c, i, j, k]
                        if ti.static(any_flip):
                            mo = grid_o[0, i, j, k]
                            for c in range(1, n_chunks):
                                mo += grid_o[c, i, j, k]
                            grid_o[0, i, j, k] = mo
                    grid_c[0, i, j, k] = touch
                    if ti.static(rigid_cid >= 0):
                        owner = grid_r[0, i, j, k]
                        rm = grid_rm[0, i, j, k]
                        rmom = grid_rv[0, i, j, k]
                        if ti.static(private_grid):
                            for c in range(1, n_chunks):
                                owner = ti.max(owner, grid_r[c, i, j, k])
                                rm += grid_rm[c, i, j, k]
                                rmom += grid_rv[c, i, j, k]
                        rv = ti.Vector.zero(ti.f32, 3)
                        if rm > 0.0:
                            rv = rmom / rm + dt * ti.Vector([gx, gy, gz], dt=ti.f32)
                            if ti.static(damping):
                                rv *= damp
                        if owner > 0:  # covered by the body, or in its fringe (-owner): see the coupling below
                            if rm < gbody[owner - 1, 9]:
                                owner = -owner
                        grid_r[0, i, j, k] = owner
                        grid_rm[0, i, j, k] = rm
                        grid_rv[0, i, j, k] = rv
                    gv = ti.Vector.zero(ti.f32, 3)
                    if m > 0.0:
                        gv = mom / m + dt * ti.Vector([gx, gy, gz], dt=ti.f32)
                        if ti.static(damping):
                            gv *= damp
                    grid_m[0, i, j, k] = m
                    grid_v[0, i, j, k] = gv
            if ti.static(rigid_cid >= 0):
                # rigid bodies as moving colliders (rigid.py "Coupling"): a node where a body's
                # particles transfer is covered by it where the rigid mass there is at least gbody[b, 9]
                # (marked 1 + b), else in its fringe (-(1 + b), grid update part 1).  The body's grid
                # field: the momentum and angular momentum of its own mass on its nodes, plus last
                # substep's reaction of the soft material it met (its prediction)
                B = gbody.shape[0]
                # sums in a fixed order (reproducible), parallel enough for a GPU: per (x, y) column
                # over z into gpart[i G + j], then per x slab over y into gpart[G^2 + i], then over x
                # (over the node box: outside it no node has mass)
                for qc in range(_box_columns(box, 0)):  # the box's (x, y) columns
                    i, j, k0, k1 = _box_column(box, 0, qc)
                    cix = i * G + j
                    for b in range(B):
                        for q in ti.static(range(N_GSUM)):
                            gpart[cix, b, q] = 0.0
                    for k in range(k0, k1):
                        # the rigid mass and momentum alone: soft material on the body's nodes meets
                        # it as an obstacle in part 2 and gives it the reaction (_body_contact)
                        o = grid_r[0, i, j, k]
                        m = ti.cast(grid_rm[0, i, j, k], ti.f64)
                        vn = ti.cast(grid_rv[0, i, j, k], ti.f64)
                        if o != 0 and m > 0.0:
                            b = ti.abs(o) - 1
                            xn = ti.Vector([i, j, k], dt=ti.f64) * ti.cast(dx, ti.f64)
                            xv = xn.cross(vn)
                            row = [m, m * xn[0], m * xn[1], m * xn[2], m * vn[0], m * vn[1], m * vn[2], m * xv[0],
                                   m * xv[1], m * xv[2], m * xn[0] * xn[0], m * xn[1] * xn[1], m * xn[2] * xn[2],
                                   m * xn[0] * xn[1], m * xn[0] * xn[2], m * xn[1] * xn[2]]
                            for q in ti.static(range(N_GSUM)):
                                gpart[cix, b, q] += row[q]
                _slab_sums(gpart, box, B, G, N_GSUM)
                ti.loop_config(serialize=True)
                for b in range(B):
                    acc = ti.Vector.zero(ti.f64, N_GSUM)
                    for i in range(box[0, 0], box[0, 3]):
                        for q in ti.static(range(N_GSUM)):
                            acc[q] += gpart[G * G + i, b, q]
                    c0 = ti.Vector.zero(ti.f64, 3)
                    V = ti.Vector.zero(ti.f64, 3)
                    w = ti.Vector.zero(ti.f64, 3)
                    Ic = ti.Matrix.zero(ti.f64, 3, 3)
                    # the reaction of the soft material the body met last substep (gbody[b, 18:24], momentum
                    # and angular momentum about the origin) as the prediction of this one's: the field the
                    # soft material meets is the body's motion with it (after the contact solve on the
                    # grid); the body takes the difference after G2P (rigid.py "Coupling")
                    Pr = ti.Vector([gbody[b, 18], gbody[b, 19], gbody[b, 20]], dt=ti.f64)
                    Lr = ti.Vector([gbody[b, 21], gbody[b, 22], gbody[b, 23]], dt=ti.f64)
                    for q in ti.static(range(6)):
                        gbody[b, 27 + q] = gbody[b, 18 + q]
                    if acc[0] > 0.0:
                        Mb = acc[0]
                        c0 = ti.Vector([acc[1], acc[2], acc[3]], dt=ti.f64) / Mb
                        Pb = ti.Vector([acc[4], acc[5], acc[6]], dt=ti.f64) + Pr
                        V = Pb / Mb
                        Lc = ti.Vector([acc[7], acc[8], acc[9]], dt=ti.f64) + Lr - c0.cross(Pb)  # about c0
                        S = ti.Matrix([[acc[10], acc[13], acc[14]], [acc[13], acc[11], acc[15]],
                                       [acc[14], acc[15], acc[12]]], dt=ti.f64) - Mb * c0.outer_product(c0)
                        Ic = (S[0, 0] + S[1, 1] + S[2, 2]) * ti.Matrix.identity(ti.f64, 3) - S
                        w = Ic.inverse() @ Lc
                    for q in ti.static(range(3)):
                        gbody[b, q] = c0[q]
                        gbody[b, 3 + q] = V[q]
                        gbody[b, 6 + q] = w[q]
                    # the field's mass and inertia about c0 (the contact solve on the grid, rigid.py)
                    gbody[b, 10] = acc[0]
                    gbody[b, 11] = Ic[0, 0]
                    gbody[b, 12] = Ic[1, 1]
                    gbody[b, 13] = Ic[2, 2]
                    gbody[b, 14] = Ic[0, 1]
                    gbody[b, 15] = Ic[0, 2]
                    gbody[b, 16] = Ic[1, 2]
        if ti.static(part != 1):
            if ti.static(rigid_cid >= 0):
                # the body's nodes: the soft material's own velocity (it meets the body, with its field
                # after the contact solve on the grid, in the boundary pass: _body_contact)
                for qc in range(n_nodes):  # the box's (x, y) columns, z inside (CUDA: nodes)
                    i, j, k0, k1 = _box_run(box, 0, qc)
                    for k in range(k0, k1):
                        o = grid_r[0, i, j, k]
                        m = grid_m[0, i, j, k]
                        if o != 0 and m > 0.0:
                            # the soft material's own momentum (none: the body's field); where it
                            # meets the body is decided in the boundary pass (_body_contact)
                            vb = _body_field(ti.abs(o) - 1, ti.Vector([i, j, k]), dx, gbody)
                            rm = grid_rm[0, i, j, k]
                            out = vb
                            if m - rm > FRINGE_SOFT * m:
                                out = (m * grid_v[0, i, j, k] - rm * grid_rv[0, i, j, k]) / (m - rm)
                            grid_v[0, i, j, k] = out
            # part 2: boundaries (colliders.py), reading part 1's field, into grid_b
            for qc in range(n_nodes):  # the box's (x, y) columns, z inside (CUDA: nodes; module docs)
                i, j, k0, k1 = _box_run(box, 0, qc)
                for k in range(k0, k1):
                    gv = grid_v[0, i, j, k]
                    if grid_m[0, i, j, k] > 0.0:
                        gv0 = gv  # before any boundary (front-band friction reads its own push on it)
                        pushed = ti.Vector.zero(ti.f32, 3)
                        I = ti.Vector([i, j, k])
                        xn = ti.cast(I, ti.f32) * dx
                        engaged = grid_c[0, i, j, k] > 0.0
                        if ti.static(rigid_cid >= 0):
                            gv, pushed = _body_contact(I, xn, gv, dx, grid_v, grid_m, grid_c, grid_r, grid_rm, grid_rv, gbody, bphi,
                                                       body_c, body_R)
                        for s in range(n_slots):
                            active, phi, n, vc, kind, fric = col.slot(s, xn, I, True, t, dx, L, wall, dyn, lvl_phi, lvl_id,
                                                                      lvl_rows)
                            # obstacles act where material touches them, on the nodes behind them and
                            # those in front whose support holds the surface; cuboids (holding regions)
                            # on every node inside, their mirrors beyond the held particles' reach
                            if active == 1:
                                if s < n_obst:
                                    if engaged and phi < FRONT_BAND * dx:
                                        # a ghost node (behind) reads its mirror only where the mirror
                                        # holds MIRROR_MASS of its own mass (colliders.py)
                                        m_min = 0.0
                                        if phi < 0.0:
                                            m_min = MIRROR_MASS * grid_m[0, i, j, k]
                                        gv, pushed = col.ghost(xn, gv, gv0, pushed, phi, n, vc, kind, fric, dx, FRONT_BAND,
                                                               m_min, grid_v, grid_m, grid_r, rigid_cid >= 0)
                                elif phi < 0.0:
                                    gv, pushed = col.ghost(xn, gv, gv0, pushed, phi, n, vc, kind, fric, dx, HELD_REACH,
                                                           MIRROR_MASS * grid_m[0, i, j, k], grid_v, grid_m, grid_r,
                                                           rigid_cid >= 0)
                    grid_b[i, j, k] = gv
            if ti.static(rigid_cid >= 0):
                # per body the reaction of its soft contacts (_body_contact): -sum dp and -sum x x dp
                # (about the origin) into gbody[b, 18:24], summed in a fixed order as the fields are
                B = gbody.shape[0]
                for qc in range(_box_columns(box, 0)):
                    i, j, k0, k1 = _box_column(box, 0, qc)
                    cix = i * G + j
                    for b in range(B):
                        for q in ti.static(range(6)):
                            gpart[cix, b, q] = 0.0
                    for k in range(k0, k1):
                        o = grid_r[0, i, j, k]
                        if o != 0:
                            b = ti.abs(o) - 1
                            dp = -ti.cast(grid_rv[0, i, j, k], ti.f64)
                            xn = ti.Vector([i, j, k], dt=ti.f64) * ti.cast(dx, ti.f64)
                            xl = xn.cross(dp)
                            row = [dp[0], dp[1], dp[2], xl[0], xl[1], xl[2]]
                            for q in ti.static(range(6)):
                                gpart[cix, b, q] += row[q]
                _slab_sums(gpart, box, B, G, 6)
                ti.loop_config(serialize=True)
                for b in range(B):
                    acc = ti.Vector.zero(ti.f64, 6)
                    for i in range(box[0, 0], box[0, 3]):
                        for q in ti.static(range(6)):
                            acc[q] += gpart[G * G + i, b, q]
                    for q in ti.static(range(6)):
                        gbody[b, 18 + q] = acc[q]
            # G2P, F update, return map, stress of the new F; boundaries on deformable particles
            if ti.static(staged):
                # the new state through shared memory (module docs "Staged stores"): a block's
                # particles are contiguous, so each store instruction writes whole sectors
                ti.loop_config(block_dim=ST.STAGE_BLOCK)
                for p in range((P + ST.STAGE_BLOCK - 1) // ST.STAGE_BLOCK * ST.STAGE_BLOCK):
                    sh = ti.simt.block.SharedArray((ST.STAGE_BLOCK * ST.STAGE_WORDS,), ti.f32)
                    tid = p % ST.STAGE_BLOCK
                    if p < P:
                        x_new, new_v, new_C, F_new, tau_new, ep_p = _g2p_particle(
                            p, x, v, C, F, tau, ep, mat, False, grid_v, grid_m, grid_b, grid_o, grid_r, gbody, bphi, body_c, body_R, mparams, mcombo,
                            dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx, G, L, wall)
                        ST.stage_put(sh, tid, x_new, new_v, new_C, F_new, tau_new)
                        if ti.static(any_fracture):
                            ep[p] = ep_p
                    ti.simt.block.sync()
                    ST.stage_write(sh, tid, p - tid, P, x, v, C, F, tau)
                    ti.simt.block.sync()  # all written: a thread's next slot (grid-stride loop) may refill sh
            else:
                for p in range(P):
                    _g2p_particle(p, x, v, C, F, tau, ep, mat, True, grid_v, grid_m, grid_b, grid_o, grid_r, gbody, bphi,
                                  body_c, body_R, mparams, mcombo, dyn, lvl_phi, lvl_id, lvl_rows, err, dt, t, dx, inv_dx,
                                  G, L, wall)

    @ti.kernel
    def substep(x: V1, v: V1, C: M1, F: M1, tau: M1, ep: S1, p_vol: S1, p_face: S1, p_mass: S1, mat: I1, act_bits: I1,
                grid_v: V4, grid_m: S4, grid_c: S4, grid_b: V3, grid_o: V4, grid_r: I4, grid_rm: S4, grid_rv: V4,
                mbody: I1, gpart: D3, gbody: D2, bphi: S4, body_c: V1d, body_R: M1d, mparams: S2, mcombo: I1, dyn: S2,
                lvl_phi: S3, lvl_id: I3, lvl_rows: S2, err: I1, box: I2, dt: ti.f32, t: ti.f32, dx: ti.f32,
                wall: ti.f32, gx: ti.f32, gy: ti.f32, gz: ti.f32, damp: ti.f32, cell_start: I1, part: ti.template()):
        """One substep of ``dt`` at time ``t`` (``part``: _substep)."""
        _substep(x, v, C, F, tau, ep, p_vol, p_face, p_mass, mat, act_bits, grid_v, grid_m, grid_c, grid_b, grid_o,
                 grid_r, grid_rm, grid_rv, mbody, gpart, gbody, bphi, body_c, body_R, mparams, mcombo, dyn, lvl_phi,
                 lvl_id, lvl_rows, err, box, dt, t, dx, wall, gx, gy, gz, damp, cell_start, part)

    reps_kernels = {}

    def substep_reps(reps: int):
        """The kernel of ``reps`` whole substeps a launch (part 0, no free rigid bodies): the
        arguments of ``substep`` with the time ``t`` replaced by ``ts``, the ``reps`` times
        (f32) of its substeps, and ``_substep`` inlined ``reps`` times, one after the other.

        Why: on CUDA a small scene's substep is launch-bound, and Taichi's host work per launch
        (the launch context, the ~40 arguments, the argument buffer's copy) is paid once for
        ``reps`` substeps; the launch still holds each substep's offloaded tasks, in the same
        order, so the state is bit for bit that of ``reps`` launches of ``substep`` (on the
        CPU).  Each time is passed, not computed from the first one: the solver accumulates its
        time in Python floats and each substep gets that time rounded to f32.  The cost: the
        kernel is ``reps`` copies of the substep's code and compiles about ``reps`` times as
        long (once per machine: the offline cache keeps it).  Built once per ``reps``."""
        if reps not in reps_kernels:
            Ts = ti.types.vector(reps, ti.f32)

            @ti.kernel
            def substep_r(x: V1, v: V1, C: M1, F: M1, tau: M1, ep: S1, p_vol: S1, p_face: S1, p_mass: S1, mat: I1,
                          act_bits: I1, grid_v: V4, grid_m: S4, grid_c: S4, grid_b: V3, grid_o: V4, grid_r: I4,
                          grid_rm: S4, grid_rv: V4, mbody: I1, gpart: D3, gbody: D2, bphi: S4, body_c: V1d,
                          body_R: M1d, mparams: S2, mcombo: I1, dyn: S2, lvl_phi: S3, lvl_id: I3, lvl_rows: S2,
                          err: I1, box: I2, dt: ti.f32, ts: Ts, dx: ti.f32, wall: ti.f32, gx: ti.f32, gy: ti.f32,
                          gz: ti.f32, damp: ti.f32, cell_start: I1):
                for r in ti.static(range(reps)):
                    _substep(x, v, C, F, tau, ep, p_vol, p_face, p_mass, mat, act_bits, grid_v, grid_m, grid_c,
                             grid_b, grid_o, grid_r, grid_rm, grid_rv, mbody, gpart, gbody, bphi, body_c, body_R,
                             mparams, mcombo, dyn, lvl_phi, lvl_id, lvl_rows, err, box, dt, ts[r], dx, wall, gx, gy,
                             gz, damp, cell_start, 0)

            reps_kernels[reps] = substep_r
        return reps_kernels[reps]

    return SimpleNamespace(substep=substep, substep_reps=substep_reps, spec=spec, colliders=col)


@functools.lru_cache(maxsize=None)
def build_constitutive(combos: tuple) -> SimpleNamespace:
    """Kernels of the constitutive models alone (no grid): ``stress(F, mat, mparams, mcombo,
    ep, tau)`` and ``update(F_trial, mat, mparams, mcombo, ep, F_out, tau_out)`` (return map,
    then the stress of the returned F, exactly as in G2P; ``ep`` is updated in place)."""
    update_of = make_dispatch(combos)
    n_combo = len(combos)
    # the stress depends on the elasticity (and tearing) alone: pairs that share it share one
    # copy of its code (an SVD each), so the kernel compiles once per elasticity, not per pair
    kinds = list(dict.fromkeys((e, f) for e, _, f in combos))
    stresses = [_make_stress(M.ELASTICITY[e], f) for e, f in kinds]
    kind_of = tuple(kinds.index((e, f)) for e, _, f in combos)  # combo index -> stress kind
    n_kind = len(kinds)

    @ti.kernel
    def stress(F: M1, mat: I1, mparams: S2, mcombo: I1, ep: S1, tau: M1):
        for p in F:
            m = mat[p]
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            kid = 0
            if ti.static(n_kind > 1):
                for ci in ti.static(range(n_combo)):
                    if cid == ci:
                        kid = kind_of[ci]  # a constant (ti.static here would bind a name, not store)
            tau_new = ti.Matrix.zero(ti.f32, 3, 3)
            for ki in ti.static(range(n_kind)):
                if kid == ki:
                    tau_new = stresses[ki](F[p], q, ep[p])
            tau[p] = tau_new

    @ti.kernel
    def update(F_trial: M1, mat: I1, mparams: S2, mcombo: I1, ep: S1, F_out: M1, tau_out: M1):
        for p in F_trial:
            m = mat[p]
            q = _qrow(mparams, m)
            cid = 0
            if ti.static(n_combo > 1):
                cid = mcombo[m]
            F_new, tau_new, ep_p = update_of(F_trial[p], cid, q, ep[p])
            F_out[p] = F_new
            tau_out[p] = tau_new
            ep[p] = ep_p

    return SimpleNamespace(stress=stress, update=update)


def _make_update(el: type, pl: type, fracture: bool = False):
    """ti.func (F_trial, U, sig, V, q, ep) -> (F, tau, ep): return map (then tearing, when the
    material fractures) and the stress of the returned F.  ``U, sig, V`` is the SVD of F_trial
    when :func:`_wants_svd` says the pair uses it (the caller computes it once for all pairs:
    one inlined SVD per kernel, not one per pair), else unused."""
    svd_ok = M.svd_available(el, pl) or fracture

    @ti.func
    def update(F_trial, U, sig, V, q, ep):
        mu = q[0]
        lam = q[1]
        F_new, U2, sig2, V2 = pl.return_map(F_trial, U, sig, V, mu, lam, q)
        d = 0.0
        ep_out = ep
        if ti.static(fracture):
            dp = 0.0
            if ti.static(pl.svd_mode == "needs"):  # U, V kept: the plastic strain is log(sig / sig2)
                dp = M.Fracture.plastic_strain(sig, sig2)
            F_new, sig2, ep_out, d = M.Fracture.update(U2, sig2, V2, ep + dp, q)
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


def _wants_svd(combo: tuple) -> bool:
    """Whether the (elasticity, plasticity, fracture) pair's update starts from the SVD of the
    trial F."""
    e, p, f = combo
    return M.svd_before_return_map(M.ELASTICITY[e], M.PLASTICITY[p]) or f


def make_dispatch(combos: tuple):
    """ti.func (F_trial, cid, q, ep) -> (F, tau, ep): the update of pair ``combos[cid]``.  The
    SVD of F_trial is inlined once, before the dispatch, and computed for the particles whose
    pair uses it (an SVD is most of a pair's code: one per pair made the kernel's compile time
    grow with every pair that needs one)."""
    updates = [_make_update(M.ELASTICITY[e], M.PLASTICITY[p], f) for e, p, f in combos]
    n_combo = len(updates)
    wants = tuple(int(_wants_svd(c)) for c in combos)  # [n_combo] 0/1
    any_svd, all_svd = any(wants), all(wants)

    @ti.func
    def dispatch(F_trial, cid, q, ep):
        U = ti.Matrix.identity(ti.f32, 3)
        V = ti.Matrix.identity(ti.f32, 3)
        sig = ti.Vector([1.0, 1.0, 1.0], dt=ti.f32)
        if ti.static(any_svd):
            need = 1
            if ti.static(not all_svd):
                need = 0
                for ci in ti.static(range(n_combo)):
                    if cid == ci:
                        need = wants[ci]  # a constant
            if need == 1:
                U, S, V = ti.svd(F_trial)
                sig = ti.Vector([S[0, 0], S[1, 1], S[2, 2]], dt=ti.f32)
        F_new = F_trial
        tau_new = ti.Matrix.zero(ti.f32, 3, 3)
        ep_new = ep
        for ci in ti.static(range(n_combo)):
            if cid == ci:
                F_new, tau_new, ep_new = updates[ci](F_trial, U, sig, V, q, ep)
        return F_new, tau_new, ep_new

    return dispatch


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
    w = P2G.bspline(fx)
    return base, fx, w


@ti.kernel
def affine_transfer(x: V1, v: V1, C: M1, p_mass: S1, grid_v: V4, grid_m: S4, dx: ti.f32, serial: ti.template()):
    """One APIC round trip of the particle velocity field at fixed positions: P2G of the
    momenta ``m (v + C dpos)`` into chunk 0 of the grid, then ``C = 4 / dx^2 sum w v_i dpos^T``.
    ``v`` is left unchanged.  Repeated, C converges to the velocity gradient the APIC transfer
    reproduces (exact for affine velocity fields: Jiang et al. 2015).  ``serial`` (the CPU):
    the P2G in one thread, so that its float sums, and thus C, are the same in every run
    (with threads and atomics they differed by up to 1.5e-5 between runs)."""
    inv_dx = 1.0 / dx
    G = grid_m.shape[1]
    for I in ti.grouped(grid_m):
        grid_v[I] = ti.Vector.zero(ti.f32, 3)
        grid_m[I] = 0.0
    ti.loop_config(serialize=serial)
    for p in range(x.shape[0]):
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
def frame_stats(x: V1, v: V1, F: M1, mat: I1, out: S2, err: I1, dx: ti.f32, G: ti.i32):
    """Per material k: out[k, :5] = [non-finite count, J min, J max, speed max, outside count]
    (started here from [0, +big, -big, 0, 0]); out[0, 5:7] = the clamped count err[0] as
    (err[0] // 4096, err[0] % 4096) (exact in f32), and ``err`` reset to 0: a frame's statistics
    in one launch and one read-back (each ``from_numpy``/``to_numpy`` of a Taichi ndarray is a
    launch and a host synchronisation of its own)."""
    inv_dx = 1.0 / dx
    ti.loop_config(serialize=True)  # K rows: with the err loop below one serial task
    for k in range(out.shape[0]):
        out[k, 0] = 0.0
        out[k, 1] = 3e38
        out[k, 2] = -3e38
        out[k, 3] = 0.0
        out[k, 4] = 0.0
        out[k, 5] = 0.0
        out[k, 6] = 0.0
    ti.loop_config(serialize=True)
    for i in range(err.shape[0]):
        if i == 0:
            out[0, 5] = ti.cast(err[0] // 4096, ti.f32)
            out[0, 6] = ti.cast(err[0] % 4096, ti.f32)
        err[i] = 0
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
def copy_state(x: V1, v: V1, C: M1, F: M1, tau: M1, ep: S1, ox: V1, ov: V1, oC: M1, oF: M1, otau: M1, oep: S1):
    """(ox, ov, oC, oF, otau, oep) = (x, v, C, F, tau, ep): the solver's backup in one launch."""
    for p in x:
        ox[p] = x[p]
        ov[p] = v[p]
        oC[p] = C[p]
        oF[p] = F[p]
        otau[p] = tau[p]
        oep[p] = ep[p]


@ti.kernel
def gather(idx: ti.types.ndarray(dtype=ti.i64, ndim=1), x: V1, F: M1, out: ti.types.ndarray(dtype=ti.f32, ndim=2),
           scale: ti.f32):
    """out[j] = (scale * x[idx[j]], F[idx[j]] row by row) [12] (stored particles, input order):
    one array, so that a frame comes to the host in one copy."""
    for j in idx:
        i = idx[j]
        xi = scale * x[i]
        Fi = F[i]
        for a in ti.static(range(3)):
            out[j, a] = xi[a]
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[j, 3 + 3 * a + b] = Fi[a, b]
