"""Physical validation of the MPM solver: cases with references, error against run time, the
stiff/extreme sweep, the report (``snakemake --cores all validation``; issue #14).

* :mod:`.base`: accuracy settings (n_grid, particles per cell, CFL), particle set-ups, one
  bounded run through the production frame loop, the :class:`~.base.Case` interface;
* :mod:`.cases`: free fall, axial vibration, rigid rotation, incline with Coulomb friction,
  column under its own weight, block resting on a floor between grid nodes (boundary
  placement), granular column collapse, dam break;
* :mod:`.sweep`: every elasticity x plasticity pair over E, nu, density extremes;
* :mod:`.report`: REPORT.md, CSVs, figures (Pareto fronts, defaults marked), before/after;
* :mod:`.stage`: the workflow's stage functions (``workflow/rules/validation.smk``).

Which runs a scale makes: :func:`runs` and :func:`sweep_pairs` (the workflow expands them).
"""
from __future__ import annotations

from ..errors import ConfigError
from . import sweep as _sweep
from .base import DEFAULT, SCALES, Setting
from .cases import CASES


def _cases(cfg: dict) -> list[str]:
    names = cfg.get("cases") or list(CASES)
    bad = [n for n in names if n not in CASES]
    if bad:
        raise ConfigError("validation.cases", f"unknown case(s) {bad}; known: {', '.join(CASES)}")
    return names


def runs(cfg: dict) -> list[tuple[str, str, str]]:
    """(case, variant, setting id) of every run the ``validation`` config asks for."""
    scale = cfg.get("scale", "cpu")
    if scale not in SCALES:
        raise ConfigError("validation.scale", f"must be one of {', '.join(SCALES)}, got {scale!r}")
    cap = cfg.get("max_grid")
    if cap is not None and (not isinstance(cap, int) or isinstance(cap, bool) or cap < 8):
        raise ConfigError("validation.max_grid", f"must be an integer >= 8 or null, got {cap!r}")
    return [(n, v, s.id) for n in _cases(cfg) for s in CASES[n].settings(scale) for v in CASES[n].variants_at(scale)
            if cap is None or s.n_grid <= cap]


def sweep_pairs(cfg: dict) -> list[str]:
    """Pair ids (``<elasticity>__<plasticity>``) of the sweep, or [] when it is switched off."""
    if not cfg.get("sweep", True):
        return []
    return [_sweep.pair_id(e, p) for e, p in _sweep.pairs(cfg.get("scale", "cpu"))]


__all__ = ["CASES", "DEFAULT", "SCALES", "Setting", "runs", "sweep_pairs"]
