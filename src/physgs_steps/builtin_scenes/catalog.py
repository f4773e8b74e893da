"""The built-in scenes as ground-truth solids (metres, z up, resting on z = 0).

The geometry of a scene is fixed (shape randomness such as the stone's bumps or the ficus'
leaf layout uses fixed internal seeds); the user's seed only changes the gaussians.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from .ground_truth import BoxRegion, CavityRegion, GroundTruth, Instance, Part
from .primitives import blob, capsule, cup, cylinder, ellipsoid, frame, rounded_box, sphere, torus

GAP_FRACTION = 0.16  # air gap between separate objects / largest side of the scene box

BROWN = (0.47, 0.30, 0.17)
TAN = (0.80, 0.64, 0.45)
DARK = (0.06, 0.05, 0.05)
RED = (0.78, 0.10, 0.10)
SILVER = (0.78, 0.79, 0.81)
YELLOW = (0.97, 0.82, 0.12)
WING = (0.95, 0.72, 0.10)
ORANGE = (0.96, 0.48, 0.06)
GREY = (0.52, 0.52, 0.50)
TERRACOTTA = (0.74, 0.40, 0.24)
SOIL = (0.28, 0.19, 0.12)
STEM = (0.42, 0.33, 0.20)
GREEN = (0.18, 0.48, 0.14)
WICKER = (0.72, 0.56, 0.32)
WICKER_RIM = (0.56, 0.40, 0.21)
MAT = (0.25, 0.40, 0.60)
CRUST_LIGHT = (0.86, 0.64, 0.33)
CRUST = (0.76, 0.50, 0.22)
SCORE = (0.93, 0.80, 0.55)
STEEL = (0.60, 0.62, 0.66)
JELLY_RED = (0.85, 0.18, 0.28)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _rotate(v, axis, degrees: float) -> np.ndarray:
    """[3] vector v rotated by ``degrees`` about ``axis`` [3]."""
    return Rotation.from_rotvec(_unit(axis) * math.radians(degrees)).apply(np.asarray(v, dtype=np.float64))


def _part(inst: Instance, name: str) -> Part:
    return next(p for p in inst.parts if p.name == name)


# ---------------------------------------------------------------------------- objects
def bear() -> Instance:
    """A sitting teddy bear facing -y, about 0.3 m tall."""
    head_c = np.array([0.0, -0.008, 0.235])
    parts = [
        Part("body", ellipsoid([0.0, 0.0, 0.115], [0.075, 0.065, 0.095]), BROWN),
        Part("belly", ellipsoid([0.0, -0.032, 0.105], [0.052, 0.036, 0.066]), TAN),
        Part("head", sphere(head_c, 0.066), BROWN),
        Part("snout", ellipsoid([0.0, -0.064, 0.222], [0.030, 0.026, 0.022]), TAN),
        Part("nose", ellipsoid([0.0, -0.089, 0.232], [0.012, 0.008, 0.008]), DARK),
    ]
    for side, s in (("left", -1.0), ("right", 1.0)):
        parts += [
            Part(f"eye_{side}", sphere(head_c + 0.062 * _unit([0.38 * s, -0.8, 0.38]), 0.0075), DARK),
            Part(f"ear_{side}", ellipsoid([0.048 * s, -0.004, 0.292], [0.024, 0.011, 0.024]), BROWN),
            Part(f"arm_{side}", capsule([0.058 * s, -0.012, 0.165], [0.088 * s, -0.058, 0.095], 0.025), BROWN),
            Part(f"leg_{side}", capsule([0.042 * s, -0.015, 0.034], [0.058 * s, -0.092, 0.032], 0.032), BROWN),
            Part(f"paw_{side}", ellipsoid([0.058 * s, -0.120, 0.034], [0.026, 0.008, 0.026]), TAN),
        ]
    return Instance("bear", parts)


def can() -> Instance:
    """A closed drink can standing on z = 0: red body, silver rims, lid and tab."""
    return Instance("can", [
        Part("bottom_rim", cylinder([0, 0, 0.0], 0.0335, 0.008, rounding=0.003), SILVER),
        Part("body", cylinder([0, 0, 0.003], 0.033, 0.114, rounding=0.004), RED),
        Part("top_rim", cylinder([0, 0, 0.109], 0.0335, 0.012, rounding=0.003), SILVER),
        Part("tab", rounded_box([0.012, 0.0, 0.1213], [0.011, 0.006, 0.0015], 0.001), SILVER),
    ])


def duck() -> Instance:
    """A rubber duck facing +x, in its resting pose (resting_instance: pitched 6.3 degrees nose
    down). Built upright its centre of mass lies 7 mm ahead of its lowest point (the head), so
    dropped upright it landed nose-heavy and rocked forward into that pose with the landing's
    energy."""
    head_c = np.array([0.05, 0.0, 0.1])
    tail_dir = np.array([-math.cos(math.radians(35)), 0.0, math.sin(math.radians(35))])
    tail_up = np.array([math.sin(math.radians(35)), 0.0, math.cos(math.radians(35))])
    parts = [
        Part("body", ellipsoid([0.0, 0.0, 0.045], [0.075, 0.056, 0.045]), YELLOW),
        Part("head", sphere(head_c, 0.036), YELLOW),
        Part("beak", ellipsoid([0.092, 0.0, 0.094], [0.024, 0.017, 0.008]), ORANGE),
        Part("tail", ellipsoid([-0.068, 0.0, 0.062], [0.030, 0.022, 0.011], rot=frame(tail_up, tail_dir)), YELLOW),
    ]
    for side, s in (("left", 1.0), ("right", -1.0)):
        parts += [
            Part(f"wing_{side}", ellipsoid([-0.012, 0.052 * s, 0.055], [0.042, 0.012, 0.024]), WING),
            Part(f"eye_{side}", sphere(head_c + 0.034 * _unit([0.55, 0.6 * s, 0.5]), 0.0065), DARK),
        ]
    return resting_instance(Instance("duck", parts), mirror_y=True)


def _resting_rotation(points, com, pitch_only: bool = False):
    """The tilt R (about x and y; only y with ``pitch_only``) at which the centre of mass
    ``com`` [3] lies lowest above the lowest of ``points`` [N, 3] (``resting``, ``resting_instance``)."""
    def rot(a):
        return Rotation.from_rotvec([0.0 if pitch_only else a[0], a[1], 0.0]).as_matrix()

    def height(a):
        R = rot(a)
        return float((R @ com)[2] - (points @ R[2]).min())

    res = minimize(height, np.zeros(2), method="Nelder-Mead",
                   options={"xatol": 1e-7, "fatol": 1e-12, "initial_simplex": [[0.0, 0.0], [0.02, 0.0], [0.0, 0.02]]})
    return rot(res.x)


def resting_instance(inst: Instance, mirror_y: bool = False) -> Instance:
    """``inst`` (a union of parts, uniform density) turned about its centre of mass into the
    resting pose nearest its own on a horizontal plane, as ``resting`` does for one solid: the
    centre of mass from points inside on a fixed grid of samples, the lowest point from
    samples of every part's surface. ``mirror_y``: the instance is mirror-symmetric about
    y = 0, so it is only pitched (about y); the sampled centre of mass's y error would
    otherwise roll it (1.2 degrees for the duck)."""
    rng = np.random.default_rng(0)
    lo, hi = inst.aabb()
    q = rng.uniform(lo, hi, (200_000, 3))
    inside = np.zeros(len(q), dtype=bool)
    for p in inst.parts:
        inside |= p.solid.inside(q)
    com = q[inside].mean(axis=0)
    surf = np.concatenate([p.solid.sample(40_000, rng)[0] for p in inst.parts])

    if mirror_y:
        com[1] = 0.0
    R = _resting_rotation(surf, com, pitch_only=mirror_y)
    return Instance(inst.name, [dataclasses.replace(
        p, solid=dataclasses.replace(p.solid, center=com + R @ (p.solid.center - com), rot=R @ p.solid.rot))
        for p in inst.parts])


def resting(solid):
    """``solid`` (a primitive with a mesh) turned about its centre of mass into the resting pose
    nearest its own on a horizontal plane: the tilt (about x and y) at which the centre of mass
    lies lowest above the solid's lowest point, a minimum of the potential energy on the plane,
    so the pose is a stable equilibrium. A free body placed on the ground in any other pose is
    not at rest: it rolls into this one and, rolling being lossless, rocks about it."""
    mesh = solid.mesh()
    v = solid.to_world(np.asarray(mesh.vertices, dtype=np.float64))
    com = solid.to_world(np.asarray(mesh.center_mass, dtype=np.float64)[None])[0]
    R = _resting_rotation(v, com)
    return dataclasses.replace(solid, center=com + R @ (solid.center - com), rot=R @ solid.rot)


def stone() -> Instance:
    """An irregular grey stepping stone: a flat ellipsoid (0.32 x 0.24 x 0.06 m) with smooth
    random bumps (fixed shape), flat enough that the duck dropped on it rests on it.

    A body whose centre of mass is h above its bottom rests on another only if the two
    surfaces' curvatures at the contact sum to less than 1/h (rolling stability, 1/h > 1/r + 1/R
    in 2-D; in 3-D the largest eigenvalue of K_duck + K_stone). The duck (body ellipsoid
    [0.075, 0.056, 0.045], pitched 6.3 degrees into its resting pose) has bottom radii r 0.121 m
    along and 0.069 m across and h 0.056 m, so the stone's top needs R > 1 / (1/0.056 - 1/0.069)
    = 0.30 m across where it lands. The previous stone (semi-axes [0.12, 0.09, 0.058], bumps
    summing to 0.3) had R 0.14 m across and 0.18 m along there (slope 5 deg; largest eigenvalue
    21.7 /m > 1/h 17.8, h times it 1.22): the duck rolled off. This one (semi-axes
    [0.16, 0.12, 0.03], bumps summing to 0.2) has R 0.51 m across and 0.64 m along under the
    duck's lowest point (principal 0.47 / 0.72 m, slope 1.7 deg; largest eigenvalue of the
    summed curvatures 16.5 /m, h times it 0.93 < 1: stable; the duck alone on a plane gives
    0.81). Its bottom is flatter too (principal radii 0.64 / 0.95 m under its centre of mass,
    rising under 1 mm within 2.5 cm; the old stone 0.21 / 0.37 m, 3.3 mm), so on the ground it
    bears on a patch of particles, not one. Volume 2.28e-3 m^3, 5.9 kg at 2600 kg/m^3 (the old
    stone 2.43e-3 m^3, 6.3 kg). tools/duck_stone_curvature.py prints these numbers."""
    rng = np.random.default_rng(20240611)
    k = 9
    amps = rng.uniform(0.4, 1.0, k)
    amps *= 0.2 / amps.sum()
    freqs = rng.normal(size=(k, 3))
    freqs *= (rng.uniform(1.5, 4.0, k) / np.linalg.norm(freqs, axis=1))[:, None]
    phases = rng.uniform(0.0, 2.0 * math.pi, k)
    rot = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    # lying on the ground at rest (resting): the centre of mass above the lowest point, the pose
    # a free body released on the ground stays in (the old stone lay 2.8 degrees off it, rolled
    # into it, 0.16 J at the simulation's scale, and rocked about it)
    return Instance("stone", [Part("stone", resting(blob([0.0, 0.0, 0.06], [0.16, 0.12, 0.03], amps, freqs,
                                                         phases, rot)), GREY)])


def ficus() -> Instance:
    """A potted ficus: terracotta pot with a lip, soil, stem, five branches, 30 thin leaves."""
    rng = np.random.default_rng(7)
    up = np.array([0.0, 0.0, 1.0])
    stem_a, stem_b = np.array([0.0, 0.0, 0.09]), np.array([0.004, 0.002, 0.30])
    parts = [
        Part("pot", cup([0, 0, 0], outer=0.07, inner=0.061, height=0.12, floor=0.012), TERRACOTTA),
        Part("pot_lip", torus([0, 0, 0.118], 0.0685, 0.0065), TERRACOTTA),
        Part("soil", cylinder([0, 0, 0.011], 0.0615, 0.094), SOIL),
        Part("stem", capsule(stem_a, stem_b, 0.0065), STEM),
    ]
    leaves: list[tuple[np.ndarray, np.ndarray]] = []  # (attach point, leaf direction)
    heights = [0.16, 0.195, 0.225, 0.255, 0.28]
    for i, h in enumerate(heights):
        az = math.radians(20.0 + 137.5 * i)
        el = math.radians(50.0 - 4.0 * i)
        d = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
        start = stem_a + (stem_b - stem_a) * (h - stem_a[2]) / (stem_b[2] - stem_a[2])
        end = start + d * (0.12 - 0.008 * i)
        parts.append(Part(f"branch_{i}", capsule(start, end, 0.0035), STEM))
        for j, s in enumerate((0.35, 0.6, 0.85)):
            side = 55.0 if j % 2 == 0 else -55.0
            ld = _rotate(d, up, side) - np.array([0.0, 0.0, 0.3])
            leaves.append((start + s * (end - start), _unit(ld)))
        leaves.append((end, _unit(d + np.array([0.0, 0.0, 0.1]))))
        leaves.append((end, _unit(_rotate(d, up, 35.0) - np.array([0.0, 0.0, 0.2]))))
    for i in range(5):
        az = math.radians(72.0 * i + 10.0)
        leaves.append((stem_b, _unit([math.cos(az), math.sin(az), 1.2])))
    for i, (at, d) in enumerate(leaves):
        a = rng.uniform(0.03, 0.04)
        normal = _rotate(_unit(up - up.dot(d) * d), d, rng.uniform(-25.0, 25.0))
        tint = np.clip(np.array(GREEN) + rng.uniform(-0.05, 0.05, 3), 0.0, 1.0)
        parts.append(Part(f"leaf_{i}", ellipsoid(at + d * 0.9 * a, [a, 0.42 * a, 0.0015], rot=frame(normal, d)),
                          tuple(tint)))
    return Instance("ficus", parts)


def basket() -> Instance:
    """An open-topped wicker basket: thick cylindrical shell with a rounded rim."""
    return Instance("basket", [
        Part("shell", cup([0, 0, 0], outer=0.12, inner=0.104, height=0.13, floor=0.016), WICKER),
        Part("rim", torus([0, 0, 0.128], 0.112, 0.0095), WICKER_RIM),
    ])


def mat() -> Instance:
    """A flat wide foam mat lying on z = 0, 5 cm thick.  (It was 1.2 cm: 0.4 grid cells at the
    default grid 32, which MPM cannot resolve; squeezed between the basket and the ground it was
    crushed to J 0.05 and blew up, particles at 6 m/s.  5 cm is 1.6 cells.)"""
    return Instance("mat", [Part("mat", rounded_box([0, 0, 0.025], [0.25, 0.18, 0.025], 0.008), MAT)])


def ball() -> Instance:
    """A steel ball, 0.12 m across."""
    return Instance("ball", [Part("ball", sphere([0.0, 0.0, 0.06], 0.06), STEEL)])


def jelly_block() -> Instance:
    """A wide jelly slab, 0.5 x 0.36 x 0.16 m, resting on z = 0."""
    return Instance("jelly", [Part("block", rounded_box([0.0, 0.0, 0.08], [0.25, 0.18, 0.08], 0.015), JELLY_RED)])


def bread() -> Instance:
    """An elongated loaf along x: rounded box base, domed top, three lighter score marks."""
    dome_c, dome_r = np.array([0.0, 0.0, 0.05]), np.array([0.134, 0.06, 0.048])
    parts = [
        Part("base", rounded_box([0.0, 0.0, 0.03], [0.14, 0.065, 0.03], 0.024), CRUST_LIGHT),
        Part("dome", ellipsoid(dome_c, dome_r), CRUST),
    ]
    for i, x in enumerate((-0.06, 0.0, 0.06)):
        top = dome_c + np.array([x, 0.0, dome_r[2] * math.sqrt(1.0 - (x / dome_r[0]) ** 2)])
        normal = _unit((top - dome_c) / dome_r**2)
        parts.append(Part(f"score_{i}", ellipsoid(top - 0.0015 * normal, [0.034, 0.006, 0.0028],
                                                  rot=frame(normal, [math.cos(0.5), math.sin(0.5), 0.0])), SCORE))
    return Instance("bread", parts)


# ---------------------------------------------------------------------------- layout
def place_apart(a: Instance, b: Instance, axis: int, fraction: float = GAP_FRACTION) -> Instance:
    """``b`` shifted along +axis so that the air between a's and b's boxes is ``fraction`` of
    the largest side of the joint box."""
    alo, ahi = a.aabb()
    blo, bhi = b.aabb()
    e = np.eye(3)[axis]
    gap = 0.0
    for _ in range(60):  # fixed point: the gap changes the joint box
        shift = ahi[axis] + gap - blo[axis]
        side = np.maximum(ahi, bhi + shift * e) - np.minimum(alo, blo + shift * e)
        gap = fraction * float(side.max())
    return b.shifted((ahi[axis] + gap - blo[axis]) * e)


def settle(instances: list[Instance]) -> tuple[list[Instance], np.ndarray]:
    """Shift everything so the joint box is centred on x = y = 0 with its bottom at z = 0.
    Returns (shifted instances, [3] shift)."""
    boxes = [i.aabb() for i in instances]
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    d = np.array([-(lo[0] + hi[0]) / 2.0, -(lo[1] + hi[1]) / 2.0, -lo[2]])
    return [i.shifted(d) for i in instances], d


def gap_region(a: Instance, b: Instance, axis: int, lo_all: np.ndarray, hi_all: np.ndarray) -> BoxRegion:
    """The slab of air between a's box and b's box (b above a along ``axis``), spanning the
    scene box along the other axes, 2% of its width away from either box."""
    lo, hi = lo_all.copy(), hi_all.copy()
    lo[axis] = a.aabb()[1][axis]
    hi[axis] = b.aabb()[0][axis]
    margin = 0.02 * (hi[axis] - lo[axis])  # float32 gaussian means may round past a flat face
    lo[axis] += margin
    hi[axis] -= margin
    return BoxRegion(lo, hi)


# ---------------------------------------------------------------------------- scenes
def _two(a: Instance, b: Instance, axis: int, order: tuple[int, int]) -> tuple[list, dict]:
    """Lay out two instances apart along ``axis``; ``order`` gives their label order."""
    b = place_apart(a, b, axis)
    (a, b), _ = settle([a, b])
    boxes = [a.aabb(), b.aabb()]
    lo = np.min([x[0] for x in boxes], axis=0)
    hi = np.max([x[1] for x in boxes], axis=0)
    pair = (a, b)
    return [pair[order[0]], pair[order[1]]], {"gap": gap_region(a, b, axis, lo, hi)}


def build(name: str) -> GroundTruth:
    """The GroundTruth of built-in scene ``name`` (one of BUILTIN_SCENES)."""
    if name == "bear":
        (b,), _ = settle([bear()])
        return GroundTruth(name, [b], {}, {"belly_center": _part(b, "belly").solid.center,
                                           "head_center": _part(b, "head").solid.center})
    if name == "bear_can":
        insts, regions = _two(bear(), can(), axis=0, order=(0, 1))
        return GroundTruth(name, insts, regions, {"belly_center": _part(insts[0], "belly").solid.center,
                                                  "can_center": _part(insts[1], "body").solid.center})
    if name == "duck_stone":
        insts, regions = _two(stone(), duck(), axis=2, order=(1, 0))
        return GroundTruth(name, insts, regions, {"duck_center": _part(insts[0], "body").solid.center,
                                                  "stone_center": _part(insts[1], "stone").solid.center})
    if name == "ficus":
        (f,), _ = settle([ficus()])
        soil = _part(f, "soil").solid
        return GroundTruth(name, [f], {}, {"pot_center": soil.center, "stem_point": _part(f, "stem").solid.center})
    if name == "basket_mat":
        insts, regions = _two(mat(), basket(), axis=2, order=(1, 0))
        shell = _part(insts[0], "shell").solid
        regions["basket_hollow"] = CavityRegion(shell, margin=0.004)
        hollow = shell.to_world(np.array([[0.0, 0.0, (shell.floor + shell.height) / 2.0]]))[0]
        wall = shell.to_world(np.array([[(shell.inner + shell.outer) / 2.0, 0.0, shell.height / 2.0]]))[0]
        return GroundTruth(name, insts, regions, {"hollow_center": hollow, "basket_wall": wall,
                                                  "mat_center": _part(insts[1], "mat").solid.center})
    if name == "ball_jelly":
        insts, regions = _two(jelly_block(), ball(), axis=2, order=(1, 0))
        return GroundTruth(name, insts, regions, {"ball_center": _part(insts[0], "ball").solid.center,
                                                  "block_center": _part(insts[1], "block").solid.center})
    if name == "bread":
        (b,), _ = settle([bread()])
        return GroundTruth(name, [b], {}, {"center": _part(b, "base").solid.center})
    raise KeyError(name)
