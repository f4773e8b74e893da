"""Physical plausibility figures of a simulation, accumulated frame by frame.

``final_sim`` feeds every frame's states of the stored particles (those that carry the
visible gaussians, see :mod:`physgs_steps.carrier`; in ``sim.particles: gaussians`` mode the
visible gaussians themselves) into a :class:`PhysicalFigures` while it simulates and stores
the result with final.h5 (attribute ``physical``), so the metrics stage reads one JSON
record instead of every frame. :func:`figures_from_file` recomputes them from any final.h5
(benchmarks, files written by other tools).

Figures (domain units): deformation ||F - I||_F (mean over particles per frame, max at the
last frame), det F range and inverted fraction, largest displacement from frame 0,
centre-of-mass shift, largest share of particles outside the unit cube (+ margin),
non-finite count, mean speed over the last two frames; checks ``finite``, ``moved``,
``stayed_in_domain``, ``no_inversion``.
"""
from __future__ import annotations

import logging

import numpy as np

DESCRIBED_OVER = "the simulated particles that carry the visible gaussians"


class PhysicalFigures:
    """Running extrema over frames (keeps O(T) numbers, never all frames).

    Args:
        n_frames: T.
        margin: tolerance of the in-domain check (domain units).
    """

    def __init__(self, n_frames: int, margin: float = 0.0) -> None:
        self.n_frames = n_frames
        self.margin = margin
        self.n_nonfinite = 0
        self.max_disp = 0.0
        self.out_frac_max = 0.0
        self.det_min, self.det_max = np.inf, -np.inf
        self.inverted_frac_max = 0.0
        self.dev_mean = np.full(n_frames, np.nan)
        self.dev_last_max = None
        self.com = np.zeros((n_frames, 3))
        self.has_f = False
        self.x_lo, self.x_hi = np.inf, -np.inf  # overall range of the finite coordinates
        self.x0 = None
        self.last = None   # (t, x) of the newest frame
        self.prev = None   # (t, x) of the frame before it
        self._last_row = None  # per-frame values of the newest frame, for repeat()

    def add(self, t: int, xt: np.ndarray, ft: np.ndarray | None, f_minus_i: np.ndarray | None = None) -> None:
        """Frame ``t``: positions xt [M, 3], deformation gradients ft [M, 3, 3] or None.

        ``f_minus_i``: ft - I as float32, given only when every entry of ft is finite (what
        :meth:`FinalWriter.frame <physgs_steps.final_frames.FinalWriter.frame>` returns); it
        saves the subtraction and the finiteness check of F.

        A frame whose x and F (as float32) are all finite takes :meth:`_add_finite`, the same
        figures from fewer passes; the others the element-wise general path. The test is one sum
        of each (an inf or NaN entry makes the sum inf or NaN; a sum of finite entries that
        overflows only sends the frame to the general path)."""
        x_in = np.asarray(xt)
        f32 = None if ft is None else np.asarray(ft, dtype=np.float32)
        if x_in.ndim == 2 and x_in.shape[1] == 3 and len(x_in) and np.isfinite(x_in.sum()) and (
                f32 is None or f_minus_i is not None or np.isfinite(f32.sum())):
            self._add_finite(t, x_in, f32, f_minus_i)
        else:
            self._add_general(t, xt, ft)

    def _add_finite(self, t: int, x_in: np.ndarray, ft: np.ndarray | None, f_minus_i: np.ndarray | None) -> None:
        """:meth:`_add_general` for a frame without NaN or inf: every figure bit for bit the
        same except the centre of mass, a pairwise sum over the particles (the general path's
        ``mean(axis=0)`` adds them one after another, 10x slower); the two differ by at most
        2 (M - 1) 2^-53 mean|x| (both sums' error bound), tests/test_carrier.py."""
        xt = np.asarray(x_in, dtype=np.float64)
        if self.x0 is None:
            self.x0 = xt.copy()
        d = xt - self.x0
        # the largest distance = sqrt of the largest squared distance (sqrt is monotonic)
        self.max_disp = max(self.max_disp, float(np.sqrt(np.einsum("ni,ni->n", d, d).max())))
        lo, hi = x_in.min(), x_in.max()   # of the float32 or float64 entries: the same values
        self.x_lo, self.x_hi = min(self.x_lo, float(lo)), max(self.x_hi, float(hi))
        if lo < -self.margin or hi > 1.0 + self.margin:
            out = ((xt < -self.margin) | (xt > 1.0 + self.margin)).any(axis=1)
            self.out_frac_max = max(self.out_frac_max, float(out.mean()))
        self.com[t] = np.ascontiguousarray(xt.T).sum(axis=1) / len(xt)
        if ft is not None:
            self.has_f = True
            det = det3(ft, np.float64)
            self.det_min, self.det_max = min(self.det_min, float(det.min())), max(self.det_max, float(det.max()))
            self.inverted_frac_max = max(self.inverted_frac_max, float((det <= 0).mean()))
            d = f_minus_i if f_minus_i is not None else ft - np.eye(3, dtype=np.float32)
            dev = np.sqrt(np.einsum("nij,nij->n", d, d))
            self.dev_mean[t] = float(dev.mean())
            self.dev_last_max = float(dev.max())
        self._last_row = 0
        self.prev, self.last = self.last, (t, xt)

    def _add_general(self, t: int, xt: np.ndarray, ft: np.ndarray | None) -> None:
        """Any frame (NaN and inf rows counted and left out of the figures)."""
        xt = np.asarray(xt, dtype=np.float64)
        if self.x0 is None:
            self.x0 = xt.copy()
        n_bad = 0
        ok = np.isfinite(xt.sum(axis=1))  # [M]
        all_ok = bool(ok.all())
        n_bad += 0 if all_ok else int((~ok).sum())
        xo, x0 = (xt, self.x0) if all_ok else (xt[ok], self.x0[ok])
        if xo.shape[0]:
            d = xo - x0
            d = np.sqrt(np.einsum("ni,ni->n", d, d))
            d = d[np.isfinite(d)] if not all_ok else d
            if d.size:
                self.max_disp = max(self.max_disp, float(d.max()))
            lo, hi = xo.min(axis=0), xo.max(axis=0)
            self.x_lo, self.x_hi = min(self.x_lo, float(lo.min())), max(self.x_hi, float(hi.max()))
            if lo.min() < -self.margin or hi.max() > 1.0 + self.margin:
                out = ((xo < -self.margin) | (xo > 1.0 + self.margin)).any(axis=1)
                self.out_frac_max = max(self.out_frac_max, float(out.mean()))
            self.com[t] = xo.mean(axis=0)
        else:
            self.com[t] = np.nan
        self.out_frac_max = max(self.out_frac_max, float((~ok).mean()))   # NaN positions are not in the domain
        if ft is not None:
            self.has_f = True
            ft = np.asarray(ft, dtype=np.float32)
            fok = np.isfinite(ft.sum(axis=(1, 2)))  # inf and nan entries make the sum non-finite
            n_bad += int((~fok).sum())
            if fok.any():
                fv = ft[fok]
                det = det3(fv.astype(np.float64))
                self.det_min, self.det_max = min(self.det_min, float(det.min())), max(self.det_max, float(det.max()))
                self.inverted_frac_max = max(self.inverted_frac_max, float((det <= 0).mean()))
                d = fv - np.eye(3, dtype=np.float32)
                dev = np.sqrt(np.einsum("nij,nij->n", d, d))
                self.dev_mean[t] = float(dev.mean())
                self.dev_last_max = float(dev.max())
        self.n_nonfinite += n_bad
        self._last_row = n_bad
        self.prev, self.last = self.last, (t, xt)

    def repeat(self, t: int) -> None:
        """Frame ``t`` repeats the newest frame's state (held at rest)."""
        if self.last is None:
            raise ValueError("repeat() before any frame was added")
        t_last, x_last = self.last
        self.com[t] = self.com[t_last]
        self.dev_mean[t] = self.dev_mean[t_last]
        self.n_nonfinite += self._last_row
        self.prev, self.last = (t_last, x_last), (t, x_last)

    def result(self, time: np.ndarray | None, moved_threshold: float = 0.005) -> dict:
        """The figures (each ``{"value", "description"}`` or ``{"value": None, "reason"}``),
        ``deformation_per_frame``, ``checks`` and ``all_checks_pass``; ``time`` [T] in s."""
        has_f = self.has_f
        no_f = {"value": None, "reason": "final.h5 has no deformation gradients"}
        speed = {"value": None, "reason": "needs at least two frames with times"}
        if self.prev is not None and time is not None and len(time) >= 2:
            (t1, x1), (t0, x0) = self.last, self.prev
            if time[t1] > time[t0]:
                v = np.linalg.norm(x1 - x0, axis=1) / (time[t1] - time[t0])
                v = v[np.isfinite(v)]
                if v.size:
                    speed = {"value": float(v.mean()), "description": "mean speed over the last two frames (domain units/s)"}
        com_shift = self.com[-1] - self.com[0]
        over = DESCRIBED_OVER
        figures = {
            "mean_deformation_last": ({"value": _num(self.dev_mean[-1]),
                                       "description": f"mean ||F - I||_F over {over} at the last frame"} if has_f else no_f),
            "max_deformation_last": ({"value": self.dev_last_max,
                                      "description": f"max ||F - I||_F over {over} at the last frame"} if has_f else no_f),
            "det_F_min": ({"value": _num(self.det_min), "description": f"smallest det F over all frames and {over}"} if has_f else no_f),
            "det_F_max": ({"value": _num(self.det_max), "description": f"largest det F over all frames and {over}"} if has_f else no_f),
            "inverted_fraction_max": ({"value": self.inverted_frac_max,
                                       "description": f"largest per-frame fraction of {over} with det F <= 0"} if has_f else no_f),
            "max_displacement": {"value": self.max_disp, "description": f"largest distance of one of {over} from its first-frame position (domain units)"},
            "com_displacement": {"value": _num(float(np.linalg.norm(com_shift))), "vector": [_num(c) for c in com_shift],
                                 "description": "centre-of-mass shift first -> last frame (domain units)"},
            "out_of_domain_fraction_max": {"value": self.out_frac_max,
                                           "description": f"largest per-frame fraction of {over} outside the unit cube (+ margin)"},
            "non_finite_count": {"value": self.n_nonfinite, "description": "NaN/inf rows of x and F over all frames"},
            "position_range": {"value": [_num(self.x_lo), _num(self.x_hi)],
                               "description": "smallest and largest coordinate over all frames (domain units)"},
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
        figures["moved_threshold"] = moved_threshold
        figures["domain_margin"] = self.margin
        return figures


def figures_from_file(path, moved_threshold: float = 0.005, margin: float = 0.0,
                      log: logging.Logger | None = None) -> dict:
    """The figures of a final.h5 recomputed by streaming its stored frames once."""
    from .final_frames import FinalFrames

    with FinalFrames(path) as fr:
        acc = PhysicalFigures(fr.n_frames, margin)
        for t in range(fr.n_frames):
            if t > 0 and fr.row(t) == fr.row(t - 1):
                acc.repeat(t)
            else:
                acc.add(t, fr.x(t), fr.F(t))
            if log and fr.n_frames >= 10 and t % max(1, fr.n_frames // 10) == 0:
                log.info("physical figures: frame %d/%d", t + 1, fr.n_frames)
        return acc.result(fr.time, moved_threshold)


def apply_thresholds(fig: dict, moved_threshold: float, margin: float) -> dict:
    """Stored figures re-judged under the metrics stage's ``moved_threshold`` and
    ``domain_margin`` (``moved`` from the largest displacement, ``stayed_in_domain`` from
    the position range); a copy."""
    out = {k: v for k, v in fig.items()}
    checks = dict(out["checks"])
    checks["moved"] = bool((out["max_displacement"]["value"] or 0.0) > moved_threshold)
    lo, hi = (out.get("position_range") or {}).get("value") or [None, None]
    if margin != out.get("domain_margin") and lo is not None and hi is not None:
        checks["stayed_in_domain"] = bool(lo >= -margin and hi <= 1.0 + margin and checks["finite"])
    out["checks"] = checks
    out["all_checks_pass"] = all(checks.values())
    out["moved_threshold"], out["domain_margin"] = moved_threshold, margin
    return out


def det3(F: np.ndarray, dtype=None) -> np.ndarray:
    """[M] determinants of [M, 3, 3] matrices, in ``dtype`` (F's by default).

    The cofactor expansion F00 (F11 F22 - F12 F21) - F01 (F10 F22 - F12 F20) + F02 (F10 F21 - F11 F20),
    each product and difference in this order (np.linalg.det runs an LU per matrix and is
    ~10x slower at these sizes), over cache-sized blocks of a [9, M] copy (contiguous rows and
    reused buffers: 2-3x faster than the same expression on [M, 3, 3] views, the same bits)."""
    F = np.asarray(F)
    dtype = np.dtype(F.dtype if dtype is None else dtype)
    m = len(F)
    flat = F.reshape(m, 9)
    out = np.empty(m, dtype)
    b = min(m, _DET_BLOCK)
    if m == 0:
        return out
    g, t = np.empty((9, b), dtype), np.empty((2, b), dtype)
    for i in range(0, m, b):
        k = min(m, i + b) - i
        G, a, c = g[:, :k], t[0, :k], t[1, :k]
        G[...] = flat[i:i + k].T
        r = out[i:i + k]
        np.multiply(G[4], G[8], out=a)
        np.multiply(G[5], G[7], out=c)
        np.subtract(a, c, out=r)
        r *= G[0]                      # F00 (F11 F22 - F12 F21)
        np.multiply(G[3], G[8], out=a)
        np.multiply(G[5], G[6], out=c)
        a -= c
        a *= G[1]                      # F01 (F10 F22 - F12 F20)
        r -= a
        np.multiply(G[3], G[7], out=a)
        np.multiply(G[4], G[6], out=c)
        a -= c
        a *= G[2]                      # F02 (F10 F21 - F11 F20)
        r += a
    return out


_DET_BLOCK = 4096


def pieces(x: np.ndarray, link: float) -> dict:
    """The pieces a particle cloud is in: connected components of the graph whose edges join
    particles closer than ``link`` (e.g. the grid spacing dx: an MPM body whose particles lie
    farther apart than dx no longer moves as one through the grid's stencils).

    x  # [N, 3]  ->  {"sizes": [K] particle counts, largest first, "labels": [N] component of each
    particle, ranked like ``sizes`` (0 the largest), "top2": share of the particles in the two
    largest pieces, "gap": smallest distance between the two largest pieces (0 with one piece)}."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x = np.asarray(x, np.float64)
    n = len(x)
    if n == 0:
        return {"sizes": np.zeros(0, np.int64), "labels": np.zeros(0, np.int64), "top2": 0.0, "gap": 0.0}
    pairs = cKDTree(x).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, lab = connected_components(graph, directed=False)
    counts = np.bincount(lab)
    order = np.argsort(-counts, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    labels = rank[lab]
    sizes = counts[order]
    gap = 0.0
    if len(sizes) > 1:
        gap = float(cKDTree(x[labels == 0]).query(x[labels == 1])[0].min())
    return {"sizes": sizes, "labels": labels, "top2": float(sizes[:2].sum() / n), "gap": gap}


def _num(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
