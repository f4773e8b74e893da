"""Stage ``cluster``: split the gaussians of ``scene.ply`` into K object instances.

FastPhysGS (Sec. 4.1, appendix C.2) runs DBSCAN with radius r (0.05-0.07 in the
normalised domain) on the gaussian means. Here:

* **Algorithm.** ``cluster.algorithm: exact`` is DBSCAN on every gaussian (scikit-learn's
  labels, computed from k-d tree queries by :func:`dbscan`, 0.1-0.3 s at 20k gaussians instead
  of scikit-learn's import and all-pairs neighbour lists, seconds). At 300k gaussians and
  r = 0.05 an eps-neighbourhood holds thousands of gaussians, so ``voxel``
  (the default above ``exact_max_points``) runs DBSCAN on the centroids of voxels of side
  ``voxel_factor * eps``, each weighted by its gaussian count (``sample_weight``, so the
  core-point rule still counts gaussians), and gives every gaussian the label of its voxel.
  Centroids move each point by at most ``sqrt(3)/2 * voxel_factor * eps``, so the two agree
  wherever objects are separated by clearly more or less than eps; ``tests/test_cluster.py``
  checks the agreement with plain DBSCAN.
* **Noise policy.** Every gaussian must belong to an instance (it is a simulation
  particle). DBSCAN noise and the gaussians of clusters smaller than
  ``min_cluster_fraction`` of the scene (floaters) join the cluster of their nearest
  clustered gaussian. clusters.json records how many and the largest such distance.
* **Ordering.** Labels are sorted by instance size, 0 = largest (ties: lower raw label).
* **Scene instances.** The scene file's ``instances`` list may give per instance ``at:
  [x, y, z]`` (a sim-frame point: the cluster of the gaussian nearest to it is that
  instance) and/or ``box: [[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (sim frame). If every
  listed instance has a box (and ``method`` is ``auto`` or ``boxes``), DBSCAN is left out:
  a gaussian takes the first listed box that contains it; gaussians in no box follow the
  noise policy. Otherwise each instance's ``config_index`` is matched by ``at``, then by
  ``box`` (the cluster with most gaussians in it), then the remaining instances by order of
  size (largest first). Clusters left over have ``config_index: null``.
* **Merge rules** ``cluster.merge: [[a, b], ...]`` join clusters (numbered after sorting).
* **Fragments.** When the scene lists instances, a cluster that matched none of them and
  holds at most ``fragment_fraction`` (0.25) of the gaussians of the matched cluster nearest
  to it (smallest gaussian-to-gaussian distance) joins that cluster: DBSCAN split it off a
  listed object (the shared udon capture: 1950 + 203 gaussians, 0.058 apart at eps 0.05).
  Each join is a warning and a ``fragments`` record in clusters.json. An unmatched cluster
  that stays records its nearest instance and the gap (``unmatched``), so that a fully
  pinned scene can say what to change.
* **Static surroundings and static instances.** Gaussians that ``prepare`` marked static
  (outside ``region.box``: extra ``static`` of scene.ply) are not clustered; their label is
  ``STATIC`` (-1). Instances left out of ``region.instances`` (cluster labels, or the name
  or hint of a scene ``instances`` entry) or pinned ``static: true`` keep their label but
  are listed in labels.npz ``static_instances`` and flagged ``static`` in clusters.json:
  the fill stage gives them no particles, they are drawn at rest (their points inside the
  domain are stored as collider geometry, particles.h5 ``static_x``).

Bad input: all gaussians labelled noise -> ConfigError naming ``cluster.eps`` with the
scene's typical neighbour distance; fewer clusters than listed instances (e.g. an eps that
merges everything) -> a warning naming ``cluster.eps`` (an error with ``cluster.strict``).
"""
from __future__ import annotations

import logging
import time
import tracemalloc

import numpy as np
from scipy.spatial import cKDTree

from .errors import ConfigError, InputError
from .runtime import atomic_path, write_json

NOISE = -1
STATIC = -1  # label of static surroundings (gaussians outside region.box) in labels.npz


# ---------------------------------------------------------------------------- config
def cluster_config(cfg: dict) -> dict:
    """``cfg["cluster"]`` merged with the schema defaults and validated (ConfigError names the key)."""
    from .config import load_schema, validate

    section = dict(cfg.get("cluster") or {})
    return validate(section, load_schema("cluster.schema.yaml"), "cluster config", "cluster")


