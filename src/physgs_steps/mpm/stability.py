"""Stability checks after each frame, and the error messages that say what to change.

A frame fails when, for some instance, a particle state is NaN/Inf, a particle left the
domain (its stencil leaves the grid), ``J = det F`` leaves ``[j_min, j_max]`` or a particle is
faster than ``max_speed``.  :func:`check` returns a :class:`Failure` naming the instance that
failed worst; :func:`explain` turns it into a message with the instance's material, its
parameters, the time-step situation and the change that would help.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field

import numpy as np

from .material import Material
from .timestep import StepPlan, TimeStepper


@dataclass(frozen=True)
class Thresholds:
    j_min: float = 0.02
    j_max: float = 20.0
    max_speed: float = 100.0  # m/s

    @classmethod
    def from_config(cls, d: dict | None) -> "Thresholds":
        d = d or {}
        return cls(j_min=float(d.get("j_min", 0.02)), j_max=float(d.get("j_max", 20.0)),
                   max_speed=float(d.get("max_speed", 100.0)))


@dataclass
class Failure:
    kind: str                 # nonfinite | outside | j_low | j_high | speed
    instance: int             # index of the worst instance
    value: float              # the offending count / J / speed
    frame: int
    time: float
    instances: list = field(default_factory=list)  # every failing instance index

    def as_dict(self, materials: list[Material]) -> dict:
        return {"kind": self.kind, "instance": materials[self.instance].name, "value": self.value,
                "frame": self.frame, "time": self.time, "instances": [materials[i].name for i in self.instances]}


def check(stats: dict, th: Thresholds, frame: int, time: float) -> Failure | None:
    """The worst failure of a frame, or None.  ``stats``: per-instance arrays from
    :meth:`MPMSolver.stats` (nonfinite, j_min, j_max, speed_max, outside) plus ``clamped``."""
    nonfinite = np.asarray(stats["nonfinite"])
    outside = np.asarray(stats["outside"])
    jlo, jhi, vmax = (np.asarray(stats[k]) for k in ("j_min", "j_max", "speed_max"))
    has = nonfinite == 0  # instances with finite particles have meaningful J/speed stats
    tests = [
        ("nonfinite", nonfinite > 0, nonfinite, True),
        ("outside", outside > 0, outside, True),
        ("speed", has & (vmax > th.max_speed), vmax, True),
        ("j_low", has & (jlo < th.j_min), jlo, False),
        ("j_high", has & (jhi > th.j_max), jhi, True),
    ]
    for kind, bad, value, largest in tests:
        if bad.any():
            idx = np.flatnonzero(bad)
            worst = int(idx[np.argmax(value[idx])] if largest else idx[np.argmin(value[idx])])
            return Failure(kind, worst, float(value[worst]), frame, time, [int(i) for i in idx])
    if int(stats.get("clamped", 0)) > 0:  # left the grid during a substep, came back by the frame's end
        return Failure("outside", int(np.argmax(outside)), float(stats["clamped"]), frame, time, [])
    return None


def explain(f: Failure, materials: list[Material], stepper: TimeStepper, plan: StepPlan, dx: float,
            n_grid: int, th: Thresholds, stage: str) -> str:
    """A user-facing message: what failed, where, with which material, and what to change."""
    m = materials[f.instance]
    # templates filled for the failure's own kind only: a speed or J that overflowed to inf is a
    # valid value of those kinds, but not a count (int(inf) raised here and lost the message)
    what = {
        "nonfinite": "{n} particles have NaN/Inf position, velocity or deformation",
        "outside": "{n} particles left the simulation domain",
        "speed": "a particle moves at {v:.3g} m/s (limit sim.stability.max_speed = {max_speed:g})",
        "j_low": "volume ratio J = det F fell to {v:.3g} (limit sim.stability.j_min = {j_min:g})",
        "j_high": "volume ratio J = det F grew to {v:.3g} (limit sim.stability.j_max = {j_max:g})",
    }[f.kind].format(n=int(f.value) if math.isfinite(f.value) else f.value, v=f.value, max_speed=th.max_speed,
                     j_min=th.j_min, j_max=th.j_max)
    where = [materials[i].name for i in (f.instances or [f.instance])]
    head = f"{stage}: the simulation became unstable at frame {f.frame} (t = {f.time:.3f} s): {what}"
    if plan.over_cfl:  # the cause is the material(s) stepped above the CFL limit, whatever broke first
        over = over_cfl_instances(materials, plan, dx, stepper.cfl)
        stiff = materials[over[0]]
        also = [materials[i].name for i in over[1:]]
        spread = [w for w in where if w not in [materials[i].name for i in over]]
        parts = [f"also over the CFL limit: {', '.join(repr(a) for a in also)}" if also else "",
                 f"it spread to {', '.join(repr(w) for w in spread)}" if spread else ""]
        extra = "; ".join(p for p in parts if p)
        return (f"{head}, in instance {stiff.describe()}, which is too stiff for the substep cap"
                f"{' (' + extra + ')' if extra else ''}. " + _advice(f, materials, stepper, plan, dx, n_grid))
    others = [w for w in where if w != m.name]
    also = f" (also affected: {', '.join(repr(o) for o in others)})" if others else ""
    return f"{head}, in instance {m.describe()}{also}. " + _advice(f, materials, stepper, plan, dx, n_grid)


def over_cfl_instances(materials: list[Material], plan: StepPlan, dx: float, cfl: float) -> list[int]:
    """Indices of the instances whose own CFL number dt c_k / dx exceeded ``cfl`` in ``plan``,
    stiffest first (at least the stiffest one)."""
    order = sorted(range(len(materials)), key=lambda i: -materials[i].cfl_speed)
    over = [i for i in order if plan.dt * materials[i].cfl_speed / dx > cfl * (1 + 1e-9)]
    return over or order[:1]


def failure_info(f: Failure, materials: list[Material], plan: StepPlan, dx: float, cfl: float) -> dict:
    """Structured account of a failure (stored in the stats next to the message)."""
    return {
        "kind": f.kind, "frame": f.frame, "time": f.time, "value": f.value,
        "instance": materials[f.instance].name,
        "instances": [materials[i].name for i in (f.instances or [f.instance])],
        "over_cfl": bool(plan.over_cfl), "dt": plan.dt, "cfl": plan.cfl,
        "cfl_per_instance": {m.name: plan.dt * m.cfl_speed / dx for m in materials},
        "over_cfl_instances": [materials[i].name for i in over_cfl_instances(materials, plan, dx, cfl)]
        if plan.over_cfl else [],
    }


def _advice(f: Failure, materials: list[Material], stepper: TimeStepper, plan: StepPlan, dx: float, n_grid: int) -> str:
    stiff = max(range(len(materials)), key=lambda i: materials[i].cfl_speed)
    ms = materials[stiff]
    m = materials[f.instance]
    if plan.over_cfl:
        need = stepper.substeps_needed(dx, ms.wave_speed)
        c_ok = stepper.cfl * dx * stepper.max_substeps / stepper.frame_dt
        e_ok = ms.max_E_for_wave_speed(c_ok)
        return (f"The time step was above the CFL limit (CFL {plan.cfl:.2f} > sim.cfl = {stepper.cfl:g}) because "
                f"sim.max_substeps = {stepper.max_substeps} caps the substeps: '{ms.name}' (E = {ms.E:.3g} Pa, "
                f"density {ms.density:g} kg/m^3) has a wave speed of {ms.wave_speed:.3g} m/s and needs about {need} "
                f"substeps per frame at n_grid {n_grid} (grid spacing dx = sim.domain_size / n_grid = {dx:.3g} m; "
                f"a smaller object needs proportionally more). Lower its E to at most {e_ok:.3g} Pa, or raise "
                f"sim.max_substeps to {need} (slower), or lower sim.n_grid.")
    if f.kind == "j_low":
        msg = (f"The material cannot carry the load (its own weight, an impact or a prescribed motion): raise E "
               f"of '{m.name}' (now {m.E:.3g} Pa; try {10 * m.E:.3g}), lower its density ({m.density:g} kg/m^3), "
               f"or give it a plasticity model that limits compression (j_clamp, drucker_prager).")
        if stepper.mode == "adaptive":
            e_ok = m.max_E_for_wave_speed(stepper.cfl * dx * stepper.max_substeps / stepper.frame_dt)
            if 10 * m.E > e_ok:
                msg += (f" But sim.max_substeps = {stepper.max_substeps} integrates '{m.name}' only up to E = "
                        f"{e_ok:.3g} Pa at grid spacing dx = {dx:.3g} m (sim.domain_size / n_grid): raise "
                        f"sim.max_substeps (about {stepper.substeps_needed(dx, m.wave_speed * 10 ** 0.5)} for "
                        "10x its E) or lower sim.n_grid.")
        return msg
    if f.kind == "j_high":
        return (f"The material is torn or inflated apart: raise E of '{m.name}' (now {m.E:.3g} Pa), lower the "
                "velocities and forces in the scene's dynamics, or use a plasticity model (j_clamp caps J).")
    if f.kind in ("outside", "speed"):
        msg = ("Check the scene's dynamics (initial velocities, impulses, enforced motions) and the domain walls; "
               f"a very soft or light material (E = {m.E:.3g} Pa, density {m.density:g} kg/m^3) can also splash "
               "out. Lower the velocities, raise E, or lower sim.cfl.")
        return msg + _speed_cap_note(stepper, dx, 1.0)
    # NaN/Inf: besides stiffness, a particle crossing many cells per substep blows the transfer up
    return (f"Lower sim.cfl (now {stepper.cfl:g}) or the stiffness of '{ms.name}' (E = {ms.E:.3g} Pa), or check "
            f"its Poisson ratio (nu = {ms.nu:g}; values near 0.5 make it nearly incompressible and hard to step)."
            + _speed_cap_note(stepper, dx, 9.8 * stepper.frame_dt))


def _speed_cap_note(stepper: TimeStepper, dx: float, v_expected: float) -> str:
    """The speed the substep cap allows (sim.cfl cells per substep), when it is below
    ``v_expected`` m/s (adaptive stepping only), else ''."""
    if stepper.mode != "adaptive":
        return ""
    v_ok = stepper.cfl * dx * stepper.max_substeps / stepper.frame_dt
    if v_ok >= v_expected:
        return ""
    return (f" At this resolution sim.max_substeps = {stepper.max_substeps} lets a particle move at most "
            f"{v_ok:.3g} m/s (sim.cfl = {stepper.cfl:g} cells of dx = {dx:.3g} m per substep; one frame of "
            f"free fall alone reaches {9.8 * stepper.frame_dt:.3g} m/s): raise sim.max_substeps or lower "
            "sim.n_grid.")


def cfl_note(materials: list[Material], stepper: TimeStepper, dx: float) -> str | None:
    """A warning when the stiffest material needs more substeps than the cap, else None."""
    stiff = max(materials, key=lambda m: m.cfl_speed)
    need = stepper.substeps_needed(dx, stiff.cfl_speed)
    if stepper.mode == "adaptive" and need > stepper.max_substeps:
        return (f"'{stiff.name}' (E = {stiff.E:.3g} Pa, wave speed {stiff.wave_speed:.3g} m/s) needs {need} substeps "
                f"per frame for CFL {stepper.cfl:g} at grid spacing dx = {dx:.3g} m; sim.max_substeps = "
                f"{stepper.max_substeps} caps it, so the run steps at CFL {stepper.cfl * need / stepper.max_substeps:.2f}")
    if stepper.mode == "fixed":
        cfl = stepper.frame_dt / stepper.fixed_substeps * stiff.cfl_speed / dx
        if cfl > stepper.cfl:
            return (f"fixed substep_dt gives CFL {cfl:.2f} for '{stiff.name}' (wave speed {stiff.wave_speed:.3g} m/s), "
                    f"above sim.cfl = {stepper.cfl:g}")
    return None

