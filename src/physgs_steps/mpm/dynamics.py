"""Scene dynamics: gravity, domain walls, ground and plane colliders, fixed or moving cuboids,
impulses, wind, enforced translation and rotation, initial velocities.  Where each boundary
sits and how it acts on the grid and the particles: :mod:`physgs_steps.mpm.colliders`.

The scene-file key ``dynamics`` (schema ``workflow/schemas/scene_dynamics.schema.yaml``, which
documents every key and its units) is parsed by :meth:`Dynamics.from_config`.  At set-up the
solver calls :meth:`Dynamics.bind` with the initial particle positions, which resolves
instance-relative boxes, selects the particles of each particle action and packs everything
into one parameter table for the kernels:

* grid actions (in the grid update, after gravity and damping, before the domain walls):
  ``surface_collider`` rows then ``cuboid`` rows;
* particle actions (on a particle's velocity just before its P2G transfer, PhysGaussian's
  "pre-P2G velocity modifiers"): acceleration rows (``particle_impulse`` and ``wind``), then
  ``enforce_particle_translation`` rows, then ``enforce_particle_velocity_rotation`` rows.
  Particle ``p`` takes part in action ``a`` when bit ``a`` of ``act_bits[p]`` is set (at most
  31 particle actions).

Table rows (``TABLE_WIDTH`` floats, SI units: metres, m/s, s):

=====================  ==================================================================
surface collider       px py pz  nx ny nz  kind(0 sticky, 1 slip, 2 separate)  friction  t0 t1
cuboid                 cx cy cz  hx hy hz  vx vy vz  t0 t1
acceleration           mx my mz  ax ay az  frequency  phase  t0 t1   (a = m + a sin(2 pi f (t - t0) + phase))
translation            vx vy vz  t0 t1
rotation               cx cy cz  nx ny nz  omega  v_axial  t0 t1
=====================  ==================================================================
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..errors import ConfigError

TABLE_WIDTH = 12
NEVER = 1.0e30  # end time of entries that never stop
SURFACE_KIND = {"sticky": 0.0, "slip": 1.0, "separate": 2.0}
GRID_TYPES = ("surface_collider", "cuboid")
PARTICLE_TYPES = ("particle_impulse", "wind", "enforce_particle_translation", "enforce_particle_velocity_rotation")
MAX_PARTICLE_ACTIONS = 31


@dataclass
class Dynamics:
    """Validated scene dynamics (domain units for positions, SI for the rest)."""

    gravity: tuple = (0.0, 0.0, -9.8)
    boundary: str = "slip"
    wall_margin: float = 0.1
    ground: dict | None = None
    damping: float = 0.0
    initial_velocity: list = field(default_factory=list)
    boundary_conditions: list = field(default_factory=list)

    @classmethod
    def from_config(cls, cfg: dict | None, source: str = "scene") -> "Dynamics":
        """Parse the scene's ``dynamics`` mapping (defaults filled from the schema).

        Raises:
            ConfigError naming ``dynamics.<key>`` and the problem.
        """
        from .. import config as C

        d = C.validate(dict(cfg or {}), C.load_schema("scene_dynamics.schema.yaml"), source, "dynamics")
        out = cls(gravity=tuple(float(g) for g in d["gravity"]), boundary=d["boundary"],
                  wall_margin=float(d["wall_margin"]), ground=d["ground"],
                  damping=float(d["damping"]), initial_velocity=list(d["initial_velocity"]),
                  boundary_conditions=[e for e in d["boundary_conditions"] if e["type"] != "bounding_box"])
        out._check(source)
        return out

    @classmethod
    def free(cls, gravity=(0.0, 0.0, -9.8), boundary: str = "slip", wall_margin: float = 0.1) -> "Dynamics":
        """Gravity and domain walls only (the CONTRACTS.md step, as in the torch pseudo-step)."""
        return cls(gravity=tuple(float(g) for g in gravity), boundary=boundary, wall_margin=float(wall_margin))

    # ------------------------------------------------------------------ checks
    def _check(self, source: str) -> None:
        for i, e in enumerate(self.boundary_conditions):
            key = f"dynamics.boundary_conditions[{i}] ({e['type']})"
            need = {
                "surface_collider": ("point", "normal"),
                "cuboid": (),
                "particle_impulse": ("delta_v",),
                "wind": (),
                "enforce_particle_translation": ("velocity",),
                "enforce_particle_velocity_rotation": ("point", "normal", "half_height_and_radius", "rotation_scale"),
            }[e["type"]]
            missing = [k for k in need if k not in e]
            if missing:
                raise ConfigError(key, f"missing {', '.join(missing)}", source)
            if e["type"] == "cuboid" and "point" not in e and "instance" not in e:
                raise ConfigError(key, "needs a box: point + size, or instance (+ bbox_min/bbox_max)", source)
            if ("point" in e) != ("size" in e) and e["type"] not in ("surface_collider", "enforce_particle_velocity_rotation"):
                raise ConfigError(key, "point and size go together (box centre and half extents)", source)
            if ("bbox_min" in e or "bbox_max" in e) and "instance" not in e:
                raise ConfigError(key, "bbox_min/bbox_max are fractions of an instance's box: give `instance`", source)
            if "normal" in e and np.linalg.norm(e["normal"]) == 0:
                raise ConfigError(key + ".normal", "must not be the zero vector", source)
            if e.get("end_time") is not None and e["end_time"] <= e["start_time"]:
                raise ConfigError(key + ".end_time", "must be later than start_time", source)
        for i, e in enumerate(self.initial_velocity):
            key = f"dynamics.initial_velocity[{i}]"
            if ("velocity" in e) == ("toward" in e):
                raise ConfigError(key, "give either velocity or toward + speed", source)
            if "toward" in e and "speed" not in e:
                raise ConfigError(key, "toward needs speed (m/s)", source)
        n_part = sum(e["type"] in PARTICLE_TYPES for e in self.boundary_conditions)
        if n_part > MAX_PARTICLE_ACTIONS:
            raise ConfigError("dynamics.boundary_conditions", f"at most {MAX_PARTICLE_ACTIONS} particle actions, got {n_part}", source)

    # ------------------------------------------------------------------ binding
    def bind(self, x: np.ndarray, material: np.ndarray, names: Sequence[str], labels: Sequence[int] | None,
             domain_size: float) -> "BoundDynamics":
        """Resolve regions against the initial particles and pack the kernel table.

        Args:
            x: [P, 3] initial positions in domain units.
            material: [P] int, index into ``names`` (one entry per instance/material).
            names: instance names (for ``instance:`` references), one per material index.
            labels: instance labels (integer references), one per material index, or None.
            domain_size: metres per domain unit.
        """
        L = float(domain_size)
        resolver = _InstanceResolver(names, labels)
        surf, cub, acc, tra, rot = [], [], [], [], []
        masks: list[np.ndarray] = []
        if self.ground is not None:
            surf.append(_surface_row([0.5, 0.5, self.ground["height"]], [0, 0, 1], self.ground["surface"],
                                     self.ground["friction"], 0.0, None, L))
        part_entries = {t: [] for t in ("acc", "tra", "rot")}
        for i, e in enumerate(self.boundary_conditions):
            key = f"dynamics.boundary_conditions[{i}] ({e['type']})"
            t0, t1 = float(e["start_time"]), e.get("end_time")
            if e["type"] == "surface_collider":
                surf.append(_surface_row(e["point"], e["normal"], e.get("surface", "separate"),
                                         e.get("friction", 0.0), t0, t1, L))
            elif e["type"] == "cuboid":
                lo, hi = _box(e, x, material, resolver, key)
                v = e.get("velocity", [0.0, 0.0, 0.0])
                cub.append(_row([*((lo + hi) / 2 * L), *((hi - lo) / 2 * L), *v, t0, _end(t1)]))
            else:
                sel = _select(e, x, material, resolver, key)
                if e["type"] == "particle_impulse":
                    dur = float(e.get("duration", 0.02))
                    row = _row([*(np.asarray(e["delta_v"], float) / dur), 0, 0, 0, 0, 0, t0, t0 + dur])
                    part_entries["acc"].append((row, sel))
                elif e["type"] == "wind":
                    row = _row([*e.get("mean", [0, 0, 0]), *e.get("amplitude", [0, 0, 0]), e.get("frequency", 0.0),
                                e.get("phase", 0.0), t0, _end(t1)])
                    part_entries["acc"].append((row, sel))
                elif e["type"] == "enforce_particle_translation":
                    part_entries["tra"].append((_row([*e["velocity"], t0, _end(t1)]), sel))
                else:
                    n = _unit(e["normal"])
                    row = _row([*(np.asarray(e["point"], float) * L), *n, float(e["rotation_scale"]),
                                float(e.get("translation_scale", 0.0)), t0, _end(t1)])
                    part_entries["rot"].append((row, sel))
        for kind in ("acc", "tra", "rot"):
            for row, sel in part_entries[kind]:
                {"acc": acc, "tra": tra, "rot": rot}[kind].append(row)
                masks.append(sel)
        act_bits = np.zeros(len(x), dtype=np.int32)
        for bit, sel in enumerate(masks):
            act_bits[sel] |= np.int32(1 << bit)
        rows = surf + cub + acc + tra + rot
        table = np.stack(rows).astype(np.float32) if rows else np.zeros((1, TABLE_WIDTH), np.float32)
        return BoundDynamics(
            gravity=np.asarray(self.gravity, np.float32), boundary=self.boundary, damping=float(self.damping),
            wall_margin=float(self.wall_margin) * L,
            counts=(len(surf), len(cub), len(acc), len(tra), len(rot)), table=table, act_bits=act_bits,
            selected=[int(m.sum()) for m in masks],
        )

    def initial_velocities(self, x: np.ndarray, material: np.ndarray, base: np.ndarray, names: Sequence[str],
                           labels: Sequence[int] | None) -> np.ndarray:
        """[P, 3] initial velocities (m/s): ``base`` [K, 3] per material, then the overrides of
        ``initial_velocity`` in order.  ``x`` [P, 3] (domain units), ``material`` [P] int."""
        resolver = _InstanceResolver(names, labels)
        v = np.asarray(base, np.float64)[material].copy()
        for i, e in enumerate(self.initial_velocity):
            key = f"dynamics.initial_velocity[{i}]"
            sel = np.ones(len(x), bool) if "instance" not in e else material == resolver(e["instance"], key)
            if "velocity" in e:
                v[sel] = np.asarray(e["velocity"], float)
            else:
                tgt = material == resolver(e["toward"], key + ".toward")
                if not sel.any() or not tgt.any():
                    raise ConfigError(key, "instance or target has no particles")
                d = x[tgt].mean(0) - x[sel].mean(0)
                if np.linalg.norm(d) == 0:
                    raise ConfigError(key, "instance and target have the same centre; give velocity instead")
                v[sel] = float(e["speed"]) * _unit(d)
        return v


@dataclass
class BoundDynamics:
    """Dynamics resolved against one particle set (see the module docstring for the table)."""

    gravity: np.ndarray          # [3] m/s^2
    boundary: str                # slip | sticky
    damping: float               # 1/s
    wall_margin: float           # m: distance of the domain walls from the domain faces
    counts: tuple                # (surface, cuboid, acceleration, translation, rotation) rows
    table: np.ndarray            # [rows, TABLE_WIDTH] f32
    act_bits: np.ndarray         # [P] int32 particle action bits
    selected: list               # particles selected per particle action

    def spec(self) -> tuple:
        """The compile-time part (what the kernel is specialised to): boundary, damping, counts."""
        return (self.boundary, self.damping > 0.0, self.counts)


# ============================================================================ helpers
class _InstanceResolver:
    def __init__(self, names: Sequence[str], labels: Sequence[int] | None):
        self.names = list(names)
        self.labels = list(labels) if labels is not None else list(range(len(names)))

    def __call__(self, ref: Any, key: str) -> int:
        if isinstance(ref, bool):
            ref = str(ref)
        if isinstance(ref, int):
            if ref in self.labels:
                return self.labels.index(ref)
        elif ref in self.names:
            return self.names.index(ref)
        known = ", ".join(f"{n} (label {l})" for n, l in zip(self.names, self.labels))
        raise ConfigError(key, f"unknown instance {ref!r}; this scene's instances are: {known}")


def _row(values: Sequence[float]) -> np.ndarray:
    r = np.zeros(TABLE_WIDTH, np.float64)
    r[: len(values)] = np.asarray(values, np.float64)
    return r


def _end(t1: float | None) -> float:
    return NEVER if t1 is None else float(t1)


def _unit(v: Sequence[float]) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _surface_row(point, normal, surface: str, friction: float, t0: float, t1, L: float) -> np.ndarray:
    return _row([*(np.asarray(point, float) * L), *_unit(normal), SURFACE_KIND[surface], float(friction), t0, _end(t1)])


def _box(e: dict, x: np.ndarray, material: np.ndarray, resolver: _InstanceResolver, key: str):
    """(lo, hi) [3] of an entry's box in domain units, or None when it has none."""
    if "point" in e and "size" in e:
        p, s = np.asarray(e["point"], float), np.asarray(e["size"], float)
        return p - s, p + s
    if "instance" in e:
        k = resolver(e["instance"], key + ".instance")
        pts = x[material == k]
        if len(pts) == 0:
            raise ConfigError(key, f"instance {e['instance']!r} has no particles")
        lo, hi = pts.min(0), pts.max(0)
        fmin = np.asarray(e.get("bbox_min", [0.0, 0.0, 0.0]), float)
        fmax = np.asarray(e.get("bbox_max", [1.0, 1.0, 1.0]), float)
        if np.any(fmax < fmin):
            raise ConfigError(key, "bbox_max must be >= bbox_min on every axis")
        ext = hi - lo
        # the fractions 0 and 1 include the instance's extreme particles
        pad = 1e-6 + 1e-6 * ext
        return lo + fmin * ext - pad * (fmin <= 0), lo + fmax * ext + pad * (fmax >= 1)
    return None


