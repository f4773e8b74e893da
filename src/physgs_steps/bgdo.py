"""BGDO, Bidirectional Graph Decoupling Optimisation of Young's modulus (FastPhysGS Sec. 4.2,
Appendix B.1-B.5, Algorithm 1): the torch pseudo step, the signals, the update and the stage.

Iterations (the workflow's DAG)::

    params_0 -> forward_sim -> forward.h5 (key frames) -> bgdo_update -> params_1 -> ... -> params_N -> final_sim

N = ``bgdo.iterations`` (default 2; 0 is the "without BGDO" ablation and runs no forward
simulation). ``forward_sim`` (physgs_steps.simulate, Taichi, no gradients) stores only the key
frames ``round(f (T - 1))``, f in ``bgdo.key_frames`` (default the paper's f_0, f_t, f_n), with
x, v, C, F of every particle. :func:`run` is the stage ``bgdo_update``.

Pseudo step
-----------
:func:`pseudo_step` is one MLS-MPM substep in torch from a stored state, exactly the step of
docs/CONTRACTS.md: the Kirchhoff stress of each instance's elasticity model
(:func:`kirchhoff`), P2G over the 27 offsets with ``index_add`` into the grid nodes the
particles touch, grid update with gravity and the domain walls (slip/sticky, 3 nodes), G2P,
then each instance's plasticity return map (:func:`return_map`). ``log E`` per instance is the
leaf; every operation is differentiable (the 3x3 SVD has a closed-form backward that stays
finite for repeated singular values, e.g. F = I). Like the Taichi solver, the stencil base is
clamped to [0, G - 3]. The pseudo step has no colliders, ground plane, damping or particle
actions (CONTRACTS.md: the Taichi solver applies those). tests/test_bgdo.py checks it against
an independent NumPy implementation (float64, 1e-8) and against one Taichi substep for every
elasticity x plasticity pair (float32 tolerance). Only one key frame and one step's graph are
in memory at a time (:func:`iter_keyframes`), so memory does not grow with the number of key
frames (measured on CPU: +91 MiB for the 13.6k-particle bear, +790 MiB for 200k particles, the
same with 3 or 9 key frames, about 4 KiB per particle); the stage records peak RSS and, on
CUDA, torch's peak allocation.

Signals (per instance k, key frame i, particle p of k)
------------------------------------------------------
    g_p     = d||tau_p||_F / d log E_k          by autograd through the stress (Pa)
    g~_i    = mean_p log(1 + |g_p| / p_ref_k)   compressed per particle, then averaged
    delta_i = mean_p d(F'_p)                    F' after the step and the return map

tau is linear in (mu, lambda), hence in E, for all five models, so g_p = ||tau_p||_F exactly
(a check in the tests): the "stress gradient" is the stress magnitude.

Update
------
    eta  = min(1, 0.1 log(1 + E_k / p_ref_k))                       (bgdo.eta_rule paper)
    G    = eta mean_i g~_i - (1 - eta) mean_{i > 0} log(delta_i / delta_target_k)
    log E_k <- log E_k - clip(G, -max_step, max_step),  never raised above the solver ceiling

This is ``variant: algorithm1`` (default) with ``deformation_signal: log_ratio`` (default).
With ``deformation_signal: difference`` it is Appendix B.5's update and Algorithm 1 literally:

    G    = sum_i w_i [eta g~_i - (1 - eta)(delta_i - delta_target_k) / s_delta] / sum_i w_i

Why the log ratio: for a linear material under a fixed load the deformation is proportional to
1 / E, so d log(delta) / d log E = -1 and log(delta / delta_target) is exactly the Newton step
of log E onto the target; (1 - eta) damps it. The literal difference is bounded below (-1 in
units of the target: a frame that does not deform at all asks for a decrease of at most
1 - eta) and grows linearly above, so its step sizes depend on s_delta and max_step rather than
on how far E is from its target: measured with the first implementation (difference, one
delta_target 0.1 for all materials), a collapse raised E by the whole max_step and a key frame
deforming 2x the target lowered it as much as one deforming 20x. The log ratio is undefined
for the rest state (frame 0, F = I, delta = 0), which carries no deformation information: the
deformation term averages the key frames after frame 0, the stress term all key frames.

Per-material target: ``delta_target: null`` (default) gives each instance delta_target_k =
rho_k g h_ref / E_ref_k (h_ref = ``reference_height``, 0.3 m): the strain its own weight causes
in a 0.3 m object of its material at the material's reference modulus (jelly 0.044, bread
0.010, rubber 0.010, foam 0.0032, stone 3.4e-4). The paper's single target 0.1
(``delta_target: 0.1``) pulls every material to 10% stretch, so a stone, a metal can or a
wooden basket lands at jelly stiffness and a light material (bread, 250 kg/m^3) far below its
band (measured with the first implementation: the stone of duck_stone 3e8 -> 3e5 -> 1.4e5 Pa,
band 5e6-1e8; bread from any start 4e3 Pa, band 1e4-5e5). A first per-material version with
one characteristic stress for every material (7 kPa / E_ref) fixed the stiff materials but
still left bread (4e3 Pa) and the foam mat (267 Pa) below their bands: the load scales with the
density, so the target has to as well.

The main text (Sec. 4.2, Eqs. 6-8) reads differently; ``variant: main_text`` implements it:

    g_tau = mean_i mean_p |g_p| / p_ref_k,   g = log(1 + g_tau),   d_F = mean_i delta_i / s_delta
    G     = eta g - (1 - eta) d_F

The differences: (1) where the compression sits: Algorithm 1 compresses each particle's
gradient and then averages (the appendix: the log "reduces the influence of extreme outliers
during spatial averaging across particles or temporal averaging across key frames"); the main
text averages over the three key frames first and compresses once. With outliers (a few
particles near inversion) the main-text signal follows the outliers, Algorithm 1's the typical
particle. (2) The deformation term: Algorithm 1 uses delta - delta_target (a key frame
deforming less than the target pushes E down, more pushes it up), the main text the plain mean
d_F, which always pushes E up, so E only falls when the stress term outweighs it. Two smaller
differences are not options: the main text differentiates with respect to E and writes the
key-frame F_i, the appendix with respect to log E and the stepped F'; both variants here use
d/dlog E (log E is the leaf; d||tau||/dE = ||tau||/E would not depend on E at all) and F'.

Units: the reference scale
--------------------------
Read literally in SI units (``scaling: si``), eta = min(1, 0.1 log(1 + E/Pa)) is 1 for every
E above e^10 - 1 = 22 kPa, so the deformation term vanishes for all solid materials and G =
mean log(1 + ||tau||/Pa) > 0: log E only decreases, by ~5.6 per iteration at the bear's
stresses of a few kPa (3e8 -> 3e5 -> 1.1e3 Pa, a collapse), and below 22 kPa the unscaled
deformation term is too weak to lift a collapsed object (30 -> 44 -> 63 Pa); see
benchmarks/bgdo_robustness.py --bgdo scaling=si. The paper's E values are in a simulator's
normalised units. ``scaling: reference`` (default) keeps the formulas and makes their
arguments dimensionless:

* E and the stress gradient in units of a reference pressure ``p_ref = reference_strain *
  E_ref`` (reference_strain 0.1), the Kirchhoff stress of the material's reference modulus at
  10% strain (||tau|| ~ E ||eps|| for small strain). E_ref is the geometric mean of the
  material's ``E_range`` in the knowledge base (data/materials.yaml; jelly: sqrt(1e4 * 5e5) =
  7.1e4 Pa, so p_ref = 7.1 kPa), or ``bgdo.reference_modulus`` for a material not in it;
  ``bgdo.reference_pressure`` fixes one p_ref for all instances. Then eta = 0.24 at E = E_ref
  for every material, 0.09 at the jelly band's lower end, 0.43 at its upper end and 1 above
  E = 22000 p_ref: an over-stiff E lets the stress term dominate (E decreases), an over-soft E
  lets the deformation term dominate (E increases), and in the band both are O(1).
* The deformation relative to its target (log_ratio), or in units of ``s_delta =
  delta_target`` (``bgdo.deformation_scale``, deformation_signal difference).
* ``max_step`` (default ln 10000) bounds |G| per iteration (a trust region for the signals).

Unstable forward runs
---------------------
forward_sim stops at the first unstable frame and stores the last stable state in place of
the key frames it could not reach (attribute ``substitute_for``). :func:`unstable_run_info`
decides per instance: "exploded" when its CFL number (wave speed x dt / dx of the failing
frame) exceeded ``bgdo.cfl_limit`` (1): it was too stiff for the substep cap; "broken" when the
failure message names it (collapse J < j_min, tearing, leaving the domain) without a CFL
violation: it could not carry its load. A failed run measures nothing for the key frames it
did not reach, so ``failure_rule: static_load`` (default) uses two facts that do not need
them (:func:`assemble_frames`, :func:`bgdo_update`):

* the solver ceiling E_cap (:func:`solver_ceiling`): the stiffest modulus the configured
  substep cap integrates at its CFL number. An exploded instance goes to min(E_cap,
  rho |g| H / delta_target), the ceiling or the modulus at which its own weight strains it by
  the target (:func:`static_stress`: rho |g| H is the static stress at the base of an
  instance of height H). No update raises E above the ceiling (``ceiling: true``), so the
  final simulation does not explode either.
* the static strain rho |g| H / E: a broken instance's missing key frames count with the
  deformation max(collapse deformation sqrt(3)(1 - j_min^(1/3)) = 1.09, static strain), and an
  instance the failure did not involve but whose static strain exceeds the collapse
  deformation (it cannot carry its own weight) is broken too. An uninvolved instance that can
  carry its weight uses the key frames that were stored, and keeps its E if none after frame 0
  was.

``failure_rule: max_step`` is the first implementation: exploded key frames count as an
infinite stress signal (the paper's log(1 + |g|) of a diverged stress), so G = max_step;
broken ones with the collapse deformation only; uninvolved instances keep E. Without any
failure handling the over-soft case goes the wrong way: the bear at 30 Pa collapses at impact,
its last stable frame (still falling) shows delta = 0.04 and BGDO would lower E (30 -> 14 ->
6.5 Pa).

Robustness (``python benchmarks/bgdo_robustness.py --scenes bear bear_can duck_stone ficus
basket_mat bread --device cuda --n-gaussians 20000 --frames 150 --forward-frames 150 --E0 3e10
3e8 30 kb`` on an H200: the main job's scene size, n_grid 32, 150 frames). E0 -> E1 -> E2 in Pa;
every final simulation is stable, and without BGDO every corrupted start is unstable. c: held
at the solver ceiling E_cap; x: outside the band.

    instance (material) band      from 3e10 (3e8: same)    from 30                  from the KB E
    bear (jelly) [1e4, 5e5]       1.23e5 -> 1.10e5         1.22e5 -> 1.10e5         5e4 -> 7.2e4 -> 8.4e4
    bear_can: bear (jelly)        1.11e5 -> 1.06e5         1.11e5 -> 1.10e5         5e4 -> 8.4e4 -> 9.4e4
    bear_can: can (metal) [5e6, 1e8] 1.37e7 -> 5.13e7 c    3e5 -> 1.54e7            2e7 -> 5.13e7 c -> 5.13e7 c
    duck (rubber) [1e5, 1e6]      2.52e5 -> 4.26e5         2.52e5 -> 5.59e5         5e5 -> 6.2e5 -> 7.1e5
    stone (stone) [5e6, 1e8]      1.43e7 -> 1.90e7 c       3e5 -> 1.90e7 c          2e7 -> 2e7 -> 2e7
    ficus (plant) [5e4, 5e6]      4.57e6 c -> 4.16e5       9.2e3 -> 4.0e4 x         3e5 -> 3.7e5 -> 2.7e5
    mat (foam) [1e4, 3e5]         2.23e3 -> 1.16e5         1.17e4 -> 1.64e5         3e4 -> 2.0e5 -> 4.0e5 x
    basket (wood) [2e6, 1e8]      3.92e6 c -> 3.92e6 c     3e5 -> 3.92e6 c          1e7 -> 1e7 -> 1e7
    bread (bread) [1e4, 5e5]      4.17e4 -> 6.27e4         4.16e4 -> 6.26e4         5e4 -> 6.8e4 -> 7.8e4

The 300k-gaussian bear at n_grid 64 (360,603 particles), which collapses at impact with its
knowledge-base E: 5e4 -> 6.5e5 -> 2.9e5 and 30 -> 1.2e5 -> 1.1e5, final runs stable (the first
implementation oscillated 5e4 -> 1.6e7 -> 1.6e4 and its final run collapsed).

Limitations (measured: benchmarks/bgdo_robustness.py, benchmarks/bgdo_stress_vs_E.py)
-------------------------------------------------------------------------------------
* BGDO does not discover E from nothing: its fixed point is where the key-frame stretch
  matches delta_target, so the target decides where it lands. With the per-material target an
  object loaded by its own weight lands near E_ref x H / 0.4 m; an object loaded by something
  else lands where that load strains it like its own weight would strain a 0.3 m object (the
  foam mat under the basket: 4e5 Pa from its KB 3e4, above its band), and an instance with no
  gravity (the ficus in wind) has no static estimate, so from 30 Pa it needs a third iteration.
* A collapse is a yes/no signal: the collapsed key frames count with at least the collapse
  deformation, so a slightly too soft E overshoots (300k bear at grid 64: 5e4 -> 6.5e5) and
  the next iteration comes back down.
* The ceiling depends on the solver settings: stiff materials (stone, metal, wood) end at E_cap,
  which falls 4x per doubling of n_grid (stone: 1.9e7 Pa at grid 32, 4.8e6 at 64, below its
  band); raise sim.max_substeps for them.
* The mean stretch over an instance dilutes local deformation (a mat deformed only under the
  basket, a plant bent at its stems).

Deformation measure
-------------------
``deformation_measure: stretch`` (default) uses d(F') = ||F' - R'||_F = ||sigma' - 1||, the
rotation-free part; ``frobenius`` the paper's ||F' - I||_F. Appendix B.3 treats ||F' - I|| as a
strain proxy "because rotations are close to identity", true for one substep's increment but
not for the accumulated elastic F: the built-in bear tips over when it lands, and at its
knowledge-base E = 5e4 Pa the key frames have mean ||F - I|| = 1.74 with ||F - R|| = 0.08, which
the literal measure reads as a material 17 times softer than the target.

Plausible band
--------------
The band of a material is its ``E_range`` in the knowledge base: simulation-effective moduli
(not handbook values) for a 0.5 m tabletop object at n_grid 32-64 and 30 fps. For jelly,
[1e4, 5e5] Pa. It is right for this simulator because it contains gelatin's measured 1-100 kPa
and matches what the bear does (benchmarks/bgdo_stress_vs_E.py, 60 runs): below ~1.2e4 Pa it
collapses at impact (J < sim.stability.j_min), from ~1.7e4 Pa it lands and wobbles, and
towards 5e5 Pa the key-frame stretch falls below 1 % (it barely deforms) while the explicit
step needs ~54 substeps per frame at n_grid 32. Stiff materials' bands (stone, metal, wood
from 2e6-5e6 Pa up) are where they barely deform at all; their upper part is beyond the solver
ceiling at the default substep cap.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from . import materials_kb
from .errors import ConfigError, SimulationError

# ----------------------------------------------------------------------------- model names
ELASTICITY = materials_kb.ELASTICITY_MODELS  # canonical names, docs/CONTRACTS.md
PLASTICITY = materials_kb.PLASTICITY_MODELS

SIG_FLOOR = 1e-6  # logs use log(max(sig, 1e-6)) (CONTRACTS.md, SVD convention)
J_FLOOR = 1e-6    # neo-Hookean: J clamped to >= 1e-6 inside the log
SVD_GAP = 1e-6    # smallest |s_j^2 - s_i^2| used in the SVD backward (repeated singular values)
G_REF = 9.81       # m/s^2: the gravity of the per-material delta_target (whatever the scene's gravity)
DELTA_FLOOR = 1e-4  # log_ratio: delta is taken as at least 1e-4 delta_target (log ratio >= -9.2)


def canonical_elasticity(name: str, key: str = "elasticity") -> str:
    """The canonical elasticity name for ``name`` (any spelling materials_kb accepts, e.g. the
    alias ``sigma`` -> stvk_hencky); ConfigError naming ``key`` if unknown."""
    return materials_kb.normalize_elasticity(name, key)


def canonical_plasticity(name: str, key: str = "plasticity") -> str:
    """The canonical plasticity name for ``name`` (``sigma`` -> j_clamp); ConfigError if unknown."""
    return materials_kb.normalize_plasticity(name, key)


# ----------------------------------------------------------------------------- SVD
class _SVD3(torch.autograd.Function):
    """Batched 3x3 SVD ``F = U diag(sig) V^T`` with U, V proper rotations (det +1).

    The forward pass is ``torch.linalg.svd`` (in float64) followed by the sign fix of
    CONTRACTS.md (a reflection moves into the last singular value, which may then be
    negative). The backward pass is the closed-form SVD derivative with the factor
    ``1 / (s_j^2 - s_i^2)`` kept finite for repeated singular values (F = I is the most
    common state in a simulation; torch's own backward returns NaN there).
    """

    @staticmethod
    def forward(ctx, F):  # F [B, 3, 3]
        A = F.detach().to(torch.float64)
        U, S, Vh = torch.linalg.svd(A)
        V = Vh.transpose(-1, -2).clone()
        U = U.clone()
        fu = torch.linalg.det(U) < 0
        fv = torch.linalg.det(V) < 0
        U[..., :, 2] = torch.where(fu[:, None], -U[..., :, 2], U[..., :, 2])
        V[..., :, 2] = torch.where(fv[:, None], -V[..., :, 2], V[..., :, 2])
        S = S.clone()
        S[:, 2] = torch.where(fu ^ fv, -S[:, 2], S[:, 2])
        U, S, V = U.to(F.dtype), S.to(F.dtype), V.to(F.dtype)
        ctx.save_for_backward(U, S, V)
        return U, S, V

    @staticmethod
    def backward(ctx, gU, gS, gV):
        U, S, V = ctx.saved_tensors
        dt = U.dtype
        U64, S64, V64 = U.double(), S.double(), V.double()
        gU = torch.zeros_like(U64) if gU is None else gU.double()
        gS = torch.zeros_like(S64) if gS is None else gS.double()
        gV = torch.zeros_like(V64) if gV is None else gV.double()
        s2 = S64 * S64
        d = s2[:, None, :] - s2[:, :, None]  # d_ij = s_j^2 - s_i^2
        sign = torch.where(d >= 0, 1.0, -1.0).to(d.dtype)
        d = torch.where(d.abs() < SVD_GAP, sign * SVD_GAP, d)
        f = 1.0 / d
        eye = torch.eye(3, dtype=d.dtype, device=d.device)
        f = f * (1 - eye)
        M = U64.transpose(-1, -2) @ gU
        N = V64.transpose(-1, -2) @ gV
        Sd = torch.diag_embed(S64)
        inner = (f * (M - M.transpose(-1, -2))) @ Sd + Sd @ (f * (N - N.transpose(-1, -2))) + torch.diag_embed(gS)
        gF = U64 @ inner @ V64.transpose(-1, -2)
        return gF.to(dt)


def svd3(F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SVD of F  # [B, 3, 3] -> U [B, 3, 3], sig [B, 3], V [B, 3, 3] (det U = det V = +1)."""
    if F.shape[0] == 0:
        z = F.new_zeros((0, 3, 3))
        return z, F.new_zeros((0, 3)), z.clone()
    return _SVD3.apply(F)


def _eye(n: int, like: torch.Tensor) -> torch.Tensor:
    return torch.eye(3, dtype=like.dtype, device=like.device).expand(n, 3, 3)


# ----------------------------------------------------------------------------- constitutive laws
def lame(E: torch.Tensor, nu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lame parameters from Young's modulus and Poisson's ratio.  # E [B], nu [B] -> mu [B], lam [B]"""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def kirchhoff(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, model: str) -> torch.Tensor:
    """Kirchhoff stress tau = P F^T of one elasticity model (CONTRACTS.md table).

    F  # [B, 3, 3] elastic deformation gradient
    mu, lam  # [B] Lame parameters (Pa)
    returns tau  # [B, 3, 3] (Pa)
    """
    model = canonical_elasticity(model)
    B = F.shape[0]
    I = _eye(B, F)
    J = torch.linalg.det(F)
    if model == "fixed_corotated":
        U, sig, V = svd3(F)
        R = U @ V.transpose(-1, -2)
        return 2.0 * mu[:, None, None] * (F - R) @ F.transpose(-1, -2) + (lam * J * (J - 1.0))[:, None, None] * I
    if model == "neo_hookean":
        logJ = torch.log(torch.clamp(J, min=J_FLOOR))
        return mu[:, None, None] * (F @ F.transpose(-1, -2) - I) + (lam * logJ)[:, None, None] * I
    if model == "stvk_hencky":
        U, sig, V = svd3(F)
        eps = torch.log(torch.clamp(sig, min=SIG_FLOOR))
        d = 2.0 * mu[:, None] * eps + (lam * eps.sum(-1))[:, None]
        return U @ torch.diag_embed(d) @ U.transpose(-1, -2)
    if model == "volume":
        kappa = 2.0 / 3.0 * mu + lam
        gamma = 2.0
        return (kappa * (J - torch.pow(J, 1.0 - gamma)))[:, None, None] * I
    # fluid
    return (lam * J * (J - 1.0))[:, None, None] * I


@dataclass
class PlasticParams:
    """Per-particle plasticity parameters (each [B]); unused ones may hold anything finite."""

    yield_stress: torch.Tensor    # [B] Pa (von Mises)
    friction_angle: torch.Tensor  # [B] degrees (Drucker-Prager)
    cohesion: torch.Tensor        # [B] dimensionless log-strain offset (Drucker-Prager)
    j_min: torch.Tensor           # [B] (J-clamp)
    j_max: torch.Tensor           # [B] (J-clamp)

    def subset(self, idx: torch.Tensor) -> "PlasticParams":
        return PlasticParams(*(getattr(self, k)[idx] for k in ("yield_stress", "friction_angle", "cohesion", "j_min", "j_max")))


def _safe_unit(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(|v|, v / |v|) for v  # [B, 3], with a finite direction (and gradient) where |v| = 0."""
    n2 = (v * v).sum(-1)
    pos = n2 > 0
    n = torch.sqrt(torch.where(pos, n2, torch.ones_like(n2)))
    unit = v / n[:, None]
    return torch.where(pos, n, torch.zeros_like(n)), torch.where(pos[:, None], unit, torch.zeros_like(unit))


def _signed_cbrt(J: torch.Tensor) -> torch.Tensor:
    return torch.sign(J) * torch.pow(J.abs(), 1.0 / 3.0)


def return_map(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, pp: PlasticParams, model: str) -> torch.Tensor:
    """Plastic return map of a trial deformation gradient (CONTRACTS.md table).

    F  # [B, 3, 3] trial elastic deformation gradient
    mu, lam  # [B] Lame parameters (Pa)
    returns F  # [B, 3, 3] projected elastic deformation gradient
    """
    model = canonical_plasticity(model)
    B = F.shape[0]
    if model == "identity":
        return F
    I = _eye(B, F)
    if model == "j_clamp":
        J = torch.linalg.det(F)
        Jc = torch.minimum(torch.maximum(J, pp.j_min), pp.j_max)
        return _signed_cbrt(Jc)[:, None, None] * I
    if model == "fluid":
        J = torch.linalg.det(F)
        return _signed_cbrt(J)[:, None, None] * I
    U, sig, V = svd3(F)
    eps = torch.log(torch.clamp(sig, min=SIG_FLOOR))
    if model == "von_mises":
        eps_hat = eps - eps.mean(-1, keepdim=True)
        n, unit = _safe_unit(eps_hat)
        dg = n - pp.yield_stress / (2.0 * mu)
        eps = torch.where((dg > 0)[:, None], eps - dg[:, None] * unit, eps)
        return U @ torch.diag_embed(torch.exp(eps)) @ V.transpose(-1, -2)
    # drucker_prager
    c = pp.cohesion[:, None]
    e = eps - c
    sphi = torch.sin(torch.deg2rad(pp.friction_angle))
    alpha = math.sqrt(2.0 / 3.0) * 2.0 * sphi / (3.0 - sphi)
    tr = e.sum(-1)
    e_hat = e - e.mean(-1, keepdim=True)
    n, unit = _safe_unit(e_hat)
    dg = n + (3.0 * lam + 2.0 * mu) / (2.0 * mu) * tr * alpha
    e_proj = torch.where((dg > 0)[:, None], e - dg[:, None] * unit, e)
    e = torch.where((tr >= 0)[:, None], torch.zeros_like(e), e_proj)
    return U @ torch.diag_embed(torch.exp(e + c)) @ V.transpose(-1, -2)


# ----------------------------------------------------------------------------- materials
@dataclass
class InstanceTable:
    """Per-instance material description (K instances) plus the per-particle instance ids.

    label  # [P] int64 instance id of every particle
    vol  # [P] particle volume in domain units^3
    nu, density  # [K]
    elasticity, plasticity: K canonical model names
    plastic: PlasticParams with [K] tensors
    """

    label: torch.Tensor
    vol: torch.Tensor
    nu: torch.Tensor
    density: torch.Tensor
    elasticity: list
    plasticity: list
    plastic: PlasticParams
    names: list = field(default_factory=list)

    @property
    def n_instances(self) -> int:
        return int(self.nu.shape[0])

    def select(self, idx: torch.Tensor) -> "InstanceTable":
        """The same instances with only the particles ``idx``  # [P'] int64."""
        return InstanceTable(self.label[idx], self.vol[idx], self.nu, self.density, list(self.elasticity),
                             list(self.plasticity), self.plastic, list(self.names))

    def to(self, device) -> "InstanceTable":
        p = self.plastic
        return InstanceTable(self.label.to(device), self.vol.to(device), self.nu.to(device), self.density.to(device),
                             list(self.elasticity), list(self.plasticity),
                             PlasticParams(*(getattr(p, k).to(device) for k in ("yield_stress", "friction_angle", "cohesion", "j_min", "j_max"))),
                             list(self.names))


_PLASTIC_DEFAULTS = {"yield_stress": math.inf, "friction_angle": 30.0, "cohesion": 0.0, "j_min": 0.05, "j_max": 1.2}


def instance_table(instances: list[dict], label, vol, dtype=torch.float32, device="cpu", source: str = "params.json") -> InstanceTable:
    """Build the table from params.json ``instances`` (sorted by ``label``) and particle arrays.

    label  # [P] int instance id per particle (0..K-1)
    vol  # [P] particle volume, domain units^3
    """
    from .errors import InputError

    by_label = {}
    for i, inst in enumerate(instances):
        try:
            by_label[int(inst["label"])] = inst
        except (KeyError, TypeError, ValueError):
            raise InputError(source, f"instances[{i}] has no integer 'label'") from None
    K = len(by_label)
    if sorted(by_label) != list(range(K)):
        raise InputError(source, f"instance labels must be 0..K-1, got {sorted(by_label)}")
    label_np = np.asarray(label)
    if label_np.size and (label_np.min() < 0 or label_np.max() >= K):
        raise InputError(source, f"particle labels span {label_np.min()}..{label_np.max()} but params has {K} instances")
    nu, rho, el, pl, names = [], [], [], [], []
    pvals = {k: [] for k in _PLASTIC_DEFAULTS}
    for k in range(K):
        inst = by_label[k]
        where = f"instances[label={k}]"
        for key in ("E", "nu", "density"):
            v = inst.get(key)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(source, f"{where}.{key} must be a finite number, got {v!r}")
        if not (0.0 <= inst["nu"] < 0.5):
            raise InputError(source, f"{where}.nu = {inst['nu']} is outside [0, 0.5)")
        if inst["density"] <= 0 or inst["E"] <= 0:
            raise InputError(source, f"{where}: E and density must be > 0 (E={inst['E']}, density={inst['density']})")
        nu.append(float(inst["nu"]))
        rho.append(float(inst["density"]))
        el.append(canonical_elasticity(str(inst.get("elasticity")), f"{source}: {where}.elasticity"))
        pl.append(canonical_plasticity(str(inst.get("plasticity")), f"{source}: {where}.plasticity"))
        names.append(str(inst.get("name", f"instance{k}")))
        pp = inst.get("plasticity_params") or {}
        for key, default in _PLASTIC_DEFAULTS.items():
            v = pp.get(key)
            v = default if v is None else v
            if not isinstance(v, (int, float)) or math.isnan(v):
                raise InputError(source, f"{where}.plasticity_params.{key} must be a number or null, got {v!r}")
            pvals[key].append(float(v))
        if pl[-1] == "von_mises" and not math.isfinite(pvals["yield_stress"][-1]):
            raise InputError(source, f"{where}: von_mises plasticity needs plasticity_params.yield_stress (Pa)")
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype, device=device)  # noqa: E731
    return InstanceTable(
        label=torch.as_tensor(label_np.astype(np.int64), device=device),
        vol=t(vol), nu=t(nu), density=t(rho), elasticity=el, plasticity=pl,
        plastic=PlasticParams(*(t(pvals[k]) for k in ("yield_stress", "friction_angle", "cohesion", "j_min", "j_max"))),
        names=names,
    )


def log_E_from_instances(instances: list[dict], dtype=torch.float64, device="cpu") -> torch.Tensor:
    """log E per instance, ordered by label  # [K]"""
    by_label = {int(i["label"]): float(i["E"]) for i in instances}
    return torch.log(torch.as_tensor([by_label[k] for k in range(len(by_label))], dtype=dtype, device=device))


# ----------------------------------------------------------------------------- the MPM step
@dataclass
class GridSpec:
    """The background grid and the forces of the pseudo step.

    n_grid: G nodes per axis; domain_size: L metres per domain unit; gravity: (3,) m/s^2;
    boundary: 'slip' | 'sticky' domain walls on the ``bound`` outermost nodes per side.
    """

    n_grid: int
    domain_size: float = 1.0
    gravity: tuple = (0.0, 0.0, -9.8)
    boundary: str = "slip"
    bound: int = 3


_OFFSETS = torch.tensor(list(itertools.product(range(3), repeat=3)), dtype=torch.int64)  # [27, 3]


def particle_stress(F: torch.Tensor, log_E_p: torch.Tensor, table: InstanceTable) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Kirchhoff stress of every particle from its instance's elasticity model.

    F  # [P, 3, 3]; log_E_p  # [P] log Young's modulus of each particle's instance
    returns tau  # [P, 3, 3] Pa, mu  # [P], lam  # [P]
    """
    E_p = torch.exp(log_E_p).to(F.dtype)
    mu, lam = lame(E_p, table.nu[table.label])
    tau = F.new_zeros(F.shape)
    for model in sorted(set(table.elasticity)):
        ks = [k for k, m in enumerate(table.elasticity) if m == model]
        idx = torch.nonzero(torch.isin(table.label, torch.as_tensor(ks, device=F.device)), as_tuple=True)[0]
        if idx.numel():
            tau = tau.index_copy(0, idx, kirchhoff(F[idx], mu[idx], lam[idx], model))
    return tau, mu, lam


def plastic_projection(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, table: InstanceTable) -> torch.Tensor:
    """Each particle's plasticity return map.  # F [P, 3, 3], mu, lam [P] -> [P, 3, 3]"""
    out = F
    pp = table.plastic.subset(table.label)
    for model in sorted(set(table.plasticity)):
        if model == "identity":
            continue
        ks = [k for k, m in enumerate(table.plasticity) if m == model]
        idx = torch.nonzero(torch.isin(table.label, torch.as_tensor(ks, device=F.device)), as_tuple=True)[0]
        if idx.numel():
            out = out.index_copy(0, idx, return_map(F[idx], mu[idx], lam[idx], pp.subset(idx), model))
    return out


def mpm_step(x, v, C, F, tau, p_mass, p_vol, dt: float, grid: GridSpec):
    """One MLS-MPM/APIC substep after the stress (CONTRACTS.md steps 2-4, without plasticity).

    All in SI: x  # [P, 3] m, v  # [P, 3] m/s, C  # [P, 3, 3] 1/s, F  # [P, 3, 3],
    tau  # [P, 3, 3] Pa, p_mass  # [P] kg, p_vol  # [P] m^3.
    returns x, v, C, F_trial (each like the input)
    """
    P = x.shape[0]
    dev, dtp = x.device, x.dtype
    G = int(grid.n_grid)
    dx = grid.domain_size / G
    inv_dx = 1.0 / dx
    offs = _OFFSETS.to(dev)
    xs = x * inv_dx
    # stencil base; clamped to [0, G - 3] like the Taichi solver so every node is on the grid
    base = torch.clamp(torch.floor(xs - 0.5).detach(), 0, G - 3)
    fx = xs - base  # [P, 3]
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], dim=1)  # [P, 3, 3] (o, axis)
    weight = w[:, offs[:, 0], 0] * w[:, offs[:, 1], 1] * w[:, offs[:, 2], 2]  # [P, 27]
    dpos = (offs[None].to(dtp) - fx[:, None, :]) * dx  # [P, 27, 3]
    node = base.long()[:, None, :] + offs[None]  # [P, 27, 3] in [0, G - 1]
    key = (node[..., 0] * G + node[..., 1]) * G + node[..., 2]
    uniq, inv = torch.unique(key.reshape(-1), return_inverse=True)  # only the M touched nodes
    M = uniq.shape[0]
    affine = -dt * p_vol[:, None, None] * 4.0 * inv_dx * inv_dx * tau + p_mass[:, None, None] * C  # [P, 3, 3]
    mom = p_mass[:, None, None] * v[:, None, :] + torch.einsum("pij,pkj->pki", affine, dpos)  # [P, 27, 3]
    grid_mv = x.new_zeros((M, 3)).index_add(0, inv, (weight[..., None] * mom).reshape(-1, 3))
    grid_m = x.new_zeros((M,)).index_add(0, inv, (weight * p_mass[:, None]).reshape(-1))
    has_mass = grid_m > 0
    gv = grid_mv / torch.where(has_mass, grid_m, torch.ones_like(grid_m))[:, None]
    g = torch.as_tensor(grid.gravity, dtype=dtp, device=dev)
    gv = torch.where(has_mass[:, None], gv + dt * g, torch.zeros_like(gv))
    gv = _walls(gv, uniq, G, grid)
    gvp = gv[inv].reshape(P, 27, 3)
    new_v = (weight[..., None] * gvp).sum(1)
    new_C = 4.0 * inv_dx * inv_dx * torch.einsum("pk,pki,pkj->pij", weight, gvp, dpos)
    new_x = x + dt * new_v
    I = _eye(P, F)
    F_trial = (I + dt * new_C) @ F
    return new_x, new_v, new_C, F_trial


