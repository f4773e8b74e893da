"""The validation harness: accuracy settings, particle set-ups, one bounded simulation run.

A :class:`Case` (one small class per physical test) knows its set-up, its reference (with
the source and the exact relation or numbers used) and its error measure.  A case may have
*variants* (e.g. the aspect ratios of the granular column); one run is one
``(case, variant, setting)`` and returns a :class:`RunRecord`.  Runs go through the
production frame loop (:func:`physgs_steps.mpm.run_frames`: adaptive CFL substeps,
stability checks), so what is validated is what the pipeline runs.

Accuracy settings (:class:`Setting`) are the knobs a user has: grid nodes per axis
(``sim.n_grid``), particles per cell (``fill.particles_per_cell``; here a k x k x k lattice per
cell) and the CFL number (``sim.cfl``).  Float64 is not offered: the kernels are written in
f32 throughout (see README "Where the paper is vague").

Units: metres, seconds, SI material parameters; the solver's domain units are converted here.
"""
from __future__ import annotations

import abc
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import ConfigError
from ..mpm import Dynamics, Material, Thresholds, TimeStepper  # no Taichi: the workflow plans from these

LOG = logging.getLogger("physgs.validation")
SCALES = ("smoke", "cpu", "full")


# ============================================================================ settings
@dataclass(frozen=True, order=True)
class Setting:
    """One point of the accuracy knobs: grid nodes per axis, particles per cell, CFL number."""

    n_grid: int
    ppc: int = 8
    cfl: float = 0.5

    def __post_init__(self) -> None:
        k = round(self.ppc ** (1 / 3))
        if k ** 3 != self.ppc or k < 1:
            raise ConfigError("validation setting", f"particles per cell must be a cube (1, 8, 27, 64), got {self.ppc}")
        if self.n_grid < 8:
            raise ConfigError("validation setting", f"n_grid must be >= 8, got {self.n_grid}")
        if not 0 < self.cfl <= 2:
            raise ConfigError("validation setting", f"cfl must be in (0, 2], got {self.cfl}")

    @property
    def per_axis(self) -> int:
        """Particles per cell along one axis (k, ppc = k^3)."""
        return round(self.ppc ** (1 / 3))

    @property
    def id(self) -> str:
        return f"g{self.n_grid}-p{self.ppc}-c{self.cfl:g}"

    @classmethod
    def parse(cls, text: str) -> "Setting":
        """The inverse of :attr:`id` (``g32-p8-c0.5``)."""
        try:
            g, p, c = text.split("-")
            assert g[0] == "g" and p[0] == "p" and c[0] == "c"
            return cls(int(g[1:]), int(p[1:]), float(c[1:]))
        except (ValueError, AssertionError, IndexError):
            raise ConfigError("validation setting", f"expected g<n_grid>-p<ppc>-c<cfl>, got {text!r}") from None


# The shipped defaults: sim.n_grid 32, fill.particles_per_cell 8, sim.cfl 0.5.
DEFAULT = Setting(32, 8, 0.5)


def ladder(scale: str, grids: dict[str, Sequence[int]], *, ppc: dict[str, Sequence[int]] | None = None,
           cfl: dict[str, Sequence[float]] | None = None, at: int | None = None) -> list[Setting]:
    """Settings of one scale: a resolution ladder at the default ppc and CFL, plus one-at-a-time
    variations of ppc and CFL at grid ``at`` (default: the default grid when on the ladder)."""
    if scale not in SCALES:
        raise ConfigError("validation.scale", f"must be one of {', '.join(SCALES)}, got {scale!r}")
    out = {Setting(g, DEFAULT.ppc, DEFAULT.cfl) for g in grids[scale]}
    base = at if at is not None else (DEFAULT.n_grid if DEFAULT.n_grid in grids[scale] else grids[scale][0])
    for p in (ppc or {}).get(scale, ()):
        out.add(Setting(base, p, DEFAULT.cfl))
    for c in (cfl or {}).get(scale, ()):
        out.add(Setting(base, DEFAULT.ppc, c))
    return sorted(out)


