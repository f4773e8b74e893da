"""The simulation particle budget and the gaussian carrier (fill artifacts).

An MLS-MPM state needs a few particles per grid cell, not one per gaussian: a real capture
has 10^5-10^7 gaussians on its surface, the grid 32^3-128^3 cells. ``sim.particles``
chooses the particle set:

* ``budget``: per instance, the surface gaussians are thinned to one *representative*
  per sub-cell of side ``s = dx / particles_per_cell^(1/3)`` (the gaussian nearest to the
  mean of the sub-cell's gaussians), and the interior particles of IPF/MCIS (drawn at
  ``particles_per_cell`` per cell) are added. The particle count follows the grid and the
  instance's size, not the gaussian count.
* ``gaussians`` (the paper, PhysGaussian): every gaussian is a particle, plus the filled ones.

The **carrier** says how every gaussian follows the simulation. Gaussian g of instance k is
driven by its ``K`` nearest particles p of the same instance (``fill.carrier_neighbors``)
with weights ``w_gp = exp(-|x_g - x_p|^2 / (2 s^2)) / sum`` (s the particle spacing above;
a gaussian never follows another object). At time t, with particle states x_p(t), F_p(t)
and rest offsets ``d_gp = x_g(0) - x_p(0)``::

    x_g(t) = sum_p w_gp (x_p(t) + F_p(t) d_gp)       # each particle's first-order prediction
    F_g(t) = sum_p w_gp F_p(t)                       # Sigma_g(t) = F_g Sigma_g F_g^T

The first line is exact for any affine motion of the neighbourhood (a rigid rotation
included, which plain averaging of displacements is not: it would shrink a tumbling
object's surface by up to half a particle spacing). In ``gaussians`` mode every gaussian
has one driver, itself, with weight 1 and offset 0, which is PhysGaussian's kinematics.

Only particles that drive at least one gaussian (*drivers*) have their states stored in
final.h5; ``carrier.h5`` indexes them by column. Gaussians of static instances or outside
the simulation region have no driver (``static``) and are drawn at rest.

carrier.h5: ``index`` [N, K] int32 (final.h5 column of each driver, -1 = unused slot),
``weight`` [N, K] float32 (rows sum to 1; 0 for static gaussians), ``drivers`` [M] int64
(rows of particles.h5 in final.h5's column order), ``static`` [N] bool; attrs ``mode``,
``neighbors``, ``spacing``, ``n_particles``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from .errors import InputError
from .runtime import atomic_path

MODES = ("budget", "gaussians")


def particle_spacing(dx: float, particles_per_cell: float) -> float:
    """Mean particle spacing s = dx / ppc^(1/3) (domain units) of the budgeted set."""
    return float(dx) / float(particles_per_cell) ** (1.0 / 3.0)


def representatives(points: np.ndarray, cell: float) -> np.ndarray:
    """One point per occupied sub-cell: the one nearest to the mean of the sub-cell's points.

    Args:
        points: [C, 3] positions (domain units).
        cell: sub-cell side.

    Returns:
        [R] int64 sorted row indices into ``points`` (R <= C, one per occupied sub-cell).
    """
    c = points.shape[0]
    if c == 0:
        return np.zeros(0, np.int64)
    keys = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)  # [C, 3]
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]  # [C]
    n_cells = int(np.prod(dims.astype(np.float64)))
    if n_cells > max(4 * c, 4096):  # sparse in a large box: number the occupied sub-cells instead
        _, flat = np.unique(flat, return_inverse=True)
        flat = flat.reshape(-1)
        n_cells = int(flat.max()) + 1
    # per sub-cell sums in row order (bincount), so the means are those of the sub-cell's rows
    counts = np.bincount(flat, minlength=n_cells)
    sums = np.stack([np.bincount(flat, weights=points[:, a], minlength=n_cells) for a in range(3)], axis=1)
    d2 = ((points - sums[flat] / counts[flat, None]) ** 2).sum(axis=1)  # [C] to the sub-cell's mean
    # the nearest of each sub-cell, the first row among equally near ones
    best = np.full(n_cells, np.inf)
    np.minimum.at(best, flat, d2)
    tie = np.flatnonzero(d2 == best[flat])
    first = np.full(n_cells, c, np.int64)
    np.minimum.at(first, flat[tie], tie)
    keep = np.zeros(c, bool)
    keep[first[first < c]] = True
    return np.flatnonzero(keep).astype(np.int64)


@dataclass
class Carrier:
    """Which particles drive each gaussian (see the module docstring).

    Attributes:
        index: [N, K] int32 final.h5 column of each driver, -1 for an unused slot.
        weight: [N, K] float32, rows sum to 1 (0 for static gaussians).
        drivers: [M] int64 rows of particles.h5, in final.h5's column order.
        static: [N] bool gaussians with no driver (drawn at rest).
        mode: ``budget`` or ``gaussians``.
        spacing: kernel width s (domain units).
        n_particles: P, rows of particles.h5.
    """

    index: np.ndarray
    weight: np.ndarray
    drivers: np.ndarray
    static: np.ndarray
    mode: str
    spacing: float
    n_particles: int

    @property
    def n(self) -> int:
        return int(self.index.shape[0])

    @property
    def neighbors(self) -> int:
        return int(self.index.shape[1])

    @property
    def identity(self) -> bool:
        """Every simulated gaussian has one driver with weight 1 (``gaussians`` mode)."""
        return self.neighbors == 1


def build_carrier(gauss_x: np.ndarray, gauss_label: np.ndarray, part_x: np.ndarray, part_label: np.ndarray,
                  part_row: np.ndarray, mode: str, neighbors: int, spacing: float) -> Carrier:
    """The carrier of N gaussians over P particles.

    Args:
        gauss_x: [N, 3] gaussian centres (sim frame).
        gauss_label: [N] instance of each gaussian; gaussians whose instance has no particle
            (static instances, label -1 outside the simulation region) become static.
        part_x: [P, 3] particle positions; part_label: [P] their instances.
        part_row: [P] int64 the gaussian row a particle stands at, -1 for filled particles.
        mode: ``gaussians`` (each gaussian driven by its own particle) or ``budget``.
        neighbors: K of ``budget`` mode.
        spacing: kernel width s.

    Returns:
        :class:`Carrier` (drivers sorted by particle row).
    """
    if mode not in MODES:
        raise ValueError(f"unknown carrier mode {mode!r}")
    n, p = gauss_x.shape[0], part_x.shape[0]
    if mode == "gaussians":
        own = np.full(n, -1, np.int64)
        stands = np.flatnonzero(part_row >= 0)
        own[part_row[stands]] = stands
        drivers = np.unique(own[own >= 0])
        col = np.full(p, -1, np.int64)
        col[drivers] = np.arange(drivers.size)
        index = np.where(own >= 0, col[np.maximum(own, 0)], -1).astype(np.int32)[:, None]
        weight = (index >= 0).astype(np.float32)
        return Carrier(index, weight, drivers, index[:, 0] < 0, mode, float(spacing), p)
    k_max = max(1, int(neighbors))
    near = np.full((n, k_max), -1, np.int64)  # particle rows
    weight = np.zeros((n, k_max), np.float32)
    for lab in np.unique(gauss_label):
        g = np.flatnonzero(gauss_label == lab)
        mine = np.flatnonzero(part_label == lab) if lab >= 0 else np.zeros(0, np.int64)
        if mine.size == 0:
            continue
        k = min(k_max, mine.size)
        d, j = cKDTree(part_x[mine]).query(gauss_x[g], k=k, workers=-1)
        d, j = d.reshape(len(g), k), j.reshape(len(g), k)
        w = np.divide(d, spacing, out=d)  # w = exp(-0.5 (d / s)^2) [G, k], in place (N x K temporaries cost
        np.square(w, out=w)                #  ~0.1 s at 10^6 gaussians); the nearest particle lies within ~s,
        w *= -0.5                          #  so w > 0
        np.exp(w, out=w)
        w /= w.sum(axis=1, keepdims=True)
        near[g, :k] = mine[j]
        weight[g, :k] = w
    used = near >= 0
    is_driver = np.zeros(p, bool)
    is_driver[near[used]] = True
    drivers = np.flatnonzero(is_driver)  # np.unique(near[used]), without sorting N x K rows
    col = np.full(p + 1, -1, np.int32)  # final.h5 column of each particle row; col[-1] = -1 for unused slots
    col[drivers] = np.arange(drivers.size)
    index = col[near]
    return Carrier(index, weight, drivers, ~used[:, 0], mode, float(spacing), p)


def write_carrier(path, c: Carrier) -> None:
    """carrier.h5 (module docstring), written atomically."""
    import h5py

    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h:
            h.create_dataset("index", data=c.index.astype(np.int32))
            h.create_dataset("weight", data=c.weight.astype(np.float32))
            h.create_dataset("drivers", data=c.drivers.astype(np.int64))
            h.create_dataset("static", data=c.static.astype(bool))
            h.attrs["mode"] = c.mode
            h.attrs["neighbors"] = c.neighbors
            h.attrs["spacing"] = float(c.spacing)
            h.attrs["n_particles"] = int(c.n_particles)


def load_carrier(path, n_gaussians: int | None = None) -> Carrier:
    """Read and check carrier.h5; InputError naming the file and the problem."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "carrier file not found (it is written by the fill stage)")
    try:
        with h5py.File(path, "r") as h:
            missing = [k for k in ("index", "weight", "drivers", "static") if k not in h]
            if missing:
                raise InputError(path, f"missing datasets {missing} (expected index, weight, drivers, static)")
            c = Carrier(np.asarray(h["index"][...], np.int32), np.asarray(h["weight"][...], np.float32),
                        np.asarray(h["drivers"][...], np.int64), np.asarray(h["static"][...], bool),
                        str(h.attrs.get("mode", "")), float(h.attrs.get("spacing", math.nan)),
                        int(h.attrs.get("n_particles", -1)))
    except OSError as e:
        raise InputError(path, f"not a readable HDF5 file: {e}") from None
    n, m = c.index.shape[0], c.drivers.shape[0]
    problems = []
    if c.index.ndim != 2 or c.weight.shape != c.index.shape:
        problems.append(f"index {c.index.shape} and weight {c.weight.shape} must both be [N, K]")
    elif n_gaussians is not None and n != n_gaussians:
        problems.append(f"has {n} gaussians but scene.ply has {n_gaussians} (stale carrier: re-run fill)")
    elif c.static.shape != (n,):
        problems.append(f"static has shape {c.static.shape}, expected ({n},)")
    elif c.index.size and (c.index.min() < -1 or c.index.max() >= m):
        problems.append(f"index spans [{c.index.min()}, {c.index.max()}] but there are {m} drivers")
    elif not np.isfinite(c.weight).all() or (c.weight < 0).any():
        problems.append("weights must be finite and >= 0")
    if problems:
        raise InputError(path, "; ".join(problems))
    return c
