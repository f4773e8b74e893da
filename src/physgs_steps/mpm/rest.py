"""Rest detection: no substeps for frames in which nothing moves.

Objects that fall, bounce and settle spend most of a 5 s clip at rest, and a substep costs
the same whether anything moves or not. After every frame :func:`run_frames` asks
:class:`RestPolicy` whether the scene is at rest: every simulated particle has stayed below
``sim.rest.speed`` (m/s) for at least ``sim.rest.duration`` seconds of frames, and no action
of the scene's dynamics is *driving* it right now. Then the state is held (no substeps,
the frames repeat the state of the frame where rest began; logged with that frame) until
the next *change point* of the dynamics' schedule: a force or enforced motion that starts
later (an impulse at 2 s, a wind that begins, a held part that is released at its
``end_time``), where substepping resumes from the held state.

Driving actions (they keep a scene from resting while they act): ``particle_impulse``,
``wind`` with a non-zero mean or amplitude, ``enforce_particle_translation`` with a non-zero
velocity, ``enforce_particle_velocity_rotation`` with a non-zero speed, ``cuboid`` with a
non-zero velocity. Gravity, the ground, colliders and zero-velocity holds are not: material
at rest under them stays at rest. Change points are the start and end times of every
boundary condition (a zero-velocity hold that ends releases what it held).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import ConfigError


@dataclass
class RestPolicy:
    """When a simulation may stop substepping (see the module docstring).

    Attributes:
        speed: rest speed in m/s; every particle must stay below it.
        duration: seconds the scene must have been below ``speed`` before it is held.
        driving: [(t0, t1)] intervals (s) in which an action drives the scene.
        changes: sorted times (s) at which the dynamics' schedule changes.
    """

    speed: float
    duration: float
    driving: list = field(default_factory=list)
    changes: list = field(default_factory=list)

    @classmethod
    def from_config(cls, rest: dict | None, dynamics) -> "RestPolicy | None":
        """``sim.rest`` plus the scene's :class:`~physgs_steps.mpm.dynamics.Dynamics`; None when disabled."""
        rest = rest or {}
        if not rest.get("enabled", True):
            return None
        speed, duration = float(rest.get("speed", 0.01)), float(rest.get("duration", 0.5))
        if not (math.isfinite(speed) and speed > 0):
            raise ConfigError("sim.rest.speed", f"must be a positive speed in m/s, got {speed!r}")
        if not (math.isfinite(duration) and duration >= 0):
            raise ConfigError("sim.rest.duration", f"must be >= 0 s, got {duration!r}")
        driving, changes = schedule(dynamics)
        return cls(speed=speed, duration=duration, driving=driving, changes=changes)

    def driven(self, t: float) -> bool:
        """Whether a driving action acts at time ``t``."""
        return any(t0 <= t < t1 for t0, t1 in self.driving)

    def next_change(self, t: float) -> float:
        """The first change point strictly after ``t`` (inf when there is none)."""
        later = [c for c in self.changes if c > t + 1e-9]
        return min(later) if later else math.inf


def schedule(dynamics) -> tuple[list, list]:
    """([(t0, t1)] driving intervals, sorted change times) of a Dynamics."""
    driving, changes = [], set()
    for e in getattr(dynamics, "boundary_conditions", []) or []:
        t0 = float(e.get("start_time", 0.0))
        t1 = e.get("end_time")
        t1 = math.inf if t1 is None else float(t1)
        kind = e["type"]
        if kind == "particle_impulse":
            t1 = t0 + float(e.get("duration", 0.02))
            moving = any(abs(float(v)) > 0 for v in e.get("delta_v", []))
        elif kind == "wind":
            moving = any(abs(float(v)) > 0 for v in list(e.get("mean", [])) + list(e.get("amplitude", [])))
        elif kind in ("enforce_particle_translation", "cuboid"):
            moving = any(abs(float(v)) > 0 for v in e.get("velocity", []))
        elif kind == "enforce_particle_velocity_rotation":
            moving = abs(float(e.get("rotation_scale", 0.0))) > 0 or abs(float(e.get("translation_scale", 0.0))) > 0
        else:  # surface colliders and the like never drive the material
            moving = False
        if moving:
            driving.append((t0, t1))
        if t0 > 0:
            changes.add(t0)
        if math.isfinite(t1):
            changes.add(t1)
    return driving, sorted(changes)


@dataclass
class RestTracker:
    """Per-frame bookkeeping of :class:`RestPolicy` inside the frame loop."""

    policy: RestPolicy
    frame_dt: float
    calm_since: float | None = None   # time since which every particle is below the rest speed
    held_since: int | None = None     # frame at which the state is held, None while stepping
    wake_time: float = math.inf
    events: list = field(default_factory=list)  # [{"frame", "time", "until_frame", "until_time"}]

    def observe(self, frame: int, t: float, v_max: float) -> bool:
        """Feed the state after ``frame`` (time ``t``, largest speed ``v_max`` m/s); True when the
        state is to be held from here on."""
        p = self.policy
        if v_max >= p.speed or p.driven(t):
            self.calm_since = None
            return False
        if self.calm_since is None:
            self.calm_since = t
        if t - self.calm_since + 1e-9 < p.duration:
            return False
        wake = p.next_change(t)
        self.held_since, self.wake_time = frame, wake
        self.events.append({"frame": frame, "time": round(t, 6), "calm_since": round(self.calm_since, 6),
                            "until_frame": None, "until_time": None if math.isinf(wake) else round(wake, 6)})
        return True

    def wakes(self, frame: int) -> bool:
        """Whether substepping resumes for ``frame`` (whose substeps run from (frame-1)/fps to
        frame/fps): the next change point falls within that interval."""
        if self.held_since is None:
            return False
        if frame * self.frame_dt > self.wake_time - 1e-9:  # at worst one frame early, never late
            self.events[-1]["until_frame"] = frame - 1
            self.held_since, self.calm_since, self.wake_time = None, None, math.inf
            return True
        return False
