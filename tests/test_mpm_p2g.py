"""Coarsened P2G and the device re-sort (src/physgs_steps/mpm/p2g_sorted.py) against the
one-atomic-per-particle transfer, on the CPU (the warp-run transfer, warp shuffles, on CUDA)."""
from __future__ import annotations

import numpy as np
import pytest

from physgs_steps.errors import ConfigError
from physgs_steps.mpm import Dynamics, MPMSolver

from test_mpm_solver import JELLY, block, p_mass

SOFT = JELLY.with_(name="soft", E=3.0e4, density=500.0)


def _two_blocks():
    """Two colliding blocks of different materials, in random row order: x, vol, mat, v [P, 3]."""
    xa, va = block([0.3, 0.4, 0.4], [0.45, 0.55, 0.55], 1 / 64, seed=1)
    xb, vb = block([0.55, 0.42, 0.42], [0.68, 0.56, 0.58], 1 / 64, seed=2)
    x, vol = np.concatenate([xa, xb]), np.concatenate([va, vb])
    mat = np.r_[np.zeros(len(xa), int), np.ones(len(xb), int)]
    rng = np.random.default_rng(0)
    order = rng.permutation(len(x))
    x, vol, mat = x[order], vol[order], mat[order]
    # fast enough that many particles change cells between re-sorts
    v = np.where(mat[:, None] == 0, [3.0, 0.0, 0.5], [-4.0, 1.0, 0.0]) + 0.3 * rng.standard_normal((len(x), 3))
    return x, vol, mat, v


