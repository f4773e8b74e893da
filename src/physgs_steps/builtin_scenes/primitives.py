"""Solid primitives with signed distances, inside tests and area-uniform surface samplers.

Every primitive lives in its own local frame: a world point ``p`` has local coordinates
``q = R^T (p - center)`` (``R`` [3, 3] maps local axes to world axes, its columns are the
local axes).  Methods take and return world-frame arrays in float64.

Common interface:
    sdf(p)            # [M, 3] -> [M] signed distance, negative inside (exact, or a
                      #   conservative bound: same sign, |value| <= true distance)
    inside(p)         # [M, 3] -> [M] bool, strictly inside the solid
    area()            # surface area in m^2
    sample(m, rng)    # -> ([m, 3] points on the surface, [m, 3] outward unit normals),
                      #   uniform with respect to surface area
    aabb()            # ([3], [3]) exact axis-aligned bounds of the solid
    shifted(d)        # the same primitive translated by d [3]
    feature           # a length below which gaussians would blur the shape (thin radius)
"""
from __future__ import annotations

import abc
import dataclasses
import math

import numpy as np
import trimesh
from scipy.special import elliprg

TWO_PI = 2.0 * math.pi


# ---------------------------------------------------------------------------- helpers
def unit_vectors(m: int, rng: np.random.Generator) -> np.ndarray:
    """[m, 3] directions uniform on the unit sphere."""
    v = rng.normal(size=(m, 3))
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    norm[norm == 0.0] = 1.0
    return v / norm


