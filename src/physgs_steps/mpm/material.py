"""Material parameters of the MPM solver, without Taichi (docs/CONTRACTS.md "params.json").

:class:`Material` carries one instance's parameters in SI units (E and yield stress in Pa,
density in kg/m^3, friction angle in degrees); :func:`preset` builds one from the material
knowledge base (``physgs_steps.materials_kb``), e.g. ``preset("jelly")``. The constitutive
models themselves (Taichi hooks) are in :mod:`.materials`, which re-exports these names; this
module is separate so that planning code (the workflow's DAG, the validation cases) can build
materials without loading Taichi.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import ConfigError
from .. import materials_kb as kb

# Columns of the per-material parameter table handed to the kernels.
PARAM_COLUMNS = ("mu", "lam", "density", "yield_stress", "dp_alpha", "cohesion", "j_min", "j_max", "sin_phi",
                 "fracture_strain", "fracture_softening", "flip")
N_PARAMS = len(PARAM_COLUMNS)
COL = {name: i for i, name in enumerate(PARAM_COLUMNS)}
DEFAULT_FRACTURE_SOFTENING = 0.2

PRESET_NAMES = ("jelly", "rubber", "elastomer", "metal", "sand", "snow", "plasticine", "water", "foam", "stone")

# FLIP share of the particle-to-grid-to-particle velocity transfer per plasticity model (the
# kernels' G2P: v_p <- APIC velocity + flip (v_p - v_p interpolated from the grid before the
# forces), "AFLIP" of Fei et al. 2021, ACM TOG 40(4)).  0: plain APIC.  Granular flow runs at
# the elastic CFL, tens of substeps per cell of flow, and APIC smooths the velocity across every
# shear band at each transfer: that loss is per substep, so a granular collapse ran out shorter
# the more substeps it took (validation column_collapse notes); keeping the particles' own
# deviation from the grid field removes it.  Elastic and fluid models keep APIC.
FLIP_RATIO = {"mohr_coulomb": 0.99, "drucker_prager": 0.99}

RIGID_MODELS = ("rigid", "identity")  # the kernel's (elasticity, plasticity) pair of a rigid instance
RIGID_KEY = RIGID_MODELS + (False,)  # ... and its kernel key (no fracture)


# ============================================================================ parameters
def lame(E: float, nu: float) -> tuple[float, float]:
    """Lame parameters (mu, lam) from Young's modulus E [Pa] and Poisson's ratio nu."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


VOLUME_GAMMA = 2.0  # Mie-Grueneisen exponent of the volume model (materials.Volume)


def wave_modulus(elasticity: str, E: float, nu: float) -> float:
    """The modulus M [Pa] of the fastest wave the elasticity model carries at rest, so that its
    speed is ``sqrt(M / rho)``: the P-wave modulus ``lam + 2 mu`` of the solid models, the
    bulk modulus of the models that carry no shear stress.  ``fluid`` (tau = lam J (J - 1) I,
    pressure -lam (J - 1)): ``lam``; ``volume`` (tau = kappa (J - J^(1 - gamma)) I, kappa =
    lam + 2 mu / 3): ``gamma kappa``.  The P-wave modulus is wrong for both: it counts a shear
    stiffness a fluid does not have (water, nu 0.3: 1.53x its sound speed, so 1.53x the
    substeps a frame it needs; validation ``dam_break``) and misses the volume model's
    gamma (nu 0.49: 0.72x, so the CFL number ran 1.39x over)."""
    mu, lam = lame(E, nu)
    if elasticity == "fluid":
        return lam
    if elasticity == "volume":
        return VOLUME_GAMMA * (lam + 2.0 * mu / 3.0)
    return lam + 2.0 * mu


# What a granular material's friction angle phi means (docs/CONTRACTS.md "params.json"): the
# angle at which it flows in simple shear, its angle of repose, mu_s = tan(phi) as in granular-flow
# rheologies.  Both return maps flow at constant volume, radially towards the hydrostatic axis, so
# in steady simple shear (a layer flowing down a slope, a wedge sliding over a deposit) the normal
# stresses are equal and the shear stress on the slope-parallel planes is tau = p sin(phi_MC) for
# a Mohr-Coulomb surface of angle phi_MC and tau = p 3 alpha / sqrt(2) for Klar et al.'s
# Drucker-Prager cone (Davis 1968's strength of a non-dilatant material in plane shear: tan(phi_ss)
# = sin(phi) cos(psi) / (1 - sin(phi) sin(psi)) with psi = 0).  Taking phi as the Mohr-Coulomb
# angle itself made a 30-degree sand flow on a 26-28 degree slope (tan 26.6 = sin 30); the
# surfaces are set so that simple shear flows at tau = p tan(phi): sin(phi_MC) = tan(phi) and
# alpha = sqrt(2) tan(phi) / 3.  A flow angle needs tan(phi) < 1: phi below 45 degrees.
FRICTION_ANGLE_MAX = kb.FRICTION_ANGLE_MAX  # degrees, exclusive


