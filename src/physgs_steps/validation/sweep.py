"""The stiff/extreme sweep: every elasticity x plasticity pair over E, nu and density extremes.

Each cell simulates a small elastic cube dropped 1 cm onto a frictional floor (n_grid 16, 8
particles per cell, the pipeline's time stepping: CFL 0.5, at most ``sim.max_substeps`` = 200
substeps per frame, 15 frames at 30 fps) and is classified:

* ``stable``: every frame simulated, every value handed out finite;
* ``error``: the run stopped with a message that names the instance's parameters and a fix
  (or the material was refused at set-up with a ConfigError naming the key);
* ``nan``: a non-finite value was handed out, or the run failed without such a message;
* ``hang``: the run exceeded its wall-clock bound (``timeout_s``).

Work per cell is bounded by construction (frames x max_substeps substeps), so a hang can only
come from a machine far slower than expected.  The pair's kernels are compiled before the
first cell (:func:`warm_up`), so compilation never counts against a cell's bound.
"""
from __future__ import annotations

import itertools
import logging
import math
import time

import numpy as np

from ..errors import ConfigError
from ..materials_kb import ELASTICITY_MODELS, PLASTICITY_MODELS
from ..mpm import Dynamics, Material
from .base import LOG, RunTimeout, Scene, Setting, simulate

E_VALUES = (30.0, 3.0e3, 3.0e5, 3.0e7, 3.0e10)  # Pa
NU_VALUES = (0.0, 0.3, 0.49)
RHO_VALUES = (10.0, 1000.0, 2.0e4)  # kg/m^3
OUTCOMES = ("stable", "error", "nan", "hang")
SETTING = Setting(16, 8, 0.5)
N_FRAMES = 15
MAX_SUBSTEPS = 200
PLASTICITY_PARAMS = {"yield_stress": None, "friction_angle": 30.0, "cohesion": 0.0, "j_min": 0.6, "j_max": 1.2}

# smoke: two pairs over the corners of the parameter box
SMOKE_PAIRS = (("fixed_corotated", "identity"), ("stvk_hencky", "drucker_prager"))
SMOKE_CELLS = tuple(itertools.product((30.0, 3.0e10), (0.3,), (10.0, 2.0e4)))


def pairs(scale: str) -> list[tuple[str, str]]:
    """(elasticity, plasticity) pairs of a scale: all of them except at smoke scale."""
    if scale == "smoke":
        return list(SMOKE_PAIRS)
    return list(itertools.product(ELASTICITY_MODELS, PLASTICITY_MODELS))


def cells(scale: str) -> list[tuple[float, float, float]]:
    """(E, nu, density) cells of a scale."""
    if scale == "smoke":
        return list(SMOKE_CELLS)
    return list(itertools.product(E_VALUES, NU_VALUES, RHO_VALUES))


def pair_id(elasticity: str, plasticity: str) -> str:
    return f"{elasticity}__{plasticity}"


def parse_pair(text: str) -> tuple[str, str]:
    try:
        el, pl = text.split("__")
    except ValueError:
        raise ConfigError("validation sweep pair", f"expected <elasticity>__<plasticity>, got {text!r}") from None
    if el not in ELASTICITY_MODELS or pl not in PLASTICITY_MODELS:
        raise ConfigError("validation sweep pair", f"unknown pair {text!r}")
    return el, pl


def clear_message(msg: str | None, name: str) -> bool:
    """Whether a failure message names the instance, its parameters and a change to make."""
    if not msg:
        return False
    return f"'{name}'" in msg and "E=" in msg and "density=" in msg and any(
        w in msg for w in ("Lower", "lower", "raise", "Raise"))