def normalize(v: np.ndarray) -> np.ndarray:
    """[M, 3] -> [M, 3] unit vectors (zero vectors stay zero)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(n > 0.0, n, 1.0)


def rejection(m: int, rng: np.random.Generator, propose, weight, wmax: float) -> np.ndarray:
    """Draw ``m`` samples with density proportional to ``weight`` (<= ``wmax``).

    ``propose(k)`` returns [k, D] candidates from the base density, ``weight(x)`` [k] >= 0.
    Returns [m, D].
    """
    out = []
    got = 0
    rate = 0.5
    while got < m:
        k = int((m - got) / rate * 1.1) + 16
        cand = propose(k)
        w = weight(cand)
        keep = rng.random(k) * wmax < w
        rate = max(keep.mean(), 1e-3)
        out.append(cand[keep])
        got += int(keep.sum())
    return np.concatenate(out)[:m]


def frame(z_axis, x_hint=(1.0, 0.0, 0.0)) -> np.ndarray:
    """[3, 3] rotation whose third column is ``z_axis`` and first column is ``x_hint``
    made orthogonal to it (columns = local axes in world coordinates)."""
    z = np.asarray(z_axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.asarray(x_hint, dtype=np.float64)
    x = x - x.dot(z) * z
    if np.linalg.norm(x) < 1e-9:
        alt = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = alt - alt.dot(z) * z
    x = x / np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _support_box(r: np.ndarray, half: np.ndarray) -> np.ndarray:
    """[3] half extents along the world axes of a box with rotation r [3, 3], half sizes [3]."""
    return np.abs(r) @ half


def _support_disc(r: np.ndarray, radius: float) -> np.ndarray:
    """[3] world half extents of a disc of ``radius`` in the local xy plane of r [3, 3]."""
    z = r[:, 2]
    return radius * np.sqrt(np.clip(1.0 - z * z, 0.0, None))


@dataclasses.dataclass
class Primitive(abc.ABC):
    """Base: a solid with a local frame (``center`` [3], ``rot`` [3, 3])."""

    center: np.ndarray
    rot: np.ndarray

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(3)
        self.rot = np.asarray(self.rot, dtype=np.float64).reshape(3, 3)

    # frame maps
    def to_local(self, p: np.ndarray) -> np.ndarray:
        """[M, 3] world -> [M, 3] local."""
        return (np.asarray(p, dtype=np.float64) - self.center) @ self.rot

    def to_world(self, q: np.ndarray) -> np.ndarray:
        """[M, 3] local -> [M, 3] world."""
        return q @ self.rot.T + self.center

    def dir_to_world(self, v: np.ndarray) -> np.ndarray:
        """[M, 3] local directions -> [M, 3] world directions."""
        return v @ self.rot.T

    # interface
    def sdf(self, p: np.ndarray) -> np.ndarray:
        return self.local_sdf(self.to_local(p))

    def inside(self, p: np.ndarray) -> np.ndarray:
        return self.sdf(p) < 0.0

    def sample(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        if m <= 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        q, n = self.local_sample(m, rng)
        return self.to_world(q), normalize(self.dir_to_world(n))

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        h = self.world_half_extent()
        return self.center - h, self.center + h

    def shifted(self, d) -> "Primitive":
        return dataclasses.replace(self, center=self.center + np.asarray(d, dtype=np.float64))

    # defined by each shape
    @abc.abstractmethod
    def local_sdf(self, q: np.ndarray) -> np.ndarray:
        """[M, 3] local points -> [M] signed distance."""

    @abc.abstractmethod
    def local_sample(self, m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """-> ([m, 3] local surface points, [m, 3] local outward normals), area-uniform."""

    @abc.abstractmethod
    def world_half_extent(self) -> np.ndarray:
        """[3] half sizes along the world axes of a box around ``center`` holding the solid."""

    @abc.abstractmethod
    def area(self) -> float:
        """Surface area in m^2."""

    @property
    def feature(self) -> float:
        return math.inf


# ---------------------------------------------------------------------------- sphere
@dataclasses.dataclass
class Sphere(Primitive):
    radius: float = 1.0

    def local_sdf(self, q):
        return np.linalg.norm(q, axis=1) - self.radius

    def local_sample(self, m, rng):
        d = unit_vectors(m, rng)
        return d * self.radius, d

    def world_half_extent(self):
        return np.full(3, self.radius)

    def area(self):
        return 4.0 * math.pi * self.radius**2

    @property
    def feature(self):
        return self.radius


def sphere(center, radius: float) -> Sphere:
    return Sphere(center=center, rot=np.eye(3), radius=float(radius))


# ---------------------------------------------------------------------------- ellipsoid
def ellipsoid_distance(q: np.ndarray, radii: np.ndarray, iterations: int = 60) -> np.ndarray:
    """Exact signed distance of local points q [M, 3] to the ellipsoid with semi-axes radii [3].

    The closest surface point is x_i = e_i^2 y_i / (t + e_i^2) with t the root of
    F(t) = sum_i (e_i y_i / (t + e_i^2))^2 - 1 on (-e_min^2, inf) (axes sorted so that
    e_0 >= e_1 >= e_2, y = |q|); the root is bracketed by [-e_2^2 + e_2 y_2, -e_2^2 + |e y|]
    and found by bisection (60 halvings reach float64 resolution).  Points whose
    smallest-axis coordinate vanishes (the degenerate case) take x_2 from the surface equation.
    """
    order = np.argsort(-np.asarray(radii, dtype=np.float64))
    e = np.asarray(radii, dtype=np.float64)[order]
    y = np.abs(np.asarray(q, dtype=np.float64)[:, order])
    e2 = e * e
    ey2 = [(e[i] * y[:, i]) ** 2 for i in range(3)]
    lo = -e2[2] + e[2] * y[:, 2]
    hi = -e2[2] + np.sqrt(ey2[0] + ey2[1] + ey2[2])
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        for _ in range(iterations):
            t = 0.5 * (lo + hi)
            f = sum(ey2[i] / np.maximum(t + e2[i], 1e-300) ** 2 for i in range(3))
            above = f > 1.0  # root lies to the right of t
            lo = np.where(above, t, lo)
            hi = np.where(above, hi, t)
    t = 0.5 * (lo + hi)
    den = t[:, None] + e2
    ok = (y > 0.0) & (den > 1e-9 * e2)
    x = np.where(ok, e2 * y / np.where(ok, den, 1.0), 0.0)
    rest = np.clip(1.0 - (x[:, 0] / e[0]) ** 2 - (x[:, 1] / e[1]) ** 2, 0.0, None)
    degenerate = den[:, 2] <= 1e-6 * e2[2]
    x[:, 2] = np.where(degenerate, e[2] * np.sqrt(rest), np.minimum(x[:, 2], e[2]))
    dist = np.linalg.norm(x - y, axis=1)
    inside = np.sum((y / e) ** 2, axis=1) < 1.0
    return np.where(inside, -dist, dist)


@dataclasses.dataclass
class Ellipsoid(Primitive):
    radii: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(3))

    def __post_init__(self):
        super().__post_init__()
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(3)

    def local_sdf(self, q):
        return ellipsoid_distance(q, self.radii)

    def inside(self, p):
        return np.sum((self.to_local(p) / self.radii) ** 2, axis=1) < 1.0

    def local_sample(self, m, rng):
        a, b, c = self.radii
        g = np.array([b * c, a * c, a * b])

        def weight(u):  # area element of the map u -> radii * u
            return np.linalg.norm(u * g, axis=1)

        u = rejection(m, rng, lambda k: unit_vectors(k, rng), weight, float(g.max()))
        return u * self.radii, normalize(u / self.radii)

    def world_half_extent(self):
        return np.sqrt((self.rot**2) @ (self.radii**2))

    def area(self):
        a, b, c = self.radii
        return float(4.0 * math.pi * a * b * c * elliprg(1.0 / a**2, 1.0 / b**2, 1.0 / c**2))

    @property
    def feature(self):
        return float(np.sort(self.radii)[1])


def ellipsoid(center, radii, rot=None) -> Ellipsoid:
    return Ellipsoid(center=center, rot=np.eye(3) if rot is None else rot, radii=radii)


# ---------------------------------------------------------------------------- capsule
@dataclasses.dataclass
class Capsule(Primitive):
    """Segment along the local z axis from -half_length to +half_length, swept by a ball."""

    half_length: float = 0.5
    radius: float = 0.1

    def local_sdf(self, q):
        z = np.clip(q[:, 2], -self.half_length, self.half_length)
        return np.linalg.norm(q - np.stack([0 * z, 0 * z, z], axis=1), axis=1) - self.radius

    def local_sample(self, m, rng):
        r, h = self.radius, self.half_length
        a_cyl = TWO_PI * r * 2.0 * h
        on_cyl = rng.random(m) * (a_cyl + 4.0 * math.pi * r * r) < a_cyl
        k = int(on_cyl.sum())
        q = np.empty((m, 3))
        n = np.empty((m, 3))
        th = rng.random(k) * TWO_PI
        n[on_cyl] = np.stack([np.cos(th), np.sin(th), np.zeros(k)], axis=1)
        q[on_cyl] = n[on_cyl] * r
        q[on_cyl, 2] = rng.uniform(-h, h, k)
        d = unit_vectors(m - k, rng)
        n[~on_cyl] = d
        q[~on_cyl] = d * r + np.where(d[:, 2:] > 0, 1.0, -1.0) * np.array([0.0, 0.0, h])
        return q, n

    def world_half_extent(self):
        return np.abs(self.rot[:, 2]) * self.half_length + self.radius

    def area(self):
        return TWO_PI * self.radius * 2.0 * self.half_length + 4.0 * math.pi * self.radius**2

    @property
    def feature(self):
        return self.radius


def capsule(a, b, radius: float) -> Capsule:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return Capsule(center=0.5 * (a + b), rot=frame(b - a), half_length=0.5 * float(np.linalg.norm(b - a)),
                   radius=float(radius))


# ---------------------------------------------------------------------------- rounded box
@dataclasses.dataclass
class RoundedBox(Primitive):
    """Box of outer half sizes ``half`` [3] whose edges and corners are rounded by ``rounding``."""

    half: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(3))
    rounding: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        self.half = np.asarray(self.half, dtype=np.float64).reshape(3)
        if not 0.0 <= self.rounding <= self.half.min():
            raise ValueError("RoundedBox.rounding must lie in [0, min(half)]")

    @property
    def core(self) -> np.ndarray:
        return self.half - self.rounding

    def local_sdf(self, q):
        d = np.abs(q) - self.core
        return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0) - self.rounding

    def _areas(self) -> np.ndarray:
        h, r = self.core, self.rounding
        faces = [8.0 * h[(i + 1) % 3] * h[(i + 2) % 3] for i in range(3)]
        edges = [4.0 * math.pi * r * h[k] for k in range(3)]
        return np.array(faces + edges + [4.0 * math.pi * r * r])

    def area(self):
        return float(self._areas().sum())

    def local_sample(self, m, rng):
        h, r = self.core, self.rounding
        a = self._areas()
        comp = rng.choice(7, size=m, p=a / a.sum())
        q = np.empty((m, 3))
        n = np.zeros((m, 3))
        for i in range(3):  # faces normal to axis i
            sel = comp == i
            k = int(sel.sum())
            s = np.where(rng.random(k) < 0.5, -1.0, 1.0)
            pts = rng.uniform(-1.0, 1.0, (k, 3)) * h
            pts[:, i] = s * (h[i] + r)
            q[sel] = pts
            nn = np.zeros((k, 3))
            nn[:, i] = s
            n[sel] = nn
        for ax in range(3):  # rounded edges parallel to axis ax
            sel = comp == 3 + ax
            k = int(sel.sum())
            i, j = (ax + 1) % 3, (ax + 2) % 3
            th = rng.random(k) * TWO_PI
            d = np.zeros((k, 3))
            d[:, i] = np.cos(th)
            d[:, j] = np.sin(th)
            pts = np.sign(d) * h + r * d
            pts[:, ax] = rng.uniform(-h[ax], h[ax], k)
            q[sel] = pts
            n[sel] = d
        sel = comp == 6  # corners
        d = unit_vectors(int(sel.sum()), rng)
        q[sel] = np.sign(d) * h + r * d
        n[sel] = d
        return q, n

    def world_half_extent(self):
        return _support_box(self.rot, self.core) + self.rounding

    @property
    def feature(self):
        return max(float(np.sort(self.half)[1]), self.rounding)


def rounded_box(center, half, rounding: float, rot=None) -> RoundedBox:
    return RoundedBox(center=center, rot=np.eye(3) if rot is None else rot, half=half, rounding=float(rounding))


# ---------------------------------------------------------------------------- cylinder
@dataclasses.dataclass
class Cylinder(Primitive):
    """Capped cylinder along local z (radius, half_height), edges rounded by ``rounding``."""

    radius: float = 1.0
    half_height: float = 1.0
    rounding: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.rounding <= min(self.radius, self.half_height):
            raise ValueError("Cylinder.rounding must lie in [0, min(radius, half_height)]")

    def local_sdf(self, q):
        rc, hc = self.radius - self.rounding, self.half_height - self.rounding
        d = np.stack([np.linalg.norm(q[:, :2], axis=1) - rc, np.abs(q[:, 2]) - hc], axis=1)
        return np.minimum(d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=1) - self.rounding

    def _areas(self) -> np.ndarray:
        rc, hc, r = self.radius - self.rounding, self.half_height - self.rounding, self.rounding
        return np.array([
            TWO_PI * self.radius * 2.0 * hc,               # side
            2.0 * math.pi * rc * rc,                       # two flat caps
            2.0 * TWO_PI * r * (rc * math.pi / 2.0 + r),   # two rounded rims
        ])

    def area(self):
        return float(self._areas().sum())

    def local_sample(self, m, rng):
        rc, hc, r = self.radius - self.rounding, self.half_height - self.rounding, self.rounding
        a = self._areas()
        comp = rng.choice(3, size=m, p=a / a.sum())
        th = rng.random(m) * TWO_PI
        s = np.where(rng.random(m) < 0.5, -1.0, 1.0)
        rho = np.full(m, self.radius)
        z = rng.uniform(-hc, hc, m)
        nr = np.ones(m)  # radial and axial parts of the normal
        nz = np.zeros(m)
        cap = comp == 1
        rho[cap] = rc * np.sqrt(rng.random(int(cap.sum())))
        z[cap] = s[cap] * self.half_height
        nr[cap], nz[cap] = 0.0, s[cap]
        rim = comp == 2
        k = int(rim.sum())
        if k:
            phi = rejection(k, rng, lambda kk: rng.random((kk, 1)) * (math.pi / 2.0),
                            lambda ph: rc + r * np.cos(ph[:, 0]), rc + r)[:, 0]
            rho[rim] = rc + r * np.cos(phi)
            z[rim] = s[rim] * (hc + r * np.sin(phi))
            nr[rim], nz[rim] = np.cos(phi), s[rim] * np.sin(phi)
        c, sn = np.cos(th), np.sin(th)
        q = np.stack([rho * c, rho * sn, z], axis=1)
        n = np.stack([nr * c, nr * sn, nz], axis=1)
        return q, n

    def world_half_extent(self):
        rc, hc = self.radius - self.rounding, self.half_height - self.rounding
        return _support_disc(self.rot, rc) + np.abs(self.rot[:, 2]) * hc + self.rounding

    @property
    def feature(self):
        return self.radius


def cylinder(bottom_center, radius: float, height: float, rounding: float = 0.0, rot=None) -> Cylinder:
    """An upright (local z) cylinder whose bottom face centre is ``bottom_center``."""
    r = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)
    c = np.asarray(bottom_center, dtype=np.float64) + r[:, 2] * height / 2.0
    return Cylinder(center=c, rot=r, radius=float(radius), half_height=height / 2.0, rounding=float(rounding))


# ---------------------------------------------------------------------------- torus
@dataclasses.dataclass
class Torus(Primitive):
    """Ring in the local xy plane: major radius (centre of the tube), minor radius (tube)."""

    major: float = 1.0
    minor: float = 0.25

    def local_sdf(self, q):
        rr = np.linalg.norm(q[:, :2], axis=1) - self.major
        return np.hypot(rr, q[:, 2]) - self.minor

    def local_sample(self, m, rng):
        big, small = self.major, self.minor
        phi = rejection(m, rng, lambda k: rng.random((k, 1)) * TWO_PI,
                        lambda ph: big + small * np.cos(ph[:, 0]), big + small)[:, 0]
        th = rng.random(m) * TWO_PI
        n = np.stack([np.cos(phi) * np.cos(th), np.cos(phi) * np.sin(th), np.sin(phi)], axis=1)
        q = np.stack([big * np.cos(th), big * np.sin(th), np.zeros(m)], axis=1) + small * n
        return q, n

    def world_half_extent(self):
        return _support_disc(self.rot, self.major) + self.minor

    def area(self):
        return 4.0 * math.pi**2 * self.major * self.minor

    @property
    def feature(self):
        return self.minor


def torus(center, major: float, minor: float, rot=None) -> Torus:
    return Torus(center=center, rot=np.eye(3) if rot is None else rot, major=float(major), minor=float(minor))


# ---------------------------------------------------------------------------- cup shell
@dataclasses.dataclass
class Cup(Primitive):
    """Open-topped thick-walled cylinder: local z from 0 (underside) to ``height`` (rim);
    wall between ``inner`` and ``outer`` radius, solid floor of thickness ``floor``.

    sdf = max(sdf_outer_cylinder, -sdf_cavity) with the cavity extending above the rim:
    exact inside, a conservative bound outside.
    """

    outer: float = 1.0
    inner: float = 0.9
    height: float = 1.0
    floor: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        if not (0.0 < self.inner < self.outer and 0.0 < self.floor < self.height):
            raise ValueError("Cup needs 0 < inner < outer and 0 < floor < height")

    def local_sdf(self, q):
        rho = np.linalg.norm(q[:, :2], axis=1)
        out_d = np.stack([rho - self.outer, np.abs(q[:, 2] - self.height / 2.0) - self.height / 2.0], axis=1)
        sd_out = np.minimum(out_d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(out_d, 0.0), axis=1)
        top = 2.0 * self.height
        cav_d = np.stack([rho - self.inner, np.abs(q[:, 2] - (self.floor + top) / 2.0) - (top - self.floor) / 2.0],
                         axis=1)
        sd_cav = np.minimum(cav_d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(cav_d, 0.0), axis=1)
        return np.maximum(sd_out, -sd_cav)

    def _areas(self) -> np.ndarray:
        ro, ri, h, f = self.outer, self.inner, self.height, self.floor
        return np.array([
            TWO_PI * ro * h,                   # outer wall
            math.pi * ro * ro,                 # underside
            math.pi * (ro * ro - ri * ri),     # rim
            TWO_PI * ri * (h - f),             # inner wall
            math.pi * ri * ri,                 # floor of the cavity
        ])

    def area(self):
        return float(self._areas().sum())

    def local_sample(self, m, rng):
        ro, ri, h, f = self.outer, self.inner, self.height, self.floor
        a = self._areas()
        comp = rng.choice(5, size=m, p=a / a.sum())
        th = rng.random(m) * TWO_PI
        u = rng.random(m)
        rho = np.select([comp == 0, comp == 1, comp == 2, comp == 3],
                        [np.full(m, ro), ro * np.sqrt(u), np.sqrt(ri * ri + u * (ro * ro - ri * ri)), np.full(m, ri)],
                        ri * np.sqrt(u))
        z = np.select([comp == 0, comp == 1, comp == 2, comp == 3],
                      [u * h, np.zeros(m), np.full(m, h), f + u * (h - f)], np.full(m, f))
        nr = np.select([comp == 0, comp == 3], [np.ones(m), -np.ones(m)], 0.0)
        nz = np.select([comp == 1, comp == 2, comp == 4], [-np.ones(m), np.ones(m), np.ones(m)], 0.0)
        c, s = np.cos(th), np.sin(th)
        return np.stack([rho * c, rho * s, z], axis=1), np.stack([nr * c, nr * s, nz], axis=1)

    def aabb(self):
        lo, hi = Primitive.aabb(self)
        mid = self.rot[:, 2] * self.height / 2.0
        return lo + mid, hi + mid

    def world_half_extent(self):
        return _support_disc(self.rot, self.outer) + np.abs(self.rot[:, 2]) * self.height / 2.0

    def cavity_contains(self, p: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """[M, 3] -> [M] bool: inside the open cavity (shrunk by ``margin``), below the rim."""
        q = self.to_local(p)
        rho = np.linalg.norm(q[:, :2], axis=1)
        return (rho < self.inner - margin) & (q[:, 2] > self.floor + margin) & (q[:, 2] < self.height)

    @property
    def feature(self):
        return self.outer - self.inner


def cup(bottom_center, outer: float, inner: float, height: float, floor: float) -> Cup:
    return Cup(center=bottom_center, rot=np.eye(3), outer=float(outer), inner=float(inner),
               height=float(height), floor=float(floor))


# ---------------------------------------------------------------------------- stone
@dataclasses.dataclass
class Blob(Primitive):
    """A star-shaped, smoothly deformed ellipsoid: in q' = q / radii the surface is
    |q'| = 1 + n(q'/|q'|) with n(u) = sum_k amp_k cos(freq_k . u + phase_k).

    sdf is h(p) / L with h = |q'| / (1 + n) - 1 and L an upper bound of |grad_p h|:
    a conservative bound of the distance.
    """

    radii: np.ndarray = dataclasses.field(default_factory=lambda: np.ones(3))
    amps: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(1))    # [K]
    freqs: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((1, 3)))  # [K, 3]
    phases: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(1))  # [K]
    subdivisions: int = 5

    def __post_init__(self):
        super().__post_init__()
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(3)
        self.amps = np.asarray(self.amps, dtype=np.float64).reshape(-1)
        self.freqs = np.asarray(self.freqs, dtype=np.float64).reshape(-1, 3)
        self.phases = np.asarray(self.phases, dtype=np.float64).reshape(-1)
        total = float(np.abs(self.amps).sum())
        if total >= 0.5:
            raise ValueError("Blob amplitudes must sum to less than 0.5 (star-shaped surface)")
        grad = float((np.abs(self.amps) * np.linalg.norm(self.freqs, axis=1)).sum())
        lo = 1.0 - total
        self._lipschitz = math.sqrt(1.0 / lo**2 + grad**2 / lo**4) / float(self.radii.min())
        self._mesh = None

    def noise(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u [M, 3] unit directions -> (n [M], grad n [M, 3] in R^3)."""
        arg = u @ self.freqs.T + self.phases
        return np.cos(arg) @ self.amps, -(np.sin(arg) * self.amps) @ self.freqs

    def local_implicit(self, q: np.ndarray) -> np.ndarray:
        """[M, 3] local points -> [M] h = |q'| / (1 + n(q'/|q'|)) - 1 with q' = q / radii."""
        qs = q / self.radii
        r = np.linalg.norm(qs, axis=1)
        u = qs / np.where(r > 0, r, 1.0)[:, None]
        n, _ = self.noise(u)
        return r / (1.0 + n) - 1.0

    def local_sdf(self, q):
        return self.local_implicit(q) / self._lipschitz

    def inside(self, p):
        return self.local_implicit(self.to_local(p)) < 0.0

    def surface_point(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u [M, 3] unit directions in scaled space -> (local points [M, 3], local normals [M, 3])."""
        n, gn = self.noise(u)
        rho = 1.0 + n
        tang = gn - np.sum(gn * u, axis=1, keepdims=True) * u
        grad_q = u / rho[:, None] - tang / (rho**2)[:, None]  # grad of h w.r.t. q' at the surface
        return u * rho[:, None] * self.radii, normalize(grad_q / self.radii)

    def mesh(self) -> trimesh.Trimesh:
        """A triangle mesh of the surface (icosphere mapped through the deformation)."""
        if self._mesh is None:
            ico = trimesh.creation.icosphere(subdivisions=self.subdivisions)
            u = normalize(np.asarray(ico.vertices, dtype=np.float64))
            pts, _ = self.surface_point(u)
            self._mesh = trimesh.Trimesh(vertices=pts, faces=ico.faces, process=False)
        return self._mesh

    def area(self):
        return float(self.mesh().area)

    def local_sample(self, m, rng):
        pts, _ = trimesh.sample.sample_surface(self.mesh(), m, seed=int(rng.integers(2**31)))
        u = normalize(np.asarray(pts, dtype=np.float64) / self.radii)
        return self.surface_point(u)

    def aabb(self):
        v = self.to_world(np.asarray(self.mesh().vertices))
        pad = 0.005 * float(self.radii.max())  # the mesh vertices lie on the surface; cover the facets' sag
        return v.min(axis=0) - pad, v.max(axis=0) + pad

    def world_half_extent(self):
        lo, hi = self.aabb()
        return np.maximum(self.center - lo, hi - self.center)

    @property
    def feature(self):
        return float(np.sort(self.radii)[1])


def blob(center, radii, amps, freqs, phases, rot=None) -> Blob:
    return Blob(center=center, rot=np.eye(3) if rot is None else rot, radii=radii, amps=amps, freqs=freqs,
                phases=phases)