def mc_sin_phi(friction_angle_deg: float) -> float:
    """sin of the Mohr-Coulomb surface's angle for a material that flows in simple shear at
    ``friction_angle_deg`` (module comment above FRICTION_ANGLE_MAX): tan(phi)."""
    return math.tan(math.radians(friction_angle_deg))


def dp_alpha(friction_angle_deg: float) -> float:
    """Drucker-Prager cone coefficient alpha (``|dev e| + (3 lam + 2 mu) / (2 mu) tr(e) alpha <= 0``)
    for a material that flows in simple shear at ``friction_angle_deg``: sqrt(2) tan(phi) / 3."""
    return math.sqrt(2.0) / 3.0 * math.tan(math.radians(friction_angle_deg))


@dataclass(frozen=True)
class Material:
    """One instance's material in SI units (see docs/CONTRACTS.md "params.json").

    ``name`` is the instance name used in messages; ``preset`` the knowledge-base material
    it came from (if any).  ``velocity`` is the instance's initial velocity in m/s.

    ``rigid``: the instance moves as one rigid body (:mod:`physgs_steps.mpm.rigid`); its
    elasticity/plasticity and E are then unused by the simulation (they are what the
    ``no_rigid`` ablation simulates).  ``fixed`` (rigid only): it does not move at all and
    does not enter the MPM; its particles become a static level-set collider
    (:mod:`physgs_steps.mpm.colliders`) with surface kind ``surface`` (sticky | slip |
    separate) and Coulomb ``friction``.
    """

    elasticity: str
    plasticity: str
    E: float
    nu: float
    density: float
    yield_stress: float | None = None
    friction_angle: float | None = None
    cohesion: float = 0.0
    j_min: float = 0.05
    j_max: float = 1.2
    fracture_strain: float | None = None
    fracture_softening: float = DEFAULT_FRACTURE_SOFTENING
    name: str = "material"
    preset: str | None = None
    velocity: tuple = (0.0, 0.0, 0.0)
    rigid: bool = False
    fixed: bool = False
    surface: str = "separate"
    friction: float = 0.5
    extra: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        where = f"material of '{self.name}'"
        object.__setattr__(self, "elasticity", kb.normalize_elasticity(self.elasticity, f"{where}: elasticity"))
        object.__setattr__(self, "plasticity", kb.normalize_plasticity(self.plasticity, f"{where}: plasticity"))
        _check_number(f"{where}: E", self.E, lo=0.0, lo_open=True)
        _check_number(f"{where}: nu", self.nu, lo=0.0, hi=0.5, hi_open=True)
        _check_number(f"{where}: density", self.density, lo=0.0, lo_open=True)
        _check_number(f"{where}: cohesion", self.cohesion, lo=0.0)
        if self.plasticity == "von_mises":
            if self.yield_stress is None:
                raise ConfigError(f"{where}: plasticity_params.yield_stress", "von_mises plasticity needs a yield stress in Pa")
            _check_number(f"{where}: plasticity_params.yield_stress", self.yield_stress, lo=0.0, lo_open=True)
        if self.plasticity in ("drucker_prager", "mohr_coulomb"):
            if self.friction_angle is None:
                raise ConfigError(f"{where}: plasticity_params.friction_angle", f"{self.plasticity} plasticity needs a friction angle in degrees")
            _check_number(f"{where}: plasticity_params.friction_angle", self.friction_angle, lo=0.0,
                          hi=FRICTION_ANGLE_MAX, hi_open=True)
        if self.fracture_strain is not None:
            _check_number(f"{where}: plasticity_params.fracture_strain", self.fracture_strain, lo=0.0, lo_open=True)
            _check_number(f"{where}: plasticity_params.fracture_softening", self.fracture_softening, lo=0.0, lo_open=True)
        if self.plasticity == "j_clamp":
            _check_number(f"{where}: plasticity_params.j_min", self.j_min, lo=0.0, lo_open=True, hi=1.0)
            _check_number(f"{where}: plasticity_params.j_max", self.j_max, lo=1.0)
        v = tuple(float(c) for c in self.velocity)
        if len(v) != 3 or not all(math.isfinite(c) for c in v):
            raise ConfigError(f"{where}: velocity", f"must be 3 finite numbers (m/s), got {self.velocity!r}")
        object.__setattr__(self, "velocity", v)
        for flag in ("rigid", "fixed"):
            if not isinstance(getattr(self, flag), (bool, np.bool_)):
                raise ConfigError(f"{where}: {flag}", f"must be true or false, got {getattr(self, flag)!r}")
            object.__setattr__(self, flag, bool(getattr(self, flag)))
        if self.fixed and not self.rigid:
            raise ConfigError(f"{where}: fixed", "only a rigid instance can be fixed (set rigid: true as well)")
        if self.surface not in ("sticky", "slip", "separate"):
            raise ConfigError(f"{where}: surface", f"must be sticky, slip or separate, got {self.surface!r}")
        _check_number(f"{where}: friction", self.friction, lo=0.0)

    # ------------------------------------------------------------------ derived
    @property
    def mu(self) -> float:
        return lame(self.E, self.nu)[0]

    @property
    def lam(self) -> float:
        return lame(self.E, self.nu)[1]

    @property
    def wave_speed(self) -> float:
        """Speed (m/s) of the fastest elastic wave of the instance's elasticity model at rest,
        ``sqrt(M / rho)`` with M from :func:`wave_modulus` (the P-wave speed of a solid, the
        sound speed of ``fluid`` and ``volume``)."""
        return math.sqrt(wave_modulus(self.elasticity, self.E, self.nu) / self.density)

    @property
    def cfl_speed(self) -> float:
        """The wave speed that limits the time step (m/s): :attr:`wave_speed` for a deformable
        instance, 0 for a rigid one (it carries no elastic waves)."""
        return 0.0 if self.rigid else self.wave_speed

    def max_E_for_wave_speed(self, c: float) -> float:
        """The largest E [Pa] whose wave speed is at most ``c`` m/s (same model, nu and density;
        inf for a model without waves: a fluid at nu = 0)."""
        m = wave_modulus(self.elasticity, 1.0, self.nu)  # M / E
        return self.density * c * c / m if m > 0 else math.inf

    def table_row(self) -> np.ndarray:
        """The kernel parameter row, [N_PARAMS] f32 in the order of PARAM_COLUMNS."""
        mu, lam = lame(self.E, self.nu)
        row = np.zeros(N_PARAMS, dtype=np.float64)
        row[COL["mu"]] = mu
        row[COL["lam"]] = lam
        row[COL["density"]] = self.density
        row[COL["yield_stress"]] = self.yield_stress if self.yield_stress is not None else 0.0
        row[COL["dp_alpha"]] = dp_alpha(self.friction_angle) if self.friction_angle is not None else 0.0
        row[COL["cohesion"]] = self.cohesion
        row[COL["j_min"]] = self.j_min
        row[COL["j_max"]] = self.j_max
        row[COL["sin_phi"]] = mc_sin_phi(self.friction_angle) if self.friction_angle is not None else 0.0
        row[COL["fracture_strain"]] = self.fracture_strain if self.fracture_strain is not None else 0.0
        row[COL["fracture_softening"]] = self.fracture_softening
        row[COL["flip"]] = FLIP_RATIO.get(self.plasticity, 0.0)
        return row.astype(np.float32)

    @property
    def models(self) -> tuple[str, str]:
        """The (elasticity, plasticity) pair the kernels run: :data:`RIGID_MODELS` for a rigid
        instance, else the instance's own models."""
        return RIGID_MODELS if self.rigid else (self.elasticity, self.plasticity)

    @property
    def role(self) -> str:
        """``fixed`` (static collider), ``rigid`` (free rigid body) or ``deformable``."""
        return "fixed" if self.fixed else "rigid" if self.rigid else "deformable"

    @property
    def fractures(self) -> bool:
        return self.fracture_strain is not None

    @property
    def kernel_key(self) -> tuple[str, str, bool]:
        """What the kernels are specialised to: (elasticity, plasticity, fracture on/off);
        :data:`RIGID_KEY` for a rigid instance (no stress, no fracture)."""
        return RIGID_KEY if self.rigid else (self.elasticity, self.plasticity, self.fractures)

    def describe(self) -> str:
        """One line naming the instance, its models and parameters (used in error messages)."""
        pp = ""
        if self.plasticity == "von_mises":
            pp = f", yield_stress={self.yield_stress:.3g} Pa"
        elif self.plasticity in ("drucker_prager", "mohr_coulomb"):
            pp = f", friction_angle={self.friction_angle:g} deg, cohesion={self.cohesion:g}"
        elif self.plasticity == "j_clamp":
            pp = f", j_min={self.j_min:g}, j_max={self.j_max:g}"
        if self.fractures:
            pp += f", fracture_strain={self.fracture_strain:g}, fracture_softening={self.fracture_softening:g}"
        tag = f"{self.preset}: " if self.preset else ""
        if self.rigid:
            what = (f"fixed rigid (static collider, {self.surface}, friction {self.friction:g})" if self.fixed
                    else "free rigid body")
            return f"'{self.name}' ({tag}{what}, density={self.density:g} kg/m^3)"
        return (f"'{self.name}' ({tag}{self.elasticity}/{self.plasticity}, E={self.E:.3g} Pa, nu={self.nu:g}, "
                f"density={self.density:g} kg/m^3{pp})")

    def with_(self, **changes: Any) -> "Material":
        return replace(self, **changes)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_params(cls, entry: dict, key: str = "instances[]") -> "Material":
        """A Material from one params.json instance entry (CONTRACTS.md format).

        Raises:
            ConfigError naming ``key`` and the offending field.
        """
        if not isinstance(entry, dict):
            raise ConfigError(key, f"must be a mapping, got {type(entry).__name__}")
        missing = [k for k in ("elasticity", "plasticity", "E", "nu", "density") if entry.get(k) is None]
        if missing:
            raise ConfigError(key, f"missing {', '.join(missing)}")
        pp = entry.get("plasticity_params") or {}
        if not isinstance(pp, dict):
            raise ConfigError(f"{key}.plasticity_params", "must be a mapping")
        full = kb.full_plasticity_params(pp)
        name = str(entry.get("name", f"label {entry.get('label', '?')}"))
        try:
            return cls(
                elasticity=entry["elasticity"], plasticity=entry["plasticity"],
                E=_num(entry["E"]), nu=_num(entry["nu"]), density=_num(entry["density"]),
                yield_stress=full["yield_stress"], friction_angle=full["friction_angle"],
                cohesion=full["cohesion"] if full["cohesion"] is not None else 0.0,
                j_min=full["j_min"] if full["j_min"] is not None else 0.05,
                j_max=full["j_max"] if full["j_max"] is not None else 1.2,
                fracture_strain=full["fracture_strain"],
                fracture_softening=(full["fracture_softening"] if full["fracture_softening"] is not None
                                    else DEFAULT_FRACTURE_SOFTENING),
                name=name, preset=entry.get("material"),
                velocity=tuple(entry.get("velocity") or (0.0, 0.0, 0.0)),
                rigid=entry.get("rigid") if entry.get("rigid") is not None else False,
                fixed=entry.get("fixed") if entry.get("fixed") is not None else False,
                surface=entry.get("surface") or "separate",
                friction=_num(entry["friction"]) if entry.get("friction") is not None else 0.5,
            )
        except (TypeError, ValueError) as e:
            raise ConfigError(key, str(e)) from None
        except ConfigError as e:
            raise ConfigError(f"{key} ({name})", e.problem) from None


