"""Free rigid bodies coupled two-way to the MLS-MPM grid (issue #15; docs/CONTRACTS.md "MPM step").

A rigid instance's particles take part in P2G like any material, carry no stress (elasticity
model ``rigid``: no elastic waves, so they do not limit the time step) and, after G2P, move as
one body.

Coupling
--------
On the grid each body is a moving collider with full impulse exchange (kernels.py, after the
grid velocities and before the boundaries; docs/CONTRACTS.md step 3).  A node where the body's
particles transfer is *covered* where their mass there is at least ``COVER rho dx^3``
(colliders.COVER = 1/6: the smoothed mass of a node half a cell outside a flat face), else in
the body's *fringe*.  The body takes the whole momentum and angular momentum of its covered
nodes (its own, the soft material's there and the stress impulses acting on them) and of its
own mass in the fringe; the covered nodes then move with its rigid velocity field, so soft
material that reaches them moves with the body instead of flowing into it, and the fringe
nodes keep the soft material's own velocity (the rigid particles read the body's field
there).  The grid's momentum and angular momentum are unchanged by this.  Before, rigid
particles read the mass-averaged node velocity and were projected afterwards: the force that
held a body up acted on the shared nodes' soft material as well, which then flowed into the
body, and a steel ball on jelly sank at about 1 cm/s without end (benchmarks/bench_rigid.py).

Where two bodies meet, a node belongs to the one with the higher index and the other's
particles read its field there: they exchange momentum through those nodes, so a collision
is perfectly inelastic, as between any two MPM materials.

Per substep, after the MPM kernel:

1. **reduce** each body b over its particles p (r_p = R_b r0_p, the offset from the centre of
   mass in the pose at the start of the substep; v_p, C_p from G2P, which for rigid particles
   reads the body field of the node's owner, not the boundary conditions: contact with
   colliders is done for the whole body in step 2):

       M = sum m_p,   P = sum m_p v_p,   L = sum m_p r_p x v_p + m_p dx^2/4 axial(C_p)

   where ``axial(C) = (C32 - C23, C13 - C31, C21 - C12)``: with the quadratic B-spline
   (APIC's D = dx^2/4 I) a particle's affine velocity C carries angular momentum
   m dx^2/4 axial(C), so the particle-grid transfers and this reduction conserve angular
   momentum exactly.  The inertia tensor in the current pose is I = R I0 R^T with
   I0 = sum m_p (|r0_p|^2 Id - r0_p r0_p^T) + m_p dx^2/2 Id (the same APIC term).
   V = P / M, omega = I^-1 L.
2. **contact** with the colliders (colliders.py: ground, surface colliders, domain walls,
   level sets of static geometry) and cuboids: every particle closer than ``CONTACT_BAND dx``
   to an obstacle (or inside an active cuboid) is a contact point (normal n, depth phi,
   collider velocity v_c, kind, friction); of the points of one body, obstacle and bin (a
   cube of ``CT_BIN`` cells) only the deepest is kept (looked up among the chunk's last
   ``CT_MERGE_BACK`` rows: the particles are stored sorted by cell), so a face resting on the
   ground has one contact per bin, not one per particle.  The support polygon is that of the
   bins (within two cells of the body's), the solve is many times shorter: a block of 600
   particles on the ground at grid 32 has 600 candidates with one per particle, 102 with one
   per cell, 42 with one per bin (the ground and the bottom wall coincide there, two obstacles);
   on an H200 (benchmarks/bench_rigid_substep.py, grid 64, 11,552 rigid particles) a substep
   took 20.4 ms with one per particle, 6.0 ms with one per cell.  Projected Gauss-Seidel over the contacts,
   ``PGS_ITERS`` sweeps, accumulated impulses: the relative normal velocity at a contact must
   not bring it past the surface within the substep (``u_n >= -max(phi, 0) / dt``,
   speculative contact), the normal impulse is >= 0 (slip surfaces: bilateral once touching),
   Coulomb friction bounds the tangential impulse by mu times the normal one; sticky
   surfaces and cuboids stop the contact point entirely.  This is why contact is done per
   body: a grid node condition acts only on the mass that sits on nodes behind the surface,
   so a rigid body resting on the ground would get a fraction of the support it needs and
   creep into it.
3. **advance**: c += dt V; R <- exp(dt [omega]x) R (Rodrigues, re-orthonormalised in f64);
   then penetration left by the linearised contact (the deepest contact per step, up to
   ``POSITION_ITERS`` times) is removed by translating the body along its contact normal;
   omega' = (R' I0^-1 R'^T) L: the angular momentum is kept in the new pose.
4. **scatter**: x_p = c + R r0_p, v_p = V + omega' x r_p, C_p = [omega']x, F_p = R (tau = 0):
   the particle state carries exactly the body's momentum and angular momentum.

Body state and sums are float64; on the CPU the reduction runs per chunk of particles (one per
thread) in a fixed order, so runs stay bitwise reproducible.
"""
import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from . import kernels as K

