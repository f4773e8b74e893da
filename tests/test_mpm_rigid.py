"""Rigid instances (issue #15): momentum exchange against the analytic result, angular momentum
of a spinning free body, fixed bodies, rest on the ground, the time step, static geometry."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from physgs_steps.errors import ConfigError, InputError
from physgs_steps.mpm import Dynamics, Material, MPMSolver, StaticGeometry
from physgs_steps.mpm import colliders
from physgs_steps.mpm import rigid as rigid_mod
from physgs_steps.mpm.rest import RestPolicy
from physgs_steps.mpm.runner import run_frames
from physgs_steps.mpm.stability import Thresholds
from physgs_steps.mpm.timestep import TimeStepper

STONE = Material("fixed_corotated", "identity", E=2.0e7, nu=0.25, density=2600.0, name="stone", rigid=True)
JELLY = Material("fixed_corotated", "identity", E=5.0e4, nu=0.3, density=1000.0, name="jelly")


def box(lo, hi, s):
    axes = [np.arange(a + s / 2, b - 1e-9, s) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


@pytest.fixture(params=["serial", "jacobi"])
def solve(request, monkeypatch):
    """Run a test with each contact solve on the CPU: the serial Gauss-Seidel (the CPU's own)
    and the parallel Jacobi one that CUDA uses (rigid.py "Parallel contact solve")."""
    monkeypatch.setattr(rigid_mod, "CONTACT_SOLVE", request.param)
    return request.param


def momenta(st, mass, sel, c=None):
    """Linear and angular momentum (about c, default the centre of mass) of rows ``sel``
    (domain units; APIC's affine part included with dx^2/4)."""
    m = mass[sel]
    x, v = st["x"][sel].astype(np.float64), st["v"][sel].astype(np.float64)
    c = (m[:, None] * x).sum(0) / m.sum() if c is None else c
    return (m[:, None] * v).sum(0), (m[:, None] * np.cross(x - c, v)).sum(0)


def test_head_on_collision_is_perfectly_inelastic(solve):
    """Two free rigid blocks in zero gravity collide head-on: MPM grid contact is sticky, so
    they leave together at the common velocity (m1 v1 + m2 v2) / (m1 + m2); momentum is exact."""
    s = 1 / 64
    xa = box([0.30, 0.5 - 5 * s, 0.5 - 5 * s], [0.40, 0.5 + 5 * s, 0.5 + 5 * s], s)  # coaxial blocks: head-on
    xb = box([0.50, 0.5 - 3 * s, 0.5 - 3 * s], [0.56, 0.5 + 3 * s, 0.5 + 3 * s], s)
    x = np.r_[xa, xb]
    mat = np.r_[np.zeros(len(xa), int), np.ones(len(xb), int)]
    heavy = STONE.with_(name="a", density=2000.0)
    light = STONE.with_(name="b", density=3000.0)
    sol = MPMSolver([heavy, light], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    vel = np.where(mat[:, None] == 0, [1.2, 0.0, 0.0], [-0.4, 0.0, 0.0])
    sol.set_particles(x, np.full(len(x), s ** 3), mat, velocity=vel)
    m1, m2 = sol.rigid.mass
    v_common = (m1 * 1.2 - m2 * 0.4) / (m1 + m2)
    P0 = m1 * 1.2 - m2 * 0.4
    for _ in range(250):  # 0.125 s: they meet after ~0.06 s
        sol.substep(5e-4)
    V = sol.rigid.state()["V"]
    assert np.abs(sol.get_state()["x"][mat == 0, 0].max() - xa[:, 0].max()) > 0.05  # it moved
    assert V[0, 0] == pytest.approx(v_common, abs=0.02 * 1.2)
    assert V[1, 0] == pytest.approx(v_common, abs=0.02 * 1.2)
    assert m1 * V[0, 0] + m2 * V[1, 0] == pytest.approx(P0, rel=1e-4)
    assert np.abs(V[:, 1:]).max() < 1e-4 and np.abs(sol.rigid.state()["omega"]).max() < 1e-3


def test_spinning_free_body_keeps_its_angular_momentum_and_shape():
    """An asymmetric block spinning about a non-principal axis (zero gravity): it tumbles, its
    angular momentum (particles, with APIC's affine part) and its shape stay exact."""
    s = 1 / 64
    x = box([0.40, 0.44, 0.46], [0.60, 0.56, 0.54], s)  # 0.2 x 0.12 x 0.08
    sol = MPMSolver([STONE], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    w0 = np.array([2.0, 1.0, 4.0])
    W = np.array([[0, -w0[2], w0[1]], [w0[2], 0, -w0[0]], [-w0[1], w0[0], 0]])
    c0 = x.mean(0)
    sol.set_state(x, np.cross(w0, x - c0), np.broadcast_to(W, (len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    body = sol.rigid.state()
    assert np.allclose(body["omega"][0], w0, rtol=1e-5)
    c, R = body["c"][0], body["R"][0]
    I = R @ sol.rigid.I0[0] @ R.T
    L0 = I @ body["omega"][0]
    for _ in range(300):  # 0.3 s: about 70 degrees about the body's axes
        sol.substep(1e-3)
    body = sol.rigid.state()
    R = body["R"][0]
    L1 = (R @ sol.rigid.I0[0] @ R.T) @ body["omega"][0]
    assert np.linalg.norm(L1 - L0) < 1e-4 * np.linalg.norm(L0)
    assert np.linalg.norm(body["omega"][0] - w0) > 0.1  # it really tumbles (omega is not conserved)
    assert np.abs(body["c"][0] - c).max() < 1e-6  # no drift
    st = sol.get_state()
    xs = st["x"].astype(np.float64)
    d0 = np.linalg.norm(x[:50, None] - x[None, -50:], axis=-1)
    d1 = np.linalg.norm(xs[:50, None] - xs[None, -50:], axis=-1)
    assert np.abs(d1 - d0).max() < 1e-5
    assert np.abs(st["F"][0] @ st["F"][0].T - np.eye(3)).max() < 1e-5
    assert np.abs(sol.get_stress()).max() == 0.0
    # the particle state carries the body's angular momentum (about the centre, m in kg)
    mass = np.full(len(x), s ** 3 * STONE.density)
    _, Lp = momenta(st, mass, slice(None), c=body["c"][0])
    Lp += mass.sum() * (1 / 32) ** 2 / 4 * np.array([st["C"][0][2, 1] - st["C"][0][1, 2],
                                                     st["C"][0][0, 2] - st["C"][0][2, 0],
                                                     st["C"][0][1, 0] - st["C"][0][0, 1]])
    assert np.linalg.norm(Lp - L1) < 1e-3 * np.linalg.norm(L1)


def test_rigid_body_rests_on_the_ground_and_a_fixed_body_holds_a_soft_one(solve):
    """A free rigid block dropped on the ground comes to rest with its lowest particles on the
    plane (contact per body: it does not creep into it); a fixed rigid slab (static geometry,
    not simulated) holds a jelly block dropped on it and never moves."""
    s = 1 / 64
    h = 0.125
    xr = box([0.20, 0.40, h + 0.03], [0.36, 0.56, h + 0.11], s)          # free rigid, dropped 3 cm
    xf = box([0.50, 0.30, h], [0.80, 0.70, h + 0.06], s)                 # fixed slab on the ground
    xj = box([0.58, 0.42, h + 0.07], [0.72, 0.58, h + 0.15], s)          # jelly 1 cm above the slab
    x = np.r_[xr, xf, xj]
    mat = np.r_[np.zeros(len(xr), int), np.ones(len(xf), int), np.full(len(xj), 2)]
    slab = STONE.with_(name="slab", fixed=True, friction=0.5)
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}, "damping": 2.0})
    sol = MPMSolver([STONE, slab, JELLY], n_grid=32, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    assert sol.rigid.solve == solve
    assert sol.n_particles == len(xr) + len(xj) and sol.roles() == ["rigid", "fixed", "deformable"]
    assert sol.wave_speeds()[0] == 0.0 and sol.wave_speeds()[1] == 0.0
    dt = 0.4 * (1 / 32) / JELLY.wave_speed
    for _ in range(int(0.6 / dt)):
        sol.substep(dt)
    st = sol.get_state()
    assert np.array_equal(st["x"][mat == 1], xf.astype(np.float32))  # fixed: exactly where it was
    zr = st["x"][mat == 0, 2]
    assert abs(zr.min() - h) < 0.02 * s  # its lowest particles on the plane
    # at rest, with either solve (the parallel one kept a limit cycle, V_z to -0.013 m/s, while
    # contacts were found at positions G2P had already moved: test_resting_block_does_not_hop)
    assert np.abs(sol.rigid.state()["V"]).max() < 0.002
    # the slab's surface lies half a spacing above its top centres (colliders.py, level sets), the
    # jelly's face half a spacing below its lowest centres; contact starts where the faces meet
    surface = xf[:, 2].max() + s / 2
    face = st["x"][mat == 2, 2].min() - s / 2
    assert face > surface - 0.3 * s          # the jelly rests on the slab, not in it
    assert face < surface + 0.2 / 32         # and is held by it (fell the 1 cm gap; measured 0.08 cells)
    assert np.abs(st["v"][mat == 2]).max() < 0.05


@pytest.mark.parametrize("h", [0.25, 0.1])
def test_sliding_block_decelerates_at_mu_g(solve, h):
    """A flat rigid block sliding on a ground with Coulomb friction mu slows down at mu g once
    it has landed, with either contact solve, and does not start to spin: with the ground above
    the domain wall (0.25) and on it (0.1, the built-in scenes' ground and wall margin: the
    frictionless wall took the load and the block slid without friction)."""
    s = 1 / 64
    mu, v0 = 0.4, 0.5
    x = box([0.30, 0.40, h], [0.50, 0.60, h + 0.0625], s)
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": mu, "surface": "separate"}})
    sol = MPMSolver([STONE], n_grid=32, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int), velocity=np.tile([v0, 0.0, 0.0], (len(x), 1)))
    assert sol.rigid.solve == solve
    dt = 5e-4
    V = []
    for i in range(200):  # it lands (falls half a particle spacing) after ~0.04 s
        sol.substep(dt)
        if (i + 1) % 100 == 0:
            V.append(sol.rigid.state()["V"][0])
    decel = (V[0][0] - V[1][0]) / (100 * dt)
    assert decel == pytest.approx(mu * 9.8, rel=0.03)
    assert abs(V[1][1]) < 1e-3 and abs(V[1][2]) < 0.01
    assert np.abs(sol.rigid.state()["omega"]).max() < 0.05


def test_level_set_of_points_places_the_surface():
    """The signed distance built from a filled box of points has its zero s/2 beyond the
    outermost points (the solid's face) to within a fine voxel, on every axis."""
    s = 1 / 128
    pts = box([0.3, 0.35, 0.25], [0.6, 0.65, 0.4], s)
    geom = StaticGeometry(pts, spacing=s)
    G = 32
    phi = colliders.level_set(geom, G, 1.0)
    i = np.arange(G) / G
    # along z through the middle: the face at z = 0.4 (top) and 0.25 (bottom)
    col = phi[int(0.45 * G), int(0.5 * G)]
    inside = (i > 0.25) & (i < 0.4)
    assert np.all(col[inside] < 0) and np.all(col[(i < 0.24) | (i > 0.41)] > 0)
    exact = np.maximum(0.25 - i, i - 0.4)
    near = np.abs(exact) < 3.0 / G
    assert np.abs(col[near] - exact[near]).max() < 0.25 / G
    with pytest.raises(InputError, match="shape"):
        StaticGeometry(np.zeros((0, 3)))
    with pytest.raises(ConfigError, match="surface"):
        StaticGeometry(pts, surface="glue")


def test_rigid_flags_and_wall_margin_errors():
    with pytest.raises(ConfigError, match="fixed"):
        Material("fixed_corotated", "identity", E=1e5, nu=0.3, density=1000.0, fixed=True)
    with pytest.raises(ConfigError, match="wall_margin"):
        MPMSolver([JELLY], n_grid=12, backend="cpu")  # 1.5 cells = 0.125 > the default margin 0.1
    with pytest.raises(InputError, match="every instance is fixed"):
        sol = MPMSolver([STONE.with_(fixed=True)], n_grid=32, backend="cpu")
        sol.set_particles(box([0.4, 0.4, 0.4], [0.5, 0.5, 0.5], 1 / 64), np.full(216, 1 / 64 ** 3), np.zeros(216, int))


def test_rigid_ball_on_jelly_comes_to_rest_at_the_depth_its_weight_predicts():
    """The ball_jelly scene at a small scale: a free steel ball (R 6 cm, 7.3 kg) dropped onto a
    jelly slab (E 5e4 Pa, nu 0.3) on the ground comes to rest sunk in by Hertz' depth for its
    weight, (9 W^2 / (16 E*^2 R))^(1/3) = 25 mm (0.8 dx here), within 30%, and stays there.
    Before the grid coupling (rigid.py "Coupling") the jelly under it flowed into the ball's
    nodes and it kept sinking at about 1 cm/s (depth 1.6x Hertz at 1 s, still growing)."""
    G, Ls = 16, 0.5
    s = Ls / G / 2
    R, ground, plinth = 0.06, 0.06, 0.03
    lo = np.array([0.12, 0.12, ground + plinth])
    xj = box(lo, lo + [0.26, 0.26, 0.1], s)
    xp = box([0.1, 0.1, ground], [0.4, 0.4, ground + plinth], s)  # a fixed stone plinth under the slab
    c = np.array([0.25, 0.25, lo[2] + 0.1 + R + s / 2])
    cube = box(c - R, c + R, s)
    xb = cube[np.linalg.norm(cube - c, axis=1) <= R]
    x = np.r_[xj, xb, xp] / Ls
    mat = np.r_[np.zeros(len(xj), int), np.ones(len(xb), int), np.full(len(xp), 2)]
    ball = STONE.with_(name="ball", density=7850.0)
    jelly = JELLY.with_(density=1050.0)
    dyn = Dynamics.from_config({"ground": {"height": ground / Ls, "friction": 0.5, "surface": "separate"},
                                "damping": 10.0})
    # (the same kernels as the test above: one compilation for both)
    sol = MPMSolver([jelly, ball, STONE.with_(name="plinth", fixed=True)], n_grid=G, domain_size=Ls, dynamics=dyn,
                    backend="cpu")
    sol.set_particles(x, np.full(len(x), (s / Ls) ** 3), mat)
    W = sol.rigid.mass[0] * 9.8
    Es = JELLY.E / (1 - JELLY.nu ** 2)
    hertz = (9 * W * W / (16 * Es * Es * R)) ** (1 / 3)
    far = (np.abs(xj[:, :2] - 0.25).max(1) > 0.09) & (xj[:, 2] > xj[:, 2].max() - s / 2)

    def depth():
        z = sol.get_state()["x"][:, 2].astype(np.float64) * Ls
        return (z[: len(xj)][far].mean() + s / 2) - (z[mat == 1].min() - s / 2)

    dt = 0.4 * (Ls / G) / JELLY.wave_speed
    out = []
    for t_end in (0.7, 1.0):
        while sol.time < t_end - 1e-9:
            sol.substep(dt)
        out.append(depth())
    print(f"ball on jelly: depth {1e3 * out[0]:.1f} mm at 0.7 s, {1e3 * out[1]:.1f} mm at 1 s, Hertz {1e3 * hertz:.1f} mm")
    assert out[1] == pytest.approx(hertz, rel=0.3), (out, hertz)
    assert abs(out[1] - out[0]) < 0.05 * hertz, out  # at rest: under 1.3 mm in 0.3 s


def test_only_fixed_rigid_instances_give_the_kernel_full_size_rigid_grids():
    """A scene whose rigid instances are all fixed (static geometry) still compiles the kernel's
    rigid grid passes (the kernel key is per material), so the rigid grids must span the grid:
    with 1-element grids the passes wrote out of bounds (a segfault once the sums were laid out
    per column)."""
    s = 1 / 64
    h = 0.125
    xf = box([0.30, 0.30, h], [0.70, 0.70, h + 0.06], s)          # fixed slab on the ground
    xj = box([0.42, 0.42, h + 0.065], [0.58, 0.58, h + 0.15], s)  # jelly resting on it
    x = np.r_[xf, xj]
    mat = np.r_[np.zeros(len(xf), int), np.ones(len(xj), int)]
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver([STONE.with_(name="slab", fixed=True, friction=0.5), JELLY], n_grid=32, dynamics=dyn,
                    backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    assert sol.rigid is None and sol.roles() == ["fixed", "deformable"]
    assert sol.grid_r.shape[1:] == (32, 32, 32)
    for _ in range(40):
        sol.substep(2e-4)
    assert np.isfinite(sol.get_state()["x"]).all()


def test_resting_block_does_not_hop(solve):
    """A rigid block resting on the ground stays still substep after substep: its contacts are
    found where the body is at the start of the substep (the pose the solve starts from), not
    where G2P has already moved its particles. Before, every contact saw a phantom penetration
    of one substep of fall (g dt^2), the solve lifted the block out of it, and the block hopped:
    V_z alternated between 0 and +g dt (0.0049 m/s) with twice its weight on every other
    substep, and a flat-bottomed body on a few contact points chattered between them."""
    s = 1 / 64
    h = 0.25
    x = box([0.40, 0.42, h], [0.56, 0.58, h + 0.0625], s)
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver([STONE], n_grid=32, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    dt = 5e-4
    for _ in range(200):  # lands (half a particle spacing) and settles
        sol.substep(dt)
    Vz, w, low = [], [], []
    for _ in range(40):
        sol.substep(dt)
        Vz.append(sol.rigid.state()["V"][0][2])
        w.append(np.abs(sol.rigid.state()["omega"][0]).max())
        low.append(sol.get_state()["x"][:, 2].min())
    # before: serial |V_z| up to 1.05 g dt; Jacobi 1.1 g dt, omega 0.05 rad/s, rows 14..28
    # (the lowest layer bobbing at the edge of the contact band), 3-6 um above the plane
    tol = 0.05 if solve == "serial" else 0.1  # the Jacobi solve's 12 iterations leave a residual
    assert np.abs(Vz).max() < tol * 9.8 * dt
    assert max(w) < 0.01
    assert np.abs(np.array(low) - h).max() < 1e-6  # on the plane, not above it


def test_fast_launch_gives_bitwise_the_plain_calls(solve, monkeypatch):
    """The substep's kernels launched through backend.Launcher (no per-call argument processing
    in Taichi's Python layer) give bitwise the state of plain kernel calls, also across
    set_materials (new material arrays: the launcher goes through Taichi again and re-plans)."""
    s = 1 / 64
    h = 0.1
    xr = box([0.30, 0.40, h + 0.01], [0.42, 0.52, h + 0.09], s)  # rigid block dropped 1 cm
    xj = box([0.46, 0.40, h], [0.60, 0.54, h + 0.08], s)         # jelly beside it
    x = np.r_[xr, xj]
    mat = np.r_[np.zeros(len(xr), int), np.ones(len(xj), int)]
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}})
    runs = []
    for fast in ("0", "1"):
        monkeypatch.setenv("PHYSGS_TI_FAST_LAUNCH", fast)
        sol = MPMSolver([STONE, JELLY], n_grid=32, dynamics=dyn, backend="cpu")
        sol.set_particles(x, np.full(len(x), s ** 3), mat)
        for i in range(120):
            sol.substep(4e-4)
            if i == 60:
                sol.set_materials([STONE, JELLY.with_(E=8.0e4)])
        for lau in (sol._launch_substep, sol._launch_reduce, sol._launch_scatter, sol.rigid._launch):
            assert (lau._plan is not None) == (fast == "1")
        runs.append((sol.get_state(), sol.rigid.state()))
    (st0, rb0), (st1, rb1) = runs
    for k in ("x", "v", "C", "F"):
        assert np.array_equal(st0[k], st1[k]), k
    for k in ("c", "R", "V", "omega"):
        assert np.array_equal(rb0[k], rb1[k]), k
    assert np.abs(st1["v"]).max() > 0.05  # something moved


def test_soft_block_rests_on_a_free_rigid_slab_and_the_rest_hold_takes_it(solve):
    """A jelly block dropped onto a free rigid slab lying on the ground settles on it and stays
    (like a jelly on the ground or on a fixed slab), every particle falls below the rest speed
    and the frame loop holds the scene.  Before the contact solve ran on the grid (rigid.py
    "Coupling"), the nodes the jelly shares with the slab moved with the slab's velocity
    *before* its ground contact (g dt and the jelly's weight pushing down) while the slab itself
    was stopped: here the jelly crept into the slab at 0.04 m/s (the gap closed 0.13 dx every
    0.2 s, the jelly's lowest particles passed the slab's top ones at 1.4 s and went on) and
    never came to rest."""
    s = 1 / 32
    h = 0.125
    xs = box([0.25, 0.25, h], [0.75, 0.75, h + 0.125], s)          # free rigid slab on the ground
    top = h + 0.125
    xj = box([0.375, 0.375, top + 0.02], [0.625, 0.625, top + 0.02 + 0.1875], s)  # jelly 2 cm above it
    x = np.r_[xs, xj]
    mat = np.r_[np.zeros(len(xs), int), np.ones(len(xj), int)]
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}, "damping": 8.0})
    sol = MPMSolver([STONE.with_(name="slab", friction=0.5), JELLY], n_grid=16, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    assert sol.roles() == ["rigid", "deformable"]
    jelly = mat == 1
    gap, v_soft = [], []

    def frame(k, t, dt):
        st = sol.get_state()
        gap.append(st["x"][jelly, 2].min() - st["x"][~jelly, 2].max())
        v_soft.append(np.linalg.norm(sol.v.to_numpy(), axis=1).max())  # what the rest check reads (stats)

    policy = RestPolicy.from_config({"speed": 0.01, "duration": 0.3}, dyn)
    res = run_frames(sol, 48, TimeStepper(fps=30.0, max_substeps=40), Thresholds(), frame, logging.getLogger("t"),
                     rest=policy, on_hold=lambda k, t: None)
    print(f"gap/dx {np.round(np.array(gap[::6]) * 16, 3)}, v_max {np.round(v_soft[::6], 4)}, rest {res.rest}")
    assert res.stable
    body = sol.rigid.state()
    assert np.abs(body["V"]).max() < 1e-3 and np.abs(body["omega"]).max() < 1e-2  # the slab stays put
    assert min(gap) > 0.0  # the jelly never gets into the slab (before: 0.08 dx into it at 1.6 s)
    late = np.array(gap[24:])  # from 0.8 s on: settled, no creep
    assert late.max() - late.min() < 0.02 * (1 / 16), late * 16
    assert res.rest and res.held_frames > 0 and res.rest[0]["time"] < 1.3, (res.rest, v_soft[-10:])


def test_soft_block_rests_on_a_free_rigid_bowl(solve):
    """A jelly block on a free rigid body with a curved underside (a half ellipsoid, flat side up,
    touching the ground over a small patch) stays on it, with either contact solve.
    Many of the body's contact rows lie in the contact band clear of the ground; when the body
    was split over every row, the touching ones got a small share of it and the solve on the
    grid left the field part of its downward velocity (duck_stone on the GPU: -0.023 m/s after
    every solve): here the gap closed 0.1 dx from 0.4 to 1.2 s with every row counted, 0.03 dx
    with the rows in touch or approaching (a residual of the Jacobi solve's convergence), not at
    all with the serial solve (rigid.py "Parallel contact solve")."""
    s = 1 / 32
    h = 0.125
    a, c = 0.25, 0.125
    top = h + c
    xs = box([0.5 - a, 0.5 - a, h], [0.5 + a, 0.5 + a, top], s)
    xs = xs[((xs[:, 0] - 0.5) ** 2 + (xs[:, 1] - 0.5) ** 2) / a ** 2 + (xs[:, 2] - top) ** 2 / c ** 2 <= 1.0]
    xj = box([0.4, 0.4, top + 0.02], [0.6, 0.6, top + 0.02 + 0.1875], s)
    x = np.r_[xs, xj]
    mat = np.r_[np.zeros(len(xs), int), np.ones(len(xj), int)]
    dyn = Dynamics.from_config({"ground": {"height": float(xs[:, 2].min()) - s / 2, "friction": 0.5,
                                           "surface": "separate"}, "damping": 8.0})
    sol = MPMSolver([STONE.with_(name="bowl", friction=0.5), JELLY], n_grid=16, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    assert sol.rigid.solve == solve
    jelly = mat == 1
    gap = []

    def frame(k, t, dt):
        st = sol.get_state()
        gap.append(st["x"][jelly, 2].min() - st["x"][~jelly, 2].max())

    res = run_frames(sol, 36, TimeStepper(fps=30.0, max_substeps=40), Thresholds(), frame, logging.getLogger("t"))
    print(f"gap/dx {np.round(np.array(gap[::3]) * 16, 3)}")
    assert res.stable
    late = np.array(gap[12:]) * 16  # from 0.4 s on: landed
    assert late.min() > 0.0 and late.max() - late.min() < 0.05, late


@pytest.mark.xfail(strict=True, reason=(
    "rest15 soft-body contact (rigid.py 'Coupling'): on a layer 1.6 cells thick the body's contact and "
    "the ground's act on the same foam nodes; the block is stopped without compressing the foam "
    "(impact 1.24 m/s, rebound -0.02 m/s, foam top unmoved; it settles 0.2 cells above the foam and "
    "creeps down at 0.016 m/s): no bounce at this resolution. Open: see the rest15 report."))
def test_rigid_block_on_a_thin_layer_on_the_ground_does_not_bounce_back_faster():
    """A free rigid block dropped on a thin elastic foam layer (1.6 cells) lying on the ground,
    no damping: the rebound is slower than the impact, as on any undamped elastic support
    (MPM's transfers only take energy out).  The ground's ghost nodes under the layer took their
    velocity from the mirror point two cells up, across the layer in the block's field, and,
    once the block left, from material leaving faster than the layer at the ground: they moved
    out of the ground into the layer while it still pressed on them, the ground did work on it,
    and the block came back at 1.17 times its impact speed (basket_mat: 1.19, the first landing
    +0.66 J).  Now the mirror leaves out the nodes a body covers and a ghost node leaves no
    faster than its own velocity (kernels.py collider_funcs.ghost): 0.86."""
    G = 16
    dxg = 1.0 / G
    s = dxg / 2
    h = 0.125
    t_mat = 1.6 * dxg
    foam = Material("neo_hookean", "identity", E=3.0e5, nu=0.2, density=60.0, name="foam")
    wood = Material("fixed_corotated", "identity", E=1e7, nu=0.3, density=600.0, name="block", rigid=True)
    xm = box([0.2, 0.2, h], [0.8, 0.8, h + t_mat], s)
    xb = box([0.375, 0.375, h + t_mat + 0.1], [0.625, 0.625, h + t_mat + 0.1 + 2 * dxg], s)
    x = np.r_[xm, xb]
    mat = np.r_[np.zeros(len(xm), int), np.ones(len(xb), int)]
    # the layer's lowest particles on the ground (within TOUCH: it engages the ground's nodes)
    dyn = Dynamics.from_config({"ground": {"height": h + s / 2 - 0.03 * dxg, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver([foam, wood], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    dt = 0.4 * dxg / foam.wave_speed
    vz = []
    for _ in range(int(0.2 / dt)):  # lands at 0.1 s, leaves the layer at about 0.13 s
        sol.substep(dt)
        vz.append(sol.rigid.state()["V"][0, 2])
    vz = np.array(vz)
    k = int(np.argmin(vz))
    impact, rebound = -vz[k], vz[k:].max()
    print(f"impact {impact:.3f} m/s, rebound {rebound:.3f} m/s")
    assert impact > 0.9  # it fell the 10 cm freely (0.94 m/s at the layer)
    assert rebound > 0.3 * impact  # it bounced (an elastic layer)
    assert rebound < 0.95 * impact, (impact, rebound)


def test_undamped_soft_block_rests_on_a_free_rigid_block_as_on_a_fixed_one():
    """An undamped jelly block dropped 3 cm onto a free rigid block lying on the ground comes to
    rest on its surface, as on the same block fixed (benchmarks/bench_soft_on_free_body.py).
    The soft material meets the body as it meets a fixed level-set collider (rigid.py
    "Coupling": the body's level set, the ground's node rule where it touches, the reaction on
    the body).  Before, the nodes the body covered (up to half a cell outside its surface) took
    the soft material's velocity into the body's field, gluing it there: the block rested on
    them a cell above the body's particles (layer gap 0.97 cells against 0.34 on the fixed
    block) and came to rest only at 1.47 s (fixed: 0.53 s); duck_stone's duck rocked on its
    stone to the end of the clip (kinetic energy 0.003-0.035 J at 3-5 s)."""
    G = 16
    s = 1 / (2 * G)
    h = 0.125
    top = h + 0.125
    xs = box([0.25, 0.25, h], [0.75, 0.75, top], s)
    xj = box([0.375, 0.375, top + 0.03], [0.625, 0.625, top + 0.03 + 0.1875], s)
    soft = Material("fixed_corotated", "identity", E=1e5, nu=0.4, density=1100.0, name="soft")
    x = np.r_[xs, xj]
    mat = np.r_[np.zeros(len(xs), int), np.ones(len(xj), int)]
    dyn = Dynamics.from_config({"ground": {"height": h, "friction": 0.5, "surface": "separate"}})
    sol = MPMSolver([STONE.with_(name="block", friction=0.5), soft], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), mat)
    js = mat == 1
    dt = 1 / 30 / int(np.ceil(1 / 30 / (0.4 * (1 / G) / soft.wave_speed)))
    vmax, gap = [], []
    while sol.time < 1.2 - 1e-9:
        for _ in range(int(round(1 / 30 / dt))):
            sol.substep(dt)
        st = sol.get_state()
        v = st["v"][js].astype(np.float64) + [0.0, 0.0, 9.8 * dt / 2]  # (stored staggered by -g dt / 2)
        vmax.append(np.linalg.norm(v, axis=1).max())
        gap.append((st["x"][js, 2].min() - st["x"][~js, 2].max()) * G)
    print(f"v_max {np.round(vmax[::3], 4)}, gap/cells {np.round(gap[::3], 3)}")
    assert np.abs(sol.rigid.state()["V"]).max() < 1e-3  # the block stays put
    assert max(vmax[-9:]) < 0.01, vmax  # at rest (sim.rest.speed) from 0.9 s on (before: 0.04 m/s at 1.0 s)
    # the two surfaces (half a spacing, 0.25 cells, beyond each particle layer) touch: the layers
    # 0.5 cells apart, within the fixed block's 0.34 and the glued 0.97
    assert 0.25 < np.mean(gap[-9:]) < 0.6, gap
