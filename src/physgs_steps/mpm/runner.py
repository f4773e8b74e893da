"""The frame loop shared by forward_sim and final_sim.

``run_frames`` steps a loaded :class:`MPMSolver` through ``n_frames`` frames (frame 0 is the
initial state), plans the substeps of each frame (timestep.py), checks stability after each
frame (stability.py) and calls ``on_frame(frame, time, dt_next)`` for every stable frame.  On a
failure it stops; with ``keep_backup`` the solver is returned to the last stable frame's state
(device copy taken after every stable frame).  It never raises for instability: the caller
decides (forward_sim flags, final_sim raises).

With a :class:`~physgs_steps.mpm.rest.RestPolicy`, a scene that has come to rest is held:
no substeps until the dynamics' next change point (or the end), the held frames reported
through ``on_hold(frame, time)`` (``on_frame`` when no ``on_hold`` is given), and the
rest periods recorded in ``RunResult.rest`` and the log.
"""
from __future__ import annotations

import logging
import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .rest import RestPolicy, RestTracker
from .solver import MPMSolver
from .stability import Failure, Thresholds, check, explain, failure_info
from .timestep import StepPlan, TimeStepper


@dataclass
class RunResult:
    frames_done: int = 0                       # stable frames including frame 0
    substeps: list = field(default_factory=list)  # per simulated frame (1..)
    dts: list = field(default_factory=list)
    cfl: list = field(default_factory=list)
    over_cfl_frames: int = 0
    failure: Failure | None = None
    message: str | None = None
    info: dict | None = None
    last_stable_frame: int = 0
    first_substep_seconds: float = 0.0        # the substep kernels' first launches: compilation / cache load
    step_seconds: float = 0.0                 # substeps and checks, without those first launches
    callback_seconds: float = 0.0
    max_speed: float = 0.0
    j_range: list = field(default_factory=lambda: [1.0, 1.0])
    rest: list = field(default_factory=list)  # rest periods: {"frame", "time", "calm_since", "until_frame", "until_time"}
    held_frames: int = 0                       # frames held at rest (no substeps)

    @property
    def stable(self) -> bool:
        return self.failure is None

    def summary(self, n_particles: int) -> dict:
        total = int(sum(self.substeps))
        rate = n_particles * max(total - 1, 0) / self.step_seconds if self.step_seconds > 0 else None
        return {
            "stable": self.stable,
            "frames_done": self.frames_done,
            "last_stable_frame": self.last_stable_frame,
            "substeps_per_frame": [int(n) for n in self.substeps],
            "substeps_total": total,
            "dt_per_frame": [float(d) for d in self.dts],
            "max_cfl": float(max(self.cfl)) if self.cfl else None,
            "cfl_capped_frames": self.over_cfl_frames,
            "first_substep_seconds": round(self.first_substep_seconds, 3),
            "simulate_seconds": round(self.step_seconds, 3),
            "particle_substeps_per_second": rate,
            "max_speed": self.max_speed,
            "j_range": self.j_range,
            "rest": self.rest,
            "held_frames": self.held_frames,
            "failure": self.message,
            "failure_info": self.info,
        }


