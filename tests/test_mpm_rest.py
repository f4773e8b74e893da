"""Rest detection (physgs_steps.mpm.rest): a scene at rest is held without substeps and
resumes when its dynamics' schedule changes."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from physgs_steps.errors import ConfigError
from physgs_steps.mpm import Dynamics, Material, MPMSolver
from physgs_steps.mpm.rest import RestPolicy, RestTracker, schedule
from physgs_steps.mpm.runner import run_frames
from physgs_steps.mpm.stability import Thresholds
from physgs_steps.mpm.timestep import TimeStepper

LOG = logging.getLogger("test.mpm.rest")


def test_schedule_driving_actions_and_change_points():
    dyn = Dynamics.from_config({"boundary_conditions": [
        {"type": "enforce_particle_translation", "velocity": [0.1, 0, 0], "end_time": 0.75},
        {"type": "enforce_particle_translation", "velocity": [0, 0, 0], "start_time": 0.75},
        {"type": "particle_impulse", "delta_v": [0, 0, 1], "start_time": 2.0, "duration": 0.05},
        {"type": "wind", "mean": [0, 0, 0], "amplitude": [0, 0, 0], "start_time": 3.0},  # blows nothing
        {"type": "cuboid", "point": [0.5, 0.5, 0.2], "size": [0.1, 0.1, 0.1], "end_time": 4.0},  # a hold released at 4 s
    ]})
    driving, changes = schedule(dyn)
    assert driving == [(0.0, 0.75), (2.0, 2.05)]
    assert changes == [0.75, 2.0, 2.05, 3.0, 4.0]
    p = RestPolicy(0.01, 0.1, driving, changes)
    assert p.driven(0.5) and not p.driven(1.0) and p.driven(2.01)
    assert p.next_change(1.0) == 2.0 and p.next_change(4.0) == math.inf
    assert RestPolicy.from_config({"enabled": False}, dyn) is None
    with pytest.raises(ConfigError, match="sim.rest.speed"):
        RestPolicy.from_config({"speed": -1.0}, dyn)


def test_tracker_needs_the_whole_duration_and_wakes_at_the_change():
    fdt = 1 / 30
    tr = RestTracker(RestPolicy(speed=0.01, duration=0.1, driving=[(1.0, 1.1)], changes=[1.0, 1.1]), fdt)
    held = [k for k in range(1, 30) if tr.held_since is None and tr.observe(k, k * fdt, 0.5 if k < 5 else 0.001)]
    # calm from frame 5 (t = 0.167 s); 0.1 s later (frame 8) the state is held
    assert held == [8] and tr.events[0]["frame"] == 8 and tr.events[0]["until_time"] == 1.0
    assert not any(tr.wakes(k) for k in range(9, 30))  # frames 9..29 end before 1.0 s
    assert tr.wakes(30) and tr.events[0]["until_frame"] == 29 and tr.held_since is None
    assert not tr.observe(31, 31 * fdt, 0.0)  # the impulse drives the scene: no rest while it acts


def _block():
    s = 1 / 40
    axes = [np.arange(lo + s / 2, hi, s) for lo, hi in ((0.4, 0.6), (0.4, 0.6), (0.3, 0.45))]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return x, np.full(len(x), s ** 3)


@pytest.fixture(scope="module")
def runs():
    """A jelly block floating without gravity, kicked upwards at 0.3 s: with and without rest detection."""
    dyn = Dynamics.from_config({"gravity": [0, 0, 0], "ground": None, "boundary_conditions": [
        {"type": "particle_impulse", "delta_v": [0.0, 0.0, 0.5], "start_time": 0.3, "duration": 0.02}]})
    out = {}
    for rest in (False, True):
        x, vol = _block()
        s = MPMSolver([Material("fixed_corotated", "identity", E=2e4, nu=0.3, density=1000.0, name="block")],
                      n_grid=16, dynamics=dyn, backend="cpu")
        s.set_particles(x, vol, np.zeros(len(x), int))
        policy = RestPolicy.from_config({"speed": 0.01, "duration": 0.1}, dyn) if rest else None
        frames, held = [], []
        res = run_frames(s, 16, TimeStepper(fps=30.0, max_substeps=40), Thresholds(),
                         lambda k, t, dt: frames.append(s.get_state()["x"]), LOG, rest=policy,
                         on_hold=lambda k, t: (held.append(k), frames.append(frames[-1])))
        out[rest] = (res, frames, held)
    return out


def test_resting_block_is_held_then_resumes_for_the_impulse(runs):
    res, frames, held = runs[True]
    ref_res, ref_frames, _ = runs[False]
    assert res.stable and len(frames) == 16
    # calm from frame 1 on; after 0.1 s (frame 4) held until the impulse at 0.3 s (frame 9 steps again)
    assert res.rest[0]["frame"] == 4 and res.rest[0]["until_frame"] == 8 and held == list(range(5, 9))
    assert res.held_frames == 4 and res.substeps[4:8] == [0] * 4 and min(res.substeps[8:]) > 0
    assert sum(res.substeps) < sum(ref_res.substeps)
    # the held frames are the state the simulation would have had, and the kick happens as without rest
    for k in range(16):
        np.testing.assert_allclose(frames[k], ref_frames[k], atol=2e-5)
    assert frames[-1][:, 2].mean() > frames[0][:, 2].mean() + 0.05