CONTACT_BAND = 1.0   # cells: particles closer than this to an obstacle are contact candidates
PGS_ITERS = 12
POSITION_ITERS = 4
CT_WIDTH = 16        # contact row: body, r(3), n(3), phi, v_c(3), kind, friction, region, slot, cell
CT_PER_PARTICLE = 3  # contact capacity per rigid particle
CT_MERGE_BACK = 32   # rows looked back for a contact of the same body, obstacle and bin
CT_BIN = 2.0         # cells: the edge of a contact bin (one contact per body, obstacle and bin)

vec3d = ti.types.vector(3, ti.f64)
mat3d = ti.types.matrix(3, 3, ti.f64)
V1d = ti.types.ndarray(dtype=vec3d, ndim=1)
M1d = ti.types.ndarray(dtype=mat3d, ndim=1)
S1d = ti.types.ndarray(dtype=ti.f64, ndim=1)
S3d = ti.types.ndarray(dtype=ti.f64, ndim=3)


@ti.func
def _skew(w):
    """[w]x in f64."""
    return ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dt=ti.f64)


@ti.func
def _rotation(w, dt):
    """exp(dt [w]x) in f64 (Rodrigues)."""
    th = w.norm() * dt
    R = ti.Matrix.identity(ti.f64, 3)
    if th > 1e-14:
        k = w / w.norm()
        Kx = _skew(k)
        R += ti.sin(th) * Kx + (1.0 - ti.cos(th)) * Kx @ Kx
    return R


@ti.func
def _orthonormal(R):
    """Gram-Schmidt on the columns (removes the drift of repeated products)."""
    a = ti.Vector([R[0, 0], R[1, 0], R[2, 0]], dt=ti.f64)
    b = ti.Vector([R[0, 1], R[1, 1], R[2, 1]], dt=ti.f64)
    a = a / a.norm()
    b = b - a.dot(b) * a
    b = b / b.norm()
    c = a.cross(b)
    return ti.Matrix.cols([a, b, c])


def body_setup(x: np.ndarray, mass: np.ndarray, dx: float) -> tuple:
    """Body-frame data of one rigid body from its particles (metres, kg): (centre [3],
    r0 [P, 3] offsets, I0 [3, 3] inertia including APIC's dx^2/2 per unit mass, M)."""
    x = np.asarray(x, np.float64)
    m = np.asarray(mass, np.float64)
    M = float(m.sum())
    c = (m[:, None] * x).sum(0) / M
    r0 = x - c
    I0 = (m[:, None, None] * ((r0 * r0).sum(1)[:, None, None] * np.eye(3) - r0[:, :, None] * r0[:, None, :])).sum(0)
    I0 += M * dx * dx / 2.0 * np.eye(3)
    return c, r0, I0, M


GPU_PARTICLES_PER_CHUNK = 64  # CUDA: rigid particles per thread of the body reduction
GPU_MAX_CHUNKS = 256  # the serial contact solve (advance) walks every chunk: keep it short