def run_cell(elasticity: str, plasticity: str, E: float, nu: float, rho: float, *, backend: str = "cpu",
             timeout_s: float = 120.0, log: logging.Logger = LOG) -> dict:
    """One cell of the sweep: {"outcome", "substeps", "seconds", "message", ...}."""
    cell = {"elasticity": elasticity, "plasticity": plasticity, "E": E, "nu": nu, "density": rho}
    t0 = time.perf_counter()
    yield_stress = 1e-3 * E if plasticity == "von_mises" else None
    try:
        m = Material(elasticity, plasticity, E=E, nu=nu, density=rho, name="cube", preset="sweep",
                     **{**PLASTICITY_PARAMS, "yield_stress": yield_stress})
    except ConfigError as e:
        return {**cell, "outcome": "error", "substeps": 0, "seconds": 0.0, "message": str(e)}
    sc = _scene(m)
    finite = [True]

    def on_frame(k, t, st):
        if not all(np.isfinite(a).all() for a in st.values()):
            finite[0] = False

    try:
        out = simulate(sc, SETTING, fps=30.0, n_frames=N_FRAMES, on_frame=on_frame, backend=backend,
                       max_substeps=MAX_SUBSTEPS, timeout_s=timeout_s, log=log)
    except RunTimeout:  # pragma: no cover - simulate catches it
        out = None
    seconds = time.perf_counter() - t0
    if out is None or out.timed_out:
        outcome = "hang"
    elif not finite[0]:
        outcome = "nan"
    elif out.stable:
        outcome = "stable"
    else:
        outcome = "error" if clear_message(out.message, "cube") else "nan"
    return {**cell, "outcome": outcome, "substeps": 0 if out is None else out.substeps, "seconds": round(seconds, 3),
            "failure": (out.info or {}).get("kind") if out is not None else None,
            "message": None if out is None else out.message}


def warm_up(elasticity: str, plasticity: str, backend: str = "cpu") -> float:
    """Compile the pair's kernels (one substep of a mild cell) so that no cell's time bound
    includes compilation; returns the seconds it took."""
    from ..mpm import MPMSolver  # Taichi: loaded when the sweep runs, not when it is planned

    t0 = time.perf_counter()
    m = Material(elasticity, plasticity, E=3e5, nu=0.3, density=1000.0, name="cube",
                 **{**PLASTICITY_PARAMS, "yield_stress": 300.0 if plasticity == "von_mises" else None})
    sc = _scene(m)
    solver = MPMSolver(sc.materials, n_grid=SETTING.n_grid, domain_size=1.0, dynamics=sc.dynamics, backend=backend)
    solver.set_particles(sc.x, sc.vol, sc.material)
    solver.substep(1e-4)
    solver.stats()
    return time.perf_counter() - t0


def _scene(m: Material) -> Scene:
    dx = 1.0 / SETTING.n_grid
    floor = 4 * dx
    dyn = Dynamics(gravity=(0.0, 0.0, -9.8), boundary="slip", ground={"height": floor, "surface": "separate",
                                                                       "friction": 0.3})
    lo = np.array([0.42, 0.42, floor + 0.01])
    return Scene.block(m, lo, lo + 0.16, SETTING, 1.0, dyn)


def run_pair(elasticity: str, plasticity: str, scale: str, *, backend: str = "cpu", timeout_s: float = 120.0,
             log: logging.Logger = LOG) -> dict:
    """Every cell of a scale for one pair: {"pair", "cells": [...], "counts": {outcome: n}}.
    The pair's kernels are compiled first (outside every cell's time bound)."""
    compile_s = warm_up(elasticity, plasticity, backend)
    log.info("%s/%s: kernels ready in %.1f s", elasticity, plasticity, compile_s)
    rows = []
    todo = cells(scale)
    for i, (E, nu, rho) in enumerate(todo):
        r = run_cell(elasticity, plasticity, E, nu, rho, backend=backend, timeout_s=timeout_s, log=log)
        rows.append(r)
        log.info("%s/%s cell %d/%d E=%.3g nu=%g rho=%g: %s (%d substeps, %.1f s)", elasticity, plasticity, i + 1,
                 len(todo), E, nu, rho, r["outcome"], r["substeps"], r["seconds"])
    counts = {o: sum(r["outcome"] == o for r in rows) for o in OUTCOMES}
    return {"pair": pair_id(elasticity, plasticity), "elasticity": elasticity, "plasticity": plasticity,
            "scale": scale, "cells": rows, "counts": counts, "compile_seconds": round(compile_s, 2),
            "seconds": round(sum(r["seconds"] for r in rows), 2)}


def wave_speed(E: float, nu: float, rho: float) -> float:
    """P-wave speed sqrt((lam + 2 mu) / rho) in m/s."""
    return math.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / rho)
