"""Stiff and extreme materials end either in a stable run or in a clear error, never in NaN
output or a hang; time-step planning; the error messages."""
from __future__ import annotations

import itertools
import logging
import math

import numpy as np
import pytest

from physgs_steps.errors import ConfigError
from physgs_steps.mpm import Dynamics, Material, MPMSolver
from physgs_steps.mpm.runner import run_frames
from physgs_steps.mpm.stability import Thresholds
from physgs_steps.mpm.timestep import TimeStepper

LOG = logging.getLogger("test.mpm")


def _cube(spacing: float = 1 / 48) -> tuple[np.ndarray, np.ndarray]:
    axes = [np.arange(lo + spacing / 2, hi, spacing) for lo, hi in ((0.4, 0.6), (0.4, 0.6), (0.3, 0.45))]
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return x, np.full(len(x), spacing ** 3)


CASES = list(itertools.product([3.0e10, 3.0e8, 30.0], [0.3, 0.49], [10.0, 20000.0]))


@pytest.mark.parametrize("E,nu,rho", CASES)
def test_extreme_material_is_stable_or_fails_clearly(E, nu, rho):
    x, vol = _cube()
    m = Material("fixed_corotated", "identity", E=E, nu=nu, density=rho, name="blob", preset="jelly")
    s = MPMSolver([m], n_grid=16, dynamics=Dynamics.free(), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    stepper = TimeStepper(fps=30.0, cfl=0.5, max_substeps=40)
    frames = []
    res = run_frames(s, 8, stepper, Thresholds(), lambda k, t, dt: frames.append(s.get_state()), LOG)
    assert sum(res.substeps) <= 7 * 40  # bounded work: no hang whatever the material
    for st in frames:  # every frame handed out is finite
        assert all(np.isfinite(a).all() for a in st.values())
    if res.stable:
        assert len(frames) == 8
    else:
        msg = res.message
        assert "'blob'" in msg and f"E={E:.3g} Pa" in msg and f"density={rho:g}" in msg
        assert "jelly" in msg and ("Lower" in msg or "raise" in msg)
        # the solver is left at (or before) the failure; what was handed out stays finite
        assert res.failure.frame >= 1 and len(frames) == res.failure.frame


def test_cfl_capped_stiff_material_names_the_fix():
    x, vol = _cube()
    m = Material("fixed_corotated", "identity", E=3.0e8, nu=0.3, density=1000.0, name="stone")
    s = MPMSolver([m], n_grid=16, dynamics=Dynamics.free(), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    stepper = TimeStepper(fps=30.0, cfl=0.5, max_substeps=40)
    res = run_frames(s, 8, stepper, Thresholds(), lambda *a: None, LOG)
    assert not res.stable
    assert "sim.max_substeps = 40" in res.message and "Lower its E to at most" in res.message
    e_ok = float(res.message.split("Lower its E to at most ")[1].split(" Pa")[0])
    c_ok = m.with_(E=e_ok).wave_speed
    assert stepper.plan(s.dx, c_ok, 0.0).n <= 40  # the suggested E fits the cap


def test_keep_backup_returns_to_last_stable_frame():
    x, vol = _cube()
    m = Material("fixed_corotated", "identity", E=3.0e8, nu=0.3, density=1000.0, name="stone")
    s = MPMSolver([m], n_grid=16, dynamics=Dynamics.free(), backend="cpu")
    s.set_particles(x, vol, np.zeros(len(x), int))
    seen = {}
    res = run_frames(s, 8, TimeStepper(max_substeps=40), Thresholds(), lambda k, t, dt: seen.update({k: s.get_state()}),
                     LOG, keep_backup=True)
    assert not res.stable
    st = s.get_state()
    last = seen[res.last_stable_frame]
    assert all(np.array_equal(st[k], last[k]) for k in st)


def test_time_step_plans():
    ts = TimeStepper(fps=30.0, cfl=0.5, max_substeps=100)
    dx = 1 / 32
    p = ts.plan(dx, 8.0, 1.0)
    assert p.n == math.ceil((1 / 30) / (0.5 * dx / 8.0)) and not p.over_cfl
    assert p.dt * p.n == pytest.approx(1 / 30) and p.cfl <= 0.5
    p = ts.plan(dx, 1000.0, 0.0)  # capped
    assert p.n == 100 and p.over_cfl and p.cfl > 0.5
    p = ts.plan(dx, 0.0, 0.0)  # nothing moves, no stiffness: one substep per frame
    assert p.n == 1
    fixed = TimeStepper(mode="fixed", substep_dt=1e-3, fps=30.0)
    assert fixed.plan(dx, 8.0, 0.0).n == 34
    with pytest.raises(ConfigError, match="sim.substep_dt"):
        TimeStepper(mode="fixed", substep_dt=1e-6, max_substeps=100)
    with pytest.raises(ConfigError, match="sim.dt_mode"):
        TimeStepper(mode="implicit")


@pytest.mark.parametrize("kind,value", [("speed", math.inf), ("j_high", math.inf), ("nonfinite", 12.0),
                                        ("outside", math.inf)])
def test_failure_message_survives_an_overflowed_value(kind, value):
    """A speed or J that overflowed float32 is inf: the message still names it (the stiff sweep's
    stvk_hencky/von_mises cell E 3e7, nu 0.3, density 10 kg/m^3 ended in OverflowError from
    int(inf) while the message was built, and the whole sweep job failed with it)."""
    from physgs_steps.mpm.stability import Failure, explain

    m = Material("stvk_hencky", "von_mises", E=3e7, nu=0.3, density=10.0, yield_stress=3e4, name="cube")
    stepper = TimeStepper()
    plan = stepper.plan(1 / 16, m.cfl_speed, 0.0)
    msg = explain(Failure(kind, 0, value, 3, 0.1, [0]), [m], stepper, plan, 1 / 16, 16, Thresholds(), "test")
    assert "frame 3" in msg and "cube" in msg
    assert ("inf" in msg) == (not math.isfinite(value))