def reduce_chunks(arch: str, cpu_threads: int, n_particles: int) -> int:
    """Threads (chunks) of the body reduction :func:`build`'s ``reduce``: the CPU's threads on
    the CPU; on CUDA one per GPU_PARTICLES_PER_CHUNK rigid particles (at most GPU_MAX_CHUNKS).
    With one chunk a GPU ran the whole loop over the bodies' particles and their contact
    candidates in a single thread: bear_can at 300k gaussians made 2.4e6 particle-substeps/s on
    an H100 against 7e7-1e8 for the soft scenes. The chunks' sums are added in chunk order, so
    a run is reproducible for a given chunk count."""
    if arch == "cpu":
        return max(1, int(cpu_threads))
    return int(max(1, min(GPU_MAX_CHUNKS, n_particles // GPU_PARTICLES_PER_CHUNK)))


@functools.lru_cache(maxsize=None)
def build(counts: tuple, boundary: str, static: bool, private_grid: bool) -> SimpleNamespace:
    """The rigid-body kernels for the given collider layout (see kernels.Spec)."""
    col = K.collider_funcs(counts, boundary, static)
    n_obst, n_slots = col.n_obst, col.n_slots

    @ti.kernel
    def reduce(x: K.V1, v: K.V1, C: K.M1, p_mass: K.S1, rb_p: K.I1, rb_b: K.I1, rb_r0: K.V1, body_R: M1d,
               part: S3d, ct: K.S3, ct_count: K.I1, dyn: K.S2, lvl_phi: K.S3, lvl_id: K.I3, lvl_rows: K.S2,
               t: ti.f32, dx: ti.f32, wall: ti.f32, G: ti.i32):
        """Per chunk: momentum and angular momentum sums of each body (part [T, B, 6]) and the
        contact candidates (ct [T, cap, CT_WIDTH], ct_count [T])."""
        T = part.shape[0]
        B = part.shape[1]
        Pr = rb_p.shape[0]
        cap = ct.shape[1]
        L = dx * ti.cast(G, ti.f32)
        inv_dx = 1.0 / dx
        for c in range(T):
            for b in range(B):
                for q in ti.static(range(6)):
                    part[c, b, q] = 0.0
            nc = 0
            for j in range(c * Pr // T, (c + 1) * Pr // T):
                p = rb_p[j]
                b = rb_b[j]
                m = ti.cast(p_mass[p], ti.f64)
                r = body_R[b] @ ti.cast(rb_r0[j], ti.f64)
                vp = ti.cast(v[p], ti.f64)
                Cp = ti.cast(C[p], ti.f64)
                ang = m * r.cross(vp) + (m * ti.cast(dx, ti.f64) ** 2 / 4.0) * ti.Vector(
                    [Cp[2, 1] - Cp[1, 2], Cp[0, 2] - Cp[2, 0], Cp[1, 0] - Cp[0, 1]], dt=ti.f64)
                for q in ti.static(range(3)):
                    part[c, b, q] += m * vp[q]
                    part[c, b, 3 + q] += ang[q]
                xp = x[p]
                ci = ti.min(ti.max(ti.cast(ti.floor(xp * (inv_dx / CT_BIN)), ti.i32), 0), G - 1)
                cell = ti.cast((ci[0] * G + ci[1]) * G + ci[2], ti.f32)  # exact in f32 up to G = 256
                for s in range(n_slots):
                    active, phi, n, vc, kind, fric = col.slot(s, xp, ti.Vector([0, 0, 0]), False, t, dx, L, wall,
                                                              dyn, lvl_phi, lvl_id, lvl_rows)
                    region = 1 if s >= n_obst else 0
                    near = phi < CONTACT_BAND * dx
                    if region == 1:
                        near = phi < 0.0
                    if active == 1 and near:
                        # one contact per body, obstacle and grid cell: its deepest particle
                        # (the particles are stored sorted by cell, so a cell's rows are among
                        # the last few; module docs "contact")
                        at = nc
                        for back in range(1, CT_MERGE_BACK + 1):
                            k = nc - back
                            if k >= 0 and at == nc:
                                if ct[c, k, 15] == cell and ct[c, k, 14] == ti.cast(s, ti.f32) and \
                                        ct[c, k, 0] == ti.cast(b, ti.f32):
                                    at = k
                        if at < nc and phi >= ct[c, at, 7]:
                            at = -1  # a deeper contact of this cell is already there
                        if at == nc and nc >= cap:
                            at = -1
                        if at >= 0:
                            rf = ti.cast(r, ti.f32)
                            row = [ti.cast(b, ti.f32), rf[0], rf[1], rf[2], n[0], n[1], n[2], phi, vc[0], vc[1],
                                   vc[2], kind, fric, ti.cast(region, ti.f32), ti.cast(s, ti.f32), cell]
                            for q in ti.static(range(CT_WIDTH)):
                                ct[c, at, q] = row[q]
                            if at == nc:
                                nc += 1
            ct_count[c] = nc

    @ti.kernel
    def advance(part: S3d, ct: K.S3, ct_count: K.I1, acc: K.S3, body_c: V1d, body_R: M1d, body_V: V1d,
                body_w: V1d, body_M: S1d, body_I0inv: M1d, dt: ti.f64):
        """Sum the chunks, solve the contacts, move each body (serial: a few bodies)."""
        T = part.shape[0]
        B = part.shape[1]
        ti.loop_config(serialize=True)
        for b in range(B):
            P = ti.Vector.zero(ti.f64, 3)
            Lm = ti.Vector.zero(ti.f64, 3)
            for c in range(T):
                for q in ti.static(range(3)):
                    P[q] += part[c, b, q]
                    Lm[q] += part[c, b, 3 + q]
            M = body_M[b]
            R = body_R[b]
            Iinv = R @ body_I0inv[b] @ R.transpose()
            V = P / M
            w = Iinv @ Lm
            # contacts: projected Gauss-Seidel with accumulated impulses
            for c in range(T):
                for j in range(ct_count[c]):
                    for q in ti.static(range(4)):
                        acc[c, j, q] = 0.0
            for it in range(PGS_ITERS):
                for c in range(T):
                    for j in range(ct_count[c]):
                        if ti.cast(ct[c, j, 0], ti.i32) == b:
                            r = ti.Vector([ct[c, j, 1], ct[c, j, 2], ct[c, j, 3]], dt=ti.f64)
                            n = ti.Vector([ct[c, j, 4], ct[c, j, 5], ct[c, j, 6]], dt=ti.f64)
                            phi = ti.cast(ct[c, j, 7], ti.f64)
                            vc = ti.Vector([ct[c, j, 8], ct[c, j, 9], ct[c, j, 10]], dt=ti.f64)
                            kind = ct[c, j, 11]
                            fric = ti.cast(ct[c, j, 12], ti.f64)
                            region = ct[c, j, 13]
                            u = V + w.cross(r) - vc
                            if region > 0.5 or (kind < 0.5 and phi <= 0.0):
                                # stick: u = 0 at the contact (K^-1 with K = Id / M - [r]x I^-1 [r]x)
                                Rx = _skew(r)
                                Km = ti.Matrix.identity(ti.f64, 3) / M - Rx @ Iinv @ Rx
                                lam = -(Km.inverse() @ u)
                                V += lam / M
                                w += Iinv @ r.cross(lam)
                            else:
                                un = u.dot(n)
                                target = -ti.max(phi, 0.0) / dt
                                rn = r.cross(n)
                                mn = 1.0 / (1.0 / M + rn.dot(Iinv @ rn))
                                old = ti.cast(acc[c, j, 0], ti.f64)
                                new = old + (target - un) * mn
                                if not (kind > 0.5 and kind < 1.5 and phi <= 0.0):  # slip: held once touching
                                    new = ti.max(new, 0.0)
                                dl = new - old
                                acc[c, j, 0] = ti.cast(new, ti.f32)
                                V += dl * n / M
                                w += Iinv @ (dl * rn)
                                if fric > 0.0:
                                    u = V + w.cross(r) - vc
                                    ut = u - u.dot(n) * n
                                    vt = ut.norm()
                                    if vt > 1e-12:
                                        tdir = ut / vt
                                        rt = r.cross(tdir)
                                        mt = 1.0 / (1.0 / M + rt.dot(Iinv @ rt))
                                        at = ti.Vector([acc[c, j, 1], acc[c, j, 2], acc[c, j, 3]], dt=ti.f64)
                                        at_new = at - vt * mt * tdir
                                        lim = fric * ti.max(acc[c, j, 0], 0.0)
                                        if at_new.norm() > lim:
                                            at_new *= lim / at_new.norm()
                                        d = at_new - at
                                        for q in ti.static(range(3)):
                                            acc[c, j, 1 + q] = ti.cast(at_new[q], ti.f32)
                                        V += d / M
                                        w += Iinv @ r.cross(d)
            Lm = (Iinv.inverse()) @ w
            # advance the pose
            cb = body_c[b] + dt * V
            R_new = _orthonormal(_rotation(w, dt) @ R)
            # remove penetration left by the linearised contacts (translation along the normal)
            shift = ti.Vector.zero(ti.f64, 3)
            for it in range(POSITION_ITERS):
                worst = ti.cast(0.0, ti.f64)
                wn = ti.Vector.zero(ti.f64, 3)
                for c in range(T):
                    for j in range(ct_count[c]):
                        if ti.cast(ct[c, j, 0], ti.i32) == b and ct[c, j, 13] < 0.5:
                            r = ti.Vector([ct[c, j, 1], ct[c, j, 2], ct[c, j, 3]], dt=ti.f64)
                            n = ti.Vector([ct[c, j, 4], ct[c, j, 5], ct[c, j, 6]], dt=ti.f64)
                            vc = ti.Vector([ct[c, j, 8], ct[c, j, 9], ct[c, j, 10]], dt=ti.f64)
                            r_new = R_new @ (R.transpose() @ r)
                            d_pos = (cb + r_new + shift) - (body_c[b] + r) - dt * vc
                            depth = ti.cast(ct[c, j, 7], ti.f64) + d_pos.dot(n)
                            if depth < worst:
                                worst = depth
                                wn = n
                if worst < 0.0:
                    shift -= worst * wn
            cb += shift
            body_c[b] = cb
            body_R[b] = R_new
            body_V[b] = V
            body_w[b] = R_new @ body_I0inv[b] @ R_new.transpose() @ Lm

    @ti.kernel
    def scatter(x: K.V1, v: K.V1, C: K.M1, F: K.M1, tau: K.M1, rb_p: K.I1, rb_b: K.I1, rb_r0: K.V1,
                body_c: V1d, body_R: M1d, body_V: V1d, body_w: V1d, body_K: M1d):
        """Particles onto the bodies' rigid motion: x = c + R r0, v = V + w x r, C = [w]x, F = R K
        (K: the constant rotation between the pose and the particles' F, identity unless a state
        with rotated F was set)."""
        for j in rb_p:
            p = rb_p[j]
            b = rb_b[j]
            R = body_R[b]
            r = R @ ti.cast(rb_r0[j], ti.f64)
            w = body_w[b]
            x[p] = ti.cast(body_c[b] + r, ti.f32)
            v[p] = ti.cast(body_V[b] + w.cross(r), ti.f32)
            C[p] = ti.cast(_skew(w), ti.f32)
            F[p] = ti.cast(R @ body_K[b], ti.f32)
            tau[p] = ti.Matrix.zero(ti.f32, 3, 3)

    return SimpleNamespace(reduce=reduce, advance=advance, scatter=scatter)


class RigidBodies:
    """The free rigid bodies of a solver: particle lists, body state, kernels.

    Args:
        bodies: per body the storage indices [P_b] of its particles.
        x: [P, 3] particle positions (m) in storage order; mass: [P] (kg).
        dx: grid spacing (m); n_chunks: threads of the reduction (:func:`reduce_chunks`).
    """

    def __init__(self, bodies: list, x: np.ndarray, mass: np.ndarray, dx: float, n_chunks: int, names: list):
        self.names = list(names)
        self.n_bodies = len(bodies)
        self.dx = float(dx)
        rb_p, rb_b, r0s = [], [], []
        cs, I0inv, Ms = [], [], []
        self.I0 = []
        for b, idx in enumerate(bodies):
            c, r0, I0, M = body_setup(x[idx], mass[idx], dx)
            rb_p.append(idx.astype(np.int32))
            rb_b.append(np.full(len(idx), b, np.int32))
            r0s.append(r0)
            cs.append(c)
            self.I0.append(I0)
            I0inv.append(np.linalg.inv(I0))
            Ms.append(M)
        order = np.concatenate(rb_p).argsort(kind="stable")  # storage order: cache-friendly and deterministic
        self.rb_p = _nd(np.concatenate(rb_p)[order], ti.i32)
        self.rb_b = _nd(np.concatenate(rb_b)[order], ti.i32)
        self.rb_r0 = _nd(np.concatenate(r0s)[order].astype(np.float32), K.vec3)
        self.n_particles = int(len(order))
        self.mass = np.array(Ms)
        self.body_M = _nd(np.array(Ms), ti.f64)
        self.body_I0inv = _nd(np.array(I0inv), mat3d)
        self._c0 = np.array(cs)
        self.body_c = _nd(np.array(cs), vec3d)
        self.body_R = _nd(np.broadcast_to(np.eye(3), (self.n_bodies, 3, 3)).copy(), mat3d)
        self.body_V = _nd(np.zeros((self.n_bodies, 3)), vec3d)
        self.body_w = _nd(np.zeros((self.n_bodies, 3)), vec3d)
        self.body_K = _nd(np.broadcast_to(np.eye(3), (self.n_bodies, 3, 3)).copy(), mat3d)
        T = max(1, int(n_chunks))
        self.part = ti.ndarray(ti.f64, (T, self.n_bodies, 6))
        cap = CT_PER_PARTICLE * (self.n_particles // T + 1) + 8
        self.ct = ti.ndarray(ti.f32, (T, cap, CT_WIDTH))
        self.acc = ti.ndarray(ti.f32, (T, cap, 4))
        self.ct_count = ti.ndarray(ti.i32, T)

    def state(self) -> dict:
        """Body state as numpy: centre [B, 3] (m), R [B, 3, 3], V [B, 3] (m/s), omega [B, 3] (rad/s)."""
        return {"c": self.body_c.to_numpy(), "R": self.body_R.to_numpy(), "V": self.body_V.to_numpy(),
                "omega": self.body_w.to_numpy(), "mass": self.mass.copy()}

    def fit_state(self, x: np.ndarray, v: np.ndarray, C: np.ndarray, F: np.ndarray, mass: np.ndarray) -> None:
        """Body poses and motion that best explain a particle state (storage order, metres):
        centre of mass, rotation by the Kabsch fit of r0 onto x - c, and the momentum and
        angular momentum of the particles (APIC's affine part included, as in the reduction),
        and K = R^T polar(mean F) so that the particles keep their F's rotation."""
        cs, Rs, Vs, ws, Ks = [], [], [], [], []
        rb_p = self.rb_p.to_numpy()
        rb_b = self.rb_b.to_numpy()
        r0 = self.rb_r0.to_numpy().astype(np.float64)
        for b in range(self.n_bodies):
            sel = rb_b == b
            p = rb_p[sel]
            m = mass[p].astype(np.float64)
            M = m.sum()
            c = (m[:, None] * x[p]).sum(0) / M
            H = (m[:, None, None] * (r0[sel][:, :, None] * (x[p] - c)[:, None, :])).sum(0)
            U, _, Vt = np.linalg.svd(H)
            Dm = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
            R = Vt.T @ Dm @ U.T
            r = x[p] - c
            Cp = C[p]
            axial = np.stack([Cp[:, 2, 1] - Cp[:, 1, 2], Cp[:, 0, 2] - Cp[:, 2, 0], Cp[:, 1, 0] - Cp[:, 0, 1]], -1)
            Vb = (m[:, None] * v[p]).sum(0) / M
            Lb = (m[:, None] * np.cross(r, v[p])).sum(0) + (m[:, None] * self.dx ** 2 / 4.0 * axial).sum(0)
            I = R @ self.I0[b] @ R.T
            cs.append(c)
            Rs.append(R)
            Vs.append(Vb)
            ws.append(np.linalg.solve(I, Lb))
            Uf, _, Vf = np.linalg.svd((m[:, None, None] * F[p]).sum(0))
            RF = Uf @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Uf @ Vf))]) @ Vf
            Ks.append(R.T @ RF)
        self.body_c.from_numpy(np.array(cs))
        self.body_K.from_numpy(np.array(Ks))
        self.body_R.from_numpy(np.array(Rs))
        self.body_V.from_numpy(np.array(Vs))
        self.body_w.from_numpy(np.array(ws))

    def copy_state(self) -> tuple:
        return tuple(a.to_numpy() for a in (self.body_c, self.body_R, self.body_V, self.body_w, self.body_K))

    def restore_state(self, st: tuple) -> None:
        for a, val in zip((self.body_c, self.body_R, self.body_V, self.body_w, self.body_K), st):
            a.from_numpy(val)


def _nd(a: np.ndarray, dtype):
    elem = 2 if dtype in (mat3d, K.mat3) else 1 if dtype in (vec3d, K.vec3) else 0
    arr = ti.ndarray(dtype, a.shape[: a.ndim - elem])
    arr.from_numpy(a)
    return arr
