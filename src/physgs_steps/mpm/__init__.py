"""MLS-MPM engine in Taichi (docs/CONTRACTS.md "MPM step"; FastPhysGS appendix A, B.1-B.2).

Quadratic B-spline MLS-MPM with APIC transfers in f32 on ti.cpu or ti.cuda, several materials
in one simulation (each particle carries its instance's models and parameters), kernels
specialised at compile time to the (elasticity, plasticity) pairs and dynamics a scene uses,
Taichi's offline cache in ``runtime.cache_dir("taichi")``.

Units.  Arrays handed in and out are in DOMAIN UNITS: positions in the unit cube [0, 1]^3 of
the simulation frame (z up), velocities in domain units/s, C in 1/s, F unit-free, particle
volumes in domain units^3.  One domain unit is ``domain_size`` metres (sim.domain_size, 1 m by
default); inside, the solver works in SI (x_phys = L x, p_vol = vol L^3, p_mass = density
p_vol), material parameters are SI (E, yield stress in Pa, density kg/m^3), gravity m/s^2.

One substep from a given state (the cross-check with the torch pseudo-step)::

    import numpy as np
    from physgs_steps.mpm import MPMSolver, Material, Dynamics

    mats = [Material("fixed_corotated", "identity", E=1e5, nu=0.3, density=1000.0, name="bear")]
    s = MPMSolver(mats, n_grid=32, domain_size=1.0, backend="cpu",
                  dynamics=Dynamics.free(gravity=(0, 0, -9.8), boundary="slip"))  # gravity + walls only
    s.set_particles(x, vol, material)   # x [P,3], vol [P], material [P] int (index into mats);
                                        # face=colliders.face_half_width(vol, ~filled): gaussians' contact at their centre
    s.set_state(x, v, C, F)             # [P,3], [P,3], [P,3,3], [P,3,3]; stresses recomputed from F
    s.substep(dt)                       # dt in seconds
    st = s.get_state()                  # {"x","v","C","F"}: float32, same row order as given
    tau = s.get_stress()                # [P,3,3] Kirchhoff stress (Pa) of the new F

``MPMSolver.kirchhoff(F, material)`` and ``MPMSolver.return_map(F_trial, material)`` evaluate
the constitutive models alone.  ``Material.from_params(entry)`` reads a params.json entry,
``preset("jelly")`` a knowledge-base material.  CPU runs are bitwise reproducible; on CUDA the
grid transfer uses float atomics, so runs agree to float tolerance.

Rigid and static instances: ``Material(..., rigid=True)`` moves as one rigid body coupled
two-way to the grid (rigid.py); ``rigid=True, fixed=True`` is static geometry, a level-set
collider that does not enter the MPM (colliders.py), as is any ``StaticGeometry(points, ...)``
given to ``MPMSolver(static=[...])``.

Modules: materials (models), solver (MPMSolver), kernels (Taichi code), dynamics (scene forces
and colliders), colliders (static geometry, where boundaries sit), rigid (rigid bodies),
timestep (CFL substeps), stability (checks and messages), runner (frame loop), backend
(Taichi start-up).
"""
import importlib

# Names are imported on first use (PEP 562), so that e.g. ``physgs_steps.mpm.timestep`` (BGDO)
# does not pull in Taichi: a stage process imports only what it uses.
_EXPORTS = {
    "Dynamics": "dynamics", "StaticGeometry": "colliders", "Material": "material", "preset": "material",
    "RunResult": "runner",
    "run_frames": "runner", "MPMSolver": "solver", "Thresholds": "stability", "TimeStepper": "timestep",
}

__all__ = ["Dynamics", "Material", "MPMSolver", "RunResult", "StaticGeometry", "Thresholds", "TimeStepper", "preset",
           "run_frames"]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