def _select(e: dict, x: np.ndarray, material: np.ndarray, resolver: _InstanceResolver, key: str) -> np.ndarray:
    """[P] bool: the particles a particle action applies to (initial positions)."""
    sel = np.ones(len(x), bool)
    if "instance" in e:
        sel &= material == resolver(e["instance"], key + ".instance")
    if e["type"] == "enforce_particle_velocity_rotation":
        c, n = np.asarray(e["point"], float), _unit(e["normal"])
        hh, r = e["half_height_and_radius"]
        d = x - c
        h = d @ n
        radial = np.linalg.norm(d - h[:, None] * n, axis=1)
        sel &= (np.abs(h) <= hh) & (radial <= r)
    else:
        box = _box(e, x, material, resolver, key)
        if box is not None:
            lo, hi = box
            sel &= np.all((x >= lo) & (x <= hi), axis=1)
    if not sel.any():
        raise ConfigError(key, "selects no particles (check point/size, bbox fractions or instance)")
    return sel


def describe_counts(b: BoundDynamics) -> str:
    s, c, a, t, r = b.counts
    return (f"gravity {tuple(round(float(g), 3) for g in b.gravity)}, walls {b.boundary} {b.wall_margin:g} m from the "
            f"domain faces, {s} surface collider(s), "
            f"{c} cuboid(s), {a} force(s), {t} enforced translation(s), {r} rotation(s), damping {b.damping:g}/s")

