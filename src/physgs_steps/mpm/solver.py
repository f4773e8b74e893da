"""The MLS-MPM solver: particle state, grid, one substep (docs/CONTRACTS.md "MPM step").

Usage (arrays in DOMAIN UNITS, as stored in HDF5 and used by the torch pseudo-step)::

    from physgs_steps.mpm import MPMSolver, Material, preset, Dynamics
    s = MPMSolver([preset("jelly", name="bear")], n_grid=32, domain_size=1.0,
                  dynamics=Dynamics.free(), backend="cpu")
    s.set_particles(x, vol, material)        # x [P,3] in [0,1], vol [P] (domain units^3), material [P] int
                                             # (face=[P]: per-particle face offset, colliders.face_half_width)
    s.set_state(x, v, C, F)                  # optional: any state (v in domain units/s)
    s.substep(dt)                            # one step of dt seconds
    s.substeps(n, dt)                        # n of them (ti.graph batches: fewer host costs on CUDA)
    st = s.get_state()                       # {"x", "v", "C", "F"} float32, rows in input order

Inside, the solver works in SI units (x_phys = L x with L = ``domain_size`` metres,
``dx = L / n_grid``, ``p_vol = vol L^3``, ``p_mass = density p_vol``); C and F are unit-free
with respect to length.  Particles are stored sorted by grid cell (better cache and atomic
locality); ``get_state``/``set_state`` use the caller's order.

Time integration (docs/CONTRACTS.md "MPM step"): the particle velocities are staggered half a
substep behind the positions (leapfrog), so a constant body force is integrated exactly
whatever the number of substeps: the stored velocity is ``v_{n-1/2} = v_n - dt/2 g``; a
substep kicks it by ``dt (g + f/m)`` on the grid and drifts ``x`` with the result.  Before the
first substep, and whenever dt changes, every velocity is shifted by ``(dt_old - dt_new)/2 g``
(``dt_old`` = 0 for velocities set from outside).  Where a collider or wall holds a body, it
removes the kick on the grid as it removes any other velocity.  ``get_state`` returns
velocities at the frame time, ``v_n = v_{n-1/2} + dt/2 g``, and ``set_state`` takes them, so
``set_state(get_state())`` continues the same trajectory.

Initial APIC matrices: ``set_particles`` sets C to the velocity gradient that the APIC
transfer reproduces for the initial velocity field (:data:`AFFINE_ITERATIONS` P2G/G2P round
trips at fixed positions; exact for affine fields, zero for uniform ones), so a spinning or
vibrating body does not lose kinetic energy in its first substep (with C = 0 a block spinning
at 1 turn/s on a 16^3 grid kept 56% of it).
"""
from __future__ import annotations

import logging
import math
import os
from typing import Sequence

import numpy as np
import taichi as ti

from ..errors import ConfigError, InputError
from . import kernels as K
from . import p2g_sorted as P2G
from .backend import Launcher, ensure_taichi
from . import colliders
from . import rigid as rigid_mod
from .colliders import StaticGeometry
from .dynamics import BoundDynamics, Dynamics
from .materials import RIGID_KEY, Material

_log = logging.getLogger("physgs.mpm")

MAX_CHUNKS = 16  # CPU: at most this many private grids
AFFINE_ITERATIONS = 16  # APIC round trips that set the initial C (the error falls ~10x per 4; 1e-4 after 16)
STAT_COLUMNS = ("nonfinite", "j_min", "j_max", "speed_max", "outside")


