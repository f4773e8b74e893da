"""Free rigid bodies simulated with proxy particles (sim.rigid_particles_per_cell, rigid.py
"Proxy particles"): the body keeps its full set's mass and inertia, every output row follows
the body's rigid motion, contacts and momentum exchange are those of the full set."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from physgs_steps import simulate
from physgs_steps.errors import ConfigError
from physgs_steps.mpm import Dynamics, MPMSolver
from physgs_steps.mpm import rigid as rigid_mod

from test_mpm_rigid import JELLY, STONE, box, solve  # noqa: F401  (solve: the contact-solve fixture)

S = 1 / 64  # particle spacing: 8 particles per cell at grid 32
H = 0.125   # ground height (domain units)


def skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def rot_angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


def _scene():
    """A free stone block on the ground (dropped 1 cm) and a jelly block dropped onto it."""
    xr = box([0.30, 0.36, H + 0.01], [0.50, 0.58, H + 0.11], S)
    xj = box([0.34, 0.42, H + 0.13], [0.46, 0.54, H + 0.21], S)
    x = np.r_[xr, xj]
    mat = np.r_[np.zeros(len(xr), int), np.ones(len(xj), int)]
    return x, mat, len(xr)


def _solver(ppc, x, mat, damping=2.0):
    dyn = Dynamics.from_config({"ground": {"height": H, "friction": 0.5, "surface": "separate"}, "damping": damping})
    sol = MPMSolver([STONE, JELLY], n_grid=32, dynamics=dyn, backend="cpu", rigid_particles_per_cell=ppc)
    sol.set_particles(x, np.full(len(x), S ** 3), mat)
    return sol


def test_proxies_keep_the_full_sets_mass_and_inertia_and_every_row_follows_the_body():
    x, mat, nr = _scene()
    sol = _solver(1, x, mat)
    n_proxy = sol.proxy_count(0)
    assert n_proxy is not None and n_proxy <= nr / 4  # 8 per cell -> about 1 per cell (cut cells at the faces)
    assert sol.proxy_count(1) is None and sol.n_particles == n_proxy + (len(x) - nr)
    L, dx = sol.L, sol.dx
    mass = np.full(nr, np.float32(S ** 3 * STONE.density)).astype(np.float64)
    c_full, _r0, I0_full, M_full = rigid_mod.body_setup(x[:nr] * L, mass, dx)
    assert sol.rigid.mass[0] == pytest.approx(M_full, rel=1e-6)
    assert np.abs(sol.rigid.I0[0] - I0_full).max() < 1e-6 * np.abs(I0_full).max()
    assert np.abs(sol.rigid.state()["c"][0] - c_full).max() < 1e-9
    assert 1.0 < sol.rigid.stretch[0] < rigid_mod.PROXY_MAX_STRETCH
    # a spin and a push
    w0, V0 = np.array([0.0, 3.0, 6.0]), np.array([0.2, 0.0, -0.1])
    c0 = x[:nr].mean(0)
    v = np.zeros_like(x)
    v[:nr] = V0 + np.cross(w0, x[:nr] - c0)
    C = np.zeros((len(x), 3, 3))
    C[:nr] = skew(w0)
    sol.set_state(x, v, C, np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    body = sol.rigid.state()
    assert np.allclose(body["omega"][0], w0, rtol=1e-5) and np.allclose(body["V"][0], V0 * L, atol=1e-6)
    dt = 4e-4
    for _ in range(50):  # 0.02 s: still in the air
        sol.substep(dt)
    st, body = sol.get_state(), sol.rigid.state()
    assert st["x"].shape == (len(x), 3)
    c, R, V, w = body["c"][0] / L, body["R"][0], body["V"][0] / L, body["omega"][0]
    assert rot_angle(R) > 0.05  # it turned
    r = (x[:nr] - c0) @ R.T
    assert np.abs(st["x"][:nr] - (c + r)).max() < 2e-6
    v_frame = V + np.cross(w, r) + 0.5 * dt * sol.bound.gravity / L  # get_state: at the frame time
    assert np.abs(st["v"][:nr] - v_frame).max() < 1e-5 * max(1.0, np.abs(v_frame).max())
    assert np.abs(st["F"][:nr] - R).max() < 1e-6
    assert np.abs(st["C"][:nr] - skew(w)).max() < 1e-5 * max(1.0, np.abs(w).max())
    assert np.abs(sol.get_stress()[:nr]).max() == 0.0 and np.abs(st["ep"][:nr]).max() == 0.0
    # final.h5's rows: the same positions and F
    gx, gF = sol.gather_rows(np.arange(len(x)))
    assert np.abs(gx - st["x"]).max() < 1e-6 and np.abs(gF - st["F"]).max() < 1e-6
    # the body's rows stay a rigid body, the jelly's are simulated
    d0 = np.linalg.norm(x[:40, None] - x[None, nr - 40:nr], axis=-1)
    d1 = np.linalg.norm(st["x"][:40, None].astype(np.float64) - st["x"][None, nr - 40:nr], axis=-1)
    assert np.abs(d1 - d0).max() < 1e-5
    # the stats see the body's full set (its fastest rows, at the corners, are not proxies)
    sp = np.linalg.norm((V + np.cross(w, r)) * L, axis=1).max()
    assert sol.stats()["speed_max"][0] == pytest.approx(sp, rel=1e-5)
    # set_state(get_state()) and a backup continue the same trajectory
    sol.save_backup()
    for _ in range(20):
        sol.substep(dt)
    a = sol.get_state()["x"]
    sol.restore_backup()
    for _ in range(20):
        sol.substep(dt)
    assert np.abs(sol.get_state()["x"] - a).max() < 1e-6
    sol.restore_backup()
    back = sol.get_state()
    sol.set_state(back["x"], back["v"], back["C"], back["F"])
    assert np.abs(sol.get_state()["x"][:nr] - back["x"][:nr]).max() < 1e-5
    assert np.abs(sol.rigid.state()["omega"][0] - body["omega"][0]).max() < 1e-3 * np.abs(body["omega"][0]).max()


def test_proxies_follow_the_full_sets_trajectory_and_rest_height(solve):
    """The block lands, the jelly lands on it and both come to rest: with proxies the block's
    centre and rotation, its rest height on the ground and the jelly's final state are those of
    the full set, and the jelly does not sink into the block more."""
    x, mat, nr = _scene()
    out = {}
    for ppc in (None, 1):
        sol = _solver(ppc, x, mat)
        assert sol.rigid.solve == solve
        dt = 0.4 * sol.dx / JELLY.wave_speed
        traj = []
        for k in range(60):
            while sol.time < (k + 1) * 0.01 - 1e-9:
                sol.substep(dt)
            traj.append(sol.rigid.state()["c"][0].copy())
        st, body = sol.get_state(), sol.rigid.state()
        gap = (st["x"][nr:, 2].min() - st["x"][:nr, 2].max()) * 32  # cells between the jelly and the block's top
        out[ppc] = (np.array(traj) / sol.L, body["R"][0], st, gap, sol.n_particles)
    (tf, Rf, sf, gf, nf), (tp, Rp, sp, gp, npx) = out[None], out[1]
    dx = 1 / 32
    print(f"particles {nf} -> {npx}; centre max diff {np.abs(tp - tf).max() / dx:.3f} dx; rotation diff "
          f"{rot_angle(Rp @ Rf.T):.2e} rad; gap {gf:.3f} / {gp:.3f} cells; jelly mean diff "
          f"{np.abs(sp['x'][nr:].mean(0) - sf['x'][nr:].mean(0)).max() / dx:.3f} dx")
    assert npx < 0.5 * nf
    assert np.abs(tp - tf).max() < 0.05 * dx
    assert rot_angle(Rp @ Rf.T) < 5e-3
    assert abs(sp["x"][:nr, 2].min() - sf["x"][:nr, 2].min()) < 0.02 * dx  # the same rest height
    assert abs(sp["x"][:nr, 2].min() - H) < 0.04 * S  # lowest particles on the plane
    assert gp > gf - 0.05  # the jelly does not sink into the block more
    assert np.abs(sp["x"][nr:].mean(0) - sf["x"][nr:].mean(0)).max() < 0.05 * dx
    assert np.abs(sp["x"][nr:] - sf["x"][nr:]).max() < 0.2 * dx


def test_head_on_collision_with_proxies_matches_the_analytic_exchange(solve):
    """Two free rigid blocks with proxies collide head-on in zero gravity: they leave at the
    common velocity (m1 v1 + m2 v2) / (m1 + m2) with the full sets' masses, momentum exact."""
    xa = box([0.30, 0.5 - 5 * S, 0.5 - 5 * S], [0.40, 0.5 + 5 * S, 0.5 + 5 * S], S)
    xb = box([0.50, 0.5 - 3 * S, 0.5 - 3 * S], [0.56, 0.5 + 3 * S, 0.5 + 3 * S], S)
    x = np.r_[xa, xb]
    mat = np.r_[np.zeros(len(xa), int), np.ones(len(xb), int)]
    heavy, light = STONE.with_(name="a", density=2000.0), STONE.with_(name="b", density=3000.0)
    sol = MPMSolver([heavy, light], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu",
                    rigid_particles_per_cell=1)
    vel = np.where(mat[:, None] == 0, [1.2, 0.0, 0.0], [-0.4, 0.0, 0.0])
    sol.set_particles(x, np.full(len(x), S ** 3), mat, velocity=vel)
    assert sol.proxy_count(0) < len(xa) / 4 and sol.proxy_count(1) < len(xb) / 4
    m1 = len(xa) * S ** 3 * 2000.0
    m2 = len(xb) * S ** 3 * 3000.0
    assert sol.rigid.mass == pytest.approx([m1, m2], rel=1e-6)
    v_common = (m1 * 1.2 - m2 * 0.4) / (m1 + m2)
    for _ in range(250):
        sol.substep(5e-4)
    V = sol.rigid.state()["V"]
    st = sol.get_state()
    assert np.abs(st["x"][mat == 0, 0].max() - xa[:, 0].max()) > 0.05
    assert V[0, 0] == pytest.approx(v_common, abs=0.02 * 1.2)
    assert V[1, 0] == pytest.approx(v_common, abs=0.02 * 1.2)
    assert m1 * V[0, 0] + m2 * V[1, 0] == pytest.approx(m1 * 1.2 - m2 * 0.4, rel=1e-4)
    # the output rows carry the bodies' motion: their momentum is the bodies'
    P_rows = (np.where(mat == 0, 2000.0, 3000.0) * S ** 3 * st["v"][:, 0]).sum()
    assert P_rows == pytest.approx(m1 * 1.2 - m2 * 0.4, rel=1e-4)


