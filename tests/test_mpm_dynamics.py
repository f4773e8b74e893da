"""Scene dynamics: ground collider, fixed cuboid, impulse, wind, enforced translation and
rotation, initial velocities, and the config errors."""
from __future__ import annotations

import numpy as np
import pytest

from physgs_steps.errors import ConfigError
from physgs_steps.mpm import Dynamics, Material, MPMSolver

NAMES = ["faller", "pinned", "kicked", "pulled", "spun", "blown"]
CENTRES = {
    "faller": [0.25, 0.25, 0.25],
    "pinned": [0.5, 0.25, 0.55],
    "kicked": [0.25, 0.6, 0.55],
    "pulled": [0.5, 0.6, 0.55],
    "spun": [0.75, 0.3, 0.55],
    "blown": [0.75, 0.7, 0.35],
}
HALF = 0.04
DYNAMICS = {
    "gravity": [0.0, 0.0, 0.0],
    "ground": {"height": 0.1, "friction": 0.5, "surface": "separate"},
    "initial_velocity": [
        {"instance": "faller", "velocity": [0.0, 0.0, -1.5]},
        {"instance": "pinned", "velocity": [1.0, 0.0, 0.0]},
    ],
    "boundary_conditions": [
        {"type": "bounding_box"},
        {"type": "cuboid", "point": CENTRES["pinned"], "size": [0.06, 0.06, 0.06], "velocity": [0, 0, 0]},
        {"type": "particle_impulse", "instance": "kicked", "delta_v": [0.0, 0.0, 0.5], "duration": 0.02},
        {"type": "enforce_particle_translation", "instance": "pulled", "bbox_min": [0, 0.5, 0], "bbox_max": [1, 1, 1],
         "velocity": [0.0, 0.3, 0.0]},
        {"type": "enforce_particle_velocity_rotation", "instance": "spun", "point": CENTRES["spun"],
         "normal": [0, 0, 1], "half_height_and_radius": [0.1, 0.1], "rotation_scale": 2.0, "translation_scale": 0.0},
        {"type": "wind", "instance": "blown", "mean": [0.0, 0.0, 2.0], "amplitude": [0.0, 0.0, 0.0], "frequency": 1.0},
    ],
}


def _blocks():
    xs, mats = [], []
    for k, n in enumerate(NAMES):
        c = np.asarray(CENTRES[n])
        axes = [np.arange(a - HALF + 0.005, a + HALF, 0.01) for a in c]
        x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        xs.append(x)
        mats.append(np.full(len(x), k))
    x = np.concatenate(xs)
    return x, np.full(len(x), 1e-6), np.concatenate(mats)


@pytest.fixture(scope="module")
def run():
    x, vol, mat = _blocks()
    mats = [Material("fixed_corotated", "identity", E=2e5, nu=0.3, density=1000.0, name=n) for n in NAMES]
    s = MPMSolver(mats, n_grid=32, dynamics=Dynamics.from_config(DYNAMICS, "test"), backend="cpu")
    s.set_particles(x, vol, mat)
    v0 = s.get_state()["v"]
    dt, n = 1e-3, 300
    for _ in range(n):
        s.substep(dt)
    return x, mat, v0, s.get_state(), n * dt, s


def test_initial_velocities(run):
    x, mat, v0, _, _, _ = run
    assert np.allclose(v0[mat == 0], [0.0, 0.0, -1.5])
    assert np.allclose(v0[mat == 1], [1.0, 0.0, 0.0])
    assert np.allclose(v0[mat > 1], 0.0)


def test_ground_reflects_a_falling_block(run):
    x, mat, _, st, _, _ = run
    # thrown down at 1.5 m/s without gravity: it reaches the plane at z = 0.1 after ~0.07 s,
    # bounces (an elastic block) and leaves upwards; nothing passes through the plane
    assert np.mean(st["v"][mat == 0, 2]) > 0.5
    assert st["x"][mat == 0, 2].min() > 0.1


def test_fixed_cuboid_holds_its_contents(run):
    x, mat, _, st, _, _ = run
    assert np.abs(st["x"][mat == 1] - x[mat == 1]).max() < 0.01


