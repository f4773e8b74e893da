"""Static geometry as level-set colliders, and how every boundary of the solver is placed.

Static geometry
---------------
:class:`StaticGeometry` is the one way to say "these points are static geometry": a fixed rigid
instance (``fixed: true``; the solver builds one from its particles) or anything else a caller
passes to ``MPMSolver(static=[...])`` (e.g. the static surroundings of a real capture)::

    from physgs_steps.mpm import MPMSolver, StaticGeometry
    table = StaticGeometry(points, spacing=0.008, surface="separate", friction=0.4, name="table")
    s = MPMSolver(materials, n_grid=32, static=[table])      # points [N, 3] in domain units

It does not enter the MPM (no particles, no cost per particle).  :func:`level_set` turns its
points into a signed distance on the simulation grid's nodes (metres, positive outside); all
static geometries of a solver are merged into one grid (the minimum) plus the index of the
nearest one per node, which gives each node its surface kind and friction.

Signed distance from points.  The points (particle centres, typically spacing ``s`` apart)
are the solid; its surface lies ``s / 2`` beyond the outermost centres (a particle stands for
a cell of size s).  The union of balls of radius ``r_occ = 1.25 s`` (wide enough to close the
gaps of randomly placed filled particles) is voxelised on a grid ``FINE`` times finer than the
simulation grid inside the points' box, enclosed cavities are filled (a closed hollow shell
becomes solid, an open cup stays open), and the Euclidean distance transform gives its signed
distance; the union's surface lies ``r_occ - s / 2`` beyond the solid's, a constant, which is
subtracted.  Node values are exact samples of the fine field (the fine grid contains the
nodes): placement error about half a fine voxel (dx / 8) plus the points' own roughness.

Boundary placement (all kinds)
------------------------------
Every boundary is a signed distance ``phi`` (m, positive on the free side) with a unit normal
``n`` pointing to the free side, a velocity ``v_c``, a surface kind and a friction
coefficient: the ground and ``surface_collider`` planes, the six domain walls (planes
``dynamics.wall_margin`` from the domain faces), ``cuboid`` boxes (their inside is held) and
the level sets above.  Two treatments make the boundary sit at ``phi = 0`` whatever the grid
(measurements: benchmarks/bench_boundaries.py, README "Where the paper is vague"):

* grid (kernels.py): an obstacle acts on a node only where material touches it: a node
  to which a particle transfers whose face is within ``TOUCH`` cells of the obstacle (or
  behind it); without this, grid contact reaches about 1.5 cells in front of the surface and
  a body comes to rest anywhere in that layer, depending on how it arrived.  A particle is a
  cube of material of its volume (side ``p_vol^(1/3)``, as the level sets above take points
  for cells of their spacing), so its face lies half that side in front of its centre: a
  body touches the surface when its material does, and one whose face is on it stays there.
  With the centres (before; validation ``resting_block`` and ``incline_friction``) a body had
  to sink until its lowest centres were within ``TOUCH`` of the plane, half a particle spacing
  less ``TOUCH`` (0.15 cells at 8 per cell): a block set on a floor fell that far and rested
  with its face that far below the plane (5 % of a 0.1 m block at n_grid 32, first order in
  dx), and a block set on a rough incline fell for a frame before it touched, sliding free
  meanwhile, and its landing braked it by about two thirds of mu times the landing's normal
  impulse (the bottom nodes' tangential velocity stops at zero): it slid 6 % too far at
  n_grid 32, 5.5 % at 48, not shrinking with dx.  The face offset is per particle
  (:func:`face_half_width`; ``MPMSolver.set_particles(face=...)``): half the side for
  material filled on a lattice, 0 for the carriers of a reconstruction's visible gaussians
  (particles.h5 ``filled`` false), which lie ON its surface: their centre is the material's
  face.  With half their side they stopped half a particle spacing above the plane (the bear's
  lowest visible row 0.32 cells above the ground at grid 32, about 1 cm, 0.09 with the
  centres).  (``TOUCH`` is a
  tenth of a cell, not zero: a resting particle bobbing by a rounding error must not switch
  its support off for a substep, which lets the lowest layers creep onto the plane.)  Such a
  node with mass and ``-GHOST_BAND dx < phi < FRONT_BAND dx`` gets a velocity on the line
  through the boundary's value at the surface and the velocity ``v_m`` sampled (trilinear,
  over nodes with mass, before any boundary) at the mirror point ``x + (d - phi) n`` on the
  free side, ``d = (FRONT_BAND + |n|_1) dx`` (the mirror's trilinear cube lies beyond the
  band, so no node reads a value that the boundary changes): relative velocity
  ``u = v_m - v_c``, ratio ``q = phi / d``.  Behind the surface (``phi < 0``, ghost nodes):
  sticky ``v = v_c + q u``; slip: normal part ``q u_n``, tangential part ``u_t``; separate: as
  slip when ``u_n < 0`` (approaching), else ``v = v_m`` (leaving is free) with its normal part
  no faster than the node's own (before any boundary): material that still presses on the
  surface is not pulled off it by a mirror two cells away (a layer thinner than that under a
  rising body: the surface did work on it); the mirror samples leave out the nodes a free
  rigid body covers (its field is not the material touching the surface); on a rough surface
  (friction mu > 0) the node keeps instead its own tangential velocity less mu times its own
  push (the change of its normal velocity), as a front node does: the ghost row carries a
  large part of the surface's reaction (the lowest layers' stress reaches it through the
  B-spline gradients; 18-65 % measured on a sliding block), and with the mirror's tangential
  velocity it charged no friction for it (a block on a rough incline slid as with mu 0.20-0.26
  instead of 0.3, less the taller it was in cells; validation ``incline_friction``).  In front of it (``0 <= phi < FRONT_BAND dx``): sticky
  ``v = v_c + q u``; slip: the node's normal part set to ``q u_n``; separate: raised to
  ``q min(u_n, 0)`` where it is below (the surface only pushes), with Coulomb friction, ``mu``
  times that push, on the node's own tangential part.  Where the bands of several obstacles
  overlap, each one's push is measured on the node's velocity before any boundary (a
  frictionless domain wall acting first must not take a rough floor's friction away), and a
  push along a normal that an earlier frictional obstacle already charged is not charged twice.  These front nodes carry the surface's
  reaction: the quadratic B-spline weighs nodes up to 1.5 cells in front of a point on the
  surface, and with a condition only behind the surface a resting body's weight has nothing
  to hold it there (its lowest layers pile up on the plane, held only by the particle
  projection: a jelly column shortened by 2.5x its exact value; bench_rigid.py).  Cuboids
  (holding regions) get the ghost rule on every node inside them and none in front (the held
  particles inside carry the reaction), with the mirror ``d = (HELD_REACH + 1) dx`` (2.5 cells)
  in front of the face: its trilinear cube lies beyond the reach of every held particle's
  stencil (1.5 cells), so a ghost node extrapolates the free material's motion only, never the
  held particles' own transfer.  With the mirror one cell in front (as before), the nodes just
  outside a face where little free material lies (a noodle clump's top inside the grip, an empty
  side of the box) carried almost only the held particles' fringe mass; the held particles
  bring no momentum (they transfer the holder's velocity), so each substep these nodes took
  their stress impulse alone, several m/s on a node of 1 % of a full node's mass; the ghost
  nodes extrapolated it into the box (up to twice) and the held particles strained with it: a
  loop with no inertia, unstable where its gain passed 2 (udon's hold at E 4.96e4 Pa: J 0.005
  at frame 9; a sparse held cluster with nothing free: NaN; tests/test_mpm_dynamics.py).  A
  cuboid's ghost node also reads its mirror only where the mirror's mean node mass is at least
  ``MIRROR_MASS`` (half) of its own, else it takes the plain rule (a sparse fringe of free
  material in front of a full holding region: a plant's stem at the pot's rim; the ficus at
  grid 64 went NaN in 4 frames before either rule; the test has a small copy).  Ground,
  surface colliders and level sets apply the same test to their ghost nodes (``phi < 0``): a
  body thinner than the mirror distance (2 cells) puts the mirror in the fringe above it,
  nodes holding the tail of one layer's stencil (0.5 % of a node's mass for a 0.8-cell block),
  whose velocity its stress drives through that tiny mass; extrapolated into the ghost row it
  closed a loop (ghost row -> lowest layer's C and F -> stress -> fringe) that grew about e-fold
  per frame: a 0.8-cell block resting on a rough incline (validation ``incline_friction``
  ``stick`` at n_grid 16) lifted off and slid 18 mm.  Their front rows keep reading any mirror
  (a thin surge front on the floor: the dam break's front is unchanged).  Deeper nodes,
  or nodes whose mirror has no mass, get the plain node rule (sticky: v_c; slip/separate:
  inward normal part removed, friction).
* particles: after G2P a deformable particle with ``phi < 0`` is moved back onto the surface
  (``x -= phi n``) and its inward normal velocity removed (sticky: ``v = v_c``).  A body's
  outermost material rests on the surface, within ``TOUCH`` (a tenth of a cell) of it: contact
  starts there (bench_boundaries.py); its outermost lattice centres half a particle's side
  above, its surface carriers on it.  A
  cuboid is a holding region, not an obstacle: a particle inside an active cuboid moves with
  the cuboid and strains with the velocity field the ghost nodes extend into the box, so the
  stress stays continuous across the face and the free material is clamped exactly at the
  face (bench_boundaries.py: the clamped bar's effective length is within 0.2 % of the true
  one at grid 32 and 64: +0.16 % and -0.02 %; +2.7 % at grid 16, where the bar is 2 cells wide;
  with the mirror one cell out, before it moved beyond the held particles' reach, +0.03 %,
  -0.02 % and +1.65 %); it transfers the cuboid's own velocity (no affine part), and forces
  on it (wind, impulses) are taken by the holder.  Rigid bodies are handled as bodies
  (:mod:`physgs_steps.mpm.rigid`).

The torch pseudo step (bgdo/torch_step.py) implements the same treatment for the domain walls.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, InputError

SURFACE_KIND = {"sticky": 0.0, "slip": 1.0, "separate": 2.0}
TOUCH = 0.1          # cells: a particle whose face (face_half_width in front of its centre) is this close to an obstacle (or behind it) touches it
GHOST_BAND = 2.0     # nodes up to this many cells behind a surface get ghost velocities
FRONT_BAND = 1.0     # cells: engaged nodes this close in front of an obstacle carry its reaction
HELD_REACH = 1.5     # cells: a held particle's stencil reaches nodes less than this far in front of its holding region (cuboid mirrors lie beyond it)
MIRROR_MASS = 0.5    # ghost nodes (cuboids; obstacles behind their surface) read their mirror only where the mirror's mean node mass is this fraction of their own
FINE = 4             # level sets: voxels per grid cell of the fine occupancy grid
MAX_FINE_VOXELS = 40_000_000
OCC_RADIUS = 1.25    # union-of-balls radius in point spacings
FAR = 1.0e3          # phi (m) of nodes far from every static geometry
COVER = 1.0 / 6.0    # rigid bodies: a node is covered where the body's mass there is this fraction of a node's inside it
FRINGE_SOFT = 1e-4   # rigid bodies: a fringe node with less soft mass than this fraction moves with the body


@dataclass
class StaticGeometry:
    """Points that are static geometry: a level-set collider that never moves.

    points: [N, 3] positions in domain units (particle centres of the solid, or surface
        samples of a closed shell).
    spacing: typical distance between neighbouring points in domain units (the cell size a
        point stands for); None = estimated from the points (median nearest-neighbour distance).
    surface: sticky | slip | separate (as ``dynamics.ground.surface``).
    friction: Coulomb coefficient (separate and slip surfaces).
    """

    points: np.ndarray
    spacing: float | None = None
    surface: str = "separate"
    friction: float = 0.5
    name: str = "static"

    def __post_init__(self) -> None:
        p = np.asarray(self.points, np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
            raise InputError(f"static geometry '{self.name}'", f"points must have shape [N, 3] with N > 0, got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise InputError(f"static geometry '{self.name}'", "points must be finite")
        self.points = p
        if self.surface not in SURFACE_KIND:
            raise ConfigError(f"static geometry '{self.name}': surface", f"must be sticky, slip or separate, got {self.surface!r}")
        if not (np.isfinite(self.friction) and self.friction >= 0):
            raise ConfigError(f"static geometry '{self.name}': friction", f"must be >= 0, got {self.friction!r}")
        if self.spacing is None:
            self.spacing = estimate_spacing(p)
        if not (np.isfinite(self.spacing) and self.spacing > 0):
            raise ConfigError(f"static geometry '{self.name}': spacing", f"must be > 0, got {self.spacing!r}")
        self.spacing = float(self.spacing)


def face_half_width(vol: np.ndarray, surface: np.ndarray | None = None) -> np.ndarray:
    """[P] float64: how far in front of each particle's centre its face lies ("Boundary
    placement"), in the units of ``vol``'s cube root: half the side of a cube of its volume
    (``0.5 vol^(1/3)``; material filled on a lattice), 0 where ``surface`` [P] bool is set (a
    reconstruction's visible gaussians, particles.h5 ``filled`` false: they lie on the
    material's surface)."""
    half = 0.5 * np.cbrt(np.asarray(vol, np.float64))
    if surface is None:
        return half
    surface = np.asarray(surface, bool)
    if surface.shape != half.shape:
        raise InputError("surface", f"expected shape {half.shape} (one flag per particle), got {surface.shape}")
    return np.where(surface, 0.0, half)


def estimate_spacing(points: np.ndarray) -> float:
    """Median distance (domain units) from a point to its nearest neighbour."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    if len(p) < 2:
        return 1e-3
    sample = p[np.random.default_rng(0).choice(len(p), min(len(p), 20000), replace=False)]
    d, _ = cKDTree(p).query(sample, k=2)
    return float(max(np.median(d[:, 1]), 1e-6))


def level_set(geom: StaticGeometry, n_grid: int, domain_size: float) -> np.ndarray:
    """[G, G, G] f32 signed distance (metres, positive outside) of ``geom`` at the grid nodes
    ``i / n_grid`` (domain units); FAR where the geometry is more than a few cells away."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    G = int(n_grid)
    dx = 1.0 / G  # domain units
    s = float(geom.spacing)
    r_occ = OCC_RADIUS * s
    pad = r_occ + (2 * GHOST_BAND + 2.0) * dx
    lo_n = np.clip(np.floor((geom.points.min(0) - pad) / dx).astype(int), 0, G - 1)
    hi_n = np.clip(np.ceil((geom.points.max(0) + pad) / dx).astype(int), 0, G - 1)
    cells = hi_n - lo_n
    f = FINE
    while f > 1 and np.prod(cells * f + 1) > MAX_FINE_VOXELS:
        f -= 1
    h = dx / f
    shape = tuple(int(c) * f + 1 for c in cells)
    axes = [lo_n[a] * dx + h * np.arange(shape[a]) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    d, _ = cKDTree(geom.points).query(grid, distance_upper_bound=r_occ)
    occ = np.isfinite(d).reshape(shape)
    occ = ndimage.binary_fill_holes(occ)
    # signed distance of the union (voxel centres; half a voxel to the boundary between them)
    out = ndimage.distance_transform_edt(~occ) * h - 0.5 * h
    ins = ndimage.distance_transform_edt(occ) * h - 0.5 * h
    sdf = np.where(occ, -ins, out) + (r_occ - 0.5 * s)
    phi = np.full((G, G, G), FAR, np.float32)
    sub = sdf[::f, ::f, ::f]
    phi[lo_n[0]:hi_n[0] + 1, lo_n[1]:hi_n[1] + 1, lo_n[2]:hi_n[2] + 1] = (sub * domain_size).astype(np.float32)
    return phi


def merge(geoms: list[StaticGeometry], n_grid: int, domain_size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All static geometries on one grid: (phi [G, G, G] f32 metres = the minimum over
    geometries, owner [G, G, G] i32 = index of the geometry giving it, rows [K, 2] f32 =
    (surface kind, friction) per geometry)."""
    G = int(n_grid)
    if not geoms:
        return np.full((1, 1, 1), FAR, np.float32), np.zeros((1, 1, 1), np.int32), np.zeros((1, 2), np.float32)
    phi = np.full((G, G, G), FAR, np.float32)
    owner = np.zeros((G, G, G), np.int32)
    for k, g in enumerate(geoms):
        pk = level_set(g, G, domain_size)
        closer = pk < phi
        phi[closer] = pk[closer]
        owner[closer] = k
    rows = np.array([[SURFACE_KIND[g.surface], g.friction] for g in geoms], np.float32)
    return phi, owner, rows


def check_wall_margin(margin: float, n_grid: int) -> None:
    """The domain walls must leave every particle's stencil and one node behind each wall on
    the grid: margin > 1.5 cells (the upper side is the tighter one)."""
    need = 1.5 / n_grid
    if not margin > need:
        raise ConfigError("dynamics.wall_margin", f"{margin:g} domain units is too close to the domain edge for "
                                                  f"sim.n_grid {n_grid}: it must exceed 1.5 grid cells ({need:.4g}); "
                                                  f"raise sim.n_grid to at least {int(np.floor(1.5 / margin)) + 1} or "
                                                  f"the margin")