def _solver(mode: str, grid_mode: str = "atomic", **kw) -> MPMSolver:
    x, vol, mat, v = _two_blocks()
    s = MPMSolver([JELLY, SOFT], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cpu",
                  grid_mode=grid_mode, p2g=mode, **kw)
    s.set_particles(x, vol, mat)
    s.set_state(x, v, np.zeros((len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
    return s


def test_coarsened_p2g_matches_atomic_across_resorts():
    """Same grid mass after one substep, same particle state after 30 substeps (several
    device re-sorts, short runs), up to float summation order; momentum conserved."""
    x, vol, mat, v = _two_blocks()
    ref = _solver("atomic")
    runs = [_solver("coarsened", run_length=5, resort_every=4), _solver("coarsened", run_length="cell", resort_every=4),
            _solver("coarsened", run_length=5, resort_every=4, split=1),  # one thread a run (default: 3), or 9
            _solver("coarsened", run_length=5, resort_every=4, split=9),
            _solver("coarsened", "private", resort_every=4)]
    for s in [ref] + runs:
        s.substep(2e-4)
    m_ref = ref.grid_m.to_numpy()[0]
    for s in runs[:4]:  # one grid, as on CUDA
        assert np.abs(s.grid_c.to_numpy()[0] - ref.grid_c.to_numpy()[0]).max() == 0  # the same touched nodes
        assert np.abs(s.grid_m.to_numpy()[0] - m_ref).max() < 1e-6 * m_ref.max()
    for s in [ref] + runs:
        for _ in range(29):
            s.substep(2e-4)
    a = ref.get_state()
    assert np.abs(a["x"] - x).max() > 0.5 / 32  # particles crossed cells
    m = p_mass(vol, np.where(mat == 0, JELLY.density, SOFT.density))
    p0 = (m[:, None] * v).sum(0)
    for s in runs:
        assert s.sort_generation == 1 + 29 // 4  # sorted at load, then every 4 substeps
        b = s.get_state()
        for k, tol in (("x", 1e-6), ("v", 2e-5), ("C", 1e-4), ("F", 1e-5)):  # measured: 1e-7, 1e-6, 3e-6, 7e-7
            scale = max(1.0, float(np.abs(a[k]).max()))
            assert np.abs(a[k] - b[k]).max() < tol * scale, k
        p1 = (m[:, None] * b["v"]).sum(0)
        assert np.abs(p1 - p0).max() < 1e-4 * np.abs(m[:, None] * v).sum(0).max()


def test_device_sort_permutes_every_particle_array_consistently():
    s = _solver("coarsened", run_length=5, resort_every=0)
    G, dx = s.n_grid, s.dx
    from physgs_steps.mpm.p2g_sorted import sorted_by_base

    assert sorted_by_base(s.x.to_numpy(), dx, G)
    for _ in range(10):
        s.substep(2e-4)
    before, stress = s.get_state(), s.get_stress()
    assert not sorted_by_base(s.x.to_numpy(), dx, G)  # moved out of order (resort_every 0: no re-sort)
    s.resort()
    assert sorted_by_base(s.x.to_numpy(), dx, G)
    after = s.get_state()
    for k in before:
        assert np.array_equal(before[k], after[k]), k
    assert np.array_equal(stress, s.get_stress())
    # per-slot data moved with the particles: mass and material agree with the caller's rows
    x, vol, mat, _ = _two_blocks()
    perm = s._perm
    assert np.array_equal(s._mat.to_numpy(), mat[perm])
    assert np.allclose(s._p_mass.to_numpy(), p_mass(vol, np.where(mat == 0, JELLY.density, SOFT.density))[perm],
                       rtol=1e-6)
    rows = np.array([0, 5, len(x) - 1])
    gx, _ = s.gather_rows(rows)
    assert np.allclose(gx, after["x"][rows])


def test_backup_restored_across_a_resort():
    s = _solver("coarsened", run_length=5, resort_every=3)
    for _ in range(2):
        s.substep(2e-4)
    s.save_backup()
    saved, gen = s.get_state(), s.sort_generation
    for _ in range(7):
        s.substep(2e-4)
    assert s.sort_generation > gen
    s.restore_backup()
    back = s.get_state()
    for k in saved:
        assert np.array_equal(saved[k], back[k]), k
    x, vol, mat, _ = _two_blocks()
    assert np.array_equal(s._mat.to_numpy(), mat[s._perm])
    s.substep(2e-4)  # and it runs on from there
    assert np.isfinite(s.get_state()["x"]).all()


def test_exclusive_scan_and_mode_errors():
    import taichi as ti

    from physgs_steps.mpm.backend import ensure_taichi
    from physgs_steps.mpm.p2g_sorted import Scan, resolve

    ensure_taichi("cpu")  # ndarrays need Taichi started; under xdist this test may run first in its worker

    rng = np.random.default_rng(1)
    for n in (1, 128, 129, 20_000):  # one block, exactly one, two, three levels
        a = rng.integers(0, 5, n).astype(np.int32)
        arr = ti.ndarray(ti.i32, n)
        arr.from_numpy(a)
        Scan(n)(arr)
        assert np.array_equal(arr.to_numpy(), np.r_[0, np.cumsum(a)[:-1]].astype(np.int32)), n
    assert resolve("auto", "cuda") in ("atomic", "coarsened")
    assert resolve("auto", "cuda", 27_000) == "atomic"  # too few runs to fill a GPU
    assert resolve("auto", "cuda", 1_000_000) == "coarsened"
    assert resolve("auto", "cpu", 1_000_000) == "atomic"
    assert resolve("coarsened", "cuda", 10) == "coarsened"  # asked for: kept
    with pytest.raises(ConfigError, match="sim.p2g"):
        resolve("shared", "cpu")
    with pytest.raises(ConfigError, match="run_length"):
        MPMSolver([JELLY], n_grid=32, backend="cpu", p2g="coarsened", run_length=0)
    with pytest.raises(ConfigError, match="split"):
        MPMSolver([JELLY], n_grid=32, backend="cpu", p2g="coarsened", split=2)
    with pytest.raises(ConfigError, match="needs CUDA"):
        MPMSolver([JELLY], n_grid=32, backend="cpu", p2g="coarsened", run_length="warp")
    with pytest.raises(ConfigError, match="staged"):  # shared memory and a block barrier: CUDA only
        MPMSolver([JELLY], n_grid=32, backend="cpu", staged=True)
    s = _solver("atomic")
    assert s.staged is False  # the CPU stores directly


def test_batched_substeps_resort_where_single_substeps_do():
    """MPMSolver.substeps ends its ti.graph batches where the device re-sort is due: the same
    re-sorts and bit for bit the same state as single substeps (private grids: reproducible)."""
    a = _solver("coarsened", "private", resort_every=4)
    b = _solver("coarsened", "private", resort_every=4)
    for _ in range(2):  # 2 x 11 substeps: the re-sorts fall inside and across the calls
        for _ in range(11):
            a.substep(2e-4)
        b.substeps(11, 2e-4)
    assert a.sort_generation == b.sort_generation > 1
    sa, sb = a.get_state(), b.get_state()
    for k in ("x", "v", "C", "F"):
        assert np.array_equal(sa[k], sb[k]), k
    assert a.time == b.time


@pytest.mark.gpu
def test_warp_runs_match_atomic_on_cuda():
    """Warp-run P2G (a thread per particle, each warp's particles sorted by stencil base and
    runs summed by shuffles; CUDA) against the atomic transfer: the same grid after one
    substep and the same state after 40, with the data re-sorted every 4 substeps and never.
    The blocks also move 10 m/s along y (2.6 cells in all): the stored order spoils, so warps
    hold many bases out of order."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    from physgs_steps.mpm import p2g_sorted as P2G
    from physgs_steps.mpm.backend import ensure_taichi

    shift = np.array([0.0, 10.0, 0.0])

    def cuda_solver(mode, **kw):
        x, vol, mat, v = _two_blocks()
        s = MPMSolver([JELLY, SOFT], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, 0)), backend="cuda",
                      p2g=mode, **kw)
        s.set_particles(x, vol, mat)
        s.set_state(x, v + shift, np.zeros((len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
        return s

    try:
        ref = cuda_solver("atomic")
        runs = [cuda_solver("coarsened", run_length="warp", resort_every=4),
                cuda_solver("coarsened", run_length="warp", resort_every=0)]
        assert all(s.run_length == P2G.WARP and s._sorter is not None for s in runs)
        assert runs[0].n_particles % P2G.WARP_SIZE != 0  # a last warp with empty lanes
        for s in [ref] + runs:
            s.substep(2e-4)
        m_ref = ref.grid_m.to_numpy()[0]
        for s in runs:
            assert np.abs(s.grid_c.to_numpy()[0] - ref.grid_c.to_numpy()[0]).max() == 0
            assert np.abs(s.grid_m.to_numpy()[0] - m_ref).max() < 1e-6 * m_ref.max()
        for s in [ref] + runs:
            for _ in range(39):
                s.substep(2e-4)
        x, vol, mat, v = _two_blocks()
        v = v + shift
        a = ref.get_state()
        unsorted = runs[1]
        xs = unsorted.x.to_numpy()
        base = np.clip(np.floor(xs / unsorted.dx - 0.5).astype(np.int64), 0, unsorted.n_grid - 3)
        keys = (base[:, 0] * unsorted.n_grid + base[:, 1]) * unsorted.n_grid + base[:, 2]
        assert np.any(np.diff(keys) < 0)  # the stored order is spoilt: equal bases apart
        m = p_mass(vol, np.where(mat == 0, JELLY.density, SOFT.density))
        p0 = (m[:, None] * v).sum(0)
        for s in runs:
            b = s.get_state()
            for k, tol in (("x", 1e-6), ("v", 2e-5), ("C", 1e-4), ("F", 1e-5)):
                scale = max(1.0, float(np.abs(a[k]).max()))
                assert np.abs(a[k] - b[k]).max() < tol * scale, k
            p1 = (m[:, None] * b["v"]).sum(0)
            assert np.abs(p1 - p0).max() < 1e-4 * np.abs(m[:, None] * v).sum(0).max()
    finally:
        ensure_taichi("cpu")


@pytest.mark.gpu
def test_staged_stores_match_direct_stores_on_cuda():
    """G2P's stores staged through shared memory (staged.py, CUDA's default without rigid
    materials) against direct stores: the same state (x, v, C, F and the stress) after one
    substep and after 40, with the atomic and the warp-run transfers; the particle count is
    not a whole number of blocks (a last block with empty threads)."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("CUDA not available")
    from physgs_steps.mpm import staged as ST
    from physgs_steps.mpm.backend import ensure_taichi

    def cuda_solver(mode, staged):
        x, vol, mat, v = _two_blocks()
        s = MPMSolver([JELLY, SOFT], n_grid=32, dynamics=Dynamics.free(gravity=(0, 0, -9.8)), backend="cuda",
                      p2g=mode, staged=staged)
        s.set_particles(x, vol, mat)
        s.set_state(x, v, np.zeros((len(x), 3, 3)), np.broadcast_to(np.eye(3), (len(x), 3, 3)))
        return s

    try:
        for mode in ("atomic", "coarsened"):
            plain, staged = cuda_solver(mode, False), cuda_solver(mode, None)
            assert staged.staged and not plain.staged
            assert staged.n_particles % ST.STAGE_BLOCK != 0
            for n in (1, 39):
                for s in (plain, staged):
                    s.substeps(n, 2e-4)
                a, b = plain.get_state(), staged.get_state()
                # the transfers' float atomics add in any order: not bit for bit
                for k, tol in (("x", 1e-6), ("v", 2e-5), ("C", 1e-4), ("F", 1e-5)):
                    scale = max(1.0, float(np.abs(a[k]).max()))
                    assert np.abs(a[k] - b[k]).max() < tol * scale, (mode, n, k)
                ta, tb = plain.get_stress(), staged.get_stress()
                assert np.abs(ta - tb).max() < 1e-3 * np.abs(ta).max(), (mode, n)
                assert np.abs(tb).max() > 0  # stress stored, not left at zero
    finally:
        ensure_taichi("cpu")