def run_frames(solver: MPMSolver, n_frames: int, stepper: TimeStepper, th: Thresholds,
               on_frame: Callable[[int, float, float], None], log: logging.Logger, *,
               keep_backup: bool = False, stage: str = "simulation", rest: RestPolicy | None = None,
               on_hold: Callable[[int, float], None] | None = None) -> RunResult:
    """Simulate frames 1..n_frames-1 after reporting frame 0; see the module docstring."""
    res = RunResult()
    tracker = RestTracker(rest, stepper.frame_dt) if rest is not None else None
    c_max = float(np.max(solver.wave_speeds()))
    frame_dt = stepper.frame_dt
    stats = solver.stats()
    fail = check(stats, th, 0, 0.0)
    plan = stepper.plan(solver.dx, c_max, float(np.max(stats["speed_max"])))
    if fail is not None:
        return _fail(res, fail, solver, stepper, plan, th, stage, log)
    _track(res, stats)
    t_cb = _time.perf_counter()
    on_frame(0, 0.0, plan.dt)
    # frame 0's callback is outside the timed window below: counted in callback_seconds, it is
    # not subtracted from step_seconds (it was: a first run in a process, whose frame-0 callback
    # loads kernels, reported its substeps seconds too low, even below zero)
    cb0 = _time.perf_counter() - t_cb
    res.callback_seconds += cb0
    if keep_backup:
        solver.save_backup()
    res.frames_done = 1
    every = max(1, (n_frames - 1) // 10)
    t_start = _time.perf_counter()
    for k in range(1, n_frames):
        if tracker is not None and tracker.held_since is not None:
            if not tracker.wakes(k):
                solver.time = k * frame_dt
                res.held_frames += 1
                res.substeps.append(0)
                res.dts.append(0.0)
                res.cfl.append(0.0)
                t_cb = _time.perf_counter()
                if on_hold is not None:
                    on_hold(k, solver.time)
                else:
                    on_frame(k, solver.time, plan.dt)
                res.callback_seconds += _time.perf_counter() - t_cb
                res.frames_done = k + 1
                res.last_stable_frame = k
                continue
            log.info("frame %d t=%.2fs: resuming substeps after rest (the dynamics' schedule changes at %.3g s)",
                     k, (k - 1) * frame_dt, tracker.events[-1]["until_time"])
        n_sub = plan.n
        if k == 1 and n_sub > 0:
            t0 = _time.perf_counter()
            solver.substep(plan.dt)
            n_sub -= 1
            reps = solver.substeps_per_launch()
            if 1 < reps <= n_sub:  # the kernel of R substeps a launch: its first launch, compiled or loaded
                solver.substeps(reps, plan.dt)
                n_sub -= reps
            _sync()
            res.first_substep_seconds = _time.perf_counter() - t0
            t_start += res.first_substep_seconds
        solver.substeps(n_sub, plan.dt)  # batched launches (MPMSolver.substeps)
        solver.time = k * frame_dt
        res.substeps.append(plan.n)
        res.dts.append(plan.dt)
        res.cfl.append(plan.cfl)
        res.over_cfl_frames += int(plan.over_cfl)
        stats = solver.stats()
        fail = check(stats, th, k, solver.time)
        if fail is not None:
            res.step_seconds = _time.perf_counter() - t_start - (res.callback_seconds - cb0)
            if keep_backup:
                solver.restore_backup()
            return _fail(res, fail, solver, stepper, plan, th, stage, log)
        _track(res, stats)
        v_max = float(np.max(stats["speed_max"]))
        used = plan
        plan = stepper.plan(solver.dx, c_max, v_max)
        t_cb = _time.perf_counter()
        on_frame(k, solver.time, plan.dt)
        res.callback_seconds += _time.perf_counter() - t_cb
        if keep_backup:
            solver.save_backup()
        res.frames_done = k + 1
        res.last_stable_frame = k
        if tracker is not None and k < n_frames - 1 and tracker.observe(k, solver.time, v_max):
            ev = tracker.events[-1]
            res.rest = tracker.events
            until = "the end" if ev["until_time"] is None else f"{ev['until_time']:.3g} s (a change of the dynamics)"
            log.info("frame %d t=%.2fs: at rest (every particle below %.3g m/s since t=%.2fs): holding the state "
                     "until %s, no substeps", k, solver.time, rest.speed, ev["calm_since"], until)
        if k % every == 0 or k == n_frames - 1:
            log.info("frame %d/%d t=%.2fs: %d substeps (dt %.2e s, CFL %.2f%s), v_max %.2f m/s, J [%.3f, %.3f], %.1f s",
                     k, n_frames - 1, solver.time, used.n, used.dt, used.cfl, ", capped" if used.over_cfl else "",
                     v_max, float(np.min(stats["j_min"])), float(np.max(stats["j_max"])),
                     _time.perf_counter() - t_start)
    res.step_seconds = _time.perf_counter() - t_start - (res.callback_seconds - cb0)
    if tracker is not None:
        res.rest = tracker.events
    return res


def _fail(res: RunResult, fail: Failure, solver: MPMSolver, stepper: TimeStepper, plan: StepPlan, th: Thresholds,
          stage: str, log: logging.Logger) -> RunResult:
    res.failure = fail
    res.message = explain(fail, solver.materials, stepper, plan, solver.dx, solver.n_grid, th, stage)
    res.info = failure_info(fail, solver.materials, plan, solver.dx, stepper.cfl)
    log.warning("%s", res.message)
    return res


def _track(res: RunResult, stats: dict) -> None:
    res.max_speed = max(res.max_speed, float(np.max(stats["speed_max"])))
    res.j_range = [min(res.j_range[0], float(np.min(stats["j_min"]))), max(res.j_range[1], float(np.max(stats["j_max"])))]


def _sync() -> None:
    import taichi as ti

    ti.sync()
