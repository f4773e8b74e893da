"""Time stepping: adaptive CFL substeps per frame, or PhysGaussian's fixed substep.

Adaptive (docs/CONTRACTS.md): ``dt = cfl * dx / max(c_max, v_max)`` limited to
``[dt_min, frame_dt]``; ``n = ceil(frame_dt / dt)`` capped at ``max_substeps``; then
``dt = frame_dt / n`` so that frames fall on ``k / fps`` exactly.  ``c_max`` is the largest
wave speed of the scene's deformable materials, ``Material.wave_speed``: the P-wave speed
``sqrt((lam + 2 mu) / rho)`` of a solid, the sound speed of ``fluid`` (``sqrt(lam / rho)``)
and ``volume`` (``sqrt(2 (lam + 2 mu / 3) / rho)``) models (a rigid
instance carries no elastic waves: ``Material.cfl_speed`` is 0; ``MPMSolver.wave_speeds``),
``v_max`` the largest particle speed at the start of the frame, rigid bodies included.  Fixed: ``n = ceil(frame_dt / substep_dt)``,
``dt = frame_dt / n``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import ConfigError


@dataclass(frozen=True)
class StepPlan:
    """Substeps of one frame."""

    n: int              # substeps this frame
    dt: float           # s
    dt_cfl: float       # the CFL time step (s), inf when nothing moves and nothing is elastic
    cfl: float          # effective CFL number: dt * max(c_max, v_max) / dx
    over_cfl: bool      # dt > dt_cfl (the cap or dt_min forced a larger step)


@dataclass(frozen=True)
class TimeStepper:
    mode: str = "adaptive"
    fps: float = 30.0
    cfl: float = 0.5
    dt_min: float = 1e-6
    max_substeps: int = 200
    substep_dt: float = 1e-4

    def __post_init__(self) -> None:
        if self.mode not in ("adaptive", "fixed"):
            raise ConfigError("sim.dt_mode", f"must be adaptive or fixed, got {self.mode!r}")
        for key, v in (("sim.fps", self.fps), ("sim.cfl", self.cfl), ("sim.dt_min", self.dt_min),
                       ("sim.substep_dt", self.substep_dt)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(key, f"must be a positive number, got {v!r}")
        if int(self.max_substeps) < 1:
            raise ConfigError("sim.max_substeps", f"must be >= 1, got {self.max_substeps}")
        if self.mode == "fixed" and self.fixed_substeps > self.max_substeps:
            raise ConfigError("sim.substep_dt", f"{self.substep_dt:g} s needs {self.fixed_substeps} substeps per frame at "
                                                f"{self.fps:g} fps, more than sim.max_substeps={self.max_substeps}; "
                                                "raise sim.max_substeps or sim.substep_dt")

    @classmethod
    def from_config(cls, sim: dict) -> "TimeStepper":
        return cls(mode=sim.get("dt_mode", "adaptive"), fps=float(sim.get("fps", 30.0)), cfl=float(sim.get("cfl", 0.5)),
                   dt_min=float(sim.get("dt_min", 1e-6)), max_substeps=int(sim.get("max_substeps", 200)),
                   substep_dt=float(sim.get("substep_dt", 1e-4)))

    @property
    def frame_dt(self) -> float:
        return 1.0 / self.fps

    @property
    def fixed_substeps(self) -> int:
        return max(1, math.ceil(self.frame_dt / self.substep_dt - 1e-9))

    def plan(self, dx: float, c_max: float, v_max: float) -> StepPlan:
        """The substeps of the next frame for grid spacing ``dx`` (m), the largest wave speed
        ``c_max`` and particle speed ``v_max`` (m/s)."""
        speed = max(c_max, v_max)
        dt_cfl = self.cfl * dx / speed if speed > 0 else math.inf
        if self.mode == "fixed":
            n = self.fixed_substeps
        else:
            dt = min(max(dt_cfl, self.dt_min), self.frame_dt)
            n = min(max(1, math.ceil(self.frame_dt / dt - 1e-9)), int(self.max_substeps))
        dt = self.frame_dt / n
        return StepPlan(n=n, dt=dt, dt_cfl=dt_cfl, cfl=dt * speed / dx, over_cfl=dt > dt_cfl * (1 + 1e-9))

    def substeps_needed(self, dx: float, speed: float) -> int:
        """Substeps per frame the CFL condition asks for at ``speed`` m/s (no cap)."""
        if speed <= 0:
            return 1
        return max(1, math.ceil(self.frame_dt / (self.cfl * dx / speed) - 1e-9))
