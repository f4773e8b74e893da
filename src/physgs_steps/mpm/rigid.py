"""Free rigid bodies coupled two-way to the MLS-MPM grid (issue #15; docs/CONTRACTS.md "MPM step").

A rigid instance's particles take part in P2G like any material, carry no stress (elasticity
model ``rigid``: no elastic waves, so they do not limit the time step) and, after G2P, move as
one body.

Coupling
--------
On the grid each body is a moving collider (kernels.py, after the grid velocities and before
the boundaries; docs/CONTRACTS.md step 3).  A node where the body's particles transfer is
*covered* where their mass there is at least ``COVER rho dx^3`` (colliders.COVER = 1/6: the
smoothed mass of a node half a cell outside a flat face), else in the body's *fringe*; the
body *owns* both (the ghost rules' mirrors leave covered nodes out).  The body's grid field is
its own mass and momentum on its nodes (V, omega about their centre), and soft material on its
nodes keeps its own velocity there; where it touches the body it meets the body as it meets a
fixed level-set collider: the body has a level set (colliders.level_set of its full particle
set in its initial pose, on the simulation grid, built once), read at a node's place in that
pose, ``c_0 + R^T (x - c)``; soft particles within ``TOUCH`` of the surface engage their nodes
(P2G, as for the ground), an engaged node of the body with soft material gets the ground's
ghost rule (separating surface, the body's friction, the body's field as the surface's
velocity: kernels.py ``_body_contact``), and after G2P a soft particle behind the surface is
moved onto it with its inward velocity relative to the body removed.  The soft material's
momentum change on the body's nodes, summed per body in a fixed order (momentum and angular
momentum), is the body's reaction: it is added to the body's momentum after G2P, before its
contact solve, so the grid's momentum is unchanged by the contact.

Before, the covered nodes took the whole momentum of every material on them into the body's
field and moved with it: soft material that reached them (up to half a cell outside the body's
surface) was glued to the body, no separation, no slip, no inelastic contact.  A soft block on
a free block rested on the covered nodes a cell above the body's particles (layer gap 0.97
cells, 0.34 on the same block fixed) and kept bouncing on them (at rest from 1.47 s, fixed:
0.53 s; benchmarks/bench_soft_on_free_body.py); duck_stone's duck sat 2.5 cm above its stone
and rocked on it to the end of the clip (kinetic energy 0.003-0.035 J from 3 to 5 s: 0.2-0.6
times that of the fixed stone at 0.4 s), so the rest hold never took the scene; basket_mat's
basket rested 1.2 cells above its foam mat, which it never dented.  Now the block rests from
0.77 s with the fixed block's gap; the duck on the stone at the fixed stone's height, below
the rest speed from 2.8 s (.devcarry figures in the rest15 report).

The soft material meets the field *after the body's contact solve* and with the body's
reaction already in it.  A substep with free bodies runs the MPM kernel in two launches
(kernels.py ``part`` 1 and 2): the first ends with the bodies' grid fields (gbody: centre c0,
V, omega, mass and inertia about c0); the field carries, as its prediction, the reaction of the
last substep (gbody[b, 18:24], copied to gbody[b, 27:33]); then each field goes through the
body's contact solve (step 2 below, ``advance`` with ``pre``, which moves nothing), and the
second launch meets the soft material with the solved field, runs the boundaries and G2P.
After G2P the body takes this substep's reaction less the prediction (_start_vw).  Without
the prediction the soft material met the body's velocity before its push (-g dt for a ball
resting on jelly): the jelly under the ball moved down at that speed every substep and the ball
followed (2.9 mm in 0.3 s in ``test_rigid_ball_on_jelly_comes_to_rest_...``); without the solve
on the grid, soft material resting on a body that rests on the ground met the body's velocity
before its ground contact and crept into it (``test_soft_block_rests_on_a_free_rigid_slab_...``).
The contacts depend only on the pose at the start of the substep, so they are found before the
first launch (``reduce`` with ``what`` 1).  After G2P the solve runs again on the momentum the
particles carry plus the reaction (steps 1-2) and the body moves.

Where two bodies meet, a node belongs to the one with the higher index, its field takes the
rigid mass of both there, and the other's particles read its field: they exchange momentum
through those nodes, so a collision is perfectly inelastic, as between any two MPM materials.
The torch pseudo-step (bgdo/torch_step.py) mirrors the grid field and the soft material's own
velocity on the body's nodes; it has no body contacts and no soft-body contact.

Per substep, after the MPM kernel's second launch:

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
   collider velocity v_c, kind, friction), all at the particles' positions in the pose at the
   start of the substep, c + R r0, where the solve and the position passes start from.  (They
   were found at x, which G2P has already moved by dt v: every contact saw a phantom
   penetration of one substep of motion, g dt^2 for a body at rest, the position pass lifted
   the body out of it, and a resting body hopped, V_z between 0 and g dt every other substep
   with twice its weight on the contacts of one of them; the parallel solve's rows switched
   between one and two layers of particles: tests/test_mpm_rigid.py
   ``test_resting_block_does_not_hop``.)  Of the points of one body, obstacle and bin (a
   cube of ``CT_BIN`` cells) only the deepest is kept (looked up among the chunk's last
   ``CT_MERGE_BACK`` rows: the particles are stored sorted by cell), so a face resting on the
   ground has one contact per bin, not one per particle.  The support polygon is that of the
   bins (within two cells of the body's), the solve is many times shorter: a block of 600
   particles on the ground at grid 32 has 600 candidates with one per particle, 102 with one
   per cell, 42 with one per bin (the ground and the bottom wall coincide there: two obstacles),
   10 once the wall under the ground is left out (below);
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

Proxy particles
---------------
A body's motion is six numbers; its particles only deposit its mass and momentum on the grid
(so soft material and the covered nodes see it) and gather the grid's momentum back.  The
fill stage samples every instance at ``fill.particles_per_cell`` before vlm_params decides
which one is rigid, so a rigid instance comes with as many particles per cell as a soft one,
and in duck_stone and basket_mat it holds most of them (2,706 of 4,249; 1,366 of 3,598).
With ``sim.rigid_particles_per_cell`` (the solver's ``rigid_particles_per_cell``) a free body
is simulated with *proxies*: its particles are grouped by cubes of edge dx / ppc^(1/3) (and by
their action bits, so scene actions still apply to exactly their particles), one proxy per
group at the group's centre of mass carrying its mass and volume (:func:`proxy_groups`).
The body's mass and centre are the full set's (the proxies' mass-weighted centre is the
full set's by construction).  Its inertia: the proxies lack their groups' own spread, so
their offsets are stretched by the symmetric A of :func:`moment_match`, which gives them the
full set's second moment; I0 (the proxies' own, with APIC's term) is then the full set's up
to rounding, and the reduction's angular momentum of a rigid motion is exactly I omega.  (With
the proxies' own moment the body would carry a different inertia; with the full set's I0 and
unstretched proxies the reduction would give I_proxy omega and omega would decay every
substep.)  A body a few groups across or one group thick (stretch above
``PROXY_MAX_STRETCH`` or a singular moment) keeps every particle.  The contacts are found at
the full set's points (``ct_r0``; reduce with ``what`` 1 reads the pose only), so a body rests
on the ground on its outermost particles as before.  The other particles of the body are not
in the solver; every output row (``get_state``, ``gather_rows``, ``stats``) places them on the
body's motion as ``scatter`` does (:meth:`RigidBodies.full_motion`), and ``set_state`` fits the
body to their state (``fit_state`` with ``full``) and scatters the proxies onto it.  Kernels
are unchanged: proxies are an ordinary rigid particle set.

Parallel contact solve
----------------------
Steps 2-3 run as ``advance`` on the CPU: one thread per body, Gauss-Seidel in the contacts'
storage order, so CPU runs stay bitwise reproducible.  On a GPU that single thread walking
the contacts was latency-bound: 3.0 of a 5.1 ms substep on an H200 (bench_rigid_substep.py,
grid 64).  There ``advance_jacobi`` solves the same contact problem in parallel over the
contacts (:func:`contact_solve` picks by arch; ``CONTACT_SOLVE`` forces one, e.g. to run the
parallel solve on the CPU in tests):

* Jacobi iterations with mass splitting (``JACOBI_ITERS``): a body with n active contact rows
  (in touch, phi <= 0, or approaching faster than their gap allows at the start velocity,
  counted before the iterations) is split into n copies of mass M / n and inertia I / n, one
  per contact.  (All rows were counted, the contact band's rows clear of the obstacle too: under
  a rock's curved underside most of them, so the touching rows got a small share of the body,
  12 iterations left part of the velocity, and on the grid (``pre``) that part fed back every
  substep: duck_stone's stone field kept -0.023 m/s after the solve and the duck crept into the
  stone on the GPU at grid 32 and 64, 0.1 m in 4 s, while the serial solve held it.  Now
  -2e-4 m/s, the gap held on the CPU with this solve; ``test_soft_block_rests_on_a_free_rigid_bowl``.)  In an
  iteration every contact computes its impulse increment from the same body velocity, with
  its copy's mass (normal, then friction from its copy's velocity after the normal impulse,
  or the full sticking impulse), and adds it and its angular impulse r x p to the body's sum
  for that iteration with atomics; the copies' velocities averaged are the body's velocity
  plus the sum over the true mass and inertia, which the next iteration starts from.  The
  accumulated impulses are kept and clamped per contact as in the serial solve (normal
  impulse >= 0 on separating surfaces, tangential impulse in the Coulomb cone of the
  normal one).  With the split masses every contact's correction is 1/n of what it would be
  alone, so the iterations cannot overshoot (mass splitting, Tonge et al. 2012).
* The position passes as parallel minima: each pass writes every contact's depth (with the
  earlier passes' translation), takes the body's deepest by an atomic minimum of the depth,
  then the first row of that depth in the serial order by an atomic minimum of the row index,
  so the pass picks the same contact as the serial one.
* Each iteration and pass is one parallel loop of the one kernel (Taichi launches them in
  order); the per-iteration sums are added in iteration order.  Atomic sums of floats make
  GPU runs reproducible to rounding only.

Measured on one H200 (``python benchmarks/bench_rigid_substep.py cuda 64 300``: grid 64, 11,552
rigid + 31,616 soft particles, 180 chunks), base 56b40c2 against this solve in the same call:
4.79 -> 2.51 ms a substep (wall clock), ``advance`` 3.017 ms -> ``advance_jacobi`` 0.424 ms of
device time a substep (its 44 launched tasks together, about 10 us each: launches, not the
solve, cost now; every other kernel 0.59 ms).  Since then its loop bounds are compile-time
constants and it launches 24 tasks: on the H200 (commit 962613c, 10068a5 in the same call)
5.01 -> 2.94 ms a substep, ``advance`` 3.01 ms -> ``advance_jacobi`` 0.26 ms; the kernels
together now take 0.86 ms of the 2.94, the rest is the host launching four kernels a substep.  CPU (serial) against CUDA (Jacobi), grid 32, 400
substeps of 2e-4 s (.devcarry/rigid_parallel/cmp_cuda.py, not in the repository): a block standing
on the ground beside a soft block agrees to 1.1e-6 in x, 3e-5 in v; a block landing and sliding
to rest on a raised ground (friction 0.5) agrees to 3.3e-4 in x, but 400 substeps after release
the CUDA run was still rocking slightly (0.076 rad/s, v 0.018 off): the landing's transient
differs, the rest state does not (tests/test_mpm_rigid.py, both solves).

Where the ground (or another obstacle with the same normal) lies on a domain wall, as in the
built-in scenes (both at 0.1), the wall's contacts are left out (``reduce``): the contact problem
had two contacts per bin there with many solutions, the serial sweep gave the whole load to
the first, the frictionless wall, so a rigid body slid on the ground without friction, and
the Jacobi solve shared it, with half the friction (tests/test_mpm_rigid.py: a sliding block
decelerates at mu g with the ground above the wall and on it, with both solves).

Body state and sums are float64; on the CPU the reduction runs per chunk of particles (one per
thread) in a fixed order, so runs stay bitwise reproducible.
"""
import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from . import kernels as K
from .backend import Launcher

