"""Physical plausibility figures of final.h5 (no weights needed).

Interface kept stable for the metrics stage: :func:`physical_figures(path, moved_threshold,
margin, log) -> dict`. The figures themselves (:mod:`physgs_steps.physical`: deformation
||F - I||_F, det F range, displacement, whether the objects moved and stayed in the domain,
final speed, pass/fail checks; every number finite or null) are accumulated by final_sim
while it simulates and stored with final.h5, so this stage reads one attribute instead of
every frame; they are recomputed by streaming the frames once only for a final.h5 without
them.
"""
from __future__ import annotations

import logging


def physical_figures(path: str, moved_threshold: float = 0.005, margin: float = 0.0,
                     log: logging.Logger | None = None) -> dict:
    """The plausibility figures of a final.h5, judged under ``moved_threshold`` and ``margin``.

    Args:
        path: final.h5 (:mod:`physgs_steps.final_frames`).
        moved_threshold: displacement (domain units) above which the scene counts as moving.
        margin: tolerance of the in-domain check (domain units).
    Returns:
        dict of metrics (each ``{"value", "description"}`` or ``{"value": None, "reason"}``),
        ``deformation_per_frame`` and ``checks`` / ``all_checks_pass``.
    """
    from ..final_frames import FinalFrames
    from ..physical import apply_thresholds, figures_from_file

    with FinalFrames(path) as fr:
        stored = fr.attr("physical")
    if stored is not None:
        if log:
            log.info("physical figures: stored with %s by final_sim", path)
        return apply_thresholds(stored, moved_threshold, margin)
    return figures_from_file(path, moved_threshold, margin, log)