# ---------------------------------------------------------------------------- DBSCAN
def dbscan_labels(points, eps: float, min_samples: int, algorithm: str = "auto",
                  voxel_factor: float = 0.25, exact_max_points: int = 20000) -> np.ndarray:
    """DBSCAN labels of points; -1 marks noise.

    Args:
        points: [N, 3] positions (domain units).
        eps: DBSCAN radius.
        min_samples: core-point threshold (points within eps, the point itself included).
        algorithm: ``exact`` (DBSCAN on all points), ``voxel`` (count-weighted voxel
            centroids, labels propagated to the voxel's points) or ``auto`` (exact up to
            ``exact_max_points`` points).
        voxel_factor: voxel side as a fraction of eps (``voxel``).
        exact_max_points: threshold of ``auto``.

    Returns:
        [N] int32 raw DBSCAN labels (0..K-1 in order of discovery, -1 = noise): the labels of
        scikit-learn's DBSCAN (``tests/test_cluster.py`` compares them), computed by
        :func:`dbscan` without scikit-learn's import and its all-pairs neighbour lists.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"dbscan_labels: points must be [N, 3], got {pts.shape}")
    if pts.shape[0] == 0:
        return np.zeros(0, np.int32)
    if algorithm == "auto":
        algorithm = "exact" if pts.shape[0] <= exact_max_points else "voxel"
    if algorithm == "exact":
        return dbscan(pts, eps, min_samples)
    if algorithm != "voxel":
        raise ValueError(f"dbscan_labels: unknown algorithm {algorithm!r}")
    centroids, counts, inverse = voxel_centroids(pts, voxel_factor * eps)
    return dbscan(centroids, eps, min_samples, counts)[inverse]


def _components(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[n] connected-component id of every node of the undirected graph with edges (a, b)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def dbscan(points: np.ndarray, eps: float, min_samples: int, sample_weight=None) -> np.ndarray:
    """Exact DBSCAN (scikit-learn's definition and label order) from k-d tree queries.

    A point is core when the weights of the points within ``eps`` (distance <= eps, itself
    included) sum to at least ``min_samples``; clusters are the connected components of core
    points closer than eps, numbered in the order of their lowest-index core point; a non-core
    point within eps of core points takes the smallest of their cluster labels (what
    scikit-learn's expansion order gives), else it is noise (-1).

    Instead of every point's eps-neighbour list (hundreds per gaussian on the built-in scenes):
    (1) points of a cell of side eps/sqrt(3) are mutual neighbours, so a cell whose weight
    reaches ``min_samples`` makes all its points core; only the others are counted. (2) The
    components of core points closer than eps/4 are parts of the true clusters; the largest
    part's links to the others come from one nearest-neighbour query, the links among the
    others from their eps-pairs.

    Args:
        points: [N, 3] positions.
        eps: neighbourhood radius.
        min_samples: core threshold (weight).
        sample_weight: [N] weights (None = 1).

    Returns:
        [N] int32 labels.
    """
    pts = np.asarray(points, dtype=np.float64)  # [N, 3]
    n = pts.shape[0]
    labels = np.full(n, NOISE, np.int64)  # [N]
    if n == 0:
        return labels.astype(np.int32)
    w = np.ones(n) if sample_weight is None else np.asarray(sample_weight, np.float64)  # [N]
    tree = cKDTree(pts)
    h = eps / np.sqrt(3.0) * (1.0 - 1e-9)  # cell diagonal just under eps
    key = np.floor((pts - pts.min(axis=0)) / h).astype(np.int64)  # [N, 3]
    dims = key.max(axis=0) + 1
    flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]  # [N]
    _, cell = np.unique(flat, return_inverse=True)
    cell = cell.reshape(-1)
    core = np.bincount(cell, w)[cell] >= min_samples  # [N] certain core points
    unsure = np.flatnonzero(~core)
    if unsure.size:
        pairs = cKDTree(pts[unsure]).sparse_distance_matrix(tree, eps, output_type="ndarray")
        core[unsure] = np.bincount(pairs["i"], w[pairs["j"]], unsure.size) >= min_samples
    cidx = np.flatnonzero(core)  # [C]
    if cidx.size == 0:
        return labels.astype(np.int32)
    cp = pts[cidx]  # [C, 3]
    ctree = cKDTree(cp)
    pr = ctree.query_pairs(eps / 4, output_type="ndarray")  # [P, 2]
    part = _components(cidx.size, pr[:, 0], pr[:, 1])  # [C] parts of clusters
    big = np.bincount(part).argmax()
    rest = np.flatnonzero(part != big)
    a = b = np.zeros(0, np.int64)
    if rest.size:
        inside = np.flatnonzero(part == big)
        d, k = cKDTree(cp[inside]).query(cp[rest], k=1, distance_upper_bound=eps)
        hit = np.isfinite(d)
        pr2 = cKDTree(cp[rest]).query_pairs(eps, output_type="ndarray")
        a = np.concatenate([part[rest[hit]], part[rest[pr2[:, 0]]]])
        b = np.concatenate([part[inside[k[hit]]], part[rest[pr2[:, 1]]]])
    comp = _components(int(part.max()) + 1, a, b)[part]  # [C] cluster of every core point
    ucomp, first = np.unique(comp, return_index=True)
    rank = np.empty(int(ucomp.max()) + 1, np.int64)
    rank[ucomp[np.argsort(first)]] = np.arange(ucomp.size)
    labels[cidx] = rank[comp]
    border = np.flatnonzero(~core)
    if border.size:
        pairs = cKDTree(pts[border]).sparse_distance_matrix(ctree, eps, output_type="ndarray")
        if pairs.size:
            low = np.full(border.size, np.iinfo(np.int64).max)
            np.minimum.at(low, pairs["i"], labels[cidx[pairs["j"]]])
            near = low < np.iinfo(np.int64).max
            labels[border[near]] = low[near]
    return labels.astype(np.int32)


def voxel_centroids(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Group points by voxel.

    Args:
        points: [N, 3] positions.
        voxel: voxel side.

    Returns:
        centroids [V, 3] mean position per occupied voxel, counts [V] points per voxel,
        inverse [N] voxel index of every point.
    """
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)  # [N, 3]
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]  # [N]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    centroids = np.stack([np.bincount(inverse, weights=points[:, a], minlength=counts.size)
                          for a in range(3)], axis=1) / counts[:, None]  # [V, 3]
    return centroids, counts, inverse