def _walls(gv: torch.Tensor, uniq: torch.Tensor, G: int, grid: GridSpec) -> torch.Tensor:
    """Domain-wall boundary conditions on grid velocities.  # gv [M, 3], uniq [M] node keys"""
    k = uniq
    idx = torch.stack([k // (G * G), (k // G) % G, k % G], dim=-1)  # [M, 3]
    low = idx < grid.bound
    high = idx > G - grid.bound
    if grid.boundary == "sticky":
        wall = (low | high).any(-1, keepdim=True)
        return torch.where(wall, torch.zeros_like(gv), gv)
    out_of_domain = (low & (gv < 0)) | (high & (gv > 0))
    return torch.where(out_of_domain, torch.zeros_like(gv), gv)


def pseudo_step(state: dict, dt: float, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec) -> dict:
    """One differentiable MPM substep from a stored state, log E per instance as the leaf.

    state: domain units, each a tensor: x  # [P, 3], v  # [P, 3], C  # [P, 3, 3], F  # [P, 3, 3]
    log_E  # [K] natural log of Young's modulus (Pa) per instance
    returns {"x", "v", "C", "F"} after the substep (domain units) and "tau"  # [P, 3, 3] Pa, the
    Kirchhoff stress of the input state; "mu", "lam"  # [P]; "log_E_p"  # [P] = log_E[label]
    (differentiate with respect to it for per-particle derivatives).
    """
    L = float(grid.domain_size)
    F = state["F"]
    log_E_p = log_E[table.label]
    tau, mu, lam = particle_stress(F, log_E_p, table)
    p_vol = table.vol * L ** 3
    p_mass = table.density[table.label] * p_vol
    x, v, C, F_trial = mpm_step(state["x"] * L, state["v"] * L, state["C"], F, tau, p_mass, p_vol, dt, grid)
    F_new = plastic_projection(F_trial, mu, lam, table)
    return {"x": x / L, "v": v / L, "C": C, "F": F_new, "tau": tau, "mu": mu, "lam": lam, "log_E_p": log_E_p}


# ----------------------------------------------------------------------------- reference scales
@dataclass
class Scales:
    """Reference scales that make the BGDO signals dimensionless (module docs, "Units").

    pressure  # [K] Pa: E and the stress gradient are divided by it (E_hat, g_hat)
    modulus  # [K] Pa: the reference modulus E_ref the pressure was derived from
    deformation  # [K] or scalar: s_delta, delta is divided by it (deformation_signal difference)
    source: per instance, where E_ref came from; band: per instance the material's KB
    ``E_range`` [lo, hi] in Pa, or None when the material is not in the knowledge base.
    target  # [K] delta_target per instance (None: 0.1 for every instance)
    """

    pressure: np.ndarray
    modulus: np.ndarray
    deformation: np.ndarray | float
    source: list
    band: list
    target: np.ndarray | None = None

    def s_delta(self, k: int) -> float:
        return float(np.broadcast_to(np.asarray(self.deformation, np.float64), self.pressure.shape)[k])

    def delta_target(self, k: int) -> float:
        return 0.1 if self.target is None else float(self.target[k])


def reference_scales(instances: list[dict], bcfg: dict) -> Scales:
    """The reference scales of every instance (ordered by label) for config ``bcfg`` (section bgdo).

    delta_target per instance: ``bgdo.delta_target`` if it is a number, else (null, default)
    ``rho g h_ref / E_ref``: the strain that its own weight causes in an object of the
    reference height h_ref (``bgdo.reference_height``, 0.3 m) of this material at the material's
    reference modulus (h_ref 0.3 m: jelly 0.044, bread 0.010, rubber 0.010, stone 3.4e-4)."""

    by_label = {int(i["label"]): i for i in instances}
    K = len(by_label)
    fixed_target = bcfg.get("delta_target")
    ref_strain = float(bcfg.get("reference_strain", 0.1))
    h_ref = float(bcfg.get("reference_height", 0.3))
    modulus, pressure, source, band, target = [], [], [], [], []
    for k in range(K):
        inst = by_label[k]
        name = inst.get("material")
        entry = None
        if isinstance(name, str) and name.strip():
            try:
                entry = materials_kb.get_material(name)
            except ConfigError:
                entry = None
        band.append(list(entry["E_range"]) if entry else None)
        if bcfg["scaling"] == "si":
            modulus.append(1.0)
            pressure.append(1.0)
            target.append(0.1 if fixed_target is None else float(fixed_target))
            source.append("si: signals in Pa, literal reading of the paper")
            continue
        if entry is not None:
            lo, hi = entry["E_range"]
            e_ref = math.sqrt(lo * hi)
            src = f"knowledge base '{entry['name']}': geometric mean of E_range [{lo:.3g}, {hi:.3g}] Pa"
        else:
            e_ref = float(bcfg["reference_modulus"])
            src = f"bgdo.reference_modulus ({e_ref:.3g} Pa): material {name!r} is not in the knowledge base"
        p = bcfg.get("reference_pressure")
        modulus.append(e_ref)
        if p is None:
            pressure.append(ref_strain * e_ref)
        else:
            pressure.append(float(p))
            src += f"; pressure fixed by bgdo.reference_pressure = {float(p):.3g} Pa"
        if fixed_target is None:
            t = float(inst["density"]) * G_REF * h_ref / e_ref
            target.append(t)
            src += f"; delta_target = rho g h_ref / E_ref = {t:.3g}"
        else:
            target.append(float(fixed_target))
        source.append(src)
    target = np.asarray(target, np.float64)
    if bcfg["scaling"] == "si":
        sdelta = np.ones(K)
    else:
        sd = bcfg.get("deformation_scale")
        sdelta = target.copy() if sd is None else np.full(K, float(sd))
    return Scales(np.asarray(pressure, np.float64), np.asarray(modulus, np.float64), sdelta, source, band, target)


# ----------------------------------------------------------------------------- solver and load limits
def solver_ceiling(instances: list[dict], sim: dict, grid: "GridSpec") -> np.ndarray:
    """The largest E per instance (Pa, label order)  # [K] that the forward/final solver integrates
    at its own CFL number: the P-wave speed sqrt((lam + 2 mu) / rho) reaches sim.cfl * dx / dt at
    the smallest substep the config allows (frame_dt / sim.max_substeps, or sim.substep_dt in
    fixed mode). Above it the substep cap binds and the explicit step runs over its CFL number;
    from about twice the wave speed (4x this E) it explodes.

        E_cap = rho (cfl dx / dt_min)^2 (1 + nu)(1 - 2 nu) / (1 - nu)
    """
    from .mpm.timestep import TimeStepper

    stepper = TimeStepper.from_config(sim or {})
    n_max = stepper.fixed_substeps if stepper.mode == "fixed" else int(stepper.max_substeps)
    dt_min = stepper.frame_dt / n_max
    dx = grid.domain_size / grid.n_grid
    c_cap = stepper.cfl * dx / dt_min
    by_label = {int(i["label"]): i for i in instances}
    out = []
    for k in range(len(by_label)):
        i = by_label[k]
        nu, rho = float(i["nu"]), float(i["density"])
        out.append(rho * c_cap ** 2 * (1 + nu) * (1 - 2 * nu) / (1 - nu))
    return np.asarray(out, np.float64)


def static_stress(x0, label, instances: list[dict], grid: "GridSpec") -> np.ndarray:
    """The static stress rho |g| H_k (Pa) at the base of each instance under gravity  # [K]

    x0  # [P, 3] particle positions (domain units) at the first key frame; label  # [P].
    H_k is the extent of instance k along gravity in metres. With no gravity it is 0.
    The strain this stress causes at modulus E, rho |g| H / E, is the deformation BGDO assumes
    for an instance whose forward run failed (module docs, "Unstable forward runs")."""
    g = np.asarray(grid.gravity, np.float64)
    gn = float(np.linalg.norm(g))
    by_label = {int(i["label"]): i for i in instances}
    K = len(by_label)
    out = np.zeros(K)
    if gn == 0.0:
        return out
    x0 = np.asarray(x0, np.float64)
    label = np.asarray(label)
    ok = np.isfinite(x0).all(axis=1)
    h = x0[ok] @ (g / gn) * grid.domain_size
    lab = label[ok]
    for k in range(K):
        hk = h[lab == k]
        if hk.size:
            out[k] = float(by_label[k]["density"]) * gn * float(hk.max() - hk.min())
    return out


# ----------------------------------------------------------------------------- signals
def _finite_rows(*arrays: torch.Tensor) -> torch.Tensor:
    ok = None
    for a in arrays:
        r = torch.isfinite(a.reshape(a.shape[0], -1)).all(dim=1)
        ok = r if ok is None else ok & r
    return ok


def frame_signals(keyframe: dict, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec, scales: Scales,
                  device="cpu", dtype=torch.float32, measure: str = "stretch") -> list[dict]:
    """BGDO signals of one key frame: one pseudo step with log E as the leaf, per instance.

    keyframe: {"frame", "time", "dt", "x" [P, 3], "v" [P, 3], "C" [P, 3, 3], "F" [P, 3, 3]} (domain
    units, numpy or torch). log_E  # [K]. Returns one dict per instance (label order) with
    n_particles, n_exploded, tau_norm (mean ||tau|| Pa), stress_grad (mean d||tau_p||/dlogE Pa),
    stress_grad_hat (the same in units of the reference pressure, mean), g_tilde (mean over
    particles of log(1 + |g_hat_p|)) and delta, the mean deformation of the stepped F' by
    ``measure``: "stretch" ||F' - R'||_F = ||sigma' - 1|| (rotation removed) or "frobenius"
    ||F' - I||_F (both are recorded, as delta_stretch and delta_frobenius).

    A particle whose stored state is not finite or lies outside the domain [0, 1]^3 is "exploded":
    it takes no part in the step, its stress signal is +inf (so a frame with exploded particles
    asks for the largest allowed decrease of E), and it is left out of delta.
    """
    st = {k: torch.as_tensor(np.asarray(keyframe[k]), dtype=dtype, device=device) for k in ("x", "v", "C", "F")}
    ok = _finite_rows(st["x"], st["v"], st["C"], st["F"])
    ok &= ((st["x"] >= 0) & (st["x"] <= 1)).all(dim=1) if ok.numel() else ok
    idx = torch.nonzero(ok, as_tuple=True)[0]
    sub = table.select(idx)
    out = None
    if idx.numel():
        out = _step_signals({k: v[idx] for k, v in st.items()}, float(keyframe["dt"]), log_E, sub, grid, measure)
    head = {"frame": int(keyframe["frame"]), "time": float(keyframe["time"]), "dt": float(keyframe["dt"])}
    return [{**head, **_instance_signals(k, table, sub, out, float(scales.pressure[k]))}
            for k in range(table.n_instances)]


def _step_signals(st: dict, dt: float, log_E: torch.Tensor, sub: InstanceTable, grid: GridSpec, measure: str) -> dict:
    """Per-particle signals of one pseudo step from the finite particles ``st`` (each [P', ...]):
    g  # [P'] d||tau_p||/dlog E, tau  # [P'] ||tau_p||, delta_frobenius, delta_stretch  # [P'] and
    delta (the one ``measure`` names). The graph is freed before returning."""
    leaf = log_E.detach().to(device=st["x"].device, dtype=torch.float64).clone().requires_grad_(True)
    res = pseudo_step(st, dt, leaf, sub, grid)
    s_p = res["tau"].flatten(1).norm(dim=1)  # ||tau_p||_F (Pa)
    g_p, = torch.autograd.grad(s_p.sum(), [res["log_E_p"]])  # d||tau_p|| / d log E_k(p)
    Fn = res["F"].detach()
    d_frob = (Fn - torch.eye(3, dtype=Fn.dtype, device=Fn.device)).flatten(1).norm(dim=1)
    d_str = torch.full_like(d_frob, math.nan)
    fin = torch.isfinite(Fn.flatten(1)).all(dim=1)
    if bool(fin.any()):
        _, sig, _ = svd3(Fn[fin])
        d_str[fin] = (sig - 1.0).norm(dim=1)
    return {"g": g_p.detach(), "tau": s_p.detach(), "delta_frobenius": d_frob, "delta_stretch": d_str,
            "delta": d_str if measure == "stretch" else d_frob}


def _instance_signals(k: int, table: InstanceTable, sub: InstanceTable, out: dict | None, p_ref: float) -> dict:
    """Instance k's means of the per-particle signals ``out`` (particles of ``sub``)."""
    none = dict(tau_norm=None, stress_grad=None, delta=None, delta_frobenius=None, delta_stretch=None)
    n_all = int((table.label == k).sum())
    if n_all == 0:
        return {"n_particles": 0, "n_exploded": 0, "stress_grad_hat": None, "g_tilde": None, **none}
    fin = torch.zeros(0, dtype=torch.bool)
    if out is not None:
        mk = sub.label == k
        sel = {name: v[mk] for name, v in out.items()}
        fin = torch.isfinite(sel["g"]) & torch.isfinite(sel["delta"])
    n_exploded = n_all - int(fin.sum())
    rec = {"n_particles": n_all, "n_exploded": n_exploded}
    if int(fin.sum()):
        ghat = sel["g"][fin].double().abs() / p_ref
        rec.update(tau_norm=float(sel["tau"][fin].double().mean()), stress_grad=float(sel["g"][fin].double().mean()),
                   **{name: float(sel[name][fin].double().mean()) for name in ("delta", "delta_frobenius", "delta_stretch")})
        ghat_mean, gt_mean = float(ghat.mean()), float(torch.log1p(ghat).mean())
    else:
        rec.update(none)
        ghat_mean, gt_mean = 0.0, 0.0
    if n_exploded:  # log(1 + inf) = inf: the mean over particles is +inf
        ghat_mean, gt_mean = math.inf, math.inf
    rec["stress_grad_hat"] = ghat_mean
    rec["g_tilde"] = gt_mean
    return rec


def bgdo_signals(keyframes, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec, scales: Scales,
                 device="cpu", dtype=torch.float32, log=None, measure: str = "stretch") -> list[list[dict]]:
    """Signals of every key frame; ``keyframes`` is an iterable of key-frame dicts (see
    :func:`frame_signals`) consumed one at a time, so only one frame and one step's graph are
    in memory. Returns ``[frame][instance]`` records."""
    frames = []
    for kf in keyframes:
        rows = frame_signals(kf, log_E, table, grid, scales, device=device, dtype=dtype, measure=measure)
        frames.append(rows)
        if log is not None:
            log.info("key frame %d: %s", rows[0]["frame"] if rows else -1,
                     "; ".join(f"[{k}] g~={r['g_tilde']:.4g} delta={r['delta'] if r['delta'] is None else round(r['delta'], 5)} "
                               f"exploded={r['n_exploded']}" for k, r in enumerate(rows) if r["g_tilde"] is not None))
    return frames


def wave_speeds(instances: list[dict]) -> np.ndarray:
    """P-wave speed sqrt((lam + 2 mu) / rho) in m/s per instance (label order)  # [K]"""
    by_label = {int(i["label"]): i for i in instances}
    out = []
    for k in range(len(by_label)):
        i = by_label[k]
        E, nu, rho = float(i["E"]), float(i["nu"]), float(i["density"])
        mu = E / (2 * (1 + nu))
        lam = E * nu / ((1 + nu) * (1 - 2 * nu))
        out.append(math.sqrt((lam + 2 * mu) / rho))
    return np.asarray(out)


def _failing_instances(message, names: list) -> list | None:
    """Indices of the instances a forward run's failure message names, or None if it names none.

    The forward stage records the failure as text (physgs_steps.mpm.stability.explain:
    "... in instance '<name>' (...) (also affected: '<a>', '<b>')")."""
    import re

    if not isinstance(message, str):
        return None
    found = re.findall(r"in instance '([^']+)'", message)
    also = re.search(r"\(also affected: ([^)]*)\)", message)
    if also:
        found += re.findall(r"'([^']+)'", also.group(1))
    idx = sorted({k for k, n in enumerate(names) if n in found})
    return idx or None


def unstable_run_info(meta: dict, instances: list[dict], grid: GridSpec, cfl_limit: float) -> dict:
    """What an unstable forward run says about each instance.

    The forward stage stops at the first unstable frame and stores the last stable frame in
    place of the key frames it could not reach (``substitute_for``). Returns {"stable",
    "missing": those key frames, "cfl": [K] CFL number c_k dt / dx of each instance in the
    failing frame (None if unknown), "fate": [K] "ok" | "exploded" | "broken",
    "delta_broken": the deformation of a broken state}. An instance is "exploded" when its CFL
    number exceeded ``cfl_limit`` (the explicit step was unstable for its stiffness: too stiff
    for the substep cap); otherwise, when the failure names it (collapse J < j_min, tearing,
    splashing out), it is "broken": it could not carry the load (too soft). ``delta_broken`` =
    sqrt(3) (1 - j_min^(1/3)) is the deformation ||sigma - 1|| of an isotropic collapse to the
    forward run's stability limit J = sim.stability.j_min, the least deformation it calls a
    collapse.
    """
    stats = meta.get("stats") or {}
    stored = [fr[1] for fr in meta["frames"]]
    missing = sorted({m for fr in meta["frames"] for m in fr[4]} - set(stored))
    K = len(instances)
    sim_cfg = meta.get("sim_config") or {}
    j_min = ((sim_cfg.get("sim") or {}).get("stability") or {}).get("j_min", 0.05)
    info = {"stable": stats.get("stable", True) is not False, "missing": missing, "cfl": None,
            "fate": ["ok"] * K, "delta_broken": math.sqrt(3.0) * (1.0 - float(j_min) ** (1.0 / 3.0)),
            "failure": stats.get("failure")}
    if info["stable"]:
        return info
    dts = stats.get("dt_per_frame") or []
    dx = sim_cfg.get("dx") or grid.domain_size / grid.n_grid
    if dts:
        cfl = wave_speeds(instances) * float(dts[-1]) / float(dx)
        info["cfl"] = [float(c) for c in cfl]
        info["fate"] = ["exploded" if c > cfl_limit else "ok" for c in cfl]
    by_label = {int(i["label"]): i for i in instances}
    names = [str(by_label[k].get("name", "")) for k in range(K)]
    failing = _failing_instances(stats.get("failure"), names)
    if failing is None:  # the message names no instance: every instance not blamed on the CFL limit
        failing = list(range(K))
    for k in failing:
        if info["fate"][k] == "ok":
            info["fate"][k] = "broken"
    return info


def assemble_frames(frames: list[list[dict]], meta: dict, info: dict) -> list[list[dict]]:
    """Weight the per-frame records and add the key frames an unstable run never reached.

    Every stored key frame that was requested counts once (the last stable frame an unstable
    run stores in place of the missing ones counts only if it was requested itself). For an
    "exploded" instance every missing key frame is an exploded state: all particles diverged,
    the compressed stress signal is +inf (the paper's log(1 + |g|) of a diverged stress) and the
    deformation undefined. For a "broken" instance every missing key frame is a collapsed state
    with the last stable frame's stress signal and the deformation max(``info["delta_broken"]``,
    the static strain ``info["static_delta"][k]`` = rho |g| H / E when given): a collapse shows
    at least the collapse deformation, and an object far too soft to carry its own weight
    would have deformed by its static strain had the run not stopped. An instance the failure
    did not involve ("ok" in an unstable run) gets nothing for the missing key frames: the run
    ended before they could show its behaviour (the last stable frame of a run that broke at
    impact shows an object still falling); if it is left with no stored key frame after frame 0
    (the rest state), it is "broken" too when its static strain exceeds the collapse
    deformation (it cannot carry its own weight; ``info["fate"]`` is updated), else it has no
    evidence and :func:`bgdo_update` leaves its E unchanged (``no_evidence``). Returns
    ``[frame][instance]`` records with a ``weight``."""
    stats = meta.get("stats") or {}
    requested = stats.get("key_frames_requested")
    fate = info["fate"]
    out = []
    last = {}
    for fr, rows in zip(meta["frames"], frames):
        frame, subs = fr[1], fr[4]
        own = 1 if (requested is None or frame in requested or not subs) else 0
        new_rows = []
        for k, r in enumerate(rows):
            new_rows.append({**r, "frame": frame, "weight": own, "substitute_for": list(subs)})
            last[k] = r
        out.append(new_rows)
    static = info.get("static_delta")
    if not info["stable"]:
        for k, f in enumerate(fate):
            informative = [rows[k] for rows in out if rows[k]["weight"] > 0 and rows[k]["frame"] > 0]
            if f == "ok" and not informative:
                if static is not None and static[k] > info["delta_broken"]:
                    # it cannot carry its own weight: the static strain alone is beyond a collapse
                    fate[k] = "broken"
                    info.setdefault("fate_reason", {})[k] = (
                        f"static strain rho |g| H / E = {static[k]:.3g} > collapse deformation {info['delta_broken']:.3g}")
                    continue
                for rows in out:
                    rows[k]["no_evidence"] = True
    if any(f != "ok" for f in fate):
        for m in info["missing"]:
            rows = []
            for k, f in enumerate(fate):
                r = last[k]
                base = {"frame": m, "time": None, "dt": None, "n_particles": r["n_particles"], "tau_norm": None,
                        "stress_grad": None, "delta_frobenius": None, "delta_stretch": None, "substitute_for": [],
                        "missing": f}
                if f == "exploded":
                    rows.append({**base, "n_exploded": r["n_particles"], "stress_grad_hat": math.inf,
                                 "g_tilde": math.inf, "delta": None, "weight": 1})
                elif f == "broken":
                    d = max(info["delta_broken"], 0.0 if r["delta"] is None else r["delta"],
                            0.0 if static is None else float(static[k]))
                    rows.append({**base, "n_exploded": 0, "stress_grad_hat": r["stress_grad_hat"],
                                 "g_tilde": r["g_tilde"], "delta": d, "weight": 1})
                else:
                    rows.append({**base, "n_exploded": 0, "stress_grad_hat": None, "g_tilde": None, "delta": None,
                                 "weight": 0, "no_evidence": bool(out[0][k].get("no_evidence"))})
            out.append(rows)
    return out


# ----------------------------------------------------------------------------- update
def eta_value(E: float, pressure: float, bcfg: dict) -> tuple[float, float]:
    """(eta, E_hat): the guidance weight for modulus E (Pa) and reference pressure (Pa)."""
    E_hat = E / pressure
    if bcfg["eta_rule"] == "constant":
        return float(bcfg["eta_constant"]), E_hat
    return min(1.0, float(bcfg["eta_coefficient"]) * math.log1p(E_hat)), E_hat


def _instance_step(frames_k: list[dict], eta: float, bcfg: dict, sdelta: float, target: float) -> tuple[float, list]:
    """(G, per-frame terms) for one instance from its per-frame records."""
    usable = [r for r in frames_k if r["g_tilde"] is not None and r.get("weight", 1) > 0]
    if not usable or any(r.get("no_evidence") for r in frames_k):
        return math.nan, []
    W = float(sum(r.get("weight", 1) for r in usable))

    def stress_term(x):  # eta * x with eta * inf = inf for eta > 0
        return math.inf if math.isinf(x) and eta > 0 else eta * x

    if bcfg["variant"] == "main_text":
        g_tau = sum(r.get("weight", 1) * r["stress_grad_hat"] for r in usable) / W
        dl = [(r.get("weight", 1), r["delta"]) for r in usable if r["delta"] is not None]
        d_F = (sum(w * d for w, d in dl) / sum(w for w, _ in dl)) / sdelta if dl else 0.0
        G = stress_term(math.log1p(g_tau)) - (1.0 - eta) * d_F
        return G, [{"frame": r["frame"], "weight": r.get("weight", 1)} for r in usable]
    if bcfg.get("deformation_signal", "log_ratio") == "difference":
        terms = []
        for r in usable:
            dterm = 0.0 if r["delta"] is None else (1.0 - eta) * (r["delta"] - target) / sdelta
            terms.append({"frame": r["frame"], "weight": r.get("weight", 1), "term": stress_term(r["g_tilde"]) - dterm})
        return sum(t["weight"] * t["term"] for t in terms) / W, terms
    # log_ratio: the stress term averaged over all key frames, the deformation term
    # log(delta / delta_target) over the key frames after the rest state (frame 0: F = I)
    floor = target * DELTA_FLOOR
    terms = [{"frame": r["frame"], "weight": r.get("weight", 1), "stress": stress_term(r["g_tilde"]),
              "log_ratio": (math.log(max(r["delta"], floor) / target)
                            if r["delta"] is not None and r["frame"] > 0 else None)} for r in usable]
    S = sum(t["weight"] * t["stress"] for t in terms) / W
    dfr = [t for t in terms if t["log_ratio"] is not None]
    Wd = float(sum(t["weight"] for t in dfr))
    D = sum(t["weight"] * t["log_ratio"] for t in dfr) / Wd if Wd > 0 else 0.0
    return S - (1.0 - eta) * D, terms


def bgdo_update(log_E, frames: list[list[dict]], scales: Scales, bcfg: dict,
                limits: dict | None = None) -> tuple[np.ndarray, list[dict]]:
    """One BGDO update of log E per instance from the key-frame signals.

    log_E  # [K] natural log of E (Pa); frames: ``[frame][instance]`` records of
    :func:`bgdo_signals` (after :func:`assemble_frames`). limits (optional): {"ceiling"  # [K]
    :func:`solver_ceiling` (Pa), "static_stress"  # [K] :func:`static_stress` (Pa), "fate": [K]
    of :func:`unstable_run_info`}. Returns (new log E  # [K], one record per instance with the
    signals, eta, E_hat, the step G, E before and after, and which rule set E).

    With ``failure_rule: static_load`` (default) an "exploded" instance goes to
    min(E_cap, static_stress / delta_target): the stiffest modulus the solver integrates, or
    the one at which its own weight strains it by the target, whichever is lower. With
    ``ceiling: true`` (default) no update raises E above max(E, E_cap).
    """
    log_E = np.asarray(torch.as_tensor(log_E).detach().cpu().double().numpy(), dtype=np.float64).reshape(-1)
    K = log_E.shape[0]
    max_step = bcfg.get("max_step")
    limits = limits or {}
    ceiling = limits.get("ceiling")
    sstress = limits.get("static_stress")
    fates = limits.get("fate") or ["ok"] * K
    new = log_E.copy()
    records = []
    for k in range(K):
        E = float(math.exp(log_E[k]))
        eta, E_hat = eta_value(E, float(scales.pressure[k]), bcfg)
        fk = [fr[k] for fr in frames]
        target = scales.delta_target(k)
        G, terms = _instance_step(fk, eta, bcfg, scales.s_delta(k), target)
        cap = None if ceiling is None else float(ceiling[k])
        rec = {"label": k, "E_before": E, "log_E_before": float(log_E[k]), "eta": eta, "E_hat": E_hat,
               "reference_pressure": float(scales.pressure[k]), "reference_modulus": float(scales.modulus[k]),
               "deformation_scale": scales.s_delta(k), "delta_target": target, "reference_source": scales.source[k],
               "band": scales.band[k], "fate": fates[k], "ceiling": cap,
               "static_stress": None if sstress is None else float(sstress[k]), "frames": fk, "terms": terms,
               "capped_by_ceiling": False, "rule": "signals"}
        if math.isnan(G):
            why = ("the forward run became unstable (other instances) before any key frame after frame 0"
                   if any(r.get("no_evidence") for r in fk) else "no particle of this instance in any key frame")
            rec.update(G=None, G_unclipped=None, clipped=False, E_after=E, log_E_after=float(log_E[k]),
                       note=f"{why}: E left unchanged", rule="unchanged")
        elif (fates[k] == "exploded" and bcfg.get("failure_rule", "static_load") == "static_load"
              and cap is not None and cap < E):
            s = 0.0 if sstress is None else float(sstress[k])
            E_new = cap if s <= 0 else min(cap, s / target)
            new[k] = math.log(E_new)
            rec.update(G=float(log_E[k] - new[k]), G_unclipped=None, clipped=False, E_after=E_new,
                       log_E_after=float(new[k]), rule=("exploded: min(E_cap, static stress / delta_target)"
                                                         if s > 0 else "exploded: E_cap"))
        else:
            if max_step is None and not math.isfinite(G):
                raise SimulationError(f"instance {k}: the forward simulation exploded (infinite stress signal) and "
                                      "bgdo.max_step is null, so the update of log E would be infinite; set "
                                      "bgdo.max_step (default ln 10000)")
            Gc = G if max_step is None else max(-float(max_step), min(float(max_step), G))
            new[k] = log_E[k] - Gc
            rec.update(G=Gc, G_unclipped=(None if math.isinf(G) else G), clipped=bool(Gc != G))
            if bcfg.get("ceiling", True) and cap is not None and new[k] > log_E[k] and new[k] > math.log(cap):
                new[k] = max(float(log_E[k]), math.log(cap))
                rec.update(capped_by_ceiling=True, G=float(log_E[k] - new[k]))
            rec.update(E_after=float(math.exp(new[k])), log_E_after=float(new[k]))
        band = scales.band[k]
        rec["in_band_before"] = None if band is None else bool(band[0] <= E <= band[1])
        rec["in_band_after"] = None if band is None else bool(band[0] <= rec["E_after"] <= band[1])
        records.append(rec)
    return new, records


# ----------------------------------------------------------------------------- key frames & files
def key_frame_indices(key_frames, n_frames: int) -> list[int]:
    """Frame indices of the key frames: ``round(f * (n_frames - 1))`` for every fraction f in
    ``key_frames`` (bgdo.key_frames, default [0, 0.5, 1] = initial, middle and last frame),
    sorted and without duplicates."""
    if n_frames < 1:
        raise ConfigError("sim.n_frames", f"must be >= 1, got {n_frames}")
    out = sorted({int(round(float(f) * (n_frames - 1))) for f in key_frames})
    return out


def read_keyframes_meta(path: str) -> dict:
    """Particles and key-frame index of a forward.h5 (CONTRACTS.md) without loading the states.

    Returns {"label" [P] int64, "vol" [P] f32, "frames": [(group name, frame, time, dt,
    substitute_for)] sorted by frame, "params": dict or None, "sim_config": dict or None,
    "stats": dict or None}. ``substitute_for`` lists the key frames an unstable forward run
    could not reach and for which this (last stable) frame stands in.
    """
    import json

    import h5py

    from .errors import InputError

    try:
        f = h5py.File(path, "r")
    except (OSError, FileNotFoundError) as e:
        raise InputError(path, f"cannot open as HDF5: {e}") from None
    with f:
        for key in ("particles/label", "particles/vol"):
            if key not in f:
                raise InputError(path, f"missing dataset '{key}' (forward.h5 format, docs/CONTRACTS.md)")
        label = np.asarray(f["particles/label"][...]).astype(np.int64)
        vol = np.asarray(f["particles/vol"][...], dtype=np.float32)
        P = label.shape[0]
        if vol.shape != (P,):
            raise InputError(path, f"particles/vol has shape {vol.shape}, expected ({P},)")
        if not np.all(np.isfinite(vol)) or np.any(vol <= 0):
            raise InputError(path, "particles/vol must be finite and > 0")
        if "keyframes" not in f or len(f["keyframes"]) == 0:
            raise InputError(path, "has no key frames (group 'keyframes' is missing or empty)")
        frames = []
        for name, g in f["keyframes"].items():
            for key in ("x", "v", "C", "F"):
                if key not in g:
                    raise InputError(path, f"key frame '{name}' lacks dataset '{key}'")
            shapes = {"x": (P, 3), "v": (P, 3), "C": (P, 3, 3), "F": (P, 3, 3)}
            for key, shp in shapes.items():
                if g[key].shape != shp:
                    raise InputError(path, f"keyframes/{name}/{key} has shape {g[key].shape}, expected {shp}")
            for a in ("frame", "time", "dt"):
                if a not in g.attrs:
                    raise InputError(path, f"key frame '{name}' lacks attribute '{a}'")
            dt = float(g.attrs["dt"])
            if not (math.isfinite(dt) and dt > 0):
                raise InputError(path, f"key frame '{name}' has dt = {dt}; expected a positive number of seconds")
            sub = g.attrs.get("substitute_for")
            sub = [] if sub is None else [int(v) for v in np.atleast_1d(sub)]
            frames.append((name, int(g.attrs["frame"]), float(g.attrs["time"]), dt, sub))
        frames.sort(key=lambda t: t[1])
        meta = {"label": label, "vol": vol, "frames": frames}
        for a in ("params", "sim_config", "stats"):
            raw = f.attrs.get(a)
            try:
                meta[a] = json.loads(raw) if raw is not None else None
            except (TypeError, ValueError):
                raise InputError(path, f"root attribute '{a}' is not valid JSON") from None
    return meta


def iter_keyframes(path: str, frames: list):
    """Yield key-frame dicts {"frame", "time", "dt", "x", "v", "C", "F"} one at a time."""
    import h5py

    for name, frame, time_, dt, _ in frames:
        with h5py.File(path, "r") as f:
            g = f["keyframes"][name]
            yield {"frame": frame, "time": time_, "dt": dt, **{k: g[k][...] for k in ("x", "v", "C", "F")}}


def resolve_device(cfg: dict) -> str:
    """'cpu' or 'cuda' from bgdo.device (null = the top-level ``device``; auto = CUDA if present)."""
    want = cfg.get("bgdo", {}).get("device") or cfg.get("device") or "auto"
    if want == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if want == "cuda" and not torch.cuda.is_available():
        raise ConfigError("bgdo.device", "is 'cuda' but torch finds no CUDA device; use 'cpu' or 'auto'")
    if want not in ("cpu", "cuda"):
        raise ConfigError("bgdo.device", f"must be auto, cpu or cuda, got {want!r}")
    return want


def grid_from_config(cfg: dict, sim_config: dict | None = None) -> GridSpec:
    """GridSpec from the forward simulation's recorded config (``sim_config`` of forward.h5:
    {"sim": {...}, "dynamics": {...}}, preferred) or cfg["sim"] and cfg["scene"]["dynamics"]:
    n_grid, domain size, gravity and domain walls (dynamics schema defaults filled)."""
    import copy

    from . import config as C

    sim = dict(cfg.get("sim") or {})
    rec = dict(sim_config or {})
    rec_sim = rec.get("sim") if isinstance(rec.get("sim"), dict) else rec  # forward.h5 nests the sim section
    n_grid = rec_sim.get("n_grid", sim.get("n_grid"))
    L = rec_sim.get("domain_size", sim.get("domain_size", 1.0))
    if not isinstance(n_grid, int) or n_grid < 8:
        raise ConfigError("sim.n_grid", f"must be an integer >= 8, got {n_grid!r}")
    if not isinstance(L, (int, float)) or not L > 0:
        raise ConfigError("sim.domain_size", f"must be a positive number of metres, got {L!r}")
    dyn = rec.get("dynamics") if isinstance(rec.get("dynamics"), dict) else (cfg.get("scene") or {}).get("dynamics")
    dyn = C.validate(copy.deepcopy(dyn or {}), C.load_schema("scene_dynamics.schema.yaml"), "scene", "dynamics")
    return GridSpec(n_grid=int(n_grid), domain_size=float(L), gravity=tuple(float(g) for g in dyn["gravity"]),
                    boundary=dyn["boundary"])


# ----------------------------------------------------------------------------- the stage
def _read_params(path: str) -> dict:
    from .errors import InputError
    from .runtime import read_json_input

    params = read_json_input(path, "params file")
    if not isinstance(params, dict) or not isinstance(params.get("instances"), list) or not params["instances"]:
        raise InputError(path, "expected an object with a non-empty 'instances' list (params.json, docs/CONTRACTS.md)")
    return params


def _check_same_E(params: dict, used: dict | None, path_kf: str, path_params: str) -> None:
    """The key frames must come from a simulation with exactly these moduli."""
    from .errors import InputError

    if not used or not isinstance(used.get("instances"), list):
        return
    mine = {int(i["label"]): float(i["E"]) for i in params["instances"]}
    theirs = {int(i["label"]): float(i["E"]) for i in used["instances"] if "label" in i and "E" in i}
    for k, E in mine.items():
        if k in theirs and not math.isclose(theirs[k], E, rel_tol=1e-6):
            raise InputError(path_kf, f"key frames were simulated with E = {theirs[k]:.6g} Pa for instance {k}, "
                                      f"but {path_params} has E = {E:.6g} Pa (stale forward simulation?)")


def run(inputs: dict, outputs: dict, cfg: dict, log) -> dict:
    """Stage bgdo_update: params_i + forward.h5 (key frames) -> params_{i+1}.

    inputs: {"keyframes": forward.h5, "params": params.json}; outputs: {"params": params.json}.
    cfg: {"bgdo": {...}, "sim": {...}, "scene": {...}, "device": ...}. Writes params.json with E
    updated, each instance's provenance set to bgdo, a record under "bgdo" and one appended to
    "history"; returns a summary (E before/after per instance, seconds per part, peak memory).
    """
    import copy
    import time

    from . import runtime

    t0 = time.perf_counter()
    bcfg = cfg["bgdo"]
    _check_config(bcfg)
    device = resolve_device(cfg)
    dtype = torch.float64 if bcfg.get("dtype") == "float64" else torch.float32
    params = _read_params(inputs["params"])
    meta = read_keyframes_meta(inputs["keyframes"])
    table = instance_table(params["instances"], meta["label"], meta["vol"], dtype=dtype, device=device,
                           source=inputs["params"])
    _check_same_E(params, meta.get("params"), inputs["keyframes"], inputs["params"])
    grid = grid_from_config(cfg, meta.get("sim_config"))
    scales = reference_scales(params["instances"], bcfg)
    log_E = log_E_from_instances(params["instances"], device=device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    log.info("BGDO on %s: %d particles, %d instances, %d key frames %s, variant %s, scaling %s",
             device, table.label.shape[0], table.n_instances, len(meta["frames"]),
             [fr[1] for fr in meta["frames"]], bcfg["variant"], bcfg["scaling"])
    t1 = time.perf_counter()
    first = {}  # x of the first key frame (the rest state), kept for the static load

    def keep_first(frames_):
        for kf in frames_:
            first.setdefault("x", kf["x"])
            yield kf

    frames = bgdo_signals(keep_first(iter_keyframes(inputs["keyframes"], meta["frames"])), log_E, table, grid, scales,
                          device=device, dtype=dtype, log=log, measure=bcfg["deformation_measure"])
    info = unstable_run_info(meta, params["instances"], grid, float(bcfg["cfl_limit"]))
    sstress = static_stress(first["x"], meta["label"], params["instances"], grid)
    E_now = np.exp(log_E.detach().cpu().double().numpy())
    info["static_delta"] = [float(s_ / e_) for s_, e_ in zip(sstress, E_now)]
    rec_sim = (meta.get("sim_config") or {}).get("sim") or cfg.get("sim") or {}
    ceiling = solver_ceiling(params["instances"], rec_sim, grid)
    log.info("static stress rho|g|H per instance %s Pa (static strain %s); solver ceiling E_cap %s Pa",
             [f"{v:.3g}" for v in sstress], [f"{v:.3g}" for v in info["static_delta"]], [f"{v:.3g}" for v in ceiling])
    if not info["stable"]:
        log.warning("the forward run was unstable (key frames %s not reached; CFL number per instance %s, "
                    "bgdo.cfl_limit %g): instance fates %s (exploded: too stiff for the substep cap; broken: "
                    "collapsed under its load; missing key frames count as such states)", info["missing"],
                    info["cfl"], float(bcfg["cfl_limit"]), info["fate"])
    frames = assemble_frames(frames, meta, info)
    t2 = time.perf_counter()
    new_log_E, records = bgdo_update(log_E, frames, scales, bcfg,
                                     limits={"ceiling": ceiling, "static_stress": sstress, "fate": info["fate"]})
    iteration = 1 + sum(1 for h in params.get("history") or [] if isinstance(h, dict) and h.get("stage") == "bgdo_update")
    out = copy.deepcopy(params)
    by_label = {int(i["label"]): i for i in out["instances"]}
    for rec in records:
        inst = by_label[rec["label"]]
        rec["E_before"] = float(inst["E"])  # exactly as read, not exp(log E)
        if rec["G"] is None:
            rec["E_after"] = rec["E_before"]
        rec["name"] = inst.get("name")
        rec["material"] = inst.get("material")
        inst["E"] = rec["E_after"]
        inst["provenance"] = {"source": "bgdo", "iteration": iteration, "E_before": rec["E_before"],
                              "E_after": rec["E_after"], "G": rec["G"], "previous": inst.get("provenance")}
        log.info("instance %d (%s, %s): E %.4g -> %.4g Pa (G = %s, eta = %.3f, E_hat = %.4g, delta_target %.3g, "
                 "rule: %s)%s%s", rec["label"], rec["name"], rec["material"], rec["E_before"], rec["E_after"],
                 "n/a" if rec["G"] is None else f"{rec['G']:.4f}", rec["eta"], rec["E_hat"], rec["delta_target"],
                 rec["rule"], " [clipped to max_step]" if rec["clipped"] else "",
                 " [held at the solver ceiling]" if rec["capped_by_ceiling"] else "")
    cuda_peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
    seconds = {"read": round(t1 - t0, 4), "signals": round(t2 - t1, 4), "total": round(time.perf_counter() - t0, 4)}
    record = {
        "iteration": iteration, "variant": bcfg["variant"], "scaling": bcfg["scaling"],
        "delta_target": bcfg["delta_target"], "deformation_measure": bcfg["deformation_measure"],
        "deformation_signal": bcfg.get("deformation_signal"), "failure_rule": bcfg.get("failure_rule"),
        "ceiling": bcfg.get("ceiling"), "eta_rule": bcfg["eta_rule"], "max_step": bcfg.get("max_step"),
        "static_stress": [float(v) for v in sstress], "static_delta": info["static_delta"],
        "solver_ceiling": [float(v) for v in ceiling], "fate_reason": {str(k): v for k, v in (info.get("fate_reason") or {}).items()},
        "device": device, "dtype": str(dtype).replace("torch.", ""),
        "forward_stable": info["stable"], "missing_key_frames": info["missing"], "forward_cfl": info["cfl"],
        "instance_fates": info["fate"], "delta_broken": info["delta_broken"],
        "key_frames": [fr[1] for fr in meta["frames"]], "grid": {"n_grid": grid.n_grid, "domain_size": grid.domain_size,
                                                                  "gravity": list(grid.gravity), "boundary": grid.boundary},
        "instances": records, "seconds": seconds,
        "peak_rss_mb": round(runtime.peak_rss_mb(), 1), "cuda_peak_mb": None if cuda_peak is None else round(cuda_peak, 1),
        "forward_stats": meta.get("stats"),
    }
    out["bgdo"] = record
    out.setdefault("history", [])
    out["history"].append({"stage": "bgdo_update", "iteration": iteration, "keyframes": str(inputs["keyframes"]),
                           "E_before": {str(r["label"]): r["E_before"] for r in records},
                           "E_after": {str(r["label"]): r["E_after"] for r in records},
                           "G": {str(r["label"]): r["G"] for r in records}})
    runtime.write_json(outputs["params"], out)
    log.info("wrote %s (BGDO iteration %d, %.2f s, peak RSS %.0f MiB%s)", outputs["params"], iteration,
             seconds["total"], record["peak_rss_mb"], "" if cuda_peak is None else f", CUDA peak {cuda_peak:.0f} MiB")
    return {"iteration": iteration, "E_before": [r["E_before"] for r in records],
            "E_after": [r["E_after"] for r in records], "seconds_parts": seconds,
            "cuda_peak_mb": record["cuda_peak_mb"]}


def _check_config(bcfg: dict) -> None:
    """Range checks beyond the schema (the schema has already filled defaults)."""
    for key in ("variant", "scaling", "eta_rule", "delta_target", "eta_coefficient", "reference_modulus", "cfl_limit",
                "deformation_measure", "max_step"):
        if key not in bcfg:
            raise ConfigError(f"bgdo.{key}", "missing (pass the section through config.section_defaults('bgdo'))")
    if bcfg["variant"] not in ("algorithm1", "main_text"):
        raise ConfigError("bgdo.variant", f"must be algorithm1 or main_text, got {bcfg['variant']!r}")
    if bcfg["scaling"] not in ("reference", "si"):
        raise ConfigError("bgdo.scaling", f"must be reference or si, got {bcfg['scaling']!r}")
    if bcfg.get("deformation_measure") not in ("stretch", "frobenius"):
        raise ConfigError("bgdo.deformation_measure", f"must be stretch or frobenius, got {bcfg.get('deformation_measure')!r}")
    if bcfg["eta_rule"] not in ("paper", "constant"):
        raise ConfigError("bgdo.eta_rule", f"must be paper or constant, got {bcfg['eta_rule']!r}")
    if bcfg.get("deformation_signal", "log_ratio") not in ("log_ratio", "difference"):
        raise ConfigError("bgdo.deformation_signal", f"must be log_ratio or difference, got {bcfg.get('deformation_signal')!r}")
    if bcfg.get("failure_rule", "static_load") not in ("static_load", "max_step"):
        raise ConfigError("bgdo.failure_rule", f"must be static_load or max_step, got {bcfg.get('failure_rule')!r}")
    if not isinstance(bcfg.get("ceiling", True), bool):
        raise ConfigError("bgdo.ceiling", f"must be true or false, got {bcfg.get('ceiling')!r}")
    for key in ("eta_coefficient", "reference_modulus", "cfl_limit", "reference_strain", "reference_height"):
        if key not in bcfg:
            continue
        v = bcfg[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ConfigError(f"bgdo.{key}", f"must be a positive number, got {v!r}")
    for key in ("reference_pressure", "deformation_scale", "max_step", "delta_target"):
        v = bcfg.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0):
            raise ConfigError(f"bgdo.{key}", f"must be a positive number or null, got {v!r}")
    ec = bcfg.get("eta_constant", 0.5)
    if isinstance(ec, bool) or not isinstance(ec, (int, float)) or not 0 <= ec <= 1:
        raise ConfigError("bgdo.eta_constant", f"must lie in [0, 1], got {ec!r}")
