"""MPM solver: conservation, free fall, rigid rotation, reproducibility, state round trips."""
from __future__ import annotations

import os

import numpy as np
import pytest

from physgs_steps.errors import InputError
from physgs_steps.mpm import Dynamics, Material, MPMSolver

JELLY = Material("fixed_corotated", "identity", E=1.0e5, nu=0.3, density=1000.0, name="jelly")


def block(lo, hi, spacing: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Jittered lattice of particles filling the box [lo, hi] (domain units): x [P, 3], vol [P]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    x += np.random.default_rng(seed).uniform(-0.2, 0.2, x.shape) * spacing
    return x, np.full(len(x), spacing ** 3)


def p_mass(vol: np.ndarray, density: float, L: float = 1.0) -> np.ndarray:
    return density * vol * L ** 3


def test_momentum_is_conserved_without_gravity_and_walls():
    xa, va = block([0.3, 0.4, 0.4], [0.45, 0.55, 0.55], 1 / 64, seed=1)
    xb, vb = block([0.55, 0.42, 0.42], [0.68, 0.56, 0.58], 1 / 64, seed=2)
    x, vol = np.concatenate([xa, xb]), np.concatenate([va, vb])
    mat = np.r_[np.zeros(len(xa), int), np.ones(len(xb), int)]
    soft = JELLY.with_(name="soft", E=3.0e4, density=500.0)
    s = MPMSolver([JELLY, soft], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    s.set_particles(x, vol, mat)
    rng = np.random.default_rng(0)
    v0 = np.where(mat[:, None] == 0, [0.5, 0.0, 0.1], [-0.8, 0.2, 0.0]) + 0.05 * rng.standard_normal((len(x), 3))
    s.set_state(x, v0, np.zeros((len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    m = p_mass(vol, np.where(mat == 0, JELLY.density, soft.density))
    p0 = (m[:, None] * v0).sum(0)
    for _ in range(150):  # the blocks meet and bounce
        s.substep(5e-4)
    st = s.get_state()
    p1 = (m[:, None] * st["v"]).sum(0)
    assert np.abs(st["x"] - x).max() > 0.02  # things moved
    assert np.abs(p1 - p0).max() < 1e-4 * np.abs(m[:, None] * v0).sum(0).max()


def test_free_fall_is_exact_whatever_the_substeps():
    """Leapfrog velocities: x = x0 - g t^2 / 2 to float precision, for any substep count and
    across changes of dt (the velocities are re-staggered)."""
    x, vol = block([0.4, 0.4, 0.6], [0.5, 0.5, 0.7], 1 / 64)
    for dts in ([1e-3] * 150, [5e-4] * 100 + [2e-3] * 50, [3e-3] * 50):
        s = MPMSolver([JELLY], n_grid=32, dynamics=Dynamics.free(), backend="cpu")
        s.set_particles(x, vol, np.zeros(len(x), int))
        for dt in dts:
            s.substep(dt)
        t = sum(dts)
        st = s.get_state()
        assert np.abs(st["x"][:, 2] - (x[:, 2] - 0.5 * 9.8 * t * t)).max() < 2e-6
        assert np.abs(st["x"][:, :2] - x[:, :2]).max() < 1e-6
        assert np.abs(st["v"][:, 2] + 9.8 * t).max() < 1e-4
        assert np.abs(st["F"] - np.eye(3)).max() < 1e-5
        # the state handed out continues the same trajectory in a fresh solver
        s2 = MPMSolver([JELLY], n_grid=32, dynamics=Dynamics.free(), backend="cpu")
        s2.set_particles(x, vol, np.zeros(len(x), int))
        s2.set_state(st["x"], st["v"], st["C"], st["F"])
        s.substep(1e-3)
        s2.substep(1e-3)
        assert np.abs(s.get_state()["x"] - s2.get_state()["x"]).max() < 1e-6


def test_block_resting_on_the_ground_stays_put():
    """The leapfrog half kick is removed by the floor where the block is supported."""
    from physgs_steps.mpm import Dynamics as D

    x, vol = block([0.4, 0.4, 0.25], [0.5, 0.5, 0.3], 1 / 64, seed=0)
    x[:, 2] = np.maximum(x[:, 2], 0.25)
    dyn = D(ground={"height": 0.25, "surface": "separate", "friction": 0.5})
    # E 1e5: P-wave speed 12 m/s, CFL 0.37 at dt 1 ms (E 1e6 would be past the explicit limit)
    s = MPMSolver([JELLY.with_(E=1e5)], n_grid=32, dynamics=dyn, backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    z = []
    for i in range(300):
        s.substep(1e-3)
        if i % 50 == 49:
            z.append(s.get_state()["x"][:, 2].mean())
    st = s.get_state()
    # settles within a fraction of a cell (where the floor acts on the grid: issue 15), then stays
    assert abs(z[-1] - x[:, 2].mean()) < 0.25 / 32
    assert np.ptp(z[2:]) < 1e-3  # no sinking or drift once settled
    assert np.abs(st["v"]).max() < 0.05


def test_initial_C_matches_the_velocity_field():
    """C from the initial velocities: exact for an affine field (here a rotation plus a
    stretch), so no kinetic energy is lost in the first substep (with C = 0 a third is)."""
    x, vol = block([0.42, 0.42, 0.42], [0.58, 0.58, 0.58], 1 / 64, seed=2)
    A = np.array([[0.3, -2.0, 0.0], [2.0, 0.1, 0.0], [0.0, 0.0, -0.2]])
    c = np.array([0.5, 0.5, 0.5])
    v = (x - c) @ A.T
    s = MPMSolver([JELLY.with_(E=1e3)], n_grid=16, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int), velocity=v)
    C0 = s.get_state()["C"]
    assert np.abs(C0 - A).max() < 1e-3 * np.abs(A).max()
    ke0 = (v ** 2).sum()
    s.substep(1e-5)
    ke1 = (s.get_state()["v"] ** 2).sum()
    assert abs(ke1 / ke0 - 1) < 1e-3


def test_spinning_block_stays_rigid_and_unstressed():
    x, vol = block([0.4, 0.4, 0.4], [0.6, 0.6, 0.6], 1 / 64)
    s = MPMSolver([JELLY], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    w = np.array([0.0, 0.0, 3.0])  # rad/s about z through the block centre
    c = np.array([0.5, 0.5, 0.5])
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    v = np.cross(w, x - c)
    s.set_state(x, v, np.broadcast_to(W, (len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    dt, n = 5e-4, 400  # 0.2 s, 34 degrees
    for _ in range(n):
        s.substep(dt)
    st = s.get_state()
    ang = 3.0 * n * dt
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    assert np.abs(st["x"] - ((x - c) @ R.T + c)).max() < 3e-3
    # F is (nearly) the rotation itself, so the stress stays tiny compared with E
    assert np.abs(st["F"] - R).max() < 5e-3
    assert np.abs(s.get_stress()).max() < 2e-3 * JELLY.E


def test_two_runs_agree_and_sorting_changes_only_rounding():
    x, vol = block([0.35, 0.35, 0.3], [0.6, 0.55, 0.5], 1 / 64, seed=3)
    runs = []
    for sort in (True, True, False):
        s = MPMSolver([JELLY], n_grid=32, backend="cpu", sort_particles=sort)
        s.set_particles(x, vol, np.zeros(len(x), int))
        for _ in range(100):
            s.substep(1e-3)
        runs.append(s.get_state())
    for k in ("x", "v", "C", "F"):
        assert np.allclose(runs[0][k], runs[1][k], atol=1e-6, rtol=1e-5), k
        assert np.allclose(runs[0][k], runs[2][k], atol=1e-3, rtol=1e-3), k


def test_atomic_grid_mode_matches_private_grids():
    """The CUDA transfer scheme (one grid, float atomics), run on the CPU, agrees with the
    CPU's per-thread grids."""
    x, vol = block([0.35, 0.35, 0.3], [0.6, 0.55, 0.5], 1 / 64, seed=3)
    runs = []
    for mode in ("private", "atomic"):
        s = MPMSolver([JELLY], n_grid=32, backend="cpu", grid_mode=mode)
        s.set_particles(x, vol, np.zeros(len(x), int))
        for _ in range(100):
            s.substep(1e-3)
        runs.append(s.get_state())
    for k in ("x", "v", "C", "F"):
        assert np.allclose(runs[0][k], runs[1][k], atol=1e-3, rtol=1e-3), k


def test_node_box_follows_the_particles_and_leaves_no_stale_mass():
    """The CPU kernel's node loops run over the box of nodes the particles reach: it moves with
    a flying block, is tight, and the nodes it leaves behind are cleared (the whole grid's mass
    is the particles' mass); a soft block on a free rigid one agrees with the full-grid
    (atomic, CUDA's scheme) transfer."""
    x, vol = block([0.2, 0.4, 0.4], [0.3, 0.5, 0.48], 1 / 64, seed=4)
    s = MPMSolver([JELLY], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    s.set_state(x, np.tile([2.0, 0.0, 0.5], (len(x), 1)), np.zeros((len(x), 3, 3)),
                np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    mass = p_mass(vol, JELLY.density).sum()
    G = s.n_grid
    for _ in range(4):
        for _ in range(49):
            s.substep(1e-3)
        xb = s.get_state()["x"] / s.L  # positions before the last substep (domain units)
        s.substep(1e-3)
        base = np.clip(np.floor(xb * G - 0.5).astype(int), 0, G - 3)
        box = s._box.to_numpy()[0]
        assert list(box) == list(base.min(0)) + list(base.max(0) + 3)
        assert box[3] - box[0] < G // 2  # far smaller than the grid
        gm = s.grid_m.to_numpy()  # [T, G, G, G]: chunk 0 holds the summed grid
        assert abs(gm[0].sum() - mass) < 1e-4 * mass, (gm[0].sum(), mass)
        inside = np.zeros((G, G, G), bool)
        inside[box[0]:box[3], box[1]:box[4], box[2]:box[5]] = True
        assert not gm[:, ~inside].any()
    assert s.get_state()["x"][:, 0].min() > 0.6  # it crossed the grid
    from physgs_steps.mpm import preset
    xr, vr = block([0.4, 0.4, 0.1], [0.55, 0.55, 0.2], 1 / 64, seed=5)
    xs, vs = block([0.42, 0.42, 0.23], [0.53, 0.53, 0.3], 1 / 64, seed=6)
    xx, vv = np.r_[xr, xs], np.r_[vr, vs]
    mat = np.r_[np.zeros(len(xr), int), np.ones(len(xs), int)]
    runs = []
    for mode in ("private", "atomic"):
        dyn = Dynamics.from_config({"ground": {"height": 0.1, "friction": 0.5, "surface": "separate"}})
        s = MPMSolver([preset("stone", rigid=True), JELLY], n_grid=32, dynamics=dyn, backend="cpu", grid_mode=mode)
        s.set_particles(xx, vv, mat)
        for _ in range(150):
            s.substep(5e-4)
        runs.append(s.get_state())
    assert np.abs(runs[1]["x"] - xx).max() > 0.01  # the jelly fell onto the stone
    assert np.allclose(runs[0]["x"], runs[1]["x"], atol=1e-4), np.abs(runs[0]["x"] - runs[1]["x"]).max()


def test_atomic_grid_mode_moves_a_free_spinning_rigid_body_like_private_grids():
    """The rigid body's sums over the grid (kernels.py: per (x, y) column over z) need whole
    columns in both transfer schemes: a free rigid block flying and spinning through a soft one,
    no gravity, no ground, ends in the same place with one grid and atomics (CUDA's scheme) as
    with per-thread grids (with one node per thread in those sums the body's mass and momentum
    were a single node's)."""
    from physgs_steps.mpm import preset
    xr, vr = block([0.2, 0.4, 0.4], [0.32, 0.52, 0.5], 1 / 64, seed=7)
    xs, vs = block([0.5, 0.38, 0.38], [0.62, 0.55, 0.52], 1 / 64, seed=8)
    xx, vv = np.r_[xr, xs], np.r_[vr, vs]
    mat = np.r_[np.zeros(len(xr), int), np.ones(len(xs), int)]
    c = xr.mean(0)
    v0 = np.zeros_like(xx)
    v0[: len(xr)] = np.array([1.5, 0.0, 0.0]) + np.cross(np.array([0.0, 0.0, 6.0]), xr - c)
    runs = []
    for mode in ("private", "atomic"):
        s = MPMSolver([preset("stone", rigid=True), JELLY], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)),
                      backend="cpu", grid_mode=mode)
        s.set_particles(xx, vv, mat, velocity=v0)
        for _ in range(120):
            s.substep(5e-4)
        runs.append(s.get_state())
    assert np.isfinite(runs[1]["x"]).all()
    assert np.abs(runs[0]["x"][: len(xr)] - xr).max() > 0.05  # the block flew and turned
    assert np.allclose(runs[0]["x"], runs[1]["x"], atol=1e-4), np.abs(runs[0]["x"] - runs[1]["x"]).max()


def test_state_round_trip_and_input_errors():
    x, vol = block([0.4, 0.4, 0.4], [0.5, 0.5, 0.5], 1 / 48)
    s = MPMSolver([JELLY], n_grid=32, backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    rng = np.random.default_rng(5)
    st = {"x": x, "v": rng.standard_normal(x.shape), "C": rng.standard_normal((len(x), 3, 3)),
          "F": np.eye(3) + 0.01 * rng.standard_normal((len(x), 3, 3))}
    s.set_state(**st)
    back = s.get_state()
    for k in st:
        assert np.allclose(back[k], st[k], atol=1e-6), k
    with pytest.raises(InputError, match="outside the simulation domain"):
        s.set_particles(np.r_[x, [[0.999, 0.5, 0.5]]], np.r_[vol, vol[:1]], np.zeros(len(x) + 1, int))
    with pytest.raises(InputError, match="non-finite"):
        s.set_state(np.full_like(x, np.nan), st["v"], st["C"], st["F"])
    with pytest.raises(InputError, match="material index"):
        s.set_particles(x, vol, np.ones(len(x), int))


def test_stats_detect_nonfinite_and_escaped_particles():
    x, vol = block([0.4, 0.4, 0.4], [0.5, 0.5, 0.5], 1 / 48)
    s = MPMSolver([JELLY], n_grid=32, backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    st = s.stats()
    assert st["nonfinite"][0] == 0 and st["outside"][0] == 0 and st["clamped"] == 0
    assert st["j_min"][0] == pytest.approx(1.0, abs=1e-5)
    # particles flung at the walls within one substep stay inside them (particle-side walls)
    v = np.zeros_like(x)
    v[:10] = [0.0, 0.0, 1.0e4]
    F = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
    s.set_state(x, v, np.zeros((len(x), 3, 3)), F)
    s.substep(1e-3)
    top = s.get_state()["x"][:10, 2]
    assert np.allclose(top, 1.0 - s.dynamics.wall_margin, atol=1e-5)
    assert s.stats()["outside"][0] == 0
    # a state outside the grid (e.g. set from a diverged run) is counted, and its stencils are
    # clamped onto the grid (no out-of-bounds access)
    xo = x.copy()
    xo[:10] = [0.5, 0.5, 1.5]
    s.set_state(xo, np.zeros_like(x), np.zeros((len(x), 3, 3)), F)
    assert s.stats()["outside"][0] >= 10
    s.substep(1e-3)
    assert s.stats()["clamped"] >= 10
    assert s.stats()["clamped"] == 0  # counted since the last call: reset by it
    s._err.from_numpy(np.array([3 * 4096 + 5, 0, 0, 0], np.int32))  # exact past f32's 2^24 too
    assert s.stats()["clamped"] == 3 * 4096 + 5
    s._err.from_numpy(np.array([2 ** 27 + 1, 0, 0, 0], np.int32))
    assert s.stats()["clamped"] == 2 ** 27 + 1
    s.set_state(x, np.zeros_like(x), np.zeros((len(x), 3, 3)), F)
    F2 = F.copy()
    F2[:3] = np.nan
    s.F.from_numpy(F2.astype(np.float32))  # device state as a diverged run leaves it
    assert s.stats()["nonfinite"][0] == 3


@pytest.mark.gpu
def test_cuda_substeps_match_cpu(monkeypatch):
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    from physgs_steps.mpm.backend import ensure_taichi

    x, vol = block([0.35, 0.35, 0.3], [0.6, 0.55, 0.5], 1 / 64, seed=4)
    states = []
    try:
        for arch, reps in (("cpu", 0), ("cuda", 0), ("cuda", 1), ("cuda", 4)):
            s = MPMSolver([JELLY], n_grid=32, backend=arch)
            assert s.arch == arch
            s.set_particles(x, vol, np.zeros(len(x), int))
            if reps:  # ti.graph batches (MPMSolver.substeps) on CUDA, reps substeps a launch
                monkeypatch.setenv("PHYSGS_TI_REPS", str(reps))
                s.substeps(100, 1e-3)
                # (substeps a launch, launches a graph): 100 = 3 x 32 + 4, or 4 x (16 + 8 + 1)
                assert sorted(s._batches._graphs) == ([(1, 4), (1, 32)] if reps == 1 else [(4, 1), (4, 8), (4, 16)])
            else:
                for _ in range(100):
                    s.substep(1e-3)
            states.append((s.get_state(), s.stats()))
    finally:
        ensure_taichi("cpu")
    (cpu, st_cpu), *gpu = states
    for g, st in gpu:
        for k in ("x", "v", "F"):
            assert np.allclose(cpu[k], g[k], atol=2e-4, rtol=1e-3), k
        for k in ("nonfinite", "outside", "clamped"):
            assert np.array_equal(st_cpu[k], st[k]), k
        assert np.allclose(st_cpu["j_min"], st["j_min"], rtol=1e-3) and np.allclose(st_cpu["j_max"], st["j_max"], rtol=1e-3)


def _windy_jelly() -> tuple[MPMSolver, np.ndarray]:
    """A small jelly block in wind at 20 Hz (a force that changes with each substep's time),
    coarsened P2G re-sorted every 40 substeps, CPU: the solver and its initial positions."""
    x, vol = block([0.35, 0.4, 0.3], [0.55, 0.6, 0.45], 1 / 48, seed=3)
    dyn = Dynamics.from_config({"boundary_conditions": [
        {"type": "wind", "instance": "jelly", "mean": [0.5, 0.0, 0.0], "amplitude": [30.0, 0.0, 0.0],
         "frequency": 20.0}]}, "test")
    s = MPMSolver([JELLY], n_grid=24, dynamics=dyn, backend="cpu", p2g="coarsened", resort_every=40)
    s.set_particles(x, vol, np.zeros(len(x), int), velocity=np.tile([0.4, -0.2, 0.0], (len(x), 1)))
    return s, x


def test_batched_substeps_give_bitwise_single_substeps(monkeypatch):
    """MPMSolver.substeps (ti.graph batches of the substep kernel) gives bit for bit the state
    and time of as many substep calls, across a change of dt (the velocities re-staggered) and
    device re-sorts (coarsened P2G, every 40 substeps: batches end there), with batch sizes that
    are not powers of two, under a force that changes with the time of each substep (wind at
    20 Hz); so does it with 2 substeps a launch (PHYSGS_TI_REPS=2: kernels.build's
    substep_reps, odd counts leaving one substep to the one-substep kernel);
    PHYSGS_TI_GRAPH=0 runs them one by one."""
    schedule = [(1, 5e-4), (37, 5e-4), (6, 8e-4), (64, 8e-4)]  # re-sorts before substeps 41 and 81
    runs = []
    for mode in ("single", "batched", "reps", "off"):
        monkeypatch.setenv("PHYSGS_TI_GRAPH", "0" if mode == "off" else "1")
        monkeypatch.setenv("PHYSGS_TI_REPS", "2" if mode == "reps" else "1")
        s, x = _windy_jelly()
        for n, dt in schedule:
            if mode == "single":
                for _ in range(n):
                    s.substep(dt)
            else:
                s.substeps(n, dt)
        # the graphs, (substeps a launch, launches): batches of 1, 37, 2 | 4, 36 | 28 substeps
        # (| a re-sort), one a launch: 37 = 32 + 4 + 1, 36 = 32 + 4, 28 = 16 + 8 + 4; two a
        # launch: 37 = 2 x (16 + 2) + 1, 36 = 2 x (16 + 2), 28 = 2 x (8 + 4 + 2)
        if mode == "batched":
            assert sorted(s._batches._graphs) == [(1, 1), (1, 2), (1, 4), (1, 8), (1, 16), (1, 32)]
        elif mode == "reps":
            assert sorted(s._batches._graphs) == [(1, 1), (2, 1), (2, 2), (2, 4), (2, 8), (2, 16)]
        else:
            assert s._batches is None
        assert s.sort_generation == 3  # at load, then twice
        runs.append((s.get_state(), s.time, s.stats()))
    (st0, t0, sa0), *others = runs
    for st, t, sa in others:
        assert t == t0
        for k in ("x", "v", "C", "F"):
            assert np.array_equal(st0[k], st[k]), k
        assert sa0["clamped"] == sa["clamped"]
    assert np.abs(st0["x"] - x).max() > 0.01  # it fell and moved


def test_run_frames_launches_each_substep_kernel_first_in_its_first_substep_window(monkeypatch):
    """run_frames times the substep kernels' first launches (compilation or cache load) apart
    from the frames' substeps: with 2 substeps a launch, frame 1 runs one substep, then one
    launch of 2, then the rest; the same state bit for bit as one substep a launch."""
    import logging

    from physgs_steps.mpm.runner import run_frames
    from physgs_steps.mpm.stability import Thresholds
    from physgs_steps.mpm.timestep import TimeStepper

    runs = []
    for reps in ("1", "2"):
        monkeypatch.setenv("PHYSGS_TI_REPS", reps)
        s, _x = _windy_jelly()
        calls = []
        batched = s.substeps
        monkeypatch.setattr(s, "substeps", lambda n, dt: (calls.append(n), batched(n, dt)))
        res = run_frames(s, 3, TimeStepper(fps=100.0, max_substeps=40), Thresholds(), lambda *a: None,
                         logging.getLogger("test"))
        assert res.stable and res.first_substep_seconds > 0
        n1, n2 = res.substeps  # frames 1 and 2
        assert calls == ([2, n1 - 3, n2] if reps == "2" else [n1 - 1, n2])
        runs.append((s.get_state(), s.time, res.substeps))
    (st0, t0, n0), (st1, t1, n1) = runs
    assert t0 == t1 and n0 == n1
    for k in ("x", "v", "C", "F"):
        assert np.array_equal(st0[k], st1[k]), k


def test_reps_knob(monkeypatch):
    """PHYSGS_TI_REPS: substeps a launch of MPMSolver.substeps (default 2 on CUDA, 1 on the
    CPU); a bad value is an error naming the variable."""
    from physgs_steps.errors import ConfigError
    from physgs_steps.mpm.solver import reps_per_launch

    monkeypatch.delenv("PHYSGS_TI_REPS", raising=False)
    assert (reps_per_launch("cpu"), reps_per_launch("cuda")) == (1, 2)
    monkeypatch.setenv("PHYSGS_TI_REPS", "8")
    assert reps_per_launch("cpu") == reps_per_launch("cuda") == 8
    for bad in ("0", "-2", "2.5", "four", "33"):
        monkeypatch.setenv("PHYSGS_TI_REPS", bad)
        with pytest.raises(ConfigError, match="PHYSGS_TI_REPS"):
            reps_per_launch("cuda")


def test_block_dim_knob_reaches_taichi():
    """PHYSGS_TI_BLOCK_DIM (the kernel experiments' knob, docs/MEASURED.md "MPM step") sets Taichi's
    default_gpu_block_dim; unset, Taichi keeps its own default."""
    import subprocess
    import sys

    code = ("from physgs_steps.mpm.backend import ensure_taichi; ensure_taichi('cpu'); "
            "from taichi.lang import impl; print('BD', impl.current_cfg().default_gpu_block_dim)")
    env = {k: v for k, v in os.environ.items() if k != "PHYSGS_TI_BLOCK_DIM"}
    got = []
    for extra in ({"PHYSGS_TI_BLOCK_DIM": "64"}, {}):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             timeout=120, check=True).stdout
        got.append(int(out.split("BD")[-1]))
    assert got[0] == 64 and got[1] != 64


def test_init_affine_is_reproducible_on_the_cpu():
    """The APIC round trips that set C for a non-uniform initial velocity field sum on the CPU
    in one thread: C comes out bit for bit the same every time (with threads and float atomics
    it differed by up to 1.5e-5 between runs, so bear_can's final.h5 differed between runs)."""
    x, vol = block([0.3, 0.3, 0.3], [0.6, 0.6, 0.6], 1 / 64, seed=3)
    v = np.c_[np.sin(7 * x[:, 0]), x[:, 1] ** 2, -x[:, 2]]
    s = MPMSolver([JELLY], n_grid=32, backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int), velocity=v)
    st = s.get_state()
    assert np.abs(st["C"]).max() > 1.0  # a real gradient (dv_x/dx up to 7 1/s)
    for _ in range(3):
        s.set_state(st["x"], st["v"], np.zeros_like(st["C"]), st["F"])
        s.init_affine()
        assert np.array_equal(s.get_state()["C"], st["C"])


def test_flip_sand_is_reproducible_on_the_cpu():
    """FLIP materials (Drucker-Prager sand) sum the pre-force momenta grid_o per chunk of
    particles, like the momenta, so the CPU's result is the same bit for bit in every run with
    several threads.  With one grid for all threads the sums' order changed from run to run: a
    sand block differed between runs from substep 17-19 on, in most particles' velocities."""
    sand = Material("fixed_corotated", "drucker_prager", E=5e4, nu=0.25, density=1500.0, name="sand",
                    friction_angle=30.0)
    rng = np.random.default_rng(3)
    x = np.array([0.3, 0.35, 0.1]) + np.array([0.12, 0.2, 0.15]) * rng.random((3000, 3))
    states = []
    for _ in range(3):
        s = MPMSolver([sand], n_grid=32, backend="cpu", grid_mode="private")
        s.set_particles(x, np.full(len(x), 0.12 * 0.2 * 0.15 / 3000), np.zeros(len(x), int))
        assert s.n_chunks >= 2 or (os.cpu_count() or 1) < 2  # the chunks are what is tested
        s.substeps(40, 2e-4)
        states.append(s.get_state())
    assert np.abs(states[0]["v"]).max() > 0
    for st in states[1:]:
        for k in ("x", "v", "C", "F"):
            assert np.array_equal(st[k], states[0][k]), k


@pytest.mark.gpu
def test_cuda_matches_cpu_with_sand_and_a_rigid_body():
    """CUDA against the CPU where the kernels take their other branches: FLIP sand (grid_o: one
    grid with atomics on CUDA, per chunk on the CPU; G2P's stores staged on CUDA) and a jelly
    with a free stone (a rigid material: G2P's direct stores on CUDA)."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    from physgs_steps.mpm.backend import ensure_taichi

    sand = Material("fixed_corotated", "drucker_prager", E=5e4, nu=0.25, density=1500.0, name="sand",
                    friction_angle=30.0)
    stone = Material("fixed_corotated", "identity", E=2.0e7, nu=0.25, density=2600.0, name="stone", rigid=True)
    xs, vs = block([0.35, 0.35, 0.12], [0.6, 0.55, 0.3], 1 / 64, seed=5)
    xj, vj = block([0.35, 0.35, 0.12], [0.6, 0.6, 0.25], 1 / 64, seed=6)
    xr, vr = block([0.42, 0.42, 0.3], [0.52, 0.52, 0.4], 1 / 64, seed=7)
    cases = [([sand], xs, vs, np.zeros(len(xs), int), True),
             ([JELLY, stone], np.r_[xj, xr], np.r_[vj, vr], np.r_[np.zeros(len(xj), int), np.ones(len(xr), int)], False)]
    try:
        for mats, x, vol, mat, staged in cases:
            out = []
            for arch in ("cpu", "cuda"):
                s = MPMSolver(mats, n_grid=32, backend=arch)
                s.set_particles(x, vol, mat)
                assert s.staged == (staged and arch == "cuda")
                s.substeps(60, 5e-4)
                out.append(s.get_state())
            cpu, gpu = out
            assert np.abs(cpu["x"] - x).max() > 1e-3  # it moved
            for k in ("x", "v", "F"):
                assert np.allclose(cpu[k], gpu[k], atol=2e-4, rtol=1e-3), (mats[0].name, k)
    finally:
        ensure_taichi("cpu")
