"""Physical plausibility figures of final.h5 (no weights needed).

Interface kept stable for the metrics stage and for peers that will compute the same figures
elsewhere: :func:`physical_figures(path, moved_threshold, margin, log) -> dict`.

final.h5: ``x`` [T, Nv, 3] (domain units), ``F`` [T, Nv, 3, 3] (optional), ``time`` [T].
Figures: deformation ||F - I||_F, det F range, displacement, whether the objects moved and
stayed in the domain, final speed, and pass/fail checks. Every number is finite or null.
"""
from __future__ import annotations

import logging

import numpy as np

from ..errors import InputError


def physical_figures(path: str, moved_threshold: float = 0.005, margin: float = 0.0,
                     log: logging.Logger | None = None) -> dict:
    """Plausibility figures of final.h5, streamed one frame at a time.

    Args:
        path: final.h5 with ``x`` [T, Nv, 3], ``F`` [T, Nv, 3, 3] (optional), ``time`` [T].
        moved_threshold: displacement (domain units) above which the scene counts as moving.
        margin: tolerance of the in-domain check (domain units).
    Returns:
        dict of metrics (each ``{"value", "description"}`` or ``{"value": None, "reason"}``),
        ``deformation_per_frame`` and ``checks`` / ``all_checks_pass``.
    """
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(path, f"cannot open HDF5: {e}") from None
    with f:
        if "x" not in f:
            raise InputError(path, "no dataset 'x' (expected [T, Nv, 3] positions)")
        x = f["x"]
        if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] < 1:
            raise InputError(path, f"'x' must be [T, Nv, 3] with T >= 1, got {x.shape}")
        fd = f["F"] if "F" in f else None
        if fd is not None and fd.shape != x.shape[:2] + (3, 3):
            raise InputError(path, f"'F' has shape {fd.shape}, expected {x.shape[:2] + (3, 3)}")
        time = np.asarray(f["time"], dtype=np.float64) if "time" in f else None
        acc = _Accumulator(x.shape[0], margin)
        x0 = np.asarray(x[0], dtype=np.float64)
        for t in range(x.shape[0]):
            acc.add(t, np.asarray(x[t], dtype=np.float64), x0, None if fd is None else np.asarray(fd[t], dtype=np.float64))
            if log and x.shape[0] >= 10 and t % max(1, x.shape[0] // 10) == 0:
                log.info("metrics: frame %d/%d", t + 1, x.shape[0])
        x_last = np.asarray(x[-1], dtype=np.float64)
        x_prev = np.asarray(x[-2], dtype=np.float64) if x.shape[0] >= 2 else None
    return acc.result(x_last, x_prev, time, moved_threshold, fd is not None)


class _Accumulator:
    """Running extrema over frames (keeps O(T) numbers, never all frames)."""

    def __init__(self, t: int, margin: float) -> None:
        self.margin = margin
        self.n_nonfinite = 0
        self.max_disp = 0.0
        self.out_frac_max = 0.0
        self.det_min, self.det_max = np.inf, -np.inf
        self.inverted_frac_max = 0.0
        self.dev_mean = np.full(t, np.nan)
        self.dev_last_max = None
        self.com = np.zeros((t, 3))

    def add(self, t: int, xt: np.ndarray, x0: np.ndarray, ft: np.ndarray | None) -> None:
        """xt, x0: [Nv, 3]; ft: [Nv, 3, 3] or None."""
        ok = np.isfinite(xt).all(axis=1)
        self.n_nonfinite += int((~ok).sum())
        if ok.any():
            d = np.linalg.norm(xt[ok] - x0[ok], axis=1)
            d = d[np.isfinite(d)]
            if d.size:
                self.max_disp = max(self.max_disp, float(d.max()))
            out = ((xt[ok] < -self.margin) | (xt[ok] > 1.0 + self.margin)).any(axis=1)
            self.out_frac_max = max(self.out_frac_max, float(out.mean()))
            self.com[t] = xt[ok].mean(axis=0)
        else:
            self.com[t] = np.nan
        self.out_frac_max = max(self.out_frac_max, float((~ok).mean()))   # NaN positions are not in the domain
        if ft is None:
            return
        fok = np.isfinite(ft).all(axis=(1, 2))
        self.n_nonfinite += int((~fok).sum())
        if not fok.any():
            return
        fv = ft[fok]
        det = np.linalg.det(fv)
        self.det_min, self.det_max = min(self.det_min, float(det.min())), max(self.det_max, float(det.max()))
        self.inverted_frac_max = max(self.inverted_frac_max, float((det <= 0).mean()))
        dev = np.linalg.norm(fv - np.eye(3), axis=(1, 2))
        self.dev_mean[t] = float(dev.mean())
        self.dev_last_max = float(dev.max())

    def result(self, x_last, x_prev, time, moved_threshold, has_f) -> dict:
        no_f = {"value": None, "reason": "final.h5 has no 'F' dataset"}
        speed = {"value": None, "reason": "needs at least two frames with times"}
        if x_prev is not None and time is not None and len(time) >= 2 and time[-1] > time[-2]:
            v = np.linalg.norm(x_last - x_prev, axis=1) / (time[-1] - time[-2])
            v = v[np.isfinite(v)]
            if v.size:
                speed = {"value": float(v.mean()), "description": "mean speed over the last two frames (domain units/s)"}
        com_shift = self.com[-1] - self.com[0]
        figures = {
            "mean_deformation_last": ({"value": _num(self.dev_mean[-1]),
                                       "description": "mean ||F - I||_F over gaussians at the last frame"} if has_f else no_f),
            "max_deformation_last": ({"value": self.dev_last_max,
                                      "description": "max ||F - I||_F over gaussians at the last frame"} if has_f else no_f),
            "det_F_min": ({"value": _num(self.det_min), "description": "smallest det F over all frames and gaussians"} if has_f else no_f),
            "det_F_max": ({"value": _num(self.det_max), "description": "largest det F over all frames and gaussians"} if has_f else no_f),
            "inverted_fraction_max": ({"value": self.inverted_frac_max,
                                       "description": "largest per-frame fraction of gaussians with det F <= 0"} if has_f else no_f),
            "max_displacement": {"value": self.max_disp, "description": "largest distance of a gaussian from its first-frame position (domain units)"},
            "com_displacement": {"value": _num(float(np.linalg.norm(com_shift))), "vector": [_num(c) for c in com_shift],
                                 "description": "centre-of-mass shift first -> last frame (domain units)"},
            "out_of_domain_fraction_max": {"value": self.out_frac_max,
                                           "description": "largest per-frame fraction of gaussians outside the unit cube (+ margin)"},
            "non_finite_count": {"value": self.n_nonfinite, "description": "NaN/inf rows of x and F over all frames"},
            "final_mean_speed": speed,
        }
        checks = {
            "finite": self.n_nonfinite == 0,
            "moved": self.max_disp > moved_threshold,
            "stayed_in_domain": self.out_frac_max == 0.0,
        }
        if has_f:
            checks["no_inversion"] = bool(np.isfinite(self.det_min) and self.det_min > 0)
        figures["deformation_per_frame"] = [_num(v) for v in self.dev_mean] if has_f else None
        figures["checks"] = checks
        figures["all_checks_pass"] = all(checks.values())
        return figures


def _num(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