def preset(material: str, name: str | None = None, **overrides: Any) -> Material:
    """A Material from the knowledge base (``jelly``, ``rubber``, ``elastomer``, ``metal``,
    ``sand``, ``snow``, ``plasticine``, ``water``, ``foam``, ``stone``, or any other KB entry or
    alias), with optional field overrides (``E=...``)."""
    e = kb.get_material(material)
    pp = e["plasticity_params"]
    fields = dict(
        elasticity=e["elasticity"], plasticity=e["plasticity"], E=e["E"], nu=e["nu"], density=e["density"],
        yield_stress=pp.get("yield_stress"), friction_angle=pp.get("friction_angle"),
        cohesion=pp.get("cohesion") or 0.0,
        j_min=pp.get("j_min") if pp.get("j_min") is not None else 0.05,
        j_max=pp.get("j_max") if pp.get("j_max") is not None else 1.2,
        fracture_strain=pp.get("fracture_strain"),
        fracture_softening=(pp.get("fracture_softening") if pp.get("fracture_softening") is not None
                            else DEFAULT_FRACTURE_SOFTENING),
        name=name or e["name"], preset=e["name"], rigid=bool(e.get("rigid", False)),
    )
    fields.update(overrides)
    return Material(**fields)


def _num(v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"expected a number, got {v!r}")
    return float(v)


def _check_number(key: str, v: Any, lo: float | None = None, hi: float | None = None,
                  lo_open: bool = False, hi_open: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(key, f"must be a finite number, got {v!r}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ConfigError(key, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ConfigError(key, f"must be {'<' if hi_open else '<='} {hi:g}, got {v:g}")