def knn_distance_hint(points: np.ndarray, k: int, max_points: int = 20000, seed: int = 0) -> float:
    """Median distance from a point to its k-th neighbour (on a subsample of points [N, 3])."""
    rng = np.random.default_rng(seed)
    sub = points if points.shape[0] <= max_points else points[rng.choice(points.shape[0], max_points, replace=False)]
    k_eff = int(min(k, max(sub.shape[0] - 1, 1)))
    d, _ = cKDTree(points).query(sub, k=k_eff + 1)
    return float(np.median(np.atleast_2d(d)[:, -1]))


# ---------------------------------------------------------------------------- label helpers
def sort_by_size(labels: np.ndarray) -> np.ndarray:
    """[N] labels >= 0 (or -1) -> [N] int32 labels renumbered 0 = largest, -1 kept."""
    labels = np.asarray(labels)
    out = np.full(labels.shape, NOISE, np.int32)
    valid = labels >= 0
    if not valid.any():
        return out
    uniq, inv, counts = np.unique(labels[valid], return_inverse=True, return_counts=True)
    order = np.lexsort((uniq, -counts))  # size descending, then raw label ascending
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    out[valid] = rank[inv.reshape(-1)]
    return out


def dissolve_small(labels: np.ndarray, min_count: int) -> tuple[np.ndarray, int, int]:
    """Turn clusters with fewer than ``min_count`` points into noise (the largest is kept).

    Args:
        labels: [N] size-sorted labels (0 = largest, -1 noise).
        min_count: smallest cluster kept.

    Returns:
        ([N] labels sorted again, number of clusters dissolved, number of points they held).
    """
    counts = np.bincount(labels[labels >= 0]) if (labels >= 0).any() else np.zeros(0, int)
    small = np.flatnonzero(counts < min_count)
    small = small[small != 0]
    if small.size == 0:
        return labels, 0, 0
    mask = np.isin(labels, small)
    out = labels.copy()
    out[mask] = NOISE
    return sort_by_size(out), int(small.size), int(mask.sum())


