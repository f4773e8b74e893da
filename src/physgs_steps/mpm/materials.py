"""Constitutive models of the MPM solver (FastPhysGS appendix A, B.1-B.2; docs/CONTRACTS.md).

One small class per model, Genesis-style:

* an elasticity model has ``kirchhoff(F, J, mu, lam) -> tau`` and
  ``kirchhoff_svd(F, U, sig, V, J, mu, lam) -> tau``, the Kirchhoff stress ``tau = P F^T`` of
  the (elastic) deformation gradient ``F`` without / with its SVD at hand;
* a plasticity model has ``return_map(F, U, sig, V, mu, lam, q) -> (F, U, sig, V)``, the
  projection of a trial ``F`` back onto its admissible set.

Both are ``ti.func`` hooks.  ``U, sig, V`` is the SVD ``F = U diag(sig) V^T`` (U, V proper
rotations, the last singular value negative for an inverted element) when the model needs
one; the solver computes it at most once per particle and substep and only for the models a
scene uses (``needs_svd`` / ``svd_mode`` below), and the kernel is specialised at compile time
to the (elasticity, plasticity) pairs present.  Fixed corotated needs only the polar rotation,
which it gets from a scaled Newton iteration (:func:`polar_rotation`) unless an SVD is at hand.  ``q`` is the material's parameter row
(:data:`PARAM_COLUMNS`).

:class:`Material` carries one instance's parameters in SI units (E and yield stress in Pa,
density in kg/m^3, friction angle in degrees); :func:`preset` builds one from the material
knowledge base (``physgs_steps.materials_kb``), e.g. ``preset("jelly")``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import taichi as ti

from ..errors import ConfigError
from .. import materials_kb as kb

LOG_FLOOR = 1e-6  # logs of singular values and of J use log(max(s, LOG_FLOOR))
VOLUME_GAMMA = 2.0  # Mie-Grueneisen exponent of the volume model

# Columns of the per-material parameter table handed to the kernels.
PARAM_COLUMNS = ("mu", "lam", "density", "yield_stress", "dp_alpha", "cohesion", "j_min", "j_max", "sin_phi",
                 "fracture_strain", "fracture_softening")
N_PARAMS = len(PARAM_COLUMNS)
COL = {name: i for i, name in enumerate(PARAM_COLUMNS)}
_Q_YIELD_STRESS, _Q_DP_ALPHA, _Q_COHESION, _Q_J_MIN, _Q_J_MAX, _Q_SIN_PHI = (
    COL["yield_stress"], COL["dp_alpha"], COL["cohesion"], COL["j_min"], COL["j_max"], COL["sin_phi"])
_Q_FRACTURE_STRAIN, _Q_FRACTURE_SOFTENING = COL["fracture_strain"], COL["fracture_softening"]
DEFAULT_FRACTURE_SOFTENING = 0.2

PRESET_NAMES = ("jelly", "rubber", "elastomer", "metal", "sand", "snow", "plasticine", "water", "foam", "stone")


# ============================================================================ helpers
@ti.func
def _diag(s):
    """3x3 diagonal matrix from a 3-vector."""
    return ti.Matrix([[s[0], 0.0, 0.0], [0.0, s[1], 0.0], [0.0, 0.0, s[2]]], dt=ti.f32)


@ti.func
def _eye():
    return ti.Matrix.identity(ti.f32, 3)


@ti.func
def _cbrt(J):
    """Real (sign-preserving) cube root."""
    a = ti.pow(ti.abs(J), 1.0 / 3.0)
    if J < 0.0:
        a = -a
    return a


@ti.func
def _log_sig(sig):
    return ti.log(ti.max(sig, LOG_FLOOR))


# ============================================================================ elasticity
POLAR_J_MIN = 1e-3  # below this J the polar rotation comes from the SVD, not Newton's iteration
POLAR_MAX_ITERS = 12


@ti.func
def polar_rotation(F):
    """Rotation R of the polar decomposition F = R S for det F > 0: scaled Newton iteration
    R <- (g R + R^-T / g) / 2 with Higham's Frobenius scaling g (3-5x faster than the 3x3 SVD
    and more accurate in f32).  Equals U V^T of the SVD."""
    R = F
    it = 0
    while it < POLAR_MAX_ITERS:
        R_inv_T = R.inverse().transpose()
        g = ti.sqrt(ti.sqrt(R_inv_T.norm_sqr() / R.norm_sqr()))
        R_next = 0.5 * (g * R + R_inv_T / g)
        change = (R_next - R).norm_sqr()
        R = R_next
        it += 1
        if change < 1e-12:
            break
    return R


class Elasticity:
    """Base of the elasticity models.

    Hooks: ``kirchhoff(F, J, mu, lam)`` (no SVD at hand) and
    ``kirchhoff_svd(F, U, sig, V, J, mu, lam)`` (a valid SVD of F at hand; optional: a model
    without it gets ``kirchhoff`` also when an SVD is at hand, see :func:`takes_svd`).
    ``needs_svd``: the model cannot work without the SVD, so the solver computes one for it.
    """

    name = ""
    needs_svd = False


class FixedCorotated(Elasticity):
    """``tau = 2 mu (F - R) F^T + lam J (J - 1) I`` with ``R = U V^T`` (Stomakhin et al. 2012)."""

    name = "fixed_corotated"
    needs_svd = False

    @staticmethod
    @ti.func
    def kirchhoff(F, J, mu, lam):
        R = _eye()
        if J > POLAR_J_MIN:
            R = polar_rotation(F)
        else:  # inverted or nearly flat: R = U V^T with proper rotations U, V
            U, S, V = ti.svd(F)
            R = U @ V.transpose()
        return 2.0 * mu * (F - R) @ F.transpose() + lam * J * (J - 1.0) * _eye()

    @staticmethod
    @ti.func
    def kirchhoff_svd(F, U, sig, V, J, mu, lam):
        # (F - R) F^T = U diag((s - 1) s) U^T for F = U diag(s) V^T, R = U V^T
        d = 2.0 * mu * (sig - 1.0) * sig
        return U @ _diag(d) @ U.transpose() + lam * J * (J - 1.0) * _eye()


class NeoHookean(Elasticity):
    """``tau = mu (F F^T - I) + lam log(J) I`` (J >= 1e-6 inside the log; Bonet & Wood)."""

    name = "neo_hookean"
    needs_svd = False

    @staticmethod
    @ti.func
    def kirchhoff(F, J, mu, lam):
        return mu * (F @ F.transpose() - _eye()) + lam * ti.log(ti.max(J, LOG_FLOOR)) * _eye()



class StVKHencky(Elasticity):
    """``tau = U diag(2 mu eps + lam tr(eps)) U^T``, ``eps = log(sig)`` (Hencky strain)."""

    name = "stvk_hencky"
    needs_svd = True

    @staticmethod
    @ti.func
    def kirchhoff_svd(F, U, sig, V, J, mu, lam):
        eps = _log_sig(sig)
        d = 2.0 * mu * eps + lam * eps.sum()
        return U @ _diag(d) @ U.transpose()


class Volume(Elasticity):
    """``tau = kappa (J - J^(1 - gamma)) I``, ``kappa = 2/3 mu + lam``, gamma = 2 (Mie-Grueneisen)."""

    name = "volume"
    needs_svd = False

    @staticmethod
    @ti.func
    def kirchhoff(F, J, mu, lam):
        kappa = 2.0 / 3.0 * mu + lam
        return kappa * (J - ti.pow(J, 1.0 - VOLUME_GAMMA)) * _eye()



class FluidElasticity(Elasticity):
    """``tau = lam J (J - 1) I`` (no shear stiffness)."""

    name = "fluid"
    needs_svd = False

    @staticmethod
    @ti.func
    def kirchhoff(F, J, mu, lam):
        return lam * J * (J - 1.0) * _eye()


class Rigid(Elasticity):
    """``tau = 0``: the particles of a rigid instance carry no stress.  After every substep
    their velocities are projected onto the body's rigid motion and F is set to its rotation
    (:mod:`physgs_steps.mpm.rigid`); with no elastic waves, the model does not limit the time
    step.  Used through :attr:`Material.rigid`, not as a params.json elasticity name."""

    name = "rigid"
    needs_svd = False

    @staticmethod
    @ti.func
    def kirchhoff(F, J, mu, lam):
        return ti.Matrix.zero(ti.f32, 3, 3)



# ============================================================================ plasticity
class Plasticity:
    """Base of the plasticity models: ``return_map`` is the return-mapping hook.

    ``svd_mode`` says how the model relates to the SVD of the trial F:
    ``needs`` (it works on singular values), ``passthrough`` (it returns F unchanged, so an
    SVD computed before it stays valid) or ``produces`` (its result is isotropic, ``c I``,
    whose SVD it returns itself).
    """

    name = ""
    svd_mode = "passthrough"


class Identity(Plasticity):
    """No plastic flow: ``F`` is returned unchanged."""

    name = "identity"
    svd_mode = "passthrough"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        return F, U, sig, V


class JClamp(Plasticity):
    """``F = cbrt(clamp(J, j_min, j_max)) I`` (PhysGaussian's "sigma" plasticity)."""

    name = "j_clamp"
    svd_mode = "produces"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        J = ti.min(ti.max(F.determinant(), q[_Q_J_MIN]), q[_Q_J_MAX])
        c = _cbrt(J)
        return c * _eye(), _eye(), ti.Vector([c, c, c], dt=ti.f32), _eye()


class VonMises(Plasticity):
    """Project the deviatoric Hencky strain onto ``|eps_hat| <= yield_stress / (2 mu)``."""

    name = "von_mises"
    svd_mode = "needs"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        eps = _log_sig(sig)
        eps_hat = eps - eps.sum() / 3.0
        norm = eps_hat.norm()
        dg = norm - q[_Q_YIELD_STRESS] / (2.0 * mu)
        if dg > 0.0:
            eps -= dg / norm * eps_hat
        s = ti.exp(eps)
        return U @ _diag(s) @ V.transpose(), U, s, V


class DruckerPrager(Plasticity):
    """Drucker-Prager sand plasticity on Hencky strains (Klar et al. 2016), with cohesion as a
    log-strain offset: tension (tr e >= 0) returns to the cone tip, shear to the cone."""

    name = "drucker_prager"
    svd_mode = "needs"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        coh = q[_Q_COHESION]
        e = _log_sig(sig) - coh
        tr = e.sum()
        if tr >= 0.0:
            e = ti.Vector.zero(ti.f32, 3)
        else:
            e_hat = e - tr / 3.0
            norm = e_hat.norm()
            dg = norm + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * q[_Q_DP_ALPHA]
            if dg > 0.0:
                e -= dg / norm * e_hat
        s = ti.exp(e + coh)
        return U @ _diag(s) @ V.transpose(), U, s, V


class MohrCoulomb(Plasticity):
    """Mohr-Coulomb sand plasticity on Hencky strains, returned like Klar et al.'s
    Drucker-Prager model (tension to the tip, shear radially towards the hydrostatic axis at
    constant volume) but onto the Mohr-Coulomb surface
    ``(t1 - t3) + (t1 + t3) sin(phi) <= 0`` of the principal Kirchhoff stresses t1 >= t2 >= t3."""

    name = "mohr_coulomb"
    svd_mode = "needs"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        coh = q[_Q_COHESION]
        e = _log_sig(sig) - coh
        tr = e.sum()
        if tr >= 0.0:
            e = ti.Vector.zero(ti.f32, 3)
        else:
            e_hat = e - tr / 3.0
            hi = e_hat.max()
            lo = e_hat.min()
            sphi = q[_Q_SIN_PHI]
            p = (2.0 * mu / 3.0 + lam) * tr  # mean Kirchhoff stress (< 0: compression)
            D = 2.0 * mu * ((hi - lo) + sphi * (hi + lo))
            if D > 0.0:
                scale = -2.0 * p * sphi / D  # the deviator's scale that lands on the surface
                if scale < 1.0:
                    e = tr / 3.0 + scale * e_hat
        s = ti.exp(e + coh)
        return U @ _diag(s) @ V.transpose(), U, s, V


class FluidPlasticity(Plasticity):
    """``F = cbrt(J) I``: all shear is forgotten, only the volume change is kept."""

    name = "fluid"
    svd_mode = "produces"

    @staticmethod
    @ti.func
    def return_map(F, U, sig, V, mu, lam, q):
        c = _cbrt(F.determinant())
        return c * _eye(), _eye(), ti.Vector([c, c, c], dt=ti.f32), _eye()


# ============================================================================ fracture
class Fracture:
    """Tearing: a per-particle damage state in the constitutive path (mpm88's ``Jp`` slot).

    A Rankine tension cut-off with softening (in the spirit of Wolper et al. 2019, "CD-MPM:
    continuum damage material point methods for dynamic fracture animation"): no principal
    elastic Hencky strain of a tearing material exceeds ``fracture_strain``; what the cut-off
    removes is crack opening and accumulates in the particle's ``ep`` [P].  The damage
    ``d = min(ep / fracture_softening, 1)`` fades the tensile principal stresses,
    ``tau_d = U diag(min(t, 0) + (1 - d) max(t, 0)) U^T`` (t the principal Kirchhoff stresses,
    U their directions), so a cracked particle no longer holds its neighbours together (the
    grid lets the pieces part) but still resists compression.  A fully cracked particle
    (d = 1) also forgets its tensile stretches (``e_i = min(e_i, 0)``).  Compression and
    shear do not crack a material (its plasticity model handles them).  Softening localises
    in a band one or two cells wide, so the energy a crack takes scales with dx (no crack-band
    regularisation).
    """

    @staticmethod
    @ti.func
    def update(U, sig, V, ep, q):
        """(F, sig, ep, d) after the tension cut-off and the damage update of a returned elastic
        state ``U diag(sig) V^T`` (U and V are kept)."""
        e = _log_sig(sig)
        ep_new = ep
        cap = q[_Q_FRACTURE_STRAIN]
        for i in ti.static(range(3)):
            if e[i] > cap:
                ep_new += e[i] - cap
                e[i] = cap
        d = ti.min(ep_new / q[_Q_FRACTURE_SOFTENING], 1.0)
        if d >= 1.0:
            e = ti.min(e, 0.0)
        s = ti.exp(e)
        return U @ _diag(s) @ V.transpose(), s, ep_new, d

    @staticmethod
    @ti.func
    def damage(ep, q):
        return ti.min(ep / q[_Q_FRACTURE_SOFTENING], 1.0)

    @staticmethod
    @ti.func
    def degrade(tau, U, d):
        """Stress of a particle with damage d: the tensile principal stresses (in the frame U
        where the isotropic models' tau is diagonal) fade, compression stays."""
        t = U.transpose() @ tau @ U
        tt = ti.Vector([t[0, 0], t[1, 1], t[2, 2]], dt=ti.f32)
        return U @ _diag(ti.min(tt, 0.0) + (1.0 - d) * ti.max(tt, 0.0)) @ U.transpose()


ELASTICITY = {c.name: c for c in (FixedCorotated, NeoHookean, StVKHencky, Volume, FluidElasticity, Rigid)}
RIGID_MODELS = ("rigid", "identity")  # the kernel's (elasticity, plasticity) pair of a rigid instance
RIGID_KEY = RIGID_MODELS + (False,)  # ... and its kernel key (no fracture)
PLASTICITY = {c.name: c for c in (Identity, JClamp, VonMises, DruckerPrager, MohrCoulomb, FluidPlasticity)}


def takes_svd(el: type) -> bool:
    """Whether the elasticity model has a ``kirchhoff_svd`` hook that uses a given SVD."""
    return any("kirchhoff_svd" in vars(c) for c in el.__mro__ if c is not Elasticity)


def svd_before_return_map(el: type, pl: type) -> bool:
    """Whether the kernel computes the SVD of the trial F before the return map."""
    return pl.svd_mode == "needs" or (pl.svd_mode == "passthrough" and el.needs_svd)


def svd_available(el: type, pl: type) -> bool:
    """Whether (U, sig, V) is a valid SVD of the returned F (so J = prod(sig))."""
    return svd_before_return_map(el, pl) or pl.svd_mode == "produces"


# ============================================================================ parameters
def lame(E: float, nu: float) -> tuple[float, float]:
    """Lame parameters (mu, lam) from Young's modulus E [Pa] and Poisson's ratio nu."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def dp_alpha(friction_angle_deg: float) -> float:
    """Drucker-Prager cone coefficient ``sqrt(2/3) 2 sin(phi) / (3 - sin(phi))``."""
    s = math.sin(math.radians(friction_angle_deg))
    return math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)


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
            _check_number(f"{where}: plasticity_params.friction_angle", self.friction_angle, lo=0.0, hi=90.0, hi_open=True)
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
        """P-wave speed ``sqrt((lam + 2 mu) / rho)`` in m/s of the elastic parameters."""
        mu, lam = lame(self.E, self.nu)
        return math.sqrt((lam + 2.0 * mu) / self.density)

    @property
    def cfl_speed(self) -> float:
        """The wave speed that limits the time step (m/s): :attr:`wave_speed` for a deformable
        instance, 0 for a rigid one (it carries no elastic waves)."""
        return 0.0 if self.rigid else self.wave_speed

    def max_E_for_wave_speed(self, c: float) -> float:
        """The largest E [Pa] whose wave speed is at most ``c`` m/s (same nu and density)."""
        m = (1.0 - self.nu) / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))  # (lam + 2 mu) / E
        return self.density * c * c / m

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
        row[COL["sin_phi"]] = math.sin(math.radians(self.friction_angle)) if self.friction_angle is not None else 0.0
        row[COL["fracture_strain"]] = self.fracture_strain if self.fracture_strain is not None else 0.0
        row[COL["fracture_softening"]] = self.fracture_softening
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
