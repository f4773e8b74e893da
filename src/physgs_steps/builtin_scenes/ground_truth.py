"""Ground-truth solids of a built-in scene: instances made of overlapping parts.

Shapes use fixed letters: M query points, K instances.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from .primitives import Primitive


@dataclasses.dataclass
class Part:
    """One primitive of an instance with its surface colour (RGB in [0, 1])."""

    name: str
    solid: Primitive
    color: tuple[float, float, float]

    def shifted(self, d) -> "Part":
        return Part(self.name, self.solid.shifted(d), self.color)


@dataclasses.dataclass
class Instance:
    """A separate object: the union of its parts."""

    name: str
    parts: list[Part]

    def shifted(self, d) -> "Instance":
        return Instance(self.name, [p.shifted(d) for p in self.parts])

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        boxes = [p.solid.aabb() for p in self.parts]
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """[M, 3] -> [M] union signed distance (min over parts).

        A part is evaluated only at points whose distance to its bounding box is below the
        best value so far (or zero): its distance is at least that, so the min is unchanged.
        """
        best = np.full(len(points), np.inf)
        for p in self.parts:
            lo, hi = p.solid.aabb()
            box_dist = np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)
            sel = np.flatnonzero((box_dist < best) | (box_dist == 0.0))
            if len(sel):
                best[sel] = np.minimum(best[sel], p.solid.sdf(points[sel]))
        return best

    def inside(self, points: np.ndarray) -> np.ndarray:
        """[M, 3] -> [M] bool."""
        out = np.zeros(len(points), dtype=bool)
        for p in self.parts:
            lo, hi = p.solid.aabb()
            near = np.flatnonzero(~out & np.all((points >= lo) & (points <= hi), axis=1))
            if len(near):
                out[near[p.solid.inside(points[near])]] = True
        return out


@dataclasses.dataclass
class BoxRegion:
    """Open axis-aligned box (lo [3], hi [3]); calling it tests points [M, 3] -> [M] bool."""

    lo: np.ndarray
    hi: np.ndarray

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return np.all((p > self.lo) & (p < self.hi), axis=1)


@dataclasses.dataclass
class CavityRegion:
    """The open cavity of a cup part, shrunk by ``margin`` (see primitives.Cup.cavity_contains)."""

    cup: Primitive
    margin: float

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return self.cup.cavity_contains(np.asarray(points, dtype=np.float64), self.margin)


class GroundTruth:
    """The true solids of a built-in scene (source frame, metres, z up).

    Attributes:
        scene: the scene name.
        instances: list of :class:`Instance` (K of them, in label order).
        instance_names: [K] names.
        bounds: ([3] min, [3] max) axis-aligned box of all solids.
        landmarks: named points [3] (e.g. ``belly_center`` inside the bear,
            ``hollow_center`` in the air inside the basket).
    """

    def __init__(self, scene: str, instances: list[Instance], regions: dict[str, Callable],
                 landmarks: dict[str, np.ndarray]):
        self.scene = scene
        self.instances = instances
        self.instance_names = [i.name for i in instances]
        boxes = [i.aabb() for i in instances]
        self.bounds = (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))
        self._regions = dict(regions)
        self.landmarks = {k: np.asarray(v, dtype=np.float64) for k, v in landmarks.items()}

    def _check(self, points) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"GroundTruth: points must have shape [M, 3], got {p.shape}")
        return p

    def _selected(self, instance) -> list[Instance]:
        if instance is None:
            return self.instances
        if isinstance(instance, str):
            if instance not in self.instance_names:
                raise ValueError(f"GroundTruth: unknown instance '{instance}'; known: {self.instance_names}")
            return [self.instances[self.instance_names.index(instance)]]
        k = int(instance)
        if not 0 <= k < len(self.instances):
            raise ValueError(f"GroundTruth: instance index {k} outside 0..{len(self.instances) - 1}")
        return [self.instances[k]]

    def inside(self, points, instance=None) -> np.ndarray:
        """points [M, 3] -> [M] bool: inside instance ``instance`` (index or name), or any if None."""
        p = self._check(points)
        out = np.zeros(len(p), dtype=bool)
        for inst in self._selected(instance):
            out |= inst.inside(p)
        return out

    def instance_of(self, points) -> np.ndarray:
        """points [M, 3] -> [M] int32 instance index, -1 outside every solid."""
        p = self._check(points)
        out = np.full(len(p), -1, dtype=np.int32)
        for k, inst in enumerate(self.instances):
            out[(out < 0) & inst.inside(p)] = k
        return out

    def empty_regions(self) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
        """name -> inside test ([M, 3] -> [M] bool) of a region of air that must stay empty."""
        return dict(self._regions)

    def sdf(self, points, instance=None) -> np.ndarray:
        """points [M, 3] -> [M] signed distance (negative inside), min over parts.

        Exact outside the solids when the nearest part is a sphere, ellipsoid, capsule,
        rounded box, cylinder or torus; elsewhere (inside overlapping parts, cups, the
        stone) a conservative bound: same sign, |value| <= true distance.
        """
        p = self._check(points)
        return np.min([inst.sdf(p) for inst in self._selected(instance)], axis=0)

    def parts(self) -> list[tuple[int, Part]]:
        """Every (instance index, part) pair."""
        return [(k, part) for k, inst in enumerate(self.instances) for part in inst.parts]
