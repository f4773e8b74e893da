"""The filling report ``fill_report.json``: counts, timings, memory and, for built-in scenes,
precision / recall / leakage of the filled particles against the ground-truth solids.

Scores (built-in scenes; ground truth rebuilt with ``builtin_scenes.ground_truth`` (the solids of
``make_scene``, which do not depend on its n_gaussians / seed), particles
mapped to its frame with ``prepare.load_transform(...).to_source``):

* **Instance mapping.** Each predicted instance is the ground-truth instance that most of
  its gaussians belong to (``gt_label`` of scene.ply, or, without it, the instance whose
  signed distance is smallest at the gaussian).
* **precision** = share of filled particles inside the true solid of their own instance.
* **recall** = share of the true solids' volume covered by particles of the matching
  instance (filled and surface gaussians). The volume is sampled at the centres of a grid of
  spacing dx/2 (dx the simulation cell); a sample is covered when a particle lies within
  dx/2 of it. At the target density of 8 particles per cell a perfectly uniform fill leaves
  about 1.5% of samples uncovered (Poisson), so recall near 0.98 is the ceiling.
  ``recall_gaussians_only`` is the same with the gaussians alone (what filling adds).
* **leakage**, per empty region of the scene (``basket_hollow``, ``gap`` between two
  objects): the filled particles inside it (count and share of all filled) and the share of
  its volume covered by filled particles (same grid and radius as recall, so particles of a
  solid that borders the region cover a strip of width dx/2 of it without entering it).

Non-built-in scenes get counts, timings and memory, and ``evaluation.available = false``
with the reason. A metric that cannot be computed is ``{"value": null, "reason": ...}``.
"""
from __future__ import annotations

import logging
import time

import numpy as np
from scipy.spatial import cKDTree

from .runtime import peak_rss_mb

BUILTIN = "builtin:"
MAX_EVAL_SAMPLES = 4_000_000


def _null(reason: str) -> dict:
    return {"value": None, "reason": reason}


def _ratio(num: int, den: int, reason: str):
    return float(num) / den if den > 0 else _null(reason)