def assign_noise(points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, dict]:
    """Give every noise point (-1) the label of its nearest labelled point.

    Args:
        points: [N, 3] positions.
        labels: [N] labels with -1 for noise and at least one labelled point.

    Returns:
        ([N] int32 labels, all >= 0; record {"count", "max_distance", "median_distance"}).
    """
    noise = labels < 0
    out = labels.astype(np.int32, copy=True)
    if not noise.any():
        return out, {"count": 0, "max_distance": 0.0, "median_distance": 0.0}
    keep = np.flatnonzero(~noise)
    d, idx = cKDTree(points[keep]).query(points[noise], k=1)
    out[noise] = labels[keep[idx]]
    return out, {"count": int(noise.sum()), "max_distance": float(d.max()), "median_distance": float(np.median(d))}


def apply_merges(labels: np.ndarray, merges: list) -> np.ndarray:
    """Merge clusters by rules [[a, b, ...], ...] (labels as sorted, transitive); re-sorted [N] labels."""
    k = int(labels.max()) + 1 if labels.size else 0
    parent = list(range(k))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, rule in enumerate(merges):
        if not isinstance(rule, (list, tuple)) or len(rule) < 2:
            raise ConfigError(f"cluster.merge[{i}]", f"must be a list of at least two labels, got {rule!r}")
        for lab in rule:
            if not isinstance(lab, (int, np.integer)) or not 0 <= int(lab) < k:
                raise ConfigError(f"cluster.merge[{i}]", f"label {lab!r} does not exist: the clustering "
                                  f"found {k} instances (labels 0..{k - 1}, sorted by size)")
        root = find(int(rule[0]))
        for lab in rule[1:]:
            r = find(int(lab))
            if r != root:
                parent[r] = root
    roots = np.array([find(a) for a in range(k)], dtype=np.int64)
    return sort_by_size(roots[labels])


# ---------------------------------------------------------------------------- scene instances
def _scene_instances(scene_cfg: dict) -> list[dict]:
    inst = scene_cfg.get("instances") or []
    if not isinstance(inst, list):
        raise ConfigError("scene.instances", f"must be a list, got {type(inst).__name__}")
    out = []
    for i, it in enumerate(inst):
        if not isinstance(it, dict):
            raise ConfigError(f"scene.instances[{i}]", f"must be a mapping, got {it!r}")
        out.append({"name": it.get("name"), "at": _point(it.get("at"), f"scene.instances[{i}].at"),
                    "box": _box(it.get("box"), f"scene.instances[{i}].box")})
    return out


def _point(v, key: str) -> np.ndarray | None:
    if v is None:
        return None
    a = np.asarray(v, dtype=np.float64) if _numeric(v) else None
    if a is None or a.shape != (3,) or not np.isfinite(a).all():
        raise ConfigError(key, f"must be a finite point [x, y, z] in the simulation frame, got {v!r}")
    return a


def _box(v, key: str) -> np.ndarray | None:
    if v is None:
        return None
    a = np.asarray(v, dtype=np.float64) if _numeric(v) else None
    if a is None or a.shape != (2, 3) or not np.isfinite(a).all():
        raise ConfigError(key, f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] in the simulation frame, got {v!r}")
    if (a[1] <= a[0]).any():
        raise ConfigError(key, f"max corner {a[1].tolist()} must exceed the min corner {a[0].tolist()} on every axis")
    return a


def _numeric(v) -> bool:
    try:
        np.asarray(v, dtype=np.float64)
        return True
    except (TypeError, ValueError):
        return False


def labels_from_boxes(points: np.ndarray, boxes: list[np.ndarray]) -> np.ndarray:
    """[N] labels = index of the first box containing the point, -1 if none.

    Args:
        points: [N, 3] positions (sim frame).
        boxes: list of [2, 3] (min, max) corners.
    """
    labels = np.full(points.shape[0], NOISE, np.int32)
    for i, b in enumerate(boxes):
        inside = (labels < 0) & np.all((points >= b[0]) & (points <= b[1]), axis=1)
        labels[inside] = i
    for i, b in enumerate(boxes):
        if not np.any(np.all((points >= b[0]) & (points <= b[1]), axis=1)):
            raise ConfigError(f"scene.instances[{i}].box", f"contains no gaussian (box {b.tolist()}, "
                              f"gaussians span {points.min(0).round(3).tolist()}..{points.max(0).round(3).tolist()})")
    return labels


