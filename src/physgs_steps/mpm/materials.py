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

:class:`Material` (one instance's parameters in SI units) and :func:`preset` live in
:mod:`.material` (no Taichi) and are re-exported here.
"""
from __future__ import annotations

import taichi as ti

from .material import (COL, DEFAULT_FRACTURE_SOFTENING, FLIP_RATIO, N_PARAMS, PARAM_COLUMNS, PRESET_NAMES, RIGID_KEY,  # noqa: F401
                       RIGID_MODELS, VOLUME_GAMMA, Material, dp_alpha, lame, preset)  # noqa: F401

LOG_FLOOR = 1e-6  # logs of singular values and of J use log(max(s, LOG_FLOOR))
_Q_YIELD_STRESS, _Q_DP_ALPHA, _Q_COHESION, _Q_J_MIN, _Q_J_MAX, _Q_SIN_PHI = (
    COL["yield_stress"], COL["dp_alpha"], COL["cohesion"], COL["j_min"], COL["j_max"], COL["sin_phi"])
_Q_FRACTURE_STRAIN, _Q_FRACTURE_SOFTENING = COL["fracture_strain"], COL["fracture_softening"]



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
D_MAX = 0.95  # largest damage: a broken particle keeps 5% of its tensile stress (Fracture)


class Fracture:
    """Tearing: a per-particle damage state in the constitutive path (mpm88's ``Jp`` slot).

    Continuum damage (in the spirit of Wolper et al. 2019, "CD-MPM: continuum damage material
    point methods for dynamic fracture animation") driven by the particle's accumulated
    inelastic strain ``ep`` [P], which grows in two ways:

    * ductile: the equivalent plastic strain of the return map (:meth:`plastic_strain`, for
      the plasticity models that return in principal space: von Mises, Drucker-Prager,
      Mohr-Coulomb) while the returned state is in mean tension (ductile damage grows with
      plastic strain under positive stress triaxiality; Lemaitre 1985, Bao & Wierzbicki 2004);
      plastic flow localises where the body necks, so a pulled plastic body tears there;
    * brittle: a Rankine tension cut-off - no principal elastic Hencky strain exceeds
      ``fracture_strain``; what the cut-off removes is crack opening added to ``ep``.

    The damage ``d = min(ep / fracture_softening, D_MAX)`` fades the tensile principal
    stresses, ``tau_d = U diag(min(t, 0) + (1 - d) max(t, 0)) U^T`` (t the principal Kirchhoff
    stresses, U their directions), so a broken particle no longer holds its neighbours together
    (the grid lets the pieces part) but still resists compression.  A broken particle keeps
    ``1 - D_MAX`` (5%) of its tensile stress (a residual stiffness, like the maximum
    degradation of FE damage models): a band of broken particles carries at most 5% of the
    intact tension, so the pieces part, but broken crumb next to intact material stays stuck
    to it instead of being shed as loose crumbs (the bread scene at 40 frames: 24 of its 2969
    particles outside the two halves at 1% residual, 9 at 5%, 53 with none).  Compression and shear do not crack a material
    (its plasticity model handles them, and its plastic flow in mean compression does not
    damage).  No crack-band regularisation: the neck, and so the band where ``ep`` grows, is
    one to three cells wide, so a coarser grid tears later (README, "Tearing").
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
        d = ti.min(ep_new / q[_Q_FRACTURE_SOFTENING], D_MAX)
        s = ti.exp(e)
        return U @ _diag(s) @ V.transpose(), s, ep_new, d

    @staticmethod
    @ti.func
    def plastic_strain(sig_trial, sig_ret):
        """Damaging plastic strain of one return map in principal space (U, V kept): the
        equivalent plastic strain ``sqrt(2/3) |log(sig_trial) - log(sig_ret)|`` where the
        returned state is in mean tension (``sum(log sig_ret) > 0``), else 0 (plastic flow
        under mean compression does not tear)."""
        e_ret = _log_sig(sig_ret)
        dp = 0.0
        if e_ret.sum() > 0.0:
            dp = ti.sqrt(2.0 / 3.0) * (_log_sig(sig_trial) - e_ret).norm()
        return dp

    @staticmethod
    @ti.func
    def damage(ep, q):
        return ti.min(ep / q[_Q_FRACTURE_SOFTENING], D_MAX)

    @staticmethod
    @ti.func
    def degrade(tau, U, d):
        """Stress of a particle with damage d: the tensile principal stresses (in the frame U
        where the isotropic models' tau is diagonal) fade, compression stays."""
        t = U.transpose() @ tau @ U
        tt = ti.Vector([t[0, 0], t[1, 1], t[2, 2]], dt=ti.f32)
        return U @ _diag(ti.min(tt, 0.0) + (1.0 - d) * ti.max(tt, 0.0)) @ U.transpose()


ELASTICITY = {c.name: c for c in (FixedCorotated, NeoHookean, StVKHencky, Volume, FluidElasticity, Rigid)}
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
