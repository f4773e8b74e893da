"""Deterministic built-in 3DGS scenes with ground-truth solids.

    scene, gt = make_scene("bear_can", n_gaussians=24000, seed=0)

``scene`` looks like a trained 3DGS reconstruction: hollow (gaussians only on the outer
surface of each object), each gaussian a flat disc oriented along the surface normal,
coloured per part, nearly opaque; ``scene.extras["gt_label"]`` [N] int32 is the true
instance of every gaussian.  ``gt`` (:class:`GroundTruth`) answers inside / instance /
signed-distance queries on the true solids and names regions of air that must stay empty
(``gap`` between two objects, ``basket_hollow`` inside the basket).

Units are metres, z up, the scene's box centred on x = y = 0 and resting on z = 0.
The geometry of each scene is fixed; ``seed`` only changes the sampled gaussians.
"""
from __future__ import annotations

import numbers

import numpy as np

from ..errors import ConfigError
from ..gaussians import GaussianScene
from .catalog import build
from .ground_truth import GroundTruth, Instance, Part
from .sampling import gaussians_from_surface

from ..builtin_names import (BUILTIN_SCENES, DEFAULT_N_GAUSSIANS, MAX_GAUSSIANS, MIN_GAUSSIANS,  # noqa: F401
                             TWO_INSTANCE_SCENES)

__all__ = ["BUILTIN_SCENES", "DEFAULT_N_GAUSSIANS", "GroundTruth", "Instance", "Part", "ground_truth", "make_scene"]


def _check_name(name) -> str:
    if isinstance(name, str) and name.startswith("builtin:"):
        name = name[len("builtin:"):]
    if name not in BUILTIN_SCENES:
        valid = ", ".join(f"builtin:{s}" for s in BUILTIN_SCENES)
        raise ConfigError("source", f"unknown built-in scene {name!r}; valid: {valid}")
    return name


def _check_int(value, key: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(key, f"must be an integer, got {value!r} ({type(value).__name__})")
    if not lo <= int(value) <= hi:
        raise ConfigError(key, f"must lie in [{lo}, {hi}], got {int(value)}")
    return int(value)


def ground_truth(name: str) -> GroundTruth:
    """The ground-truth solids of built-in scene ``name`` (no gaussians)."""
    return build(_check_name(name))


def make_scene(name: str, n_gaussians: int | None = None, seed: int = 0) -> tuple[GaussianScene, GroundTruth]:
    """A built-in scene of ``n_gaussians`` surface gaussians (default per scene: 20000, or
    24000 for two-instance scenes) and its ground truth.  Deterministic for a given seed.

    Raises ConfigError naming ``source`` for an unknown name, ``builtin.n_gaussians``
    outside [100, 2_000_000] and ``builtin.seed`` for a seed that is not an integer >= 0.
    """
    name = _check_name(name)
    n = DEFAULT_N_GAUSSIANS[name] if n_gaussians is None else _check_int(
        n_gaussians, "builtin.n_gaussians", MIN_GAUSSIANS, MAX_GAUSSIANS)
    seed = _check_int(seed, "builtin.seed", 0, 2**63 - 1)
    gt = build(name)
    scene = gaussians_from_surface(gt, n, np.random.default_rng(seed))
    return scene, gt