def eval_grid(lo: np.ndarray, hi: np.ndarray, spacing: float) -> np.ndarray:
    """[S, 3] centres of a grid of the given spacing covering the box [lo, hi] ([3] each)."""
    n = np.maximum(np.ceil((hi - lo) / spacing).astype(int), 1)
    while int(np.prod(n)) > MAX_EVAL_SAMPLES:
        spacing *= 1.25
        n = np.maximum(np.ceil((hi - lo) / spacing).astype(int), 1)
    axes = [lo[a] + (np.arange(n[a]) + 0.5) * spacing for a in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([v.ravel() for v in g], axis=1)


def gaussian_gt_labels(points_src: np.ndarray, gt, extras: dict) -> np.ndarray:
    """[N] true instance of each gaussian: ``gt_label`` extra, else argmin of the instances' sdf."""
    if "gt_label" in extras:
        return np.asarray(extras["gt_label"], np.int32)
    sdf = np.stack([gt.sdf(points_src, instance=j) for j in range(len(gt.instance_names))], axis=1)
    return np.argmin(sdf, axis=1).astype(np.int32)


def instance_mapping(labels: np.ndarray, gt_labels: np.ndarray, k: int) -> list[int | None]:
    """[K] ground-truth instance of each predicted label by majority of its gaussians (None if none)."""
    out: list[int | None] = []
    for lab in range(k):
        g = gt_labels[(labels == lab) & (gt_labels >= 0)]
        out.append(int(np.bincount(g).argmax()) if g.size else None)
    return out


def _inside_own(x_src: np.ndarray, filled_idx: np.ndarray, p_label: np.ndarray, mapping: list, gt) -> np.ndarray:
    """[F] bool: each filled particle lies inside the true solid of its own (mapped) instance."""
    own = np.array([mapping[lab] if mapping[lab] is not None else -1 for lab in p_label[filled_idx]], np.int64)
    inside = np.zeros(filled_idx.size, bool)
    for j in range(len(gt.instance_names)):
        sel = own == j
        if sel.any():
            inside[sel] = gt.inside(x_src[filled_idx[sel]], instance=j)
    return inside


def _recall_records(x_src, p_label, n_gaussians, mapping, samples, sample_gt, names, radius) -> list[dict]:
    """Per ground-truth instance: covered share of its volume samples (all particles / gaussians only)."""
    out = []
    for j, name in enumerate(names):
        labs = [lab for lab in range(len(mapping)) if mapping[lab] == j]
        target = samples[sample_gt == j]
        cov_g = _covered(target, x_src[:n_gaussians][np.isin(p_label[:n_gaussians], labs)], radius)
        # all particles are these gaussians and the filled particles of the same labels: a sample is
        # covered by them iff by one of the two sets, so only the samples left uncovered by the
        # gaussians are asked of the filled particles (one tree of the N gaussians, not two)
        cov = cov_g.copy()
        cov[~cov_g] = _covered(target[~cov_g], x_src[n_gaussians:][np.isin(p_label[n_gaussians:], labs)], radius)
        out.append({"gt_instance": j, "name": name, "labels": labs, "volume_samples": int(target.shape[0]),
                    "covered": int(cov.sum()), "covered_gaussians_only": int(cov_g.sum()),
                    "recall": _ratio(int(cov.sum()), target.shape[0], "no ground-truth volume sample"),
                    "recall_gaussians_only": _ratio(int(cov_g.sum()), target.shape[0], "no ground-truth volume sample")})
    return out


def _leakage(filled_pts: np.ndarray, samples: np.ndarray, gt, radius: float) -> dict:
    """Per empty region: filled particles inside it and the share of its volume they cover."""
    out = {}
    n = filled_pts.shape[0]
    for name, fn in gt.empty_regions().items():
        in_region = np.asarray(fn(filled_pts), bool) if n else np.zeros(0, bool)
        reg_samples = samples[np.asarray(fn(samples), bool)]
        cov = _covered(reg_samples, filled_pts, radius)
        out[name] = {
            "filled_inside": int(in_region.sum()),
            "share_of_filled": _ratio(int(in_region.sum()), n, "no filled particles"),
            "volume_samples": int(reg_samples.shape[0]),
            "volume_covered": _ratio(int(cov.sum()), reg_samples.shape[0], "region has no volume sample"),
        }
    return out


def evaluate(x_src: np.ndarray, p_label: np.ndarray, p_filled: np.ndarray, gauss_gt: np.ndarray,
             n_gaussians: int, gt, radius_src: float) -> dict:
    """Precision, recall and leakage of a particle set against a ground truth.

    Args:
        x_src: [P, 3] particle positions in the ground truth's (source) frame; rows
            0..n_gaussians-1 are the gaussians.
        p_label: [P] predicted instance of each particle.
        p_filled: [P] bool filled flag.
        gauss_gt: [N] true instance of each gaussian.
        gt: the GroundTruth.
        radius_src: coverage radius and half the sample spacing (dx/2 in source units).

    Returns:
        The ``evaluation`` record.
    """
    k = int(p_label.max()) + 1 if p_label.size else 0
    mapping = instance_mapping(p_label[:n_gaussians], gauss_gt, k)
    names = list(gt.instance_names)
    filled_idx = np.flatnonzero(p_filled)
    inside_own = _inside_own(x_src, filled_idx, p_label, mapping, gt)
    lo, hi = np.asarray(gt.bounds[0], float), np.asarray(gt.bounds[1], float)
    samples = eval_grid(lo - radius_src, hi + radius_src, 2.0 * radius_src)
    gt_records = _recall_records(x_src, p_label, n_gaussians, mapping, samples, gt.instance_of(samples), names,
                                 radius_src)
    inst_records = []
    for lab in range(k):
        mine = p_label[filled_idx] == lab
        n_in = int(inside_own[mine].sum())
        inst_records.append({
            "label": lab, "gt_instance": mapping[lab],
            "gt_name": names[mapping[lab]] if mapping[lab] is not None else None,
            "n_filled": int(mine.sum()), "n_filled_inside": n_in,
            "precision": _ratio(n_in, int(mine.sum()), "no filled particles in this instance"),
        })
    tot_in = sum(r["volume_samples"] for r in gt_records)
    return {
        "available": True,
        "precision": _ratio(int(inside_own.sum()), int(filled_idx.size), "no filled particles"),
        "recall": _ratio(sum(r["covered"] for r in gt_records), tot_in, "no ground-truth volume sample"),
        "recall_gaussians_only": _ratio(sum(r["covered_gaussians_only"] for r in gt_records), tot_in,
                                        "no ground-truth volume sample"),
        "leakage": _leakage(x_src[filled_idx], samples, gt, radius_src),
        "instances": inst_records,
        "ground_truth": gt_records,
        "sample_spacing_src": 2.0 * radius_src,
        "cover_radius_src": radius_src,
        "n_samples": int(samples.shape[0]),
    }


def _covered(targets: np.ndarray, particles: np.ndarray, radius: float) -> np.ndarray:
    """[S] bool: a particle ([Q, 3]) lies within radius of each target ([S, 3])."""
    if targets.shape[0] == 0:
        return np.zeros(0, bool)
    if particles.shape[0] == 0:
        return np.zeros(targets.shape[0], bool)
    d, _ = cKDTree(particles).query(targets, k=1, distance_upper_bound=radius * (1 + 1e-9), workers=-1)
    return np.isfinite(d)


def _cluster_timing(labels_path) -> dict:
    try:
        with np.load(labels_path) as z:
            return {"seconds": float(z["seconds"]), "peak_alloc_mb": float(z["peak_alloc_mb"])}
    except (KeyError, OSError, ValueError, TypeError):
        return _null("labels.npz carries no cluster timing")


def build_report(scene, labels: np.ndarray, result, fcfg: dict, scene_cfg: dict, inputs: dict,
                 fill_seconds: float, log: logging.Logger) -> dict:
    """The fill_report.json record (evaluation against the ground truth for built-in scenes).

    Args:
        scene: the sim-frame GaussianScene (N gaussians).
        labels: [N] instance labels.
        result: the :class:`~physgs_steps.fill.FillResult`.
        inputs: the stage inputs (``labels`` for the cluster timing, ``transform``).
        fill_seconds: wall time of the fill stage so far.
    """
    from .fill import grid_dx

    n, f = scene.n, int(result.x.shape[0])
    report = {
        "method": fcfg["method"], "occupancy": fcfg["occupancy"], "mcis": fcfg["mcis"],
        "config": fcfg, "source": scene_cfg.get("source"), "dx": grid_dx(fcfg),
        "n_gaussians": n, "n_filled": f, "n_particles": n + f,
        "n_instances": len(result.instances),
        "instances": [i.record() for i in result.instances],
        "voxel_size": result.voxel_size,
        "warnings": list(result.warnings),
        "timings": {
            "cluster": _cluster_timing(inputs.get("labels")),
            "fill": {"seconds": round(fill_seconds, 4),
                     "steps": {k: round(v, 4) for k, v in result.seconds.items()},
                     "peak_alloc_mb": round(result.peak_alloc_mb, 2),
                     "process_peak_rss_mb": round(peak_rss_mb(), 1)},
        },
    }
    source = str(scene_cfg.get("source") or "")
    if not source.startswith(BUILTIN):
        report["evaluation"] = {"available": False, "reason": "precision, recall and leakage need ground-truth "
                                "solids, which only built-in scenes (source: builtin:<name>) have"}
        return report
    t0 = time.perf_counter()
    from .builtin_scenes import ground_truth
    from .prepare import load_transform

    name = source[len(BUILTIN):]
    gt = ground_truth(name)  # the solids do not depend on the scene's n_gaussians / seed
    tf = load_transform(inputs["transform"])
    x = np.concatenate([scene.means.astype(np.float64), result.x.astype(np.float64)])
    x_src = tf.to_source(x)
    p_label = np.concatenate([labels, result.label]).astype(np.int32)
    p_filled = np.concatenate([np.zeros(n, bool), np.ones(f, bool)])
    gauss_gt = gaussian_gt_labels(x_src[:n], gt, scene.extras)
    radius = grid_dx(fcfg) / 2.0 / tf.scale
    ev = evaluate(x_src, p_label, p_filled, gauss_gt, n, gt, radius)
    ev["seconds"] = round(time.perf_counter() - t0, 4)
    report["evaluation"] = ev
    report["timings"]["evaluation"] = {"seconds": ev["seconds"]}
    log.info("evaluation vs ground truth of %s: precision %s, recall %s (gaussians only %s), leakage %s",
             name, _fmt(ev["precision"]), _fmt(ev["recall"]), _fmt(ev["recall_gaussians_only"]),
             {k: v["filled_inside"] for k, v in ev["leakage"].items()})
    return report


def _fmt(v) -> str:
    return f"{v:.3f}" if isinstance(v, float) else "n/a"


def metric_value(v):
    """A metric's number, or None for ``{"value": null, ...}`` records."""
    return v if isinstance(v, (int, float)) else None
