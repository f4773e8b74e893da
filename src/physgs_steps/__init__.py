"""physgs_steps: FastPhysGS as a library of pipeline stages.

Public API:
    load_gaussians(path) -> GaussianScene     # INRIA .ply or antimatter15 .splat
    save_gaussians(scene, path)               # INRIA binary little-endian .ply
    GaussianScene                             # the scene type (see gaussians.py)

Importing the package itself loads nothing heavy (no numpy): a Snakemake job's client
(``python -m physgs_steps.job``) must start in milliseconds.  ``GaussianScene`` is imported on
first use.
"""
__all__ = ["GaussianScene", "load_gaussians", "save_gaussians"]
__version__ = "0.1.0"


def load_gaussians(path):
    """Load a 3DGS scene from an INRIA ``.ply`` or an antimatter15 ``.splat`` file."""
    from .scene_io import load_gaussians as _load

    return _load(path)


def save_gaussians(scene, path):
    """Save a scene as a binary little-endian INRIA ``.ply`` (atomic write)."""
    from .scene_io import save_gaussians as _save

    return _save(scene, path)


def __getattr__(name):
    if name == "GaussianScene":
        from .gaussians import GaussianScene

        return GaussianScene
    raise AttributeError(f"module 'physgs_steps' has no attribute {name!r}")