def test_impulse_gives_its_velocity_change(run):
    _, mat, _, st, _, _ = run
    assert np.mean(st["v"][mat == 2, 2]) == pytest.approx(0.5, abs=0.02)


def test_enforced_translation_moves_the_selected_particles(run):
    x, mat, _, st, t, _ = run
    sel = (mat == 3) & (x[:, 1] >= x[mat == 3, 1].min() + 0.5 * np.ptp(x[mat == 3, 1]))
    dy = st["x"][sel, 1] - x[sel, 1]
    assert np.median(dy) == pytest.approx(0.3 * t, rel=0.1)


def test_enforced_rotation_spins_the_cylinder(run):
    x, mat, _, st, t, _ = run
    c = np.asarray(CENTRES["spun"])
    sel = mat == 4
    a0 = np.arctan2(x[sel, 1] - c[1], x[sel, 0] - c[0])
    a1 = np.arctan2(st["x"][sel, 1] - c[1], st["x"][sel, 0] - c[0])
    turn = np.angle(np.exp(1j * (a1 - a0)))
    assert np.median(turn) == pytest.approx(2.0 * t, rel=0.1)


def test_wind_accelerates_its_instance_only(run):
    x, mat, _, st, t, _ = run
    assert np.mean(st["v"][mat == 5, 2]) == pytest.approx(2.0 * t, rel=0.05)
    assert np.abs(st["v"][mat == 4, 2]).max() < 0.05


def test_bound_dynamics_table(run):
    *_, s = run
    assert s.bound.counts == (1, 1, 2, 1, 1)
    assert s.bound.selected[0] == np.sum(_blocks()[2] == 2)


def test_initial_velocity_toward_another_instance():
    d = Dynamics.from_config({"initial_velocity": [{"instance": "a", "toward": "b", "speed": 2.0}]})
    x = np.array([[0.3, 0.5, 0.5], [0.3, 0.5, 0.5], [0.7, 0.5, 0.5]])
    v = d.initial_velocities(x, np.array([0, 0, 1]), np.zeros((2, 3)), ["a", "b"], [0, 1])
    assert np.allclose(v, [[2, 0, 0], [2, 0, 0], [0, 0, 0]])


def test_dynamics_config_errors_name_the_key():
    with pytest.raises(ConfigError, match="allowed keys"):
        Dynamics.from_config({"gravitation": [0, 0, -9.8]})
    with pytest.raises(ConfigError, match=r"boundary_conditions\[0\].*delta_v"):
        Dynamics.from_config({"boundary_conditions": [{"type": "particle_impulse"}]})
    with pytest.raises(ConfigError, match="point and size"):
        Dynamics.from_config({"boundary_conditions": [{"type": "wind", "point": [0.5, 0.5, 0.5]}]})
    d = Dynamics.from_config({"boundary_conditions": [{"type": "cuboid", "instance": "pot"}]})
    with pytest.raises(ConfigError, match="unknown instance 'pot'.*ficus"):
        d.bind(np.full((4, 3), 0.5), np.zeros(4, int), ["ficus"], [0], 1.0)
    d = Dynamics.from_config({"boundary_conditions": [{"type": "wind", "point": [0.1, 0.1, 0.1], "size": [0.01] * 3}]})
    with pytest.raises(ConfigError, match="selects no particles"):
        d.bind(np.full((4, 3), 0.5), np.zeros(4, int), ["ficus"], [0], 1.0)