CONTACT_BAND = 1.0   # cells: particles closer than this to an obstacle are contact candidates
PGS_ITERS = 12
POSITION_ITERS = 4
JACOBI_ITERS = 12    # iterations of the parallel solve (advance_jacobi)
CONTACT_SOLVE = None  # "serial" | "jacobi" | None: serial on the CPU, jacobi elsewhere (contact_solve)
CT_WIDTH = 16        # contact row: body, r(3), n(3), phi, v_c(3), kind, friction, region, slot, cell
CT_PER_PARTICLE = 3  # contact capacity per rigid particle
CT_MERGE_BACK = 32   # rows looked back for a contact of the same body, obstacle and bin
CT_BIN = 2.0         # cells: the edge of a contact bin (one contact per body, obstacle and bin)

vec3d = ti.types.vector(3, ti.f64)
mat3d = ti.types.matrix(3, 3, ti.f64)
V1d = ti.types.ndarray(dtype=vec3d, ndim=1)
M1d = ti.types.ndarray(dtype=mat3d, ndim=1)
S1d = ti.types.ndarray(dtype=ti.f64, ndim=1)
S2d = ti.types.ndarray(dtype=ti.f64, ndim=2)
S3d = ti.types.ndarray(dtype=ti.f64, ndim=3)
I2d = ti.types.ndarray(dtype=ti.i32, ndim=2)