def match_instances(points: np.ndarray, labels: np.ndarray, instances: list[dict]) -> tuple[list, list[str]]:
    """config_index per label: by ``at`` (nearest gaussian), then ``box`` (most gaussians inside),
    then by order of size. Returns ([K] config index or None, warnings)."""
    k = int(labels.max()) + 1
    cfg_index: list[int | None] = [None] * k
    warnings: list[str] = []
    pending = []
    tree = None
    for i, inst in enumerate(instances):
        lab = None
        if inst["at"] is not None:
            tree = tree or cKDTree(points)
            _, j = tree.query(inst["at"])
            lab = int(labels[j])
        elif inst["box"] is not None:
            b = inst["box"]
            inside = np.all((points >= b[0]) & (points <= b[1]), axis=1)
            if inside.any():
                lab = int(np.bincount(labels[inside], minlength=k).argmax())
            else:
                warnings.append(f"scene.instances[{i}].box contains no gaussian; matched by size instead")
        if lab is None:
            pending.append(i)
        elif cfg_index[lab] is not None:
            warnings.append(f"scene.instances[{i}] ({inst['name']}) points at the same cluster as "
                            f"scene.instances[{cfg_index[lab]}]; lower cluster.eps or give boxes")
        else:
            cfg_index[lab] = i
    free = [lab for lab in range(k) if cfg_index[lab] is None]
    for i, lab in zip(pending, free):
        cfg_index[lab] = i
    return cfg_index, warnings


def _gaps(points: np.ndarray, labels: np.ndarray, lab: int, others: list[int]) -> tuple[int, float]:
    """(the label among ``others`` nearest to cluster ``lab``, the smallest gaussian distance)."""
    sel = np.isin(labels, others)
    d, j = cKDTree(points[sel]).query(points[labels == lab], k=1)
    i = int(np.argmin(d))
    return int(labels[sel][j[i]]), float(d[i])


def join_fragments(points: np.ndarray, labels: np.ndarray, cfg_index: list, fraction: float
                   ) -> tuple[np.ndarray, list, list[dict]]:
    """Join unmatched clusters (``cfg_index`` None) that hold at most ``fraction`` of the gaussians
    of their nearest matched cluster to it (module docs, "Fragments").

    Args:
        points: [N, 3] positions; labels: [N] size-sorted labels; cfg_index: [K] per label.
    Returns:
        ([N] labels sorted by size again, config index per new label, one record per join).
    """
    k = int(labels.max()) + 1
    matched = [lab for lab in range(k) if cfg_index[lab] is not None]
    if fraction <= 0 or not matched or len(matched) == k:
        return labels, cfg_index, []
    counts = np.bincount(labels, minlength=k)
    target = np.arange(k)
    records = []
    for lab in range(k):
        if cfg_index[lab] is not None:
            continue
        near, gap = _gaps(points, labels, lab, matched)
        if counts[lab] <= fraction * counts[near]:
            target[lab] = near
            sel = points[labels == lab]
            records.append({"count": int(counts[lab]), "bbox_min": np.round(sel.min(0), 4).tolist(),
                            "bbox_max": np.round(sel.max(0), 4).tolist(), "gap": gap,
                            "fraction": float(counts[lab] / counts[near]), "joined_config_index": cfg_index[near],
                            "joined_label": None, "joined_name": None, "_old": near})
    if not records:
        return labels, cfg_index, []
    joined = target[labels]
    new = sort_by_size(joined)
    old_to_new = {int(o): int(n) for o, n in zip(joined, new)}
    new_index = [None] * (int(new.max()) + 1)
    for old, n in old_to_new.items():
        new_index[n] = cfg_index[old]
    for r in records:
        r["joined_label"] = old_to_new[r.pop("_old")]
    return new.astype(np.int32), new_index, records


def _note_unmatched(points: np.ndarray, labels: np.ndarray, recs: list[dict]) -> None:
    """Add ``unmatched`` {nearest_label, gap, fraction} to the records of clusters that match no
    scene instance (the pinned-params stage quotes it when such a cluster has no pins)."""
    matched = [r["label"] for r in recs if r["config_index"] is not None]
    for r in recs:
        if r["config_index"] is None and matched:
            near, gap = _gaps(points, labels, r["label"], matched)
            r["unmatched"] = {"nearest_label": near, "gap": gap, "fraction": r["count"] / recs[near]["count"]}


