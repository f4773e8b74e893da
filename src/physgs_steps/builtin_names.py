"""Names and default sizes of the built-in scenes, without their geometry.

Light to import (no NumPy, trimesh or SciPy): the workflow reads these while it plans (job
resources, ``physgs check``) in every Snakemake start; :mod:`physgs_steps.builtin_scenes`
re-exports them and builds the solids and gaussians on demand.
"""
from __future__ import annotations

BUILTIN_SCENES: tuple[str, ...] = ("bear", "bear_can", "duck_stone", "ficus", "basket_mat", "bread", "ball_jelly")
TWO_INSTANCE_SCENES = ("bear_can", "duck_stone", "basket_mat", "ball_jelly")
DEFAULT_N_GAUSSIANS: dict[str, int] = {s: 24000 if s in TWO_INSTANCE_SCENES else 20000 for s in BUILTIN_SCENES}
MIN_GAUSSIANS, MAX_GAUSSIANS = 100, 2_000_000