# advance_jacobi's per-body scratch row (work [B, _W_WIDTH] f64)
_W_V, _W_W, _W_N, _W_L, _W_C, _W_R, _W_WORST = 0, 3, 6, 7, 10, 13, 22
_W_WIDTH = _W_WORST + POSITION_ITERS
_NO_WIN = 2 ** 31 - 1  # no contact below the surface in that position pass


@ti.func
def _skew(w):
    """[w]x in f64."""
    return ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]], dt=ti.f64)


@ti.func
def _contact(ct: ti.template(), c, j):
    """Row j of chunk c of the contact table: r, n, phi, v_c (f64), kind, friction (f64), region."""
    r = ti.Vector([ct[c, j, 1], ct[c, j, 2], ct[c, j, 3]], dt=ti.f64)
    n = ti.Vector([ct[c, j, 4], ct[c, j, 5], ct[c, j, 6]], dt=ti.f64)
    vc = ti.Vector([ct[c, j, 8], ct[c, j, 9], ct[c, j, 10]], dt=ti.f64)
    return r, n, ti.cast(ct[c, j, 7], ti.f64), vc, ct[c, j, 11], ti.cast(ct[c, j, 12], ti.f64), ct[c, j, 13]


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


@ti.func
def _work_R(work: ti.template(), b):
    """The new rotation kept in advance_jacobi's scratch row."""
    R = ti.Matrix.zero(ti.f64, 3, 3)
    for q in ti.static(range(9)):
        R[q // 3, q % 3] = work[b, _W_R + q]
    return R


@ti.func
def _jacobi_vw(work: ti.template(), jac: ti.template(), b, M, Iinv, upto: ti.template()):
    """Body b's velocity (V, omega) in advance_jacobi after its first ``upto`` iterations: the
    start plus their impulse sums, added in iteration order."""
    dP = ti.Vector.zero(ti.f64, 3)
    dL = ti.Vector.zero(ti.f64, 3)
    for k in ti.static(range(upto)):
        dP += ti.Vector([jac[b, k, 0], jac[b, k, 1], jac[b, k, 2]], dt=ti.f64)
        dL += ti.Vector([jac[b, k, 3], jac[b, k, 4], jac[b, k, 5]], dt=ti.f64)
    V = ti.Vector([work[b, _W_V], work[b, _W_V + 1], work[b, _W_V + 2]], dt=ti.f64) + dP / M
    w = ti.Vector([work[b, _W_W], work[b, _W_W + 1], work[b, _W_W + 2]], dt=ti.f64) + Iinv @ dL
    return V, w


@ti.func
def _shift(ct: ti.template(), work: ti.template(), win: ti.template(), b, cap, upto: ti.template()):
    """The translation of body b by the first ``upto`` position passes (in pass order)."""
    shift = ti.Vector.zero(ti.f64, 3)
    for k in ti.static(range(upto)):
        idx = win[b, k]
        if idx != _NO_WIN:
            c = idx // cap
            j = idx % cap
            n = ti.Vector([ct[c, j, 4], ct[c, j, 5], ct[c, j, 6]], dt=ti.f64)
            shift -= work[b, _W_WORST + k] * n
    return shift


@ti.func
def _body_mass(body_M: ti.template(), body_R: ti.template(), body_I0inv: ti.template(), gbody: ti.template(),
               body_c: ti.template(), b, pre: ti.template()):
    """What body b's contact solve moves: (M, I^-1 in the current pose, roff: the offset of the
    body's centre of mass from the solve's reference point, added to the contacts' arms).  The
    body itself (reference: its centre of mass), or with ``pre`` its grid field: its own mass
    and inertia on its nodes about their centre c0 (gbody, kernels.py)."""
    M = body_M[b]
    R = body_R[b]
    Iinv = R @ body_I0inv[b] @ R.transpose()
    roff = ti.Vector.zero(ti.f64, 3)
    if ti.static(pre):
        if gbody[b, 10] > 0.0:
            M = gbody[b, 10]
            Ig = ti.Matrix([[gbody[b, 11], gbody[b, 14], gbody[b, 15]], [gbody[b, 14], gbody[b, 12], gbody[b, 16]],
                            [gbody[b, 15], gbody[b, 16], gbody[b, 13]]], dt=ti.f64)
            Iinv = Ig.inverse()
            roff = body_c[b] - ti.Vector([gbody[b, 0], gbody[b, 1], gbody[b, 2]], dt=ti.f64)
    return M, Iinv, roff


@ti.func
def _start_vw(part: ti.template(), gbody: ti.template(), body_c: ti.template(), b, T, M, Iinv,
              pre: ti.template()):
    """Body b's velocity (V at the reference point of :func:`_body_mass`, omega) before its
    contact solve: from the chunks' momentum sums (part, after G2P), or with ``pre`` its grid
    field (gbody: V at c0, omega)."""
    V = ti.Vector.zero(ti.f64, 3)
    w = ti.Vector.zero(ti.f64, 3)
    if ti.static(pre):
        w = ti.Vector([gbody[b, 6], gbody[b, 7], gbody[b, 8]], dt=ti.f64)
        V = ti.Vector([gbody[b, 3], gbody[b, 4], gbody[b, 5]], dt=ti.f64)
    else:
        P = ti.Vector.zero(ti.f64, 3)
        Lm = ti.Vector.zero(ti.f64, 3)
        for c in range(T):
            for q in ti.static(range(3)):
                P[q] += part[c, b, q]
                Lm[q] += part[c, b, 3 + q]
        # the reaction of the soft material the body met on the grid (kernels.py _body_contact):
        # gbody[b, 18:21] momentum, [21:24] angular momentum about the origin, less the prediction
        # its grid field already carried (last substep's, gbody[b, 27:33]; module docs "Coupling")
        Pr = ti.Vector([gbody[b, 18] - gbody[b, 27], gbody[b, 19] - gbody[b, 28], gbody[b, 20] - gbody[b, 29]],
                       dt=ti.f64)
        Lr = ti.Vector([gbody[b, 21] - gbody[b, 30], gbody[b, 22] - gbody[b, 31], gbody[b, 23] - gbody[b, 32]],
                       dt=ti.f64)
        P += Pr
        Lm += Lr - body_c[b].cross(Pr)
        V = P / M
        w = Iinv @ Lm
    return V, w


@ti.func
def _grid_vw(gbody: ti.template(), b, V, w):
    """Body b's solved field (V at c0, omega) back into gbody."""
    for q in ti.static(range(3)):
        gbody[b, 3 + q] = V[q]
        gbody[b, 6 + q] = w[q]


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


PROXY_MAX_STRETCH = 1.25  # a body whose proxies would need more stretch is simulated with its full set


def proxy_groups(x: np.ndarray, act: np.ndarray, edge: float) -> np.ndarray:
    """The proxy particle of each particle of one rigid body (module docs "Proxy particles"):
    [n] group index 0..G-1 by the cube of edge ``edge`` (the unit of ``x``, cubes aligned with
    the origin) the particle lies in and its action bits ``act`` [n] (particles under different
    scene actions never share a proxy)."""
    cell = np.floor(np.asarray(x, np.float64) / float(edge)).astype(np.int64)
    key = np.concatenate([cell, np.asarray(act, np.int64)[:, None]], 1)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    return inv.reshape(-1)


def moment_match(rp: np.ndarray, mp: np.ndarray, rf: np.ndarray, mf: np.ndarray) -> np.ndarray | None:
    """The symmetric positive definite A [3, 3] with sum mp (A rp)(A rp)^T = sum mf rf rf^T:
    proxy offsets rp [m, 3] (masses mp) stretched by A have the second moment, hence the
    inertia, of the full set's offsets rf [n, 3] (masses mf).  (The proxies sit at the mass
    centres of their groups, so their second moment lacks the groups' own spread, a fraction
    (group size / body size)^2 of it.)  None when the proxies' moment is singular or the stretch
    exceeds PROXY_MAX_STRETCH (a body a few groups across)."""
    Sp = (np.asarray(mp, np.float64)[:, None, None] * rp[:, :, None] * rp[:, None, :]).sum(0)
    Sf = (np.asarray(mf, np.float64)[:, None, None] * rf[:, :, None] * rf[:, None, :]).sum(0)
    ev, U = np.linalg.eigh(Sp)
    if ev.min() <= 1e-9 * max(ev.max(), 1e-300):
        return None
    h = U @ np.diag(np.sqrt(ev)) @ U.T  # Sp^(1/2)
    hi = U @ np.diag(1.0 / np.sqrt(ev)) @ U.T
    e2, U2 = np.linalg.eigh(h @ Sf @ h)
    mid = U2 @ np.diag(np.sqrt(np.maximum(e2, 0.0))) @ U2.T
    A = hi @ mid @ hi
    A = 0.5 * (A + A.T)
    if np.linalg.eigvalsh(A).max() > PROXY_MAX_STRETCH:
        return None
    return A


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


def contact_solve(arch: str) -> str:
    """The contact solve of :func:`build` for an arch: ``CONTACT_SOLVE`` where set, else the
    serial projected Gauss-Seidel (``advance``) on the CPU, whose fixed order keeps CPU runs
    bitwise reproducible, and the parallel Jacobi solve (``advance_jacobi``) on a GPU, where
    one thread walking the contacts was 83 % of a substep (module docs)."""
    if CONTACT_SOLVE is not None:
        if CONTACT_SOLVE not in ("serial", "jacobi"):
            raise ValueError(f"rigid.CONTACT_SOLVE must be 'serial', 'jacobi' or None, not {CONTACT_SOLVE!r}")
        return CONTACT_SOLVE
    return "serial" if arch == "cpu" else "jacobi"


@functools.lru_cache(maxsize=None)
def build(counts: tuple, boundary: str, static: bool, private_grid: bool) -> SimpleNamespace:
    """The rigid-body kernels for the given collider layout (see kernels.Spec)."""
    col = K.collider_funcs(counts, boundary, static)
    n_obst, n_slots = col.n_obst, col.n_slots

    @ti.kernel
    def reduce(v: K.V1, C: K.M1, p_mass: K.S1, rb_p: K.I1, rb_b: K.I1, rb_r0: K.V1, body_c: V1d,
               body_R: M1d, part: S3d, ct: K.S3, ct_count: K.I1, dyn: K.S2, lvl_phi: K.S3, lvl_id: K.I3,
               lvl_rows: K.S2, t: ti.f32, dx: ti.f32, wall: ti.f32, G: ti.i32, what: ti.template()):
        """Per chunk: momentum and angular momentum sums of each body (part [T, B, 0:6]) and
        the contact candidates (ct [T, cap, CT_WIDTH], ct_count [T]) with their number per body
        (part [T, B, 6]), found at the particles' positions in the pose at the start of the
        substep, c + R r0 (not at x, which G2P has already moved by dt v: module docs
        "contact").  ``what`` (compile-time): 0 both, 1 the contacts only (they depend on the
        pose alone: found before the substep's MPM kernel, for the contact solve on the grid),
        2 the momentum sums only (after G2P)."""
        T = part.shape[0]
        B = part.shape[1]
        Pr = rb_p.shape[0]
        cap = ct.shape[1]
        L = dx * ti.cast(G, ti.f32)
        inv_dx = 1.0 / dx
        for c in range(T):
            for b in range(B):
                if ti.static(what != 1):
                    for q in ti.static(range(6)):
                        part[c, b, q] = 0.0
                if ti.static(what != 2):
                    part[c, b, 6] = 0.0
            nc = 0
            for j in range(c * Pr // T, (c + 1) * Pr // T):
                p = rb_p[j]
                b = rb_b[j]
                r = body_R[b] @ ti.cast(rb_r0[j], ti.f64)
                if ti.static(what != 1):
                    m = ti.cast(p_mass[p], ti.f64)
                    vp = ti.cast(v[p], ti.f64)
                    Cp = ti.cast(C[p], ti.f64)
                    ang = m * r.cross(vp) + (m * ti.cast(dx, ti.f64) ** 2 / 4.0) * ti.Vector(
                        [Cp[2, 1] - Cp[1, 2], Cp[0, 2] - Cp[2, 0], Cp[1, 0] - Cp[0, 1]], dt=ti.f64)
                    for q in ti.static(range(3)):
                        part[c, b, q] += m * vp[q]
                        part[c, b, 3 + q] += ang[q]
                if ti.static(what == 2):
                    continue
                xp = ti.cast(body_c[b] + r, ti.f32)  # where the contact solve starts from (advance: d_pos)
                ci = ti.min(ti.max(ti.cast(ti.floor(xp * (inv_dx / CT_BIN)), ti.i32), 0), G - 1)
                cell = ti.cast((ci[0] * G + ci[1]) * G + ci[2], ti.f32)  # exact in f32 up to G = 256
                for s in range(n_slots):
                    active, phi, n, vc, kind, fric = col.slot(s, xp, ti.Vector([0, 0, 0]), False, t, dx, L, wall,
                                                              dyn, lvl_phi, lvl_id, lvl_rows)
                    region = 1 if s >= n_obst else 0
                    near = phi < CONTACT_BAND * dx
                    if region == 1:
                        near = phi < 0.0
                    if active == 1 and near and s < 6:
                        # a domain wall with a ground or other obstacle on it (or in front of
                        # it, same normal) is left out: that obstacle holds the body.  Where the
                        # ground lies on the bottom wall (the built-in scenes: both at 0.1) the
                        # serial solve gave the whole load to the first contact, the frictionless
                        # wall, and a rigid body slid on the ground without friction
                        for s2 in range(6, n_obst):
                            a2, phi2, n2, _vc2, _k2, _f2 = col.slot(s2, xp, ti.Vector([0, 0, 0]), False, t, dx, L,
                                                                   wall, dyn, lvl_phi, lvl_id, lvl_rows)
                            if a2 == 1 and n2.dot(n) > 0.99 and phi2 <= phi + 0.01 * dx:
                                near = False
                    if active == 1 and near:
                        # one contact per body, obstacle and bin: its deepest particle (the
                        # particles are stored sorted by cell, so a bin's rows are mostly among
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
                                part[c, b, 6] += 1.0  # the body's contact rows (mass splitting)
            if ti.static(what != 2):
                ct_count[c] = nc

    @ti.kernel
    def advance(part: S3d, ct: K.S3, ct_count: K.I1, acc: K.S3, body_c: V1d, body_R: M1d, body_V: V1d,
                body_w: V1d, body_M: S1d, body_I0inv: M1d, gbody: S2d, dt: ti.f64, pre: ti.template()):
        """Sum the chunks, solve the contacts, move each body (serial: a few bodies).  With ``pre``
        (compile-time) the contact solve on the grid (module docs "Coupling"): the velocities are
        the bodies' grid fields (gbody: centre, V, omega), the solved ones go back there, and
        nothing moves."""
        T = part.shape[0]
        B = part.shape[1]
        ti.loop_config(serialize=True)
        for b in range(B):
            R = body_R[b]
            M, Iinv, roff = _body_mass(body_M, body_R, body_I0inv, gbody, body_c, b, pre)
            V, w = _start_vw(part, gbody, body_c, b, T, M, Iinv, pre)
            # contacts: projected Gauss-Seidel with accumulated impulses
            for c in range(T):
                for j in range(ct_count[c]):
                    for q in ti.static(range(4)):
                        acc[c, j, q] = 0.0
            for it in range(PGS_ITERS):
                for c in range(T):
                    for j in range(ct_count[c]):
                        if ti.cast(ct[c, j, 0], ti.i32) == b:
                            r, n, phi, vc, kind, fric, region = _contact(ct, c, j)
                            r += roff
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
            if ti.static(pre):
                _grid_vw(gbody, b, V, w)
            else:
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
                                r, n, phi, vc, _kind, _fric, _region = _contact(ct, c, j)
                                r_new = R_new @ (R.transpose() @ r)
                                d_pos = (cb + r_new + shift) - (body_c[b] + r) - dt * vc
                                depth = phi + d_pos.dot(n)
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
    def advance_jacobi(part: S3d, ct: K.S3, ct_count: K.I1, acc: K.S3, body_c: V1d, body_R: M1d, body_V: V1d,
                       body_w: V1d, body_M: S1d, body_I0inv: M1d, work: S2d, jac: S3d, depth: S2d, win: I2d,
                       gbody: S2d, dt: ti.f64, n_rows: ti.template(), B: ti.template(), pre: ti.template()):
        """:func:`advance` in parallel over the contacts (module docs "Parallel contact solve"):
        Jacobi iterations with mass splitting, the position passes as a parallel minimum.
        n_rows = T * cap (the contact table's rows) and B (the bodies) are compile-time
        constants (one compile per solver layout): with a bound read at run time Taichi (without
        advanced_optimization, backend.py) launches a serial task to compute it before each of
        the loops, 44 tasks instead of 24.  ``pre``: the contact solve on the grid, as in
        :func:`advance` (velocities from and back to gbody, no position passes)."""
        T = part.shape[0]
        cap = ct.shape[1]
        for b in range(B):  # the chunks' sums (in chunk order), the scratch rows zeroed
            M, Iinv, _roff = _body_mass(body_M, body_R, body_I0inv, gbody, body_c, b, pre)
            V, w = _start_vw(part, gbody, body_c, b, T, M, Iinv, pre)
            for q in ti.static(range(3)):
                work[b, _W_V + q] = V[q]
                work[b, _W_W + q] = w[q]
            work[b, _W_N] = 0.0
            for k in ti.static(range(JACOBI_ITERS)):
                for q in ti.static(range(6)):
                    jac[b, k, q] = 0.0
            for k in ti.static(range(POSITION_ITERS)):
                work[b, _W_WORST + k] = 0.0
                win[b, k] = _NO_WIN
        for i in range(n_rows):
            # the rows the body is split over: those in touch (phi <= 0) or approaching faster than
            # their gap allows at the start velocity; not the band's rows clear of the obstacle, which
            # take no impulse (a rock's curved underside: with them counted the touching rows got
            # a small share of the body and the solve left part of the velocity, module docs)
            c = i // cap
            j = i - c * cap
            if j < ct_count[c]:
                b = ti.cast(ct[c, j, 0], ti.i32)
                M, Iinv, roff = _body_mass(body_M, body_R, body_I0inv, gbody, body_c, b, pre)
                V = ti.Vector([work[b, _W_V], work[b, _W_V + 1], work[b, _W_V + 2]], dt=ti.f64)
                w = ti.Vector([work[b, _W_W], work[b, _W_W + 1], work[b, _W_W + 2]], dt=ti.f64)
                r, n, phi, vc, kind, fric, region = _contact(ct, c, j)
                r += roff
                un = (V + w.cross(r) - vc).dot(n)
                if region > 0.5 or phi <= 0.0 or un < -phi / dt:
                    ti.atomic_add(work[b, _W_N], 1.0)
        for it in ti.static(range(JACOBI_ITERS)):
            # every contact from the same body velocity (the start plus the earlier iterations'
            # sums, added in iteration order), its increments summed per body with atomics
            for i in range(n_rows):
                c = i // cap
                j = i - c * cap
                if j < ct_count[c]:
                    b = ti.cast(ct[c, j, 0], ti.i32)
                    M, Iinv, roff = _body_mass(body_M, body_R, body_I0inv, gbody, body_c, b, pre)
                    V, w = _jacobi_vw(work, jac, b, M, Iinv, it)
                    # mass splitting: this contact's share of the body, mass M / n, inertia I / n
                    ns = ti.max(work[b, _W_N], 1.0)
                    Ms = M / ns
                    Is = Iinv * ns
                    r, n, phi, vc, kind, fric, region = _contact(ct, c, j)
                    r += roff
                    u = V + w.cross(r) - vc
                    imp = ti.Vector.zero(ti.f64, 3)  # this iteration's impulse at the contact
                    if region > 0.5 or (kind < 0.5 and phi <= 0.0):
                        Rx = _skew(r)
                        Km = ti.Matrix.identity(ti.f64, 3) / Ms - Rx @ Is @ Rx
                        imp = -(Km.inverse() @ u)
                    else:
                        un = u.dot(n)
                        target = -ti.max(phi, 0.0) / dt
                        rn = r.cross(n)
                        mn = 1.0 / (1.0 / Ms + rn.dot(Is @ rn))
                        old = ti.cast(0.0, ti.f64)
                        if ti.static(it > 0):
                            old = ti.cast(acc[c, j, 0], ti.f64)
                        new = old + (target - un) * mn
                        if not (kind > 0.5 and kind < 1.5 and phi <= 0.0):  # slip: held once touching
                            new = ti.max(new, 0.0)
                        dl = new - old
                        acc[c, j, 0] = ti.cast(new, ti.f32)
                        imp = dl * n
                        if fric > 0.0:
                            # the contact's share of the body after its normal impulse
                            Vs = V + dl * n / Ms
                            ws = w + Is @ (dl * rn)
                            u = Vs + ws.cross(r) - vc
                            ut = u - u.dot(n) * n
                            vt = ut.norm()
                            if vt > 1e-12:
                                tdir = ut / vt
                                rt = r.cross(tdir)
                                mt = 1.0 / (1.0 / Ms + rt.dot(Is @ rt))
                                at = ti.Vector.zero(ti.f64, 3)
                                if ti.static(it > 0):
                                    at = ti.Vector([acc[c, j, 1], acc[c, j, 2], acc[c, j, 3]], dt=ti.f64)
                                at_new = at - vt * mt * tdir
                                lim = fric * ti.max(acc[c, j, 0], 0.0)
                                if at_new.norm() > lim:
                                    at_new *= lim / at_new.norm()
                                for q in ti.static(range(3)):
                                    acc[c, j, 1 + q] = ti.cast(at_new[q], ti.f32)
                                imp += at_new - at
                            elif ti.static(it == 0):
                                for q in ti.static(range(3)):
                                    acc[c, j, 1 + q] = 0.0
                        elif ti.static(it == 0):
                            for q in ti.static(range(3)):
                                acc[c, j, 1 + q] = 0.0
                    ang = r.cross(imp)
                    for q in ti.static(range(3)):
                        ti.atomic_add(jac[b, it, q], imp[q])
                        ti.atomic_add(jac[b, it, 3 + q], ang[q])
        if ti.static(pre):
            for b in range(B):
                M, Iinv, _roff = _body_mass(body_M, body_R, body_I0inv, gbody, body_c, b, pre)
                V, w = _jacobi_vw(work, jac, b, M, Iinv, JACOBI_ITERS)
                _grid_vw(gbody, b, V, w)
        else:
            for b in range(B):  # the velocities after the solve, the new pose before the position passes
                M = body_M[b]
                R = body_R[b]
                Iinv = R @ body_I0inv[b] @ R.transpose()
                V, w = _jacobi_vw(work, jac, b, M, Iinv, JACOBI_ITERS)
                Lm = (Iinv.inverse()) @ w
                cb = body_c[b] + dt * V
                R_new = _orthonormal(_rotation(w, dt) @ R)
                for q in ti.static(range(3)):
                    work[b, _W_V + q] = V[q]
                    work[b, _W_L + q] = Lm[q]
                    work[b, _W_C + q] = cb[q]
                for q in ti.static(range(9)):
                    work[b, _W_R + q] = R_new[q // 3, q % 3]
            for it in ti.static(range(POSITION_ITERS)):
                # the deepest contact per body: its depth by an atomic minimum, then the first row
                # (in the serial solve's order) of that depth by an atomic minimum of the row index
                for i in range(n_rows):
                    c = i // cap
                    j = i - c * cap
                    if j < ct_count[c] and ct[c, j, 13] < 0.5:
                        b = ti.cast(ct[c, j, 0], ti.i32)
                        shift = _shift(ct, work, win, b, cap, it)
                        r, n, phi, vc, _kind, _fric, _region = _contact(ct, c, j)
                        R_new = _work_R(work, b)
                        cb = ti.Vector([work[b, _W_C], work[b, _W_C + 1], work[b, _W_C + 2]], dt=ti.f64)
                        r_new = R_new @ (body_R[b].transpose() @ r)
                        d_pos = (cb + r_new + shift) - (body_c[b] + r) - dt * vc
                        d = phi + d_pos.dot(n)
                        depth[c, j] = d
                        if d < 0.0:
                            ti.atomic_min(work[b, _W_WORST + it], d)
                for i in range(n_rows):
                    c = i // cap
                    j = i - c * cap
                    if j < ct_count[c] and ct[c, j, 13] < 0.5:
                        b = ti.cast(ct[c, j, 0], ti.i32)
                        d = depth[c, j]
                        if d < 0.0 and d == work[b, _W_WORST + it]:
                            ti.atomic_min(win[b, it], i)
            for b in range(B):
                shift = _shift(ct, work, win, b, ct.shape[1], POSITION_ITERS)
                R_new = _work_R(work, b)
                body_c[b] = ti.Vector([work[b, _W_C], work[b, _W_C + 1], work[b, _W_C + 2]], dt=ti.f64) + shift
                body_R[b] = R_new
                body_V[b] = ti.Vector([work[b, _W_V], work[b, _W_V + 1], work[b, _W_V + 2]], dt=ti.f64)
                Lm = ti.Vector([work[b, _W_L], work[b, _W_L + 1], work[b, _W_L + 2]], dt=ti.f64)
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

    return SimpleNamespace(reduce=reduce, advance=advance, advance_jacobi=advance_jacobi, scatter=scatter)


class RigidBodies:
    """The free rigid bodies of a solver: particle lists, body state, kernels.

    Args:
        bodies: per body the storage indices [P_b] of its particles.
        x: [P, 3] particle positions (m) in storage order; mass: [P] (kg).
        dx: grid spacing (m); n_chunks: threads of the reduction (:func:`reduce_chunks`).
        solve: the contact solve, "serial" or "jacobi" (:func:`contact_solve`).
        full: per body None (its storage particles are the whole body) or, for a body simulated
            with proxy particles (module docs "Proxy particles"), ``(x_full [n, 3] m, mass_full
            [n] kg)``: its complete particle set (in the caller's order); the body's centre, mass
            and inertia are those of the full set, the proxies' offsets are stretched
            (:func:`moment_match`) so that their inertia is the same, and the contacts are found
            at the full set's points.
    """

    def __init__(self, bodies: list, x: np.ndarray, mass: np.ndarray, dx: float, n_chunks: int, names: list,
                 solve: str = "serial", full: list | None = None):
        if solve not in ("serial", "jacobi"):
            raise ValueError(f"rigid contact solve must be 'serial' or 'jacobi', not {solve!r}")
        self.solve = solve
        self.names = list(names)
        self.n_bodies = len(bodies)
        self.dx = float(dx)
        full = list(full) if full is not None else [None] * len(bodies)
        rb_p, rb_b, r0s = [], [], []
        cs, I0inv, Ms = [], [], []
        self.I0 = []
        self.full_r0 = []  # per body: None, or the full set's offsets [n, 3] (m, body frame), caller's order
        self.full_mass = []
        self.stretch = []  # per body: the proxies' largest stretch (1: no proxies)
        ct_r0, ct_b, ct_x = [], [], []
        for b, idx in enumerate(bodies):
            if full[b] is None:
                c, r0, I0, M = body_setup(x[idx], mass[idx], dx)
                self.full_r0.append(None)
                self.full_mass.append(None)
                self.stretch.append(1.0)
            else:
                xf, mf = full[b]
                c, rf, I0f, Mf = body_setup(xf, mf, dx)
                rp = np.asarray(x[idx], np.float64) - c
                A = moment_match(rp, mass[idx], rf, mf)
                if A is None:
                    raise ValueError(f"rigid body {names[b]!r}: its proxy particles cannot carry its inertia "
                                     f"(too few or flat: use the full set)")
                r0 = rp @ A  # A symmetric
                # the proxies' own inertia: the full set's up to rounding (moment_match), and
                # exactly what the reduction's angular momentum of a rigid motion gives
                _c, _r, I0, M = body_setup(c + r0, mass[idx], dx)
                self.full_r0.append(rf)
                self.full_mass.append(np.asarray(mf, np.float64))
                self.stretch.append(float(np.linalg.eigvalsh(A).max()))
                ct_r0.append(rf)
                ct_b.append(np.full(len(rf), b, np.int32))
                ct_x.append(np.asarray(xf, np.float64))
            rb_p.append(idx.astype(np.int32))
            rb_b.append(np.full(len(idx), b, np.int32))
            r0s.append(r0)
            cs.append(c)
            self.I0.append(I0)
            I0inv.append(np.linalg.inv(I0))
            Ms.append(M)
            if full[b] is None and any(f is not None for f in full):
                ct_r0.append(r0)
                ct_b.append(np.full(len(idx), b, np.int32))
                ct_x.append(np.asarray(x[idx], np.float64))
        order = np.concatenate(rb_p).argsort(kind="stable")  # storage order: cache-friendly and deterministic
        self.rb_p = _nd(np.concatenate(rb_p)[order], ti.i32)
        self.rb_b = _nd(np.concatenate(rb_b)[order], ti.i32)
        self.rb_r0 = _nd(np.concatenate(r0s)[order].astype(np.float32), K.vec3)
        self.n_particles = int(len(order))
        self.proxies = any(f is not None for f in full)
        if self.proxies:
            # the contact candidates (reduce with what 1): the full sets' points of the bodies with
            # proxies (and the particles of the others), sorted by cell as the storage is, so that
            # the merge per bin finds its rows among the last few (module docs "contact")
            cell = np.floor(np.concatenate(ct_x) / self.dx).astype(np.int64)
            corder = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))  # row-major in (x, y, z), stable
            self.ct_b = _nd(np.concatenate(ct_b)[corder], ti.i32)
            self.ct_r0 = _nd(np.concatenate(ct_r0)[corder].astype(np.float32), K.vec3)
            self.ct_p = _nd(np.zeros(len(corder), np.int32), ti.i32)  # not read by the contacts pass
            self.n_points = int(len(corder))
        else:
            self.ct_p, self.ct_b, self.ct_r0 = self.rb_p, self.rb_b, self.rb_r0
            self.n_points = self.n_particles
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
        self.part = ti.ndarray(ti.f64, (T, self.n_bodies, 7))
        cap = CT_PER_PARTICLE * (max(self.n_particles, self.n_points) // T + 1) + 8
        self.ct = ti.ndarray(ti.f32, (T, cap, CT_WIDTH))
        self.acc = ti.ndarray(ti.f32, (T, cap, 4))
        self.ct_count = ti.ndarray(ti.i32, T)
        self._launch = None  # the contact solve's backend.Launcher (advance)
        self._launch_pre = None  # the same for the contact solve on the grid (advance with pre)
        if solve == "jacobi":  # advance_jacobi's scratch
            self.work = ti.ndarray(ti.f64, (self.n_bodies, _W_WIDTH))
            self.jac = ti.ndarray(ti.f64, (self.n_bodies, JACOBI_ITERS, 6))
            self.depth = ti.ndarray(ti.f64, (T, cap))
            self.win = ti.ndarray(ti.i32, (self.n_bodies, POSITION_ITERS))

    def advance(self, kr: SimpleNamespace, dt: float, gbody, pre: bool = False) -> None:
        """Solve the contacts and move the bodies (``kr``: :func:`build`'s kernels; ``gbody``: the
        solver's per-body grid fields).  ``pre``: the contact solve on the grid between the
        substep's two MPM launches (module docs "Coupling"), which solves the bodies' grid
        fields in gbody and moves nothing."""
        args = (self.part, self.ct, self.ct_count, self.acc, self.body_c, self.body_R, self.body_V, self.body_w,
                self.body_M, self.body_I0inv)
        kernel = kr.advance_jacobi if self.solve == "jacobi" else kr.advance
        name = "_launch_pre" if pre else "_launch"
        launch = getattr(self, name)
        if launch is None or launch.kernel is not kernel:
            launch = Launcher(kernel)  # backend.Launcher: no per-call argument processing
            setattr(self, name, launch)
        if self.solve == "jacobi":
            T, cap = self.ct.shape[0], self.ct.shape[1]
            launch(*args, self.work, self.jac, self.depth, self.win, gbody, float(dt), int(T * cap),
                   int(self.n_bodies), bool(pre))
        else:
            launch(*args, gbody, float(dt), bool(pre))

    def state(self) -> dict:
        """Body state as numpy: centre [B, 3] (m), R [B, 3, 3], V [B, 3] (m/s), omega [B, 3] (rad/s),
        mass [B] (kg), K [B, 3, 3] (the particles' F is R K: scatter)."""
        return {"c": self.body_c.to_numpy(), "R": self.body_R.to_numpy(), "V": self.body_V.to_numpy(),
                "omega": self.body_w.to_numpy(), "mass": self.mass.copy(), "K": self.body_K.to_numpy()}

    def fit_state(self, x: np.ndarray, v: np.ndarray, C: np.ndarray, F: np.ndarray, mass: np.ndarray,
                  full: list | None = None) -> None:
        """Body poses and motion that best explain a particle state (storage order, metres):
        centre of mass, rotation by the Kabsch fit of r0 onto x - c, and the momentum and
        angular momentum of the particles (APIC's affine part included, as in the reduction),
        and K = R^T polar(mean F) so that the particles keep their F's rotation.  A body with
        proxies is fitted to its full set's state, ``full[b]`` = (x, v, C, F) of its full set
        (rows as given to the constructor; metres)."""
        cs, Rs, Vs, ws, Ks = [], [], [], [], []
        rb_p = self.rb_p.to_numpy()
        rb_b = self.rb_b.to_numpy()
        r0_all = self.rb_r0.to_numpy().astype(np.float64)
        for b in range(self.n_bodies):
            if self.full_r0[b] is not None:
                if full is None or full[b] is None:
                    raise ValueError(f"rigid body {self.names[b]!r} has proxies: fit_state needs its full set's state")
                xb, vb, Cb, Fb = (np.asarray(a, np.float64) for a in full[b])
                m, r0 = self.full_mass[b], self.full_r0[b]
            else:
                sel = rb_b == b
                p = rb_p[sel]
                xb, vb, Cb, Fb = x[p], v[p], C[p], F[p]
                m, r0 = mass[p].astype(np.float64), r0_all[sel]
            M = m.sum()
            c = (m[:, None] * xb).sum(0) / M
            H = (m[:, None, None] * (r0[:, :, None] * (xb - c)[:, None, :])).sum(0)
            U, _, Vt = np.linalg.svd(H)
            Dm = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
            R = Vt.T @ Dm @ U.T
            r = xb - c
            Cp = Cb
            axial = np.stack([Cp[:, 2, 1] - Cp[:, 1, 2], Cp[:, 0, 2] - Cp[:, 2, 0], Cp[:, 1, 0] - Cp[:, 0, 1]], -1)
            Vb = (m[:, None] * vb).sum(0) / M
            Lb = (m[:, None] * np.cross(r, vb)).sum(0) + (m[:, None] * self.dx ** 2 / 4.0 * axial).sum(0)
            I = R @ self.I0[b] @ R.T
            cs.append(c)
            Rs.append(R)
            Vs.append(Vb)
            ws.append(np.linalg.solve(I, Lb))
            Uf, _, Vf = np.linalg.svd((m[:, None, None] * Fb).sum(0))
            RF = Uf @ np.diag([1.0, 1.0, np.sign(np.linalg.det(Uf @ Vf))]) @ Vf
            Ks.append(R.T @ RF)
        self.body_c.from_numpy(np.array(cs))
        self.body_K.from_numpy(np.array(Ks))
        self.body_R.from_numpy(np.array(Rs))
        self.body_V.from_numpy(np.array(Vs))
        self.body_w.from_numpy(np.array(ws))

    def full_motion(self, b: int, st: dict | None = None) -> tuple:
        """The full set of body ``b`` (proxies) on the body's rigid motion: x [n, 3] (m), v [n, 3]
        (m/s, the bodies' stored velocity, staggered as the particles'), C [3, 3] = [omega]x and
        F [3, 3] = R K, as :func:`build`'s scatter gives its particles (``st``: :meth:`state`)."""
        st = self.state() if st is None else st
        R, w = st["R"][b], st["omega"][b]
        r = self.full_r0[b] @ R.T
        Wx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        return st["c"][b] + r, st["V"][b] + np.cross(w, r), Wx, R @ st["K"][b]

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