# ---------------------------------------------------------------------------- labelling
def raw_labels(points: np.ndarray, instances: list[dict], ccfg: dict, ply_labels: np.ndarray | None,
               log: logging.Logger) -> tuple[np.ndarray, str, dict]:
    """Labels before sorting and the noise policy, by the configured method.

    Args:
        points: [N, 3] gaussian means (sim frame).
        instances: the parsed scene instances (``name``, ``at``, ``box``).
        ccfg: the validated ``cluster`` section.
        ply_labels: [N] int ``label`` property of scene.ply, or None.

    Returns:
        ([N] int32 raw labels, -1 = unlabelled; the method used; extra record fields).
    """
    n = points.shape[0]
    method = ccfg["method"]
    all_boxes = bool(instances) and all(it["box"] is not None for it in instances)
    if method == "auto":
        method = "boxes" if all_boxes else "dbscan"
    if method == "boxes":
        if not all_boxes:
            missing = [i for i, it in enumerate(instances) if it["box"] is None]
            raise ConfigError("cluster.method", "is 'boxes' but scene.instances "
                              f"{missing or '(none listed)'} have no `box`")
        log.info("every scene instance has a box: DBSCAN left out, labels from %d boxes", len(instances))
        return labels_from_boxes(points, [it["box"] for it in instances]), method, {}
    if method == "ply_labels":
        if ply_labels is None:
            raise ConfigError("cluster.method", "is 'ply_labels' but scene.ply has no integer `label` property")
        raw = np.where(np.asarray(ply_labels) >= 0, ply_labels, NOISE).astype(np.int32)
        if (raw < 0).all():
            raise ConfigError("cluster.method", "is 'ply_labels' but every `label` in scene.ply is negative")
        return raw, method, {}
    raw = dbscan_labels(points, ccfg["eps"], ccfg["min_samples"], ccfg["algorithm"],
                        ccfg["voxel_factor"], ccfg["exact_max_points"])
    if (raw < 0).all():
        hint = knn_distance_hint(points, ccfg["min_samples"])
        raise ConfigError("cluster.eps", f"DBSCAN labelled all {n} gaussians as noise (eps={ccfg['eps']}, "
                          f"min_samples={ccfg['min_samples']}): the median distance to the "
                          f"{ccfg['min_samples']}th neighbour is {hint:.4g}; raise cluster.eps above it "
                          "or lower cluster.min_samples")
    algorithm = ccfg["algorithm"] if ccfg["algorithm"] != "auto" else (
        "exact" if n <= ccfg["exact_max_points"] else "voxel")
    return raw, method, {"algorithm": algorithm}


def _merged_warning(k: int, instances: list[dict], ccfg: dict) -> str | None:
    """The message for DBSCAN finding fewer instances than the scene lists (None if not)."""
    if not instances or k >= len(instances):
        return None
    msg = (f"DBSCAN found {k} instance(s) but the scene lists {len(instances)} "
           f"({', '.join(str(it['name']) for it in instances)}): objects closer than cluster.eps="
           f"{ccfg['eps']} were merged; lower cluster.eps, or give each instance a `box` in the scene file")
    if ccfg["strict"]:
        raise ConfigError("cluster.eps", msg)
    return msg