def test_build_solver_uses_proxies_by_default_but_not_in_the_no_rigid_ablation():
    x, mat, nr = _scene()
    parts = {"x": x.astype(np.float32), "label": mat.astype(np.int32), "vol": np.full(len(x), S ** 3, np.float32),
             "filled": np.zeros(len(x), bool), "driver": np.ones(len(x), bool), "static_x": np.zeros((0, 3))}
    sim = {"n_grid": 32, "domain_size": 1.0, "backend": "cpu"}
    cfg = {"sim": sim, "scene": {"dynamics": {"ground": {"height": H}}}}
    log = logging.getLogger("test.proxies")
    sol = simulate.build_solver(parts, [STONE, JELLY], [0, 1], cfg, log)
    assert sol.rigid_particles_per_cell == simulate.RIGID_PARTICLES_PER_CELL
    assert sol.proxy_count(0) is not None and sol.n_particles < len(x) - nr + nr / 4
    full = simulate.build_solver(parts, [STONE, JELLY], [0, 1], {**cfg, "sim": {**sim, "rigid_particles_per_cell": None}},
                                 log)
    assert full.proxy_count(0) is None and full.n_particles == len(x)
    ablation = simulate.build_solver(parts, [STONE, JELLY], [0, 1], {**cfg, "sim": {**sim, "rigid_bodies": False}}, log)
    assert ablation.rigid is None and ablation.n_particles == len(x) and ablation.roles() == ["deformable"] * 2
    with pytest.raises(ConfigError, match="rigid_particles_per_cell"):
        MPMSolver([STONE], n_grid=32, backend="cpu", rigid_particles_per_cell=0)


def test_a_body_too_small_for_proxies_keeps_every_particle():
    """A flat body one proxy thick cannot carry its inertia with proxies: it keeps its full set."""
    xr = box([0.40, 0.40, 0.40], [0.60, 0.60, 0.40 + 2 * S], S)  # two layers of particles: one cell thick
    sol = MPMSolver([STONE], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu",
                    rigid_particles_per_cell=1)
    sol.set_particles(xr, np.full(len(xr), S ** 3), np.zeros(len(xr), int))
    assert sol.proxy_count(0) is None and sol.n_particles == len(xr) and not sol.rigid.proxies
