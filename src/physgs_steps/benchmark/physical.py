"""Weight-free physical figures that the metrics stage does not compute, read from final.h5:

* **ground penetration**: how far the gaussians sink below the ground plane (scene
  ``dynamics.ground.height``), the deepest point over the sampled frames, in mm, and the
  largest share of gaussians below it;
* **inter-instance penetration**: for every ordered pair of instances (A, B), the share of A's
  gaussians inside the convex hull of B's gaussians, minus that share at frame 0 (objects that
  already overlap their hulls at rest, e.g. a plant's leaves over its pot, do not count), the
  largest over pairs and sampled frames. A convex hull over-approximates a concave object (a
  basket's hollow counts as inside), so this is an upper bound for concave instances.

Frames are sampled evenly (first and last included) so that a 150-frame, 300k-gaussian run
costs seconds; the hull is built from at most ``hull_points`` of B's gaussians and tested on at
most ``test_points`` of A's (fixed random subsets, so re-runs give the same figures).
"""
from __future__ import annotations

import numpy as np

from .readers import Cell, FinalView, missing


def sample_frames(n_frames: int, n: int) -> list[int]:
    if n_frames < 1:
        return []
    return sorted(set(np.linspace(0, n_frames - 1, min(n, n_frames)).round().astype(int).tolist()))


def _subset(idx: np.ndarray, n: int, seed: int) -> np.ndarray:
    if idx.size <= n:
        return idx
    return np.sort(np.random.default_rng(seed).choice(idx, n, replace=False))


def _inside_hull(points: np.ndarray, hull_pts: np.ndarray, chunk: int = 20000) -> np.ndarray | None:
    """[n] bool: points inside the convex hull of hull_pts (None if the hull is degenerate)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(hull_pts)
    except (QhullError, ValueError):
        return None
    eq = hull.equations  # [m, 4]: normal . x + offset <= 0 inside
    tol = 1e-9
    out = np.empty(points.shape[0], bool)
    for s in range(0, points.shape[0], chunk):
        p = points[s:s + chunk]
        out[s:s + chunk] = (p @ eq[:, :3].T + eq[:, 3] <= tol).all(axis=1)
    return out


def penetration(final_h5: str, labels_npz: str | None, ground_height: float | None, domain_size: float = 1.0,
                n_sample: int = 8, hull_points: int = 4000, test_points: int = 20000,
                particles_h5: str | None = None) -> dict:
    """{"ground_penetration_mm", "ground_below_fraction", "instance_penetration"} as Cells.

    Instance labels come from labels.npz when final.h5 stores gaussians, from particles.h5
    when it stores particles (readers.FinalView)."""
    import h5py

    out = {}
    try:
        f = h5py.File(final_h5, "r")
    except OSError as e:
        r = missing(f"cannot open {final_h5}: {e}")
        return {"ground_penetration_mm": r, "ground_below_fraction": r, "instance_penetration": r}
    with f:
        try:
            view = FinalView(f)
        except KeyError as e:
            r = missing(f"{final_h5}: {e}")
            return {"ground_penetration_mm": r, "ground_below_fraction": r, "instance_penetration": r}
        frames = sample_frames(view.n_frames, n_sample)
        rows, rows_of = view.index, view.index_of
        xs = {t: view.x(t) for t in frames}
    if ground_height is None:
        r = missing("the scene has no ground plane")
        out["ground_penetration_mm"] = r
        out["ground_below_fraction"] = r
    else:
        depth, below = 0.0, 0.0
        for p in xs.values():
            z = p[np.isfinite(p).all(axis=1), 2]
            if z.size:
                depth = max(depth, float(ground_height - z.min()))
                below = max(below, float((z < ground_height).mean()))
        out["ground_penetration_mm"] = Cell(max(depth, 0.0) * domain_size * 1000.0)
        out["ground_below_fraction"] = Cell(below)
    labels_all = _labels(labels_npz if rows_of == "gaussians" else particles_h5, rows_of)
    out["instance_penetration"] = _instance_penetration(xs, frames, rows, labels_all, hull_points, test_points)
    return out


def _labels(path: str | None, rows_of: str) -> np.ndarray | Cell:
    """[N] instance label per gaussian (labels.npz ``labels``) or per particle (particles.h5
    ``label``), or a missing Cell with the reason."""
    if path is None:
        return missing("no instance labels")
    try:
        if rows_of == "gaussians":
            with np.load(path) as z:
                return np.asarray(z["labels"])
        import h5py

        with h5py.File(path, "r") as f:
            return np.asarray(f["label"][...])
    except (OSError, KeyError, ValueError) as e:
        return missing(f"cannot read the instance labels of {path}: {e}")


def _instance_penetration(xs: dict, frames: list, rows, labels_all, hull_points, test_points) -> Cell:
    if isinstance(labels_all, Cell):
        return labels_all
    if rows is None:
        return missing("final.h5 does not say which gaussians its columns are")
    if rows.size and rows.max() >= labels_all.size:
        return missing("the instance labels do not match final.h5's rows")
    lab = labels_all[rows]
    ids = sorted(int(k) for k in np.unique(lab))
    if len(ids) < 2:
        return missing("one instance (nothing to penetrate)")
    subsets = {k: np.flatnonzero(lab == k) for k in ids}
    worst = 0.0
    t0 = frames[0]
    for a in ids:
        test = _subset(subsets[a], test_points, 1 + a)
        for b in ids:
            if a == b:
                continue
            hull_idx = _subset(subsets[b], hull_points, 101 + b)
            base = None
            for t in frames:
                p = xs[t]
                pa, pb = p[test], p[hull_idx]
                pa, pb = pa[np.isfinite(pa).all(axis=1)], pb[np.isfinite(pb).all(axis=1)]
                if pa.shape[0] == 0 or pb.shape[0] < 4:
                    continue
                inside = _inside_hull(pa, pb)
                if inside is None:
                    continue
                share = float(inside.mean())
                if t == t0 or base is None:
                    base = share
                worst = max(worst, share - base)
    return Cell(worst)