def compute_labels(points: np.ndarray, scene_cfg: dict, ccfg: dict, ply_labels: np.ndarray | None,
                   log: logging.Logger) -> tuple[np.ndarray, dict]:
    """Instance labels for every gaussian and the clusters.json record (without timings).

    Args:
        points: [N, 3] gaussian means (sim frame).
        scene_cfg: the scene dict (``instances``).
        ccfg: the validated ``cluster`` section.
        ply_labels: [N] int ``label`` property of scene.ply, or None.

    Returns:
        ([N] int32 labels 0..K-1 sorted by size, record dict).
    """
    instances = _scene_instances(scene_cfg)
    raw, method, extra = raw_labels(points, instances, ccfg, ply_labels, log)
    labels = sort_by_size(raw)
    dissolved, dissolved_pts = 0, 0
    if method == "dbscan":
        min_count = int(np.ceil(ccfg["min_cluster_fraction"] * points.shape[0]))
        labels, dissolved, dissolved_pts = dissolve_small(labels, min_count)
    labels, noise_rec = assign_noise(points, labels)
    if ccfg["merge"]:
        labels = apply_merges(labels, ccfg["merge"])
        log.info("applied merge rules %s", ccfg["merge"])
    k = int(labels.max()) + 1
    fragments: list[dict] = []
    if method == "boxes":  # the box a label came from is its config index
        cfg_index = [int(np.bincount(raw[(labels == lab) & (raw >= 0)], minlength=len(instances)).argmax())
                     for lab in range(k)]
        warnings = []
    else:
        cfg_index, warnings = match_instances(points, labels, instances)
        if instances:
            labels, cfg_index, fragments = join_fragments(points, labels, cfg_index, ccfg["fragment_fraction"])
            k = int(labels.max()) + 1
            for f in fragments:
                f["joined_name"] = instances[f["joined_config_index"]]["name"]
                warnings.append(f"a cluster of {f['count']} gaussians (box {f['bbox_min']}..{f['bbox_max']}) matched no "
                                f"scene instance; joined instance '{f['joined_name'] or f['joined_label']}' "
                                f"{f['gap']:.3g} away as a fragment of it ({f['fraction']:.3g} of its size <= "
                                f"cluster.fragment_fraction {ccfg['fragment_fraction']}); if it is an object of its own, "
                                "list it in the scene's instances (e.g. with `at` inside that box)")
    merged = _merged_warning(k, instances, ccfg) if method == "dbscan" else None
    if merged:
        warnings.append(merged)
    for w in warnings:
        log.warning("%s", w)
    record = {
        "method": method, **extra,
        "n_instances": k,
        "raw_clusters": int(raw.max()) + 1,
        "noise": {"policy": "nearest: DBSCAN noise, gaussians outside every box and dissolved small clusters "
                            "join the cluster of the nearest labelled gaussian",
                  "unlabelled": int((raw < 0).sum()), "dissolved_clusters": dissolved,
                  "dissolved_points": dissolved_pts, **noise_rec},
        "eps": ccfg["eps"], "min_samples": ccfg["min_samples"], "merge": ccfg["merge"],
        "warnings": warnings,
        "fragment_fraction": ccfg["fragment_fraction"], "fragments": fragments,
        "instances": _instance_records(points, labels, cfg_index, instances),
    }
    if instances:
        _note_unmatched(points, labels, record["instances"])
    return labels, record


def _instance_records(points: np.ndarray, labels: np.ndarray, cfg_index: list, instances: list[dict]) -> list[dict]:
    out = []
    for lab in range(int(labels.max()) + 1):
        sel = points[labels == lab]
        ci = cfg_index[lab]
        out.append({"label": lab, "count": int(sel.shape[0]),
                    "bbox_min": sel.min(axis=0).tolist(), "bbox_max": sel.max(axis=0).tolist(),
                    "config_index": ci, "name": instances[ci]["name"] if ci is not None else None})
    return out