@pytest.mark.parametrize("ground", [0.125, 0.1375])  # the plane on a node plane, and 0.3 cells above one
def test_column_resting_on_the_ground_shortens_by_its_weight(ground):
    """A free jelly column (nu = 0: uniaxial stress, Cauchy sigma = E (lambda - 1)) settled on a
    frictionless ground shortens, between its bottom and top particle layers, by
    rho g ((h - s/2)^2 - (s/2)^2) / (2 E).  The ground must carry it at the plane: where it acts
    only on nodes behind it, the lowest layers pile up on the plane (2.5-3x the exact value)."""
    G, E, rho, h, w = 24, 1.0e4, 1000.0, 0.25, 0.25
    s = 0.5 / G
    axes = [np.arange(0.5 - w / 2 + s / 2, 0.5 + w / 2, s)] * 2 + [np.arange(ground + s / 2, ground + h, s)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    m = Material("fixed_corotated", "identity", E=E, nu=0.0, density=rho, name="column")
    dyn = Dynamics.from_config({"ground": {"height": ground, "friction": 0.0, "surface": "separate"}, "damping": 8.0})
    sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    dt = 0.4 * (1.0 / G) / m.wave_speed
    z0 = x[:, 2]
    bot, top = z0 < z0.min() + s / 2, z0 > z0.max() - s / 2
    short = []
    n = int(1.6 / dt)
    for k in range(n):
        sol.substep(dt)
        if k >= n - int(0.2 / dt):  # the last 0.2 s, settled (damping 8 / s)
            z = sol.get_state()["x"][:, 2]
            short.append((z0[top].mean() - z0[bot].mean()) - (z[top].mean() - z[bot].mean()))
    exact = rho * 9.8 * ((h - s / 2) ** 2 - (s / 2) ** 2) / (2 * E)
    assert abs(np.mean(short) / exact - 1.0) < 0.15, (np.mean(short), exact)
    assert np.ptp(short) < 0.05 * exact  # at rest, no creep


def _storage_face(sol) -> np.ndarray:
    """The solver's per-particle face offsets (domain units) back in input order (-1: proxies)."""
    rows = sol._sim_rows[sol._perm]
    out = np.full(sol.n_input, -1.0)
    out[rows[rows >= 0]] = sol._p_face.to_numpy()[rows >= 0] / sol.L
    return out


@pytest.mark.parametrize("p2g", ["atomic", "coarsened"])  # coarsened: the device re-sort permutes the rows
def test_surface_gaussians_rest_on_the_ground_lattice_faces_too(p2g):
    """Contact starts at each particle's face (colliders.py "Boundary placement"): half its side
    in front of a lattice particle's centre, at the centre of a visible gaussian, which lies on
    the material's surface.  Two blocks fall 0.3 cells onto the ground: a lattice block rests
    with its face (its lowest centres less half a spacing) on the plane; a reconstruction-like
    block, the same lattice plus a layer of surface carriers on its bottom face (``filled``
    false), rests with the carriers' centres on the plane.  With the lattice rule for every
    particle the carriers stopped half their side (0.25 cells) above it: the visible object
    hovered."""
    from physgs_steps.mpm.colliders import TOUCH, face_half_width

    G = 32
    dx = 1.0 / G
    s = dx / 2
    ground, gap = 0.2, 0.3 * dx

    def lattice(x0, z0, layers):
        axes = [np.arange(x0 + s / 2, x0 + 0.1, s), np.arange(0.4 + s / 2, 0.5, s), z0 + s * np.arange(layers)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    a = lattice(0.2, ground + gap + s / 2, 6)              # lattice block: face gap above the ground
    b = lattice(0.6, ground + gap + s / 2, 6)              # the same lattice ...
    c = lattice(0.6, ground + gap, 1)                      # ... and gaussians on its bottom face
    x = np.concatenate([a, b, c])
    vol = np.full(len(x), s ** 3)
    surface = np.r_[np.zeros(len(a) + len(b), bool), np.ones(len(c), bool)]
    face = face_half_width(vol, surface)
    m = Material("fixed_corotated", "identity", E=1e5, nu=0.3, density=1000.0, name="jelly")
    dyn = Dynamics.from_config({"ground": {"height": ground, "friction": 0.5, "surface": "separate"}, "damping": 5.0})
    sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu", p2g=p2g, resort_every=8)
    sol.set_particles(x, vol, np.zeros(len(x), int), face=face)
    assert (sol._sorter is not None) == (p2g == "coarsened")
    dt = 0.4 * dx / m.wave_speed
    for _ in range(int(0.4 / dt)):
        sol.substep(dt)
    np.testing.assert_array_equal(_storage_face(sol), face.astype(np.float32))  # followed every sort
    z = sol.get_state()["x"][:, 2]
    lattice_face = (z[: len(a)].min() - s / 2 - ground) / dx  # cells above the ground
    carriers = (z[len(a) + len(b):].mean() - ground) / dx
    assert -0.05 < lattice_face < TOUCH + 0.05, lattice_face
    assert -0.05 < carriers < TOUCH + 0.05, carriers
    # the lattice rows above the carriers rest with their face on them
    assert abs((z[len(a): len(a) + len(b)].min() - s / 2 - ground) / dx - carriers) < 0.05


def test_face_offsets_follow_proxies_and_default_to_half_the_side():
    """set_particles(face=...): the offsets reach the simulated rows in storage order; the
    proxy particles of a free rigid body (rigid.py "Proxy particles") take half their side;
    without ``face`` every particle gets half its side; a negative offset is an error."""
    from physgs_steps.errors import InputError
    from physgs_steps.mpm.colliders import face_half_width

    s = 1.0 / 64
    axes = [np.arange(0.3 + s / 2, 0.4, s)] * 3
    cube = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    x = np.concatenate([cube, cube + [0.3, 0, 0]])
    mat = np.r_[np.zeros(len(cube), int), np.ones(len(cube), int)]
    vol = np.full(len(x), s ** 3)
    surface = np.zeros(len(x), bool)
    surface[: len(cube)] = cube[:, 2] < 0.3 + s  # the jelly's bottom layer: gaussians
    mats = [Material("fixed_corotated", "identity", E=1e5, nu=0.3, density=1000.0, name="jelly"),
            Material("fixed_corotated", "identity", E=1e5, nu=0.3, density=1000.0, name="box", rigid=True)]
    sol = MPMSolver(mats, n_grid=32, backend="cpu", rigid_particles_per_cell=1)
    sol.set_particles(x, vol, mat, face=face_half_width(vol, surface))
    assert sol.proxy_count(1) is not None and sol.proxy_count(1) < len(cube)
    got = _storage_face(sol)
    np.testing.assert_array_equal(got[: len(cube)], np.where(surface[: len(cube)], 0.0, s / 2).astype(np.float32))
    rows = sol._sim_rows[sol._perm]
    proxies = sol._p_face.to_numpy()[rows < 0]
    assert len(proxies) == sol.proxy_count(1) and np.all(proxies > 0)
    sol.set_particles(x, vol, mat)
    np.testing.assert_allclose(_storage_face(sol)[: len(cube)], s / 2, rtol=1e-6)
    with pytest.raises(InputError, match="face"):
        sol.set_particles(x, vol, mat, face=np.full(len(x), -1.0))


def test_held_block_under_a_sparse_free_fringe_stays_finite():
    """A fixed cuboid holding a block under a one-particle-per-cell fringe of free material
    that the wind pushes (the ficus stem at the pot's rim): the ghost nodes' mirror samples
    are light there, and before the mirror-mass rule (colliders.MIRROR_MASS) the held
    particles' strain fed back through them until the state was NaN."""
    G = 32
    dx = 1.0 / G
    s = dx / 2  # held block: 8 particles per cell; fringe: one layer, 1 per cell, 0.3 dx above the face

    def lattice(*axes):  # [N, 3]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    held = lattice(*[np.arange(0.4 + s / 2, 0.6, s)] * 2, np.arange(0.3 + s / 2, 0.4, s))
    fringe = lattice(*[np.arange(0.4 + dx / 2, 0.6, dx)] * 2, [0.4 + 0.3 * dx])
    x = np.concatenate([held, fringe])
    dyn = Dynamics.from_config({"gravity": [0, 0, 0], "ground": None, "boundary_conditions": [
        {"type": "cuboid", "point": [0.5, 0.5, 0.35], "size": [0.1, 0.1, 0.05], "velocity": [0, 0, 0]},
        {"type": "wind", "point": [0.5, 0.5, 0.4], "size": [0.2, 0.2, 0.2], "mean": [3.0, 0.0, 0.0],
         "amplitude": [2.0, 0.0, 0.0], "frequency": 2.0}]}, "test")
    m = Material("fixed_corotated", "identity", E=3e5, nu=0.3, density=700.0, name="plant")
    sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
    sol.set_particles(x, np.full(len(x), s ** 3), np.zeros(len(x), int))
    dt = 0.4 * dx / np.sqrt(3e5 / 700)
    for _ in range(600):
        sol.substep(dt)
    st = sol.get_state()
    dev = np.abs(st["F"][: len(held)] - np.eye(3)).max()  # the held block barely strains
    assert np.isfinite(st["x"]).all() and dev < 0.05, dev


def test_frictionless_wall_in_the_floor_band_keeps_the_floor_friction():
    """Overlapping front bands: a frictionless domain wall 0.2 cells behind a rough ground acts
    on the same nodes first; the ground's Coulomb friction must still be mu times its own push
    (before the fix it braked only with what the wall had left: the block slid 30% farther)."""
    G, mu = 32, 0.3
    dx = 1.0 / G
    th = np.radians(30.0)
    m = Material("fixed_corotated", "identity", E=1e6, nu=0.3, density=1000.0, name="block")

    def slide(ground_cells):
        zf = ground_cells * dx
        axes = [np.arange(0.2 + dx / 4, 0.45, dx / 2), np.arange(0.375 + dx / 4, 0.625, dx / 2),
                np.arange(zf + dx / 4, zf + 0.125, dx / 2)]
        x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        dyn = Dynamics(gravity=(9.8 * np.sin(th), 0.0, -9.8 * np.cos(th)), boundary="slip", wall_margin=1.6 * dx,
                       boundary_conditions=[{"type": "surface_collider", "point": [0.5, 0.5, zf], "normal": [0, 0, 1],
                                             "surface": "separate", "friction": mu, "start_time": 0.0}])
        sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
        sol.set_particles(x, np.full(len(x), (dx / 2) ** 3), np.zeros(len(x), int))
        dt = 0.5 * dx / m.wave_speed
        for _ in range(int(0.3 / dt)):
            sol.substep(dt)
        return sol.get_state()["x"][:, 0].mean() - x[:, 0].mean()

    clear, overlap = slide(9.8), slide(1.8)  # the wall's band [1.6, 2.6) cells holds the ground's node 2
    assert abs(overlap / clear - 1.0) < 0.1, (overlap, clear)


def test_sparse_held_clusters_with_nothing_free_stay_finite():
    """Sparse clusters of strained material just inside a fixed cuboid's face, nothing free
    around them: the nodes just outside the face hold only the held particles' fringe mass, and
    each substep their stress impulse alone (the held particles bring no momentum).  With the
    ghost nodes' mirror one cell in front of the face, the ghost nodes extrapolated that impulse
    into the box and the held particles strained with it: 6 of these 30 clusters went NaN or
    J <= 0 (the udon scene's grip: J 0.005 at frame 9).  The mirror now lies beyond the held
    particles' reach (colliders.HELD_REACH)."""
    G = 32
    dx = 1.0 / G
    dyn = Dynamics.from_config({"gravity": [0, 0, 0], "ground": None, "boundary_conditions": [
        {"type": "cuboid", "point": [0.5, 0.5, 0.35], "size": [0.1, 0.1, 0.05], "velocity": [0, 0, 0]}]}, "test")
    m = Material("fixed_corotated", "identity", E=5e4, nu=0.3, density=1000.0, name="held")
    dt = 0.5 * dx / m.wave_speed
    worst = []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        ppc = rng.uniform(0.5, 3.0)  # particles per cell, up to 2 cells below the top face (z 0.4)
        lo = np.array([0.45, 0.45, 0.4 - rng.uniform(0.5, 2.0) * dx])
        hi = np.array([0.55, 0.55, 0.4 - rng.uniform(0.0, 0.5) * dx])
        n = max(8, int(np.prod((hi - lo) / dx) * ppc))
        x = lo + rng.random((n, 3)) * (hi - lo)
        sol = MPMSolver([m], n_grid=G, dynamics=dyn, backend="cpu")
        sol.set_particles(x, np.full(n, dx ** 3 / 4), np.zeros(n, int))
        st = sol.get_state()
        sol.set_state(st["x"], st["v"], st["C"], np.eye(3) + rng.normal(0.0, 0.1, (n, 3, 3)))
        for _ in range(300):
            sol.substep(dt)
        F = sol.get_state()["F"]
        J = np.linalg.det(F) if np.isfinite(F).all() else np.array([np.nan])
        worst.append((seed, float(np.min(J)), float(np.max(J))))
    bad = [w for w in worst if not (0.4 < w[1] and w[2] < 2.5)]  # initial J 0.7-1.4
    assert not bad, bad