class MPMSolver:
    """Multi-material MLS-MPM on a dense ``n_grid^3`` grid over ``[0, domain_size]^3`` metres.

    Args:
        materials: one :class:`Material` per instance; particle ``material`` indices refer to it.
        n_grid: grid nodes per axis (G).
        domain_size: metres per domain unit (L).
        dynamics: scene dynamics (default: gravity (0, 0, -9.8) and slip walls).
        backend: cpu | cuda | auto (Taichi arch).
        labels: instance label of each material (for ``instance: <label>`` references).
        sort_particles: store particles sorted by cell (faster; results equal up to float
            summation order).
        grid_mode: how P2G accumulates: ``private`` (one grid per CPU thread's chunk of
            particles, plain adds, reproducible), ``atomic`` (one grid, float atomics), or
            ``auto`` (private on the CPU, atomic on CUDA).
        p2g: how P2G writes the grid (p2g_sorted.py): ``atomic`` (every particle adds to its
            27 nodes), ``coarsened`` (a thread sums a run of consecutive particles with the
            same stencil base in registers and writes the nodes once per run; particles are
            re-sorted on the device every ``resort_every`` substeps), or ``auto``
            (p2g_sorted.AUTO per arch).  Results equal up to float summation order.
        run_length: coarsened P2G on one grid (CUDA): particles per thread, ``"cell"``: one
            thread per stencil-base cell of the last sort, or ``"warp"``: one thread per particle,
            each warp's particles sorted by base and runs summed across its lanes
            (p2g_sorted.py "warp runs"); ``"auto"``: p2g_sorted.RUN_AUTO per arch (warp on
            CUDA, RUN_LENGTH on the CPU).
        resort_every: coarsened P2G: substeps between device re-sorts (0: sort only at load;
            None: p2g_sorted.RESORT_EVERY, or RESORT_EVERY_WARP for warp runs).
        split: coarsened P2G with ``run_length`` particles per thread: threads per run (1, 3 or
            9), each summing its share of the 27 nodes (p2g_sorted.SPLITS); else unused.
        staged: G2P's new particle state stored through shared memory (staged.py): None (the
            default) on CUDA without a rigid material, False never; True outside CUDA (or with
            private grids) is a ConfigError. With a rigid material G2P stores directly.
        rigid_particles_per_cell: simulate each free rigid body with proxy particles, about this
            many per grid cell (rigid.py "Proxy particles"); None: with every particle.
    """

    def __init__(self, materials: Sequence[Material], *, n_grid: int = 32, domain_size: float = 1.0,
                 dynamics: Dynamics | None = None, backend: str = "cpu", labels: Sequence[int] | None = None,
                 sort_particles: bool = True, grid_mode: str = "auto", static: Sequence[StaticGeometry] = (),
                 p2g: str = "auto", run_length: int | str = "auto", resort_every: int | None = None,
                 split: int = P2G.SPLIT, staged: bool | None = None,
                 rigid_particles_per_cell: float | None = None):
        if not materials:
            raise ConfigError("materials", "at least one material is needed")
        if int(n_grid) < 8:
            raise ConfigError("sim.n_grid", f"must be >= 8, got {n_grid}")
        if not (domain_size > 0 and math.isfinite(domain_size)):
            raise ConfigError("sim.domain_size", f"must be a positive number of metres, got {domain_size}")
        if rigid_particles_per_cell is not None and (isinstance(rigid_particles_per_cell, bool) or not (
                isinstance(rigid_particles_per_cell, (int, float)) and 0 < rigid_particles_per_cell <= 64)):
            raise ConfigError("sim.rigid_particles_per_cell",
                              f"must be a number in (0, 64] or null (every particle), got {rigid_particles_per_cell!r}")
        self.rigid_particles_per_cell = None if rigid_particles_per_cell is None else float(rigid_particles_per_cell)
        self.materials = list(materials)
        self.labels = list(labels) if labels is not None else list(range(len(self.materials)))
        self.n_grid = int(n_grid)
        self.L = float(domain_size)
        self.dx = self.L / self.n_grid
        self.inv_dx = 1.0 / self.dx
        self.dynamics = dynamics if dynamics is not None else Dynamics.free()
        colliders.check_wall_margin(self.dynamics.wall_margin, self.n_grid)
        self._static_in = list(static)
        self.arch = ensure_taichi(backend)
        self.sort_particles = sort_particles
        if grid_mode not in ("auto", "private", "atomic"):
            raise ConfigError("grid_mode", f"must be auto, private or atomic, got {grid_mode!r}")
        self.private_grid = grid_mode == "private" or (grid_mode == "auto" and self.arch == "cpu")
        self.n_chunks = max(1, min(os.cpu_count() or 1, MAX_CHUNKS)) if self.private_grid else 1
        self._p2g_asked = p2g
        self.p2g = P2G.resolve(p2g, self.arch)  # again in load_particles, with the particle count
        if run_length == "auto":
            run_length = P2G.RUN_AUTO[self.arch]
        run_length = {"cell": P2G.CELL, "warp": P2G.WARP}.get(run_length, run_length)
        if resort_every is None:
            resort_every = P2G.RESORT_EVERY_WARP if run_length == P2G.WARP else P2G.RESORT_EVERY
        if not isinstance(run_length, int) or (run_length < 1 and run_length not in (P2G.CELL, P2G.WARP)) \
                or int(resort_every) < 0:
            raise ConfigError("p2g", f"run_length must be >= 1, 'cell' or 'warp' and resort_every >= 0, got "
                                     f"{run_length!r}, {resort_every!r}")
        if run_length == P2G.WARP and self.arch != "cuda":
            raise ConfigError("p2g", f"run_length 'warp' needs CUDA (warp shuffles), the backend is {self.arch}")
        if split not in P2G.SPLITS:
            raise ConfigError("p2g", f"split must be one of {', '.join(map(str, P2G.SPLITS))}, got {split!r}")
        self.run_length = run_length
        self.resort_every = int(resort_every)
        self.split = int(split)
        if staged and (self.arch != "cuda" or self.private_grid):
            raise ConfigError("staged", f"staged G2P stores need CUDA and one grid, the backend is {self.arch}")
        self._staged_asked = staged  # None: CUDA without rigid materials (staged.py); resolved with the particles
        self.staged = False
        self._sorter = None  # coarsened P2G: the device sort (p2g_sorted.DeviceSort)
        self._since_sort = 0
        self.sort_generation = 0  # counts device re-sorts (storage order changes)
        self.combos = tuple(sorted({m.kernel_key for m in self.materials}))
        self.time = 0.0
        self._stagger = 0.0  # dt the stored velocities are staggered with (v_{n-1/2} = v_n - dt/2 g)
        self.n_particles = 0
        self.bound: BoundDynamics | None = None
        self._k = None
        self._batches = None
        self._kc = K.build_constitutive(self.combos)
        self._upload_materials()

    # ------------------------------------------------------------------ set-up
    def set_particles(self, x: np.ndarray, vol: np.ndarray, material: np.ndarray,
                      velocity: np.ndarray | None = None, face: np.ndarray | None = None) -> None:
        """Load particles at rest (F = I, C = 0) with their initial velocities.

        The particles of a fixed rigid instance do not enter the MPM: they become static
        geometry (a level-set collider, colliders.py) and keep their place in every state
        returned.  Each free rigid instance becomes one rigid body (rigid.py); with
        ``rigid_particles_per_cell`` it is simulated with proxy particles and its rows follow
        its rigid motion in every state returned (rigid.py "Proxy particles").

        Args:
            x: [P, 3] positions in domain units (inside the domain walls).
            vol: [P] particle volumes in domain units^3 (> 0).
            material: [P] int, index into ``materials``.
            velocity: [P, 3] initial velocities in m/s; default: each material's ``velocity``
                then the dynamics' ``initial_velocity`` overrides.
            face: [P] how far in front of its centre each particle's face lies, domain units
                (>= 0; where contact with an obstacle starts, colliders.py "Boundary
                placement"); default ``colliders.face_half_width(vol)``, half the side of a
                cube of its volume (lattice material); 0 for particles on the material's
                surface (a reconstruction's visible gaussians).  Proxy particles of rigid
                bodies take the default (rigid particles do not use it).
        """
        x = _as_array(x, np.float64, (None, 3), "x")
        P = len(x)
        vol = _as_array(vol, np.float64, (P,), "vol")
        material = _as_array(material, np.int64, (P,), "material")
        if P == 0:
            raise InputError("particles", "no particles to simulate")
        if material.min() < 0 or material.max() >= len(self.materials):
            raise InputError("particles", f"material index out of range 0..{len(self.materials) - 1}")
        if np.any(vol <= 0):
            raise InputError("particles", "particle volumes must be > 0")
        face = colliders.face_half_width(vol) if face is None else _as_array(face, np.float64, (P,), "face")
        if np.any(face < 0):
            raise InputError("face", "particle face offsets must be >= 0")
        fixed_k = [k for k, m in enumerate(self.materials) if m.fixed]
        fixed = np.isin(material, fixed_k)
        if fixed.all():
            raise InputError("particles", "every instance is fixed (static geometry): nothing to simulate")
        self._check_inside(x[~fixed])
        names = [m.name for m in self.materials]
        if velocity is None:
            base = np.array([m.velocity for m in self.materials], np.float64)
            velocity = self.dynamics.initial_velocities(x, material, base, names, self.labels)
        velocity = _as_array(velocity, np.float64, (P, 3), "velocity")
        # fixed instances -> static geometry; the rest is simulated
        self._n_input = P
        self._vol_in, self._mat_in = vol, material  # the full sets of bodies with proxies (set_materials)
        self._static_rows = np.flatnonzero(fixed)
        self._x_static = x[fixed].astype(np.float32)
        self._static_fixed = [StaticGeometry(x[material == k], spacing=float(np.median(vol[material == k])) ** (1 / 3),
                                             surface=self.materials[k].surface, friction=self.materials[k].friction,
                                             name=self.materials[k].name)
                              for k in fixed_k if np.any(material == k)]
        bound = self.dynamics.bind(x, material, names, self.labels, self.L)
        # free rigid bodies with proxy particles (rigid.py "Proxy particles"): their rows are not
        # simulated, each proxy (row -1) stands for a group of them
        sim_rows, pxs, pvol, pmat, pact, self._proxy_full = self._proxies(x, vol, material, fixed, bound.act_bits)
        self._sim_rows = np.r_[sim_rows, np.full(len(pxs), -1, np.int64)]
        xs = np.r_[x[sim_rows], pxs]
        ms = np.r_[material[sim_rows], pmat]
        self._mat_pre = ms
        vs = np.r_[vol[sim_rows], pvol]
        fs = np.r_[face[sim_rows], colliders.face_half_width(pvol)]
        self.bound = BoundDynamics(**{**bound.__dict__, "act_bits": np.r_[bound.act_bits[sim_rows], pact]})
        perm = self._sort_order(xs) if self.sort_particles else np.arange(len(xs))
        Ps = len(xs)
        self.n_particles = Ps
        self._allocate(Ps)
        self._order.from_numpy(perm.astype(np.int32))
        self._perm = perm
        self._mat.from_numpy(ms[perm].astype(np.int32))
        self._act_bits.from_numpy(self.bound.act_bits[perm])
        p_vol = vs[perm] * self.L ** 3
        density = np.array([m.density for m in self.materials])[ms[perm]]
        self._p_vol.from_numpy(p_vol.astype(np.float32))
        self._p_face.from_numpy((fs[perm] * self.L).astype(np.float32))
        p_mass = (p_vol * density).astype(np.float32)
        self._p_mass.from_numpy(p_mass)
        self._dyn = _ndarray_from(self.bound.table, ti.f32)
        self._setup_static()
        self.p2g = P2G.resolve(self._p2g_asked, self.arch, self.n_particles)
        if self.p2g == "coarsened" and any(m.rigid and not m.fixed for m in self.materials):
            # the coarsened transfer does not deposit the rigid bodies' own grids (grid_r, grid_rm,
            # grid_rv: the moving-collider coupling); with a free rigid body the atomic one runs
            self.p2g = "atomic"
        self._sorting = self.p2g == "coarsened" and self._can_resort()
        run = self.run_length if self.p2g == "coarsened" and not self.private_grid else 0  # else unused: one build
        if run == P2G.CELL and not self._sorting:
            run = P2G.RUN_LENGTH  # cells need the device sort's ranges
        # staged G2P stores (staged.py): CUDA, one grid, no rigid material (rigid.py sets its F and tau)
        can_stage = self.arch == "cuda" and not self.private_grid and RIGID_KEY not in self.combos
        self.staged = can_stage and self._staged_asked is not False
        spec = K.Spec(self.combos, *self.bound.spec(), bool(self._static_geoms), self.private_grid, p2g=self.p2g,
                      run=run, split=self.split if run > 0 else 1, staged=self.staged)
        self._k = K.build(spec)
        self._launch_substep = Launcher(self._k.substep)  # backend.Launcher: no per-call argument processing
        self._batches = None  # substeps(): ti.graph batches of the substep kernel (_Batches), built on first use
        self._launch_substep_b = Launcher(self._k.substep)  # its second part with free rigid bodies (substep)
        self._setup_rigid(xs[perm] * self.L, p_mass.astype(np.float64), ms[perm], self._full_sets(x, vol, material))
        eye = np.broadcast_to(np.eye(3), (P, 3, 3))
        self.set_state(x, velocity / self.L, np.zeros((P, 3, 3)), eye)
        if np.ptp(velocity, axis=0).max() > 0:  # a non-uniform field: C = its APIC velocity gradient
            self.init_affine()
        self.time = 0.0
        self._sorter = None
        self._cell_start = _ndarray_from(np.array([0, self.n_particles], np.int32), ti.i32)  # read with CELL runs only
        if self._sorting:
            self._sorter = P2G.DeviceSort(self.n_particles, self.n_grid, self.arch)
            self._cell_start = self._sorter.count
            self.resort()

    # ------------------------------------------------------------------ storage order
    @property
    def _perm(self) -> np.ndarray:
        """[P] the caller's row of each storage slot (particles are stored sorted; a device
        re-sort changes it: read back from ``_order`` when needed)."""
        if self._perm_gen != self.sort_generation:
            self._perm_np = self._order.to_numpy().astype(np.int64)
            self._perm_gen = self.sort_generation
        return self._perm_np

    @_perm.setter
    def _perm(self, value: np.ndarray) -> None:
        self._perm_np = np.asarray(value, np.int64)
        self._perm_gen = self.sort_generation

    def _can_resort(self) -> bool:
        """Whether the storage order may change on the device (not with sort_particles off, nor
        with free rigid instances: rigid.RigidBodies keeps their particles' storage slots)."""
        return self.sort_particles and not any(m.rigid and not m.fixed for m in self.materials)

    def resort(self) -> None:
        """Re-sort the particles by stencil base node on the device (coarsened P2G; a no-op
        otherwise).  Rows in ``get_state`` etc. stay in the caller's order."""
        if self._sorter is None:
            return
        self._sorter.sort(self)
        self.sort_generation += 1
        self._since_sort = 0

    def _proxies(self, x: np.ndarray, vol: np.ndarray, material: np.ndarray, fixed: np.ndarray,
                 act_bits: np.ndarray) -> tuple:
        """The proxy particles of the free rigid bodies (rigid.py "Proxy particles"), with
        ``rigid_particles_per_cell`` set: the particles of a body grouped by cubes of edge
        dx / rigid_particles_per_cell^(1/3) (and action bits), one proxy per group at its
        centre of volume (the body's density is uniform: its centre of mass) carrying its
        volume.  A body keeps its full set where that would not make it smaller or its proxies
        could not carry its inertia (rigid.moment_match).  Returns (rows simulated as
        themselves [S] (input rows, ascending), proxy x [Q, 3] (domain units), vol [Q],
        material [Q], action bits [Q], {material index: its full set's input rows})."""
        keep = ~fixed
        px, pv, pm, pa, full = [], [], [], [], {}
        if self.rigid_particles_per_cell is not None:
            edge = 1.0 / (self.n_grid * self.rigid_particles_per_cell ** (1.0 / 3.0))  # domain units
            for k, m in enumerate(self.materials):
                rows = np.flatnonzero(material == k)
                if not (m.rigid and not m.fixed) or len(rows) < 8:
                    continue
                g = rigid_mod.proxy_groups(x[rows], act_bits[rows], edge)
                n = int(g.max()) + 1
                if n >= len(rows):
                    continue
                w = vol[rows]
                W = np.bincount(g, w, n)
                xg = np.stack([np.bincount(g, w * x[rows, d], n) for d in range(3)], 1) / W[:, None]
                cf = (w[:, None] * x[rows]).sum(0) / w.sum()
                if rigid_mod.moment_match(xg - cf, W, x[rows] - cf, w) is None:
                    continue  # too small or flat for proxies: every particle
                act = np.zeros(n, act_bits.dtype)
                act[g] = act_bits[rows]
                px.append(xg)
                pv.append(W)
                pm.append(np.full(n, k, np.int64))
                pa.append(act)
                full[k] = rows
                keep[rows] = False
        if not px:
            return np.flatnonzero(keep), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64), \
                np.zeros(0, act_bits.dtype), {}
        return np.flatnonzero(keep), np.concatenate(px), np.concatenate(pv), np.concatenate(pm), \
            np.concatenate(pa), full

    def _full_sets(self, x: np.ndarray, vol: np.ndarray, material: np.ndarray) -> dict:
        """{material index: (x [n, 3] m, mass [n] kg)} of the full sets of the bodies simulated
        with proxies (input arrays in domain units; rows ``_proxy_full``)."""
        out = {}
        for k, rows in self._proxy_full.items():
            mass = (vol[rows] * self.L ** 3 * self.materials[k].density).astype(np.float32).astype(np.float64)
            out[k] = (np.asarray(x[rows], np.float64) * self.L, mass)
        return out

    def _setup_rigid(self, xs: np.ndarray, mass: np.ndarray, mat_sorted: np.ndarray, full: dict | None = None) -> None:
        """One rigid body per free rigid instance (storage order arrays: xs [P, 3] m, mass [P] kg;
        ``full``: the full sets of the bodies with proxies, :meth:`_full_sets`)."""
        full = full or {}
        free = [k for k, m in enumerate(self.materials) if m.rigid and not m.fixed and np.any(mat_sorted == k)]
        self._rigid_k = free
        self.rigid = None
        # per body: the input rows of its full set where it runs with proxies (their state is the
        # body's rigid motion: _proxy_rows), else None
        self._body_rows = [self._proxy_full.get(k) for k in free]
        mbody = np.full(len(self.materials), -1, np.int32)
        mbody[free] = np.arange(len(free), dtype=np.int32)
        self._mbody = _ndarray_from(mbody, ti.i32)
        nb = max(len(free), 1)
        G, T = self.n_grid, self.n_chunks
        # the kernels carry the rigid grid passes whenever a material is rigid (fixed ones
        # included: the kernel key is per material), so the grids are full-size then
        grids = bool(free) or RIGID_KEY in self.combos
        self.grid_r = ti.ndarray(ti.i32, (T, G, G, G) if grids else (1, 1, 1, 1))
        self._gpart = ti.ndarray(ti.f64, (G * G + G if grids else 1, nb, K.N_GSUM))  # per column, slab, body: grid sums
        self.grid_rm = ti.ndarray(ti.f32, (T, G, G, G) if grids else (1, 1, 1, 1))  # rigid mass per node
        self.grid_rv = ti.ndarray(K.vec3, (T, G, G, G) if grids else (1, 1, 1, 1))  # rigid momentum, velocity
        # per body: centre, V, omega of its grid field; covering mass; the field's mass, inertia; the
        # body's friction; the reaction of the soft material it meets (momentum, angular momentum)
        gbody = np.zeros((nb, 33))  # ... its centre in its initial pose (its level set's frame); last reaction
        gbody[: len(free), 9] = [colliders.COVER * self.materials[k].density * self.dx ** 3 for k in free]
        gbody[: len(free), 17] = [self.materials[k].friction for k in free]
        if free:
            bodies = [np.flatnonzero(mat_sorted == k) for k in free]
            chunks = rigid_mod.reduce_chunks(self.arch, self.n_chunks, sum(len(i) for i in bodies) +
                                             sum(len(full[k][1]) for k in free if k in full))
            self.rigid = rigid_mod.RigidBodies(bodies, xs, mass, self.dx, chunks, [self.materials[k].name for k in free],
                                               rigid_mod.contact_solve(self.arch), full=[full.get(k) for k in free])
            gbody[: len(free), 24:27] = self.rigid._c0
            # per body its level set in its initial pose (the soft material's contact, kernels.py
            # _body_contact): from its full set of particles
            # (the spacing a point stands for from the particles' volumes, as for fixed instances)
            phis = []
            for k, i in zip(free, bodies):
                pts, pm = (full[k][0], full[k][1]) if k in full else (xs[i], mass[i])
                spacing = float(np.median(pm / self.materials[k].density)) ** (1 / 3) / self.L
                geom = StaticGeometry(pts / self.L, spacing=spacing, name=self.materials[k].name)
                phis.append(colliders.level_set(geom, G, self.L))
            self._bphi = _ndarray_from(np.stack(phis), ti.f32)
            self._bpose = (self.rigid.body_c, self.rigid.body_R)
            bd = self.bound
            self._kr = rigid_mod.build(bd.counts, bd.boundary, bool(self._static_geoms), self.private_grid)
            self._launch_reduce, self._launch_scatter = Launcher(self._kr.reduce), Launcher(self._kr.scatter)
            self._launch_contacts = Launcher(self._kr.reduce)  # its contacts-only instance (substep)
        else:
            self._bphi = ti.ndarray(ti.f32, (1, 1, 1, 1))
            self._bpose = (ti.ndarray(rigid_mod.vec3d, 1), ti.ndarray(rigid_mod.mat3d, 1))
        self._gbody = _ndarray_from(gbody, ti.f64)  # once, complete (the bodies' initial centres above)

    def init_affine(self, iterations: int = AFFINE_ITERATIONS) -> None:
        """Set every particle's C to the velocity gradient the APIC transfer reproduces for the
        current velocities (P2G/G2P round trips at fixed positions, velocities unchanged)."""
        self._require_particles()
        for _ in range(iterations):
            K.affine_transfer(self.x, self.v, self.C, self._p_mass, self.grid_v, self.grid_m, float(self.dx),
                              self.arch == "cpu")  # CPU: reproducible sums (one thread)
        self._box_full()  # it wrote the whole grid

    def set_materials(self, materials: Sequence[Material]) -> None:
        """Replace material parameters (same models per index) without recompiling; recomputes
        masses and stresses."""
        if [m.kernel_key for m in materials] != [m.kernel_key for m in self.materials]:
            raise ConfigError("materials", "set_materials keeps each index's elasticity/plasticity models and fracture")
        old_rho = np.array([m.density for m in self.materials])
        self.materials = list(materials)
        self._upload_materials()
        if self.n_particles:
            mat = self._mat.to_numpy()
            rho = np.array([m.density for m in self.materials])
            self._p_mass.from_numpy((self._p_mass.to_numpy() * (rho / old_rho)[mat]).astype(np.float32))
            if self.rigid is not None and not np.allclose(rho, old_rho):
                st = self.get_state()
                x0 = self.x.to_numpy().astype(np.float64)
                self._setup_rigid(x0, self._p_mass.to_numpy().astype(np.float64), mat,
                                  self._full_sets(st["x"], self._vol_in, self._mat_in))
                self.set_state(st["x"], st["v"], st["C"], st["F"])
            self._update_stress()

    def _upload_materials(self) -> None:
        table = np.stack([m.table_row() for m in self.materials]).astype(np.float32)
        self._mparams = _ndarray_from(table, ti.f32)
        combo = np.array([self.combos.index(m.kernel_key) for m in self.materials], np.int32)
        self._mcombo = _ndarray_from(combo, ti.i32)

    def _allocate(self, P: int) -> None:
        G = self.n_grid
        self.x = ti.ndarray(K.vec3, P)
        self.v = ti.ndarray(K.vec3, P)
        self.C = ti.ndarray(K.mat3, P)
        self.F = ti.ndarray(K.mat3, P)
        self.tau = ti.ndarray(K.mat3, P)
        self.ep = ti.ndarray(ti.f32, P)
        self._p_vol = ti.ndarray(ti.f32, P)
        self._p_face = ti.ndarray(ti.f32, P)  # m: the face's distance in front of the centre (contact)
        self._p_mass = ti.ndarray(ti.f32, P)
        self._mat = ti.ndarray(ti.i32, P)
        self._act_bits = ti.ndarray(ti.i32, P)
        self._order = ti.ndarray(ti.i32, P)  # the caller's row of each storage slot
        T = self.n_chunks
        self.grid_v = ti.ndarray(K.vec3, (T, G, G, G))
        self.grid_m = ti.ndarray(ti.f32, (T, G, G, G))
        self.grid_c = ti.ndarray(ti.f32, (T, G, G, G))  # 1 where a particle touching an obstacle transfers
        self.grid_b = ti.ndarray(K.vec3, (G, G, G))  # grid velocities after the boundary conditions
        # FLIP materials (materials.FLIP_RATIO): the pre-force momenta of the substep's P2G, a grid per
        # chunk like grid_v (summed into chunk 0 in the grid update: reproducible on the CPU)
        self.grid_o = ti.ndarray(K.vec3, (T, G, G, G) if K.uses_flip(self.combos) else (1, 1, 1, 1))
        self.grid_r = ti.ndarray(ti.i32, (1, 1, 1, 1))  # rigid bodies: 1 + the body covering a node (_setup_rigid)
        self.grid_rm = ti.ndarray(ti.f32, (1, 1, 1, 1))
        self.grid_rv = ti.ndarray(K.vec3, (1, 1, 1, 1))
        self._err = ti.ndarray(ti.i32, 4)
        self._err.from_numpy(np.zeros(4, np.int32))
        # the node box of the substep kernel (kernels.py): rows cur, previous, union, per chunk
        self._box = ti.ndarray(ti.i32, (3 + T, 6))
        self._box_full()
        # kernels.frame_stats: the STAT_COLUMNS, then the clamped count (row 0) in two columns
        self._stats = ti.ndarray(ti.f32, (len(self.materials), len(STAT_COLUMNS) + 2))
        self._launch_stats = Launcher(K.frame_stats)
        self._backup = None

    def _box_full(self) -> None:
        """Mark the whole grid as last substep's node box, so the next substep clears all of it
        (after the grids were made or written by another kernel)."""
        G = self.n_grid
        self._box.from_numpy(np.tile(np.array([0, 0, 0, G, G, G], np.int32), (self._box.shape[0], 1)))

    def _sort_order(self, x: np.ndarray) -> np.ndarray:
        """[P] permutation sorting particles by grid cell (row-major in (x, y, z))."""
        cell = np.clip(np.floor(x * self.n_grid).astype(np.int64), 0, self.n_grid - 1)
        key = (cell[:, 0] * self.n_grid + cell[:, 1]) * self.n_grid + cell[:, 2]
        return np.argsort(key, kind="stable")

    def _check_inside(self, x: np.ndarray) -> None:
        m = float(self.dynamics.wall_margin)
        out = np.any((x < m) | (x > 1.0 - m), axis=1)
        if out.any():
            raise InputError("particles", f"{int(out.sum())} particles lie outside the simulation domain "
                                          f"[{m:.4f}, {1.0 - m:.4f}]^3 (domain units: the domain walls stand "
                                          f"dynamics.wall_margin = {m:g} inside the unit cube)")

    def _setup_static(self) -> None:
        """The level-set grid of the static geometry (colliders.py): the solver's ``static``
        argument plus the fixed instances."""
        self._static_geoms = list(self._static_in) + list(self._static_fixed)
        phi, owner, rows = colliders.merge(self._static_geoms, self.n_grid, self.L)
        self._lvl_phi = _ndarray_from(phi, ti.f32)
        self._lvl_id = _ndarray_from(owner, ti.i32)
        self._lvl_rows = _ndarray_from(rows, ti.f32)

    # ------------------------------------------------------------------ state
    def set_state(self, x: np.ndarray, v: np.ndarray, C: np.ndarray, F: np.ndarray,
                  ep: np.ndarray | None = None) -> None:
        """Set the state (domain units: x [P,3], v [P,3] in domain units/s at the state's time,
        C [P,3,3] in 1/s, F [P,3,3]; rows in the order given to set_particles) and recompute the
        stresses.  The next substep staggers the velocities by half its dt (module docstring).
        ``ep`` [P]: accumulated inelastic strain of tearing materials (default 0, intact).
        Rows of fixed instances are ignored (static geometry stays where it was loaded); each
        rigid body takes the pose and motion that best fit its particles' state (all its rows,
        where it runs with proxies; the proxies are then put on that motion)."""
        self._require_particles()
        P = self._n_input
        x = _as_array(x, np.float64, (P, 3), "x")
        v = _as_array(v, np.float64, (P, 3), "v")
        C = _as_array(C, np.float64, (P, 3, 3), "C")
        F = _as_array(F, np.float64, (P, 3, 3), "F")
        p = self._sim_rows[self._perm]  # -1: a proxy (its state follows from its body's)
        q = np.maximum(p, 0)
        self.x.from_numpy((x[q] * self.L).astype(np.float32))
        self.v.from_numpy((v[q] * self.L).astype(np.float32))
        self.C.from_numpy(C[q].astype(np.float32))
        self.F.from_numpy(F[q].astype(np.float32))
        ep = np.zeros(P) if ep is None else _as_array(ep, np.float64, (P,), "ep")
        self.ep.from_numpy(np.where(p >= 0, ep[q], 0.0).astype(np.float32))
        self._stagger = 0.0
        if self.rigid is not None:
            full = [None if r is None else (x[r] * self.L, v[r] * self.L, C[r], F[r]) for r in self._body_rows]
            self.rigid.fit_state(x[q] * self.L, v[q] * self.L, C[q], F[q], self._p_mass.to_numpy(), full)
            if self.rigid.proxies:  # the proxies (and every rigid particle) onto the fitted motion
                rb = self.rigid
                self._launch_scatter(self.x, self.v, self.C, self.F, self.tau, rb.rb_p, rb.rb_b, rb.rb_r0, rb.body_c,
                                     rb.body_R, rb.body_V, rb.body_w, rb.body_K)
        self._update_stress()

    def _full(self, a: np.ndarray, static_value, proxied=None) -> np.ndarray:
        """Storage-order rows ``a`` [P_sim, ...] -> input order [P, ...] with the static rows
        (fixed instances) set to ``static_value`` (an array [P_static, ...] or a scalar) and
        the rows of bodies simulated with proxies to ``proxied`` ([(rows, values)])."""
        out = np.empty((self._n_input,) + a.shape[1:], a.dtype)
        rows = self._sim_rows[self._perm]
        real = rows >= 0
        out[rows[real]] = a[real]
        out[self._static_rows] = static_value
        for r, val in proxied or ():
            out[r] = val
        return out

    def _proxied_state(self) -> list:
        """Per body with proxies: (its full set's input rows, x [n, 3] m, v [n, 3] m/s (staggered
        as stored), C [3, 3], F [3, 3], body index): the body's rigid motion
        (rigid.RigidBodies.full_motion)."""
        if self.rigid is None or not self.rigid.proxies:
            return []
        st = self.rigid.state()
        return [(rows, *self.rigid.full_motion(b, st), b) for b, rows in enumerate(self._body_rows) if rows is not None]

    def get_state(self) -> dict:
        """{"x", "v", "C", "F", "ep"}: float32 arrays in domain units, rows in input order; v is
        the velocity at the state's time (the stored half-step velocity plus dt/2 g); ep the
        accumulated inelastic strain of tearing materials (0 elsewhere).  The rows of fixed
        instances: their initial position, v = 0, C = 0, F = I, ep = 0.  The rows of a body
        simulated with proxies: its rigid motion, x = c + R r0, v = V + omega x r, C = [omega]x,
        F = R K, ep = 0 (as rigid.py's scatter sets its particles)."""
        self._require_particles()
        inv = np.float32(1.0 / self.L)
        v = self.v.to_numpy()
        shift = 0.5 * self._stagger * self.bound.gravity.astype(np.float64)
        if self._stagger != 0.0:
            v = v + shift.astype(np.float32)
        px = self._proxied_state()
        return {"x": self._full(self.x.to_numpy() * inv, self._x_static, [(r, x / self.L) for r, x, _v, _C, _F, _b in px]),
                "v": self._full(v * inv, 0.0, [(r, (v_ + shift) / self.L) for r, _x, v_, _C, _F, _b in px]),
                "C": self._full(self.C.to_numpy(), 0.0, [(r, C_) for r, _x, _v, C_, _F, _b in px]),
                "F": self._full(self.F.to_numpy(), np.eye(3, dtype=np.float32),
                                [(r, F_) for r, _x, _v, _C, F_, _b in px]),
                "ep": self._full(self.ep.to_numpy(), 0.0, [(r, 0.0) for r, *_ in px])}

    def get_stress(self) -> np.ndarray:
        """[P, 3, 3] Kirchhoff stress (Pa) of the current F, rows in input order."""
        return self._full(self.tau.to_numpy(), 0.0, [(r, 0.0) for r in self._body_rows if r is not None])

    @property
    def n_input(self) -> int:
        """Rows of the particle set given to set_particles (simulated + static)."""
        return self._n_input

    def proxy_count(self, k: int) -> int | None:
        """Proxy particles simulating material ``k``'s rigid body (rigid.py "Proxy particles"), or
        None where every particle of it is simulated."""
        if k not in self._proxy_full:
            return None
        return int(np.count_nonzero((self._sim_rows < 0) & (np.r_[self._mat_pre] == k)))

    def proxy_total(self) -> int:
        """Proxy particles of all rigid bodies (rigid.py "Proxy particles")."""
        return int(np.count_nonzero(self._sim_rows < 0))

    def roles(self) -> list[str]:
        """Per material: ``deformable``, ``rigid`` (free rigid body) or ``fixed`` (static geometry)."""
        return [m.role for m in self.materials]

    def _update_stress(self) -> None:
        self._kc.stress(self.F, self._mat, self._mparams, self._mcombo, self.ep, self.tau)

    # ------------------------------------------------------------------ constitutive models alone
    def kirchhoff(self, F: np.ndarray, material: np.ndarray) -> np.ndarray:
        """Kirchhoff stress [N, 3, 3] (Pa) of deformation gradients ``F`` [N, 3, 3] under the
        materials ``material`` [N] (indices into ``materials``); no particles needed."""
        F, material = self._constitutive_args(F, material)
        out = ti.ndarray(K.mat3, len(F))
        self._kc.stress(_ndarray_from(F, K.mat3), _ndarray_from(material, ti.i32), self._mparams, self._mcombo,
                        _ndarray_from(np.zeros(len(F), np.float32), ti.f32), out)
        return out.to_numpy()

    def return_map(self, F_trial: np.ndarray, material: np.ndarray, ep: np.ndarray | None = None,
                   with_ep: bool = False) -> tuple:
        """The G2P constitutive update: (F, tau) [N, 3, 3] after the return map of ``F_trial``
        [N, 3, 3] under ``material`` [N], tau being the stress of the returned F; with
        ``with_ep`` also the updated accumulated inelastic strain [N] (input ``ep``, default 0)."""
        F_trial, material = self._constitutive_args(F_trial, material)
        F_out, tau = ti.ndarray(K.mat3, len(F_trial)), ti.ndarray(K.mat3, len(F_trial))
        ep_arr = _ndarray_from(np.zeros(len(F_trial), np.float32) if ep is None else np.asarray(ep, np.float32), ti.f32)
        self._kc.update(_ndarray_from(F_trial, K.mat3), _ndarray_from(material, ti.i32), self._mparams,
                        self._mcombo, ep_arr, F_out, tau)
        if with_ep:
            return F_out.to_numpy(), tau.to_numpy(), ep_arr.to_numpy()
        return F_out.to_numpy(), tau.to_numpy()

    def _constitutive_args(self, F, material):
        F = _as_array(F, np.float32, (None, 3, 3), "F")
        material = _as_array(material, np.int32, (len(F),), "material")
        if len(F) == 0:
            raise InputError("F", "empty")
        if material.min() < 0 or material.max() >= len(self.materials):
            raise InputError("material", f"index out of range 0..{len(self.materials) - 1}")
        return F, material

    def _require_particles(self) -> None:
        if self._k is None:
            raise RuntimeError("call set_particles() first")

    # ------------------------------------------------------------------ stepping
    def _begin_substep(self, dt: float) -> float:
        """What comes before a substep of ``dt``: the leapfrog stagger (when dt changed) and the
        device re-sort (when due); returns the damping factor of ``dt``."""
        self._require_particles()
        b = self.bound
        if dt != self._stagger:  # leapfrog: stagger the velocities by half of this dt
            shift = 0.5 * (self._stagger - dt) * b.gravity.astype(np.float64)
            K.add_velocity(self.v, float(shift[0]), float(shift[1]), float(shift[2]))
            self._stagger = dt
        if self._sorter is not None and self.resort_every > 0 and self._since_sort >= self.resort_every:
            self.resort()
        return math.exp(-b.damping * dt) if b.damping > 0 else 1.0

    def _substep_args(self, dt: float, damp: float) -> tuple:
        """The substep kernel's arguments but ``part`` (kernels.build's ``substep``)."""
        b = self.bound
        return (self.x, self.v, self.C, self.F, self.tau, self.ep, self._p_vol, self._p_face, self._p_mass, self._mat,
                self._act_bits, self.grid_v, self.grid_m, self.grid_c, self.grid_b, self.grid_o, self.grid_r,
                self.grid_rm, self.grid_rv, self._mbody, self._gpart, self._gbody, self._bphi, *self._bpose, self._mparams, self._mcombo, self._dyn,
                self._lvl_phi, self._lvl_id, self._lvl_rows, self._err, self._box, float(dt), float(self.time),
                float(self.dx), float(b.wall_margin), float(b.gravity[0]), float(b.gravity[1]), float(b.gravity[2]),
                float(damp), self._cell_start)

    def substeps(self, n: int, dt: float) -> None:
        """Advance by ``n`` substeps of ``dt`` seconds: the same as ``n`` calls of :meth:`substep`
        (the same kernel code with the same arguments and times, so the same state bit for bit on
        the CPU).

        Without free rigid bodies the substeps go to Taichi in batches, each one call of a
        ``ti.graph`` that holds 1, 2, 4, ... 32 launches (:class:`_Batches`): Taichi's C++ then
        sets the arguments of each launch, instead of Python (about 40 arguments a launch; the
        per-launch host time that leaves the GPU idle between a small scene's kernels, README
        "GPU").  Each launch runs R substeps (:func:`reps_per_launch`, ``PHYSGS_TI_REPS``; the
        remainder of a batch one a launch), so Taichi's fixed and per-argument work of a launch
        is paid once per R substeps.  A batch ends where the device re-sort is due.
        ``PHYSGS_TI_GRAPH=0`` runs them one by one."""
        n = int(n)
        if n <= 0:
            return
        if self.rigid is not None or self._batches is False or not batches_enabled():
            for _ in range(n):
                self.substep(dt)
            return
        reps = reps_per_launch(self.arch)
        done = 0
        while done < n:
            damp = self._begin_substep(dt)
            m = n - done
            if self._sorter is not None and self.resort_every > 0:
                m = min(m, self.resort_every - self._since_sort)
            if self._batches is None:
                try:
                    self._batches = _Batches(self._k, self._substep_args(dt, damp))
                except Exception as e:  # pragma: no cover - Taichi without the graph API used here
                    _log.warning("substep batches unavailable (%s: %s): one launch a substep", type(e).__name__, e)
                    self._batches = False
                    for _ in range(n - done):
                        self.substep(dt)
                    return
            self.time = self._batches.run(self._substep_args(dt, damp), m, self.time, dt, reps)
            self._since_sort += m
            done += m

    def substeps_per_launch(self) -> int:
        """Substeps in each launch of :meth:`substeps`' batches: R (:func:`reps_per_launch`), or
        1 where it runs them one by one (free rigid bodies, ``PHYSGS_TI_GRAPH=0``)."""
        if self.rigid is not None or self._batches is False or not batches_enabled():
            return 1
        return reps_per_launch(self.arch)

    def substep(self, dt: float) -> None:
        """Advance by one substep of ``dt`` seconds (CONTRACTS.md step plus scene dynamics)."""
        damp = self._begin_substep(dt)
        b = self.bound
        self._since_sort += 1
        args = self._substep_args(dt, damp)
        if self.rigid is None:
            self._launch_substep(*args, 0)
        else:
            # free rigid bodies (rigid.py "Coupling"): their contacts (from the pose at the start of
            # the substep), the MPM up to their grid fields, the contact solve on those fields, the
            # rest of the MPM (covered nodes move with the solved fields), then the bodies' own
            # momentum from their particles, the contact solve again and the move
            rb, kr = self.rigid, self._kr
            rargs = (self.v, self.C, self._p_mass, rb.rb_p, rb.rb_b, rb.rb_r0, rb.body_c, rb.body_R, rb.part, rb.ct,
                     rb.ct_count, self._dyn, self._lvl_phi, self._lvl_id, self._lvl_rows, float(self.time),
                     float(self.dx), float(b.wall_margin), self.n_grid)
            # the contacts at the bodies' points: their particles, or their full sets where they
            # run with proxies (rigid.py "Proxy particles")
            self._launch_contacts(*rargs[:3], rb.ct_p, rb.ct_b, rb.ct_r0, *rargs[6:], 1)
            self._launch_substep(*args, 1)
            rb.advance(kr, dt, self._gbody, pre=True)
            self._launch_substep_b(*args, 2)
            self._launch_reduce(*rargs, 2)
            rb.advance(kr, dt, self._gbody)
            self._launch_scatter(self.x, self.v, self.C, self.F, self.tau, rb.rb_p, rb.rb_b, rb.rb_r0, rb.body_c,
                                 rb.body_R, rb.body_V, rb.body_w, rb.body_K)
        self.time += dt

    def stats(self) -> dict:
        """Per-material statistics of the current state: {column: [K] array} with columns
        nonfinite (count), j_min, j_max, speed_max (m/s), outside (count) plus ``clamped``
        (particles whose stencil left the grid since the last call)."""
        self._require_particles()
        self._launch_stats(self.x, self.v, self.F, self._mat, self._stats, self._err, float(self.dx), self.n_grid)
        raw = self._stats.to_numpy()  # the one host synchronisation (kernels.frame_stats)
        clamped = int(raw[0, -2]) * 4096 + int(raw[0, -1])
        a = raw[:, : len(STAT_COLUMNS)].astype(np.float64)
        for _rows, x, v, _C, _F, b in self._proxied_state():  # bodies with proxies: their full sets too
            k = self._rigid_k[b]
            bad = ~(np.isfinite(x).all(1) & np.isfinite(v).all(1))
            g = x[~bad] / self.dx
            a[k, 0] += bad.sum()
            a[k, 3] = max(a[k, 3], float(np.linalg.norm(v[~bad], axis=1).max(initial=0.0)))
            a[k, 4] += ((g.min(1) < 0.5) | (g.max(1) >= self.n_grid - 1.5)).sum()
        empty = a[:, 1] > a[:, 2]  # no simulated particle (fixed instances): neutral values
        a[empty, 1:3] = 1.0
        out = {c: a[:, i] for i, c in enumerate(STAT_COLUMNS)}
        out["clamped"] = clamped
        return out

    # ------------------------------------------------------------------ backup / output
    def save_backup(self) -> None:
        """Keep a device copy of (x, v, C, F, tau, ep, time) (the last stable state)."""
        if self._backup is None:
            P = self.n_particles
            self._backup = {"x": ti.ndarray(K.vec3, P), "v": ti.ndarray(K.vec3, P), "C": ti.ndarray(K.mat3, P),
                            "F": ti.ndarray(K.mat3, P), "tau": ti.ndarray(K.mat3, P), "ep": ti.ndarray(ti.f32, P)}
            self._launch_save = Launcher(K.copy_state)  # one launch for the six arrays
            self._launch_restore = Launcher(K.copy_state)
        bk = self._backup
        self._launch_save(self.x, self.v, self.C, self.F, self.tau, self.ep,
                          bk["x"], bk["v"], bk["C"], bk["F"], bk["tau"], bk["ep"])
        self._backup_time = self.time
        self._backup_order = (self.sort_generation, self._perm.copy())
        self._backup_rigid = self.rigid.copy_state() if self.rigid is not None else None
        self._backup_stagger = self._stagger

    def restore_backup(self) -> None:
        """Return to the state saved by :meth:`save_backup`."""
        if self._backup is None:
            raise RuntimeError("no backup saved")
        bk = self._backup
        self._launch_restore(bk["x"], bk["v"], bk["C"], bk["F"], bk["tau"], bk["ep"],
                             self.x, self.v, self.C, self.F, self.tau, self.ep)
        self._restore_order(*self._backup_order)
        self.time = self._backup_time
        if self.rigid is not None:
            self.rigid.restore_state(self._backup_rigid)
        self._stagger = self._backup_stagger

    def _restore_order(self, generation: int, perm: np.ndarray) -> None:
        """After a backup's state arrays came back: if the particles were re-sorted since, put
        the arrays the backup does not hold (mass, volume, face, material, action bits) into the
        backup's storage order ``perm`` too."""
        if generation == self.sort_generation:
            return
        slot = np.empty_like(self._perm)
        slot[self._perm] = np.arange(len(slot))
        src = slot[perm]  # current slot of each backup slot's particle
        for name in ("_p_vol", "_p_face", "_p_mass", "_mat", "_act_bits"):
            arr = getattr(self, name)
            arr.from_numpy(arr.to_numpy()[src])
        self._order.from_numpy(perm.astype(np.int32))
        self.sort_generation += 1
        self._perm = perm
        self._since_sort = 0

    def gather_rows(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions [R, 3] (domain units) and F [R, 3, 3] of particle ``rows`` (input order)."""
        rows = np.asarray(rows, np.int64)
        if not hasattr(self, "_gather_cache") or self._gather_cache[0] is not rows or \
                self._gather_gen != self.sort_generation:
            self._gather_gen = self.sort_generation
            storage = np.full(self._n_input, -1, np.int64)
            slot_rows = self._sim_rows[self._perm]
            real = slot_rows >= 0
            storage[slot_rows[real]] = np.flatnonzero(real)
            st = storage[rows]
            sim = np.flatnonzero(st >= 0)
            static_pos = np.full(self._n_input, -1, np.int64)
            static_pos[self._static_rows] = np.arange(len(self._static_rows))
            stat = np.flatnonzero(static_pos[rows] >= 0)
            # rows of bodies with proxies: (body, the positions in ``rows``, the rows' index in its full set)
            proxied = []
            for b, brows in enumerate(self._body_rows):
                if brows is None:
                    continue
                at = np.full(self._n_input, -1, np.int64)
                at[brows] = np.arange(len(brows))
                sel = np.flatnonzero(at[rows] >= 0)
                if len(sel):
                    proxied.append((b, sel, at[rows[sel]]))
            idx = _ndarray_from(st[sim].astype(np.int64) if len(sim) else np.zeros(1, np.int64), ti.i64)
            n = max(len(sim), 1)
            self._gather_cache = (rows, idx, ti.ndarray(ti.f32, (n, 12)), sim, stat, static_pos[rows[stat]], proxied)
        _, idx, out, sim, stat, spos, proxied = self._gather_cache
        if len(sim):
            K.gather(idx, self.x, self.F, out, 1.0 / self.L)
            a = out.to_numpy()[: len(sim)]  # [S, 12]: x, then F row by row
        if len(sim) and len(sim) == len(rows):  # every row simulated (sim is then 0..R-1): no scatter into place
            return np.ascontiguousarray(a[:, :3]), a[:, 3:].reshape(-1, 3, 3)
        out_x = np.empty((len(rows), 3), np.float32)
        out_F = np.empty((len(rows), 3, 3), np.float32)
        if len(sim):
            out_x[sim] = a[:, :3]
            out_F[sim] = a[:, 3:].reshape(-1, 3, 3)
        out_x[stat] = self._x_static[spos]
        out_F[stat] = np.eye(3, dtype=np.float32)
        if proxied:
            bst = self.rigid.state()
            for b, sel, k in proxied:
                R = bst["R"][b]
                out_x[sel] = (bst["c"][b] + self.rigid.full_r0[b][k] @ R.T) / self.L
                out_F[sel] = R @ bst["K"][b]
        return out_x, out_F

    def device_bytes(self) -> int:
        """Bytes of the solver's arrays (particles, grid, tables, backup)."""
        P, G = self.n_particles, self.n_grid
        per_particle = 4 * (3 + 3 + 9 + 9 + 9 + 1 + 1 + 1 + 1 + 1 + 1 + 1)
        backup = 4 * (3 + 3 + 9 + 9 + 9 + 1) * P if self._backup is not None else 0
        sort = self._sorter.nbytes() if self._sorter is not None else 0
        owner = 20 * self.n_chunks * G ** 3 if RIGID_KEY in self.combos else 0  # grid_r, grid_rm, grid_rv
        flip = 12 * self.n_chunks * G ** 3 if K.uses_flip(self.combos) else 0  # grid_o
        grids = 20 * self.n_chunks * G ** 3 + 12 * G ** 3  # grid_v, grid_m, grid_c per chunk; grid_b
        return per_particle * P + grids + owner + flip + backup + sort

    # ------------------------------------------------------------------ helpers
    def wave_speeds(self) -> np.ndarray:
        """[K] the wave speed of each material that limits the time step, m/s: ``Material.wave_speed``
        of a deformable instance (its model's fastest wave: P-wave, or sound for fluid/volume), 0 for a rigid or fixed one (no
        elastic waves; its particles' speeds still count through v_max)."""
        return np.array([m.cfl_speed for m in self.materials])


def _as_array(a, dtype, shape: tuple, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=dtype)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        raise InputError(name, f"expected shape {tuple('P' if s is None else s for s in shape)}, got {a.shape}")
    if np.issubdtype(a.dtype, np.floating) and not np.all(np.isfinite(a)):
        raise InputError(name, f"{int((~np.isfinite(a)).sum())} non-finite values")
    return a


def _ndarray_from(a: np.ndarray, dtype) -> "ti.Ndarray":
    """A Taichi ndarray holding ``a`` (the trailing 1 or 2 axes are the vec3/mat3 element)."""
    elem = 2 if dtype is K.mat3 else 1 if dtype is K.vec3 else 0
    arr = ti.ndarray(dtype, a.shape[: a.ndim - elem])
    arr.from_numpy(a)
    return arr


def batches_enabled() -> bool:
    """Whether :meth:`MPMSolver.substeps` runs substeps in ``ti.graph`` batches (on unless
    PHYSGS_TI_GRAPH=0)."""
    return os.environ.get("PHYSGS_TI_GRAPH", "1") != "0"


# reps_per_launch's default per arch.  CUDA 2, not 4: on one H100 (2026-11-27, the pipeline's
# bear, 5,554 particles, bench_substep_launch.py --reps) R = 1 / 2 / 4 took 0.118 / 0.075 /
# 0.068 ms a substep (host 0.107 / 0.067 / 0.047 ms) but the first call (compilation) 0 / 10.9 /
# 22.5 s; the warm default bear ran 3.73-4.03 s with R = 2 and 3.84-4.51 s with R = 4, and the
# pipeline from an empty kernel cache 28.4 s with R = 2 (forward_sim 14 s) against about 57 s
# with R = 4 (forward_sim 38 s)
DEFAULT_REPS = {"cpu": 1, "cuda": 2}
REPS_MAX = 32


def reps_per_launch(arch: str) -> int:
    """Substeps a launch in :meth:`MPMSolver.substeps`' batches: ``PHYSGS_TI_REPS`` (1 to
    :data:`REPS_MAX`), else :data:`DEFAULT_REPS` of the arch.  R trades host time for compile
    time (kernels.build's ``substep_reps``): on CUDA a small scene is launch-bound and a launch
    of R substeps pays Taichi's per-launch work once; the kernel holds R copies of the
    substep's code and compiles R times as long on a machine without the offline cache.  On
    the CPU a launch's host work is a small part of a substep: 1.  ``PHYSGS_TI_REPS=1``: one
    substep a launch, the one-substep kernel alone."""
    raw = os.environ.get("PHYSGS_TI_REPS", "").strip()
    if not raw:
        return DEFAULT_REPS[arch]
    try:
        reps = int(raw)
    except ValueError:
        reps = 0
    if not 1 <= reps <= REPS_MAX:
        raise ConfigError("PHYSGS_TI_REPS", f"must be a whole number of substeps a launch, 1 to {REPS_MAX}, "
                                            f"got {raw!r}", source="the environment")
    return reps


class _Batches:
    """Runs ``m`` substeps through ``ti.graph``: one compiled graph per kernel and batch size 2^j
    (j <= :data:`_BATCH_LOG2`), each holding 2^j launches of that kernel, with the arrays and
    scalars shared and the times arguments of each launch.  The kernels: the substep kernel's
    compiled instance for ``part`` = 0 (one substep a launch, time ``t``), and for R > 1
    kernels.build's ``substep_reps(R)`` (R substeps a launch, their times ``ts``).  ``m``
    substeps are ``m // R`` launches of R then ``m % R`` of one, each count in the binary digits
    of batches, largest first.

    Taichi 1.7's Python ``GraphBuilder.dispatch`` cannot take a kernel with template arguments
    (``part``): the graph is built on the compiled instance directly (``ensure_compiled`` with
    the real arguments, as a plain call does), with symbolic arguments for the others, named as
    the kernel's parameters."""

    _ND, _SCALAR, _MATRIX = range(3)

    def __init__(self, kernels, args: tuple):
        """``kernels``: kernels.build's namespace; ``args``: MPMSolver._substep_args."""
        from taichi.graph import _graph

        self._k = kernels
        self._Arg, self._Kind, self._Builder = ti.graph.Arg, ti.graph.ArgKind, _graph.GraphBuilder
        self._kernels: dict = {}  # R -> (compiled kernel, [(name, annotation, kind)] of its non-template parameters)
        self._graphs: dict = {}  # (R, size) -> compiled graph
        names = [name for name, _ann, _kind in self._compiled(1, args)[1]]
        if names.count("t") != 1:
            raise ValueError("the substep kernel has no time argument 't'")
        self._i_t = names.index("t")

    def _compiled(self, reps: int, args: tuple):
        got = self._kernels.get(reps)
        if got is None:
            from taichi.lang.matrix import MatrixType
            from taichi.types import ndarray_type, template

            if reps == 1:
                kernel, call = self._k.substep, args + (0,)  # part 0: the whole substep
            else:
                kernel = self._k.substep_reps(reps)
                call = args[: self._i_t] + (ti.Vector([0.0] * reps, dt=ti.f32),) + args[self._i_t + 1:]
            primal = kernel._primal
            key = primal.ensure_compiled(*call)
            params = []
            for a, val in zip(primal.arguments, call):
                if isinstance(a.annotation, template):
                    if val != 0:
                        raise ValueError("batches are built for part = 0")
                    continue
                kind = (self._ND if isinstance(a.annotation, ndarray_type.NdarrayType) else
                        self._MATRIX if isinstance(a.annotation, MatrixType) else self._SCALAR)
                params.append((a.name, a.annotation, kind))
            got = self._kernels[reps] = (primal.compiled_kernels[key], params)
        return got

    def _graph(self, reps: int, size: int):
        g = self._graphs.get((reps, size))
        if g is None:
            t_kernel, params = self._kernels[reps]
            gb = self._Builder()
            shared = {}
            for name, ann, kind in params:
                if kind == self._ND:
                    shared[name] = self._Arg(self._Kind.NDARRAY, name, dtype=ann.dtype, ndim=ann.ndim)
                elif name not in ("t", "ts"):
                    shared[name] = self._Arg(self._Kind.SCALAR, name, ann)
            for k in range(size):
                syms = []
                for name, ann, kind in params:
                    if name == "t":  # the launch's own time
                        syms.append(self._Arg(self._Kind.SCALAR, f"t{k}", ann))
                    elif name == "ts":  # the launch's R times
                        syms.append(self._Arg(self._Kind.MATRIX, f"ts{k}", dtype=ann))
                    else:
                        syms.append(shared[name])
                gb._graph_builder.dispatch(t_kernel, syms)
            g = self._graphs[(reps, size)] = gb._graph_builder.compile()
        return g

    def run(self, args: tuple, m: int, time: float, dt: float, reps: int = 1) -> float:
        """``m`` substeps from ``time``, ``reps`` a launch (the rest one a launch); ``args`` as
        MPMSolver._substep_args (its ``t`` unused).  Returns the time after them, advanced by
        ``dt`` per substep as MPMSolver.substep does; each substep's time is the one that
        MPMSolver.substep would pass (``float(time)``, rounded to f32 by Taichi)."""
        base = {}
        for (name, _ann, kind), val in zip(self._kernels[1][1], args):
            if name != "t":
                base[name] = val.arr if kind == self._ND else val
        config = _current_prog_config()
        q, rest = divmod(m, reps)
        for r, count in ((reps, q), (1, rest)):
            if count:
                self._compiled(r, args)
            size = 1 << _BATCH_LOG2
            while count > 0:
                while size > count:
                    size >>= 1
                values = dict(base)
                for k in range(size):
                    times = []
                    for _ in range(r):
                        times.append(float(time))
                        time += dt
                    if r == 1:
                        values[f"t{k}"] = times[0]
                    else:
                        values[f"ts{k}"] = times
                self._graph(r, size).jit_run(config, values)
                count -= size
        return time


_BATCH_LOG2 = 5  # batches of at most 32 launches


def _current_prog_config():
    from taichi.lang import impl

    return impl.get_runtime().prog.config()