# ============================================================================ geometry
def lattice(lo: Sequence[float], hi: Sequence[float], spacing: float, jitter: float = 0.0,
            seed: int = 0) -> np.ndarray:
    """Points of a cell-centred lattice filling the box [lo, hi] (metres) exactly: along each
    axis ``max(1, round(extent / spacing))`` points at the spacing that divides the extent
    (:func:`fitted_spacing`), so the particles' cells tile the box whatever ``spacing`` is;
    optional uniform jitter (fraction of the spacing).  Returns x [P, 3]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    hs = fitted_spacing(lo, hi, spacing)
    axes = [a + (np.arange(int(round((b - a) / s))) + 0.5) * s for a, b, s in zip(lo, hi, hs)]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    if jitter > 0:
        x = x + np.random.default_rng(seed).uniform(-jitter, jitter, x.shape) * hs
    return x


def fitted_spacing(lo: Sequence[float], hi: Sequence[float], spacing: float) -> np.ndarray:
    """[3] the lattice spacing per axis that fills [lo, hi] exactly with the count nearest to
    ``spacing`` (at least one point per axis)."""
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    return ext / np.maximum(1, np.round(ext / spacing))


@dataclass
class Scene:
    """What one validation run simulates (SI units)."""

    materials: list[Material]
    x: np.ndarray                      # [P, 3] m
    vol: np.ndarray                    # [P] m^3
    material: np.ndarray               # [P] int, index into materials
    domain_size: float                 # m (the cube's side)
    dynamics: Dynamics = field(default_factory=Dynamics.free)
    velocity: np.ndarray | None = None  # [P, 3] m/s (None: at rest)

    @classmethod
    def block(cls, material: Material, lo, hi, setting: Setting, domain_size: float, dynamics: Dynamics | None = None,
              velocity: Callable[[np.ndarray], np.ndarray] | None = None, jitter: float = 0.0) -> "Scene":
        """One material filling the box [lo, hi] (m) with ``setting.ppc`` particles per grid cell."""
        h = domain_size / setting.n_grid / setting.per_axis
        x = lattice(lo, hi, h, jitter)
        v = velocity(x) if velocity is not None else None
        return cls([material], x, np.full(len(x), float(np.prod(fitted_spacing(lo, hi, h)))), np.zeros(len(x), int),
                   domain_size, dynamics if dynamics is not None else Dynamics.free(), v)

    @property
    def mass(self) -> np.ndarray:
        """[P] particle masses (kg)."""
        rho = np.array([m.density for m in self.materials])[self.material]
        return rho * self.vol


# ============================================================================ one run
class RunTimeout(Exception):
    """A run exceeded its wall-clock bound (reported as a hang)."""


@dataclass
class SimOutput:
    """What :func:`simulate` measured."""

    stable: bool
    message: str | None
    frames: int                 # stable frames handed out (frame 0 included)
    substeps: int
    sim_seconds: float          # wall seconds of the substeps (compilation excluded)
    first_substep_seconds: float  # the substep kernels' first launches (kernel compilation or cache load)
    wall_seconds: float         # everything: set-up, compilation, substeps, measurements
    n_particles: int
    timed_out: bool = False
    info: dict | None = None


def simulate(scene: Scene, setting: Setting, *, fps: float, n_frames: int,
             on_frame: Callable[[int, float, dict], None], backend: str = "cpu",
             max_substeps: int = 5000, timeout_s: float | None = None,
             thresholds: Thresholds | None = None, log: logging.Logger = LOG) -> SimOutput:
    """Simulate ``scene`` at ``setting`` for ``n_frames`` frames (frame 0 = the initial state)
    at ``fps``; ``on_frame(k, t, state)`` gets every stable frame's state in METRES
    (``x`` [P,3] m, ``v`` [P,3] m/s, ``C``, ``F``).  Bounded: at most ``max_substeps`` per
    frame and ``timeout_s`` wall seconds."""
    from ..mpm import MPMSolver, run_frames  # Taichi: loaded when a case runs, not when it is planned

    t_wall = time.perf_counter()
    L = scene.domain_size
    solver = MPMSolver(scene.materials, n_grid=setting.n_grid, domain_size=L, dynamics=scene.dynamics,
                       backend=backend)
    solver.set_particles(scene.x / L, scene.vol / L ** 3, scene.material, velocity=scene.velocity)
    stepper = TimeStepper(fps=fps, cfl=setting.cfl, max_substeps=max_substeps)
    th = thresholds or Thresholds()

    spent = [0.0]

    def frame(k: int, t: float, dt_next: float) -> None:
        t_cb = time.perf_counter()
        st = solver.get_state()
        on_frame(k, t, {"x": st["x"].astype(np.float64) * L, "v": st["v"].astype(np.float64) * L,
                        "C": st["C"], "F": st["F"]})
        spent[0] += time.perf_counter() - t_cb
        if timeout_s is not None and time.perf_counter() - t_wall > timeout_s:
            raise RunTimeout(f"stopped after {time.perf_counter() - t_wall:.0f} s (bound {timeout_s:g} s)")

    timed_out = False
    t_run = time.perf_counter()
    try:
        res = run_frames(solver, n_frames, stepper, th, frame, log, stage="validation")
    except RunTimeout as e:
        log.warning("%s", e)
        timed_out = True
        res = None
    run_seconds = time.perf_counter() - t_run
    wall = time.perf_counter() - t_wall
    if res is None:
        return SimOutput(False, "timeout", 0, 0, wall, 0.0, wall, solver.n_particles, timed_out=True)
    # substeps and stability checks only: without the first substep (compilation) and the measurements
    sim = max(run_seconds - res.first_substep_seconds - spent[0], 0.0)
    return SimOutput(res.stable, res.message, res.frames_done, int(sum(res.substeps)), sim,
                     res.first_substep_seconds, wall, solver.n_particles, timed_out, res.info)


# ============================================================================ records
@dataclass
class RunRecord:
    """The outcome of one (case, variant, setting) run (one JSON file of the workflow)."""

    case: str
    variant: str
    setting: str
    error: float | None          # the case's relative error measure (None: run failed)
    sim_seconds: float
    wall_seconds: float
    substeps: int
    n_particles: int
    stable: bool
    metrics: dict = field(default_factory=dict)
    series: dict = field(default_factory=dict)   # time series for figures
    message: str | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def rel(a: float, b: float) -> float:
    """|a - b| / |b|."""
    return abs(a - b) / abs(b)


def front_position(x: np.ndarray, axis: int, spacing: float, min_count: float, origin: float = 0.0) -> float:
    """The farthest coordinate along ``axis`` where the material is at least one particle layer
    thick: particles are binned in slices ``[origin + k spacing, origin + (k + 1) spacing)``;
    the front is the outer edge of the last slice holding at least ``min_count`` particles
    (one full layer across a slab), or of the last non-empty slice when none does.  ``origin``
    is the wall the material started against, so an undisturbed block measures exactly."""
    k = np.floor((x[:, axis] - origin) / spacing).astype(int)
    shift = min(int(k.min()), 0)  # particles behind the origin (pushed through a wall) still count
    counts = np.bincount(k - shift)
    full = np.flatnonzero(counts >= min_count)
    last = int(full[-1]) if len(full) else int(np.flatnonzero(counts)[-1])
    return float(origin + (last + shift + 1) * spacing)


def sine_fit(t: np.ndarray, y: np.ndarray, f_guess: float) -> tuple[float, float, float]:
    """Least-squares fit y ~ B + A sin(2 pi f t + phi): returns (f, A, residual rms / A)."""
    from scipy.optimize import curve_fit

    def model(t, B, A, f, phi):
        return B + A * np.sin(2 * math.pi * f * t + phi)

    A0 = (y.max() - y.min()) / 2
    best = None
    for phi0 in (0.0, math.pi / 2, math.pi, 3 * math.pi / 2):
        try:
            p, _ = curve_fit(model, t, y, p0=(y.mean(), A0, f_guess, phi0), maxfev=20000)
        except RuntimeError:
            continue
        r = float(np.sqrt(np.mean((model(t, *p) - y) ** 2)))
        if best is None or r < best[1]:
            best = (p, r)
    if best is None:
        return float("nan"), float("nan"), float("nan")
    p, r = best
    return float(abs(p[2])), float(abs(p[1])), r / max(abs(p[1]), 1e-30)


# ============================================================================ cases
class Case(abc.ABC):
    """One physical test: set-up, reference, error measure.

    Subclasses set ``name``, ``title``, ``reference`` (Markdown: the relation or data used and
    its source), ``error_doc`` (what the error number means), ``variants`` and the settings per
    scale (``grids``, ``ppcs``, ``cfls``), and implement :meth:`run_variant`.  ``error`` of a
    run is a relative error (0 = exact); the case's error at a setting is the largest over its
    variants (:meth:`combine`).
    """

    name = ""
    title = ""
    reference = ""
    error_doc = ""
    variants: tuple = ("main",)
    smoke_variants: tuple | None = None  # the variants the smoke scale runs (None: all)
    grids: dict = {"smoke": (16,), "cpu": (16, 24, 32, 48, 64), "full": (32, 64, 96, 128)}
    ppcs: dict = {"smoke": (), "cpu": (1, 27), "full": (1, 27, 64)}
    cfls: dict = {"smoke": (), "cpu": (0.25, 0.9), "full": (0.25, 0.9)}
    ppc_cfl_grid: dict = {"smoke": None, "cpu": None, "full": 64}

    def settings(self, scale: str) -> list[Setting]:
        return ladder(scale, self.grids, ppc=self.ppcs, cfl=self.cfls, at=self.ppc_cfl_grid.get(scale))

    def variants_at(self, scale: str) -> tuple:
        return self.smoke_variants if scale == "smoke" and self.smoke_variants else self.variants

    def run(self, variant: str, setting: Setting, *, backend: str = "cpu", timeout_s: float | None = None,
            log: logging.Logger = LOG) -> RunRecord:
        if variant not in self.variants:
            raise ConfigError("validation variant", f"case {self.name} has variants {', '.join(self.variants)}, got {variant!r}")
        return self.run_variant(variant, setting, backend=backend, timeout_s=timeout_s, log=log)

    @abc.abstractmethod
    def run_variant(self, variant: str, setting: Setting, *, backend: str, timeout_s: float | None,
                    log: logging.Logger) -> RunRecord:
        """One run of ``variant`` at ``setting`` (the case's own set-up and error measure)."""

    def record(self, variant: str, setting: Setting, out: SimOutput, error: float | None, metrics: dict,
               series: dict | None = None) -> RunRecord:
        ok = out.stable and not out.timed_out and error is not None and math.isfinite(error)
        return RunRecord(self.name, variant, setting.id, float(error) if ok else None, round(out.sim_seconds, 4),
                         round(out.wall_seconds, 3), out.substeps, out.n_particles, bool(out.stable and not out.timed_out),
                         metrics, series or {}, out.message)

    notes = ""  # Markdown: what the measurements of this case show and why (report)
    # optional: a method (ax, records) drawing the measured quantity against its reference
    physics_plot: Callable | None = None

    @property
    def has_physics_plot(self) -> bool:
        return self.physics_plot is not None

    def combine(self, records: Sequence[RunRecord]) -> float | None:
        """The case's error at one setting from its variants' records (None if any failed)."""
        errs = [r.error for r in records]
        if not errs or any(e is None for e in errs):
            return None
        return max(errs)