# ---------------------------------------------------------------------------- stage
def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Stage entry point.

    inputs: ``{"scene": scene.ply}`` (sim frame). outputs: ``{"labels": labels.npz,
    "clusters": clusters.json}``. cfg: ``{"cluster": {...}, "scene": {...}}``.
    """
    from .scene_io import load_gaussians

    ccfg = cluster_config(cfg)
    t0 = time.perf_counter()
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    tracemalloc.reset_peak()
    try:
        scene = load_gaussians(inputs["scene"], log=log)
        points = scene.means.astype(np.float64)
        if not np.isfinite(points).all():
            raise InputError(inputs["scene"], "non-finite gaussian means")
        ply_labels = scene.extras.get("label")
        static = np.asarray(scene.extras.get("static", np.zeros(scene.n)), dtype=np.int64) != 0
        if static.all():
            raise InputError(inputs["scene"], "every gaussian is marked static (outside region.box): nothing to simulate")
        labels = np.full(scene.n, STATIC, np.int32)
        labels[~static], record = compute_labels(points[~static], cfg.get("scene") or {}, ccfg,
                                                 None if ply_labels is None else ply_labels[~static], log)
        static_instances = select_static(record, cfg.get("scene") or {})
        for r in record["instances"]:
            r["static"] = r["label"] in static_instances
        record["static_instances"] = static_instances
        record["n_static_surroundings"] = int(static.sum())
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        if started:
            tracemalloc.stop()
    record["seconds"] = round(seconds, 4)
    record["peak_alloc_mb"] = round(peak, 2)
    record["n_gaussians"] = int(points.shape[0])
    with atomic_path(outputs["labels"]) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, labels=labels.astype(np.int32), seconds=np.float64(seconds), peak_alloc_mb=np.float64(peak),
                     static_instances=np.asarray(static_instances, np.int32))
    write_json(outputs["clusters"], record)
    sizes = [r["count"] for r in record["instances"]]
    log.info("%s: %d instances (sizes %s), %d noise gaussians joined their nearest cluster, %.2f s; wrote %s and %s",
             record["method"], record["n_instances"], sizes, record["noise"]["count"], seconds,
             outputs["labels"], outputs["clusters"])
    if static.any() or static_instances:
        log.info("static (drawn at rest, not simulated): %d gaussians outside region.box, instances %s",
                 int(static.sum()), static_instances)
    return {"n_instances": record["n_instances"], "seconds": round(seconds, 3)}


def select_static(record: dict, scene_cfg: dict) -> list[int]:
    """Sorted labels of the instances that are not simulated: those left out of
    ``region.instances`` and those whose scene entry says ``static: true``.

    Args:
        record: the clusters.json record (``instances`` with ``label`` and ``config_index``).
        scene_cfg: the scene dict (``region``, ``instances``).

    Raises:
        ConfigError naming ``region.instances`` for a reference that matches nothing or a
        selection that leaves nothing to simulate.
    """
    entries = scene_cfg.get("instances") or []
    by_entry = {r["config_index"]: r["label"] for r in record["instances"] if r["config_index"] is not None}
    k = len(record["instances"])
    static = {by_entry[i] for i, e in enumerate(entries) if isinstance(e, dict) and e.get("static") and i in by_entry}
    chosen = (scene_cfg.get("region") or {}).get("instances")
    if chosen is not None:
        keep = set()
        for j, ref in enumerate(chosen):
            key = f"region.instances[{j}]"
            if isinstance(ref, bool) or not isinstance(ref, (int, str)):
                raise ConfigError(key, f"must be a cluster label or an instance name/hint, got {ref!r}")
            if isinstance(ref, int):
                if not 0 <= ref < k:
                    raise ConfigError(key, f"label {ref} does not exist: the clustering found {k} instances "
                                           f"(labels 0..{k - 1}, 0 = largest; see clusters.json)")
                keep.add(ref)
                continue
            hits = [i for i, e in enumerate(entries) if isinstance(e, dict) and ref in (e.get("name"), e.get("hint"))]
            if not hits:
                names = [e.get("name") for e in entries if isinstance(e, dict)]
                raise ConfigError(key, f"{ref!r} is neither the name nor the hint of a scene instance (names: {names})")
            labs = [by_entry[i] for i in hits if i in by_entry]
            if not labs:
                raise ConfigError(key, f"{ref!r} names a scene instance that matched no cluster")
            keep.update(labs)
        static |= set(range(k)) - keep
    if len(static) >= k:
        raise ConfigError("region.instances", f"every one of the {k} instances is static (region.instances / "
                                              "static: true): nothing is left to simulate")
    return sorted(int(v) for v in static)


def load_labels(path) -> np.ndarray:
    """[N] int32 labels from labels.npz: 0..K-1, STATIC (-1) for static surroundings
    (InputError when missing or malformed)."""
    try:
        with np.load(path) as z:
            labels = np.asarray(z["labels"])
    except (OSError, KeyError, ValueError) as e:
        raise InputError(path, f"cannot read instance labels: {e}") from None
    if labels.ndim != 1 or labels.dtype.kind not in "iu" or (labels.size and labels.min() < STATIC):
        raise InputError(path, f"'labels' must be [N] integers >= {STATIC}, got {labels.dtype} {labels.shape}")
    if labels.size and labels.max() < 0:
        raise InputError(path, "every gaussian is static (label -1): nothing to simulate")
    return labels.astype(np.int32)


def load_static_instances(path) -> list[int]:
    """The labels of static instances listed in labels.npz (empty when the file has none)."""
    try:
        with np.load(path) as z:
            if "static_instances" not in z:
                return []
            return sorted(int(v) for v in np.asarray(z["static_instances"]).ravel())
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read instance labels: {e}") from None
