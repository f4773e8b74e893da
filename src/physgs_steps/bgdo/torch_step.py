"""The torch mirror of one MLS-MPM substep (docs/CONTRACTS.md "MPM step"): constitutive laws,
return maps, the per-instance material table and the differentiable pseudo step BGDO runs
from a stored key frame.  Overview: :mod:`physgs_steps.bgdo`."""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .. import materials_kb
from ..mpm.colliders import COVER, FRINGE_SOFT, FRONT_BAND, GHOST_BAND, MIRROR_MASS, TOUCH, face_half_width
from ..mpm.material import FLIP_RATIO

# ----------------------------------------------------------------------------- model names
ELASTICITY = materials_kb.ELASTICITY_MODELS  # canonical names, docs/CONTRACTS.md
PLASTICITY = materials_kb.PLASTICITY_MODELS

SIG_FLOOR = 1e-6  # logs use log(max(sig, 1e-6)) (CONTRACTS.md, SVD convention)
J_FLOOR = 1e-6    # neo-Hookean: J clamped to >= 1e-6 inside the log
SVD_GAP = 1e-6    # smallest |s_j^2 - s_i^2| used in the SVD backward (repeated singular values)


def canonical_elasticity(name: str, key: str = "elasticity") -> str:
    """The canonical elasticity name for ``name`` (any spelling materials_kb accepts, e.g. the
    alias ``sigma`` -> stvk_hencky); ConfigError naming ``key`` if unknown."""
    return materials_kb.normalize_elasticity(name, key)


def canonical_plasticity(name: str, key: str = "plasticity") -> str:
    """The canonical plasticity name for ``name`` (``sigma`` -> j_clamp); ConfigError if unknown."""
    return materials_kb.normalize_plasticity(name, key)


# ----------------------------------------------------------------------------- SVD
JACOBI_SWEEPS = 6  # cyclic Jacobi sweeps of the 3x3 eigenproblem (float64 round-off after 5, tests/test_bgdo.py)


def det3(F: torch.Tensor) -> torch.Tensor:
    """Determinant of 3x3 matrices by cofactors (differentiable).  # F [..., 3, 3] -> [...]

    Element-wise only: no LAPACK/cuSOLVER call (``torch.linalg.det`` loads cuSOLVER or MAGMA on
    CUDA, seconds on the first call of a process)."""
    return (F[..., 0, 0] * (F[..., 1, 1] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 1])
            - F[..., 0, 1] * (F[..., 1, 0] * F[..., 2, 2] - F[..., 1, 2] * F[..., 2, 0])
            + F[..., 0, 2] * (F[..., 1, 0] * F[..., 2, 1] - F[..., 1, 1] * F[..., 2, 0]))


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Batched 3x3 product element-wise (no BLAS).  # [B, 3, 3] x [B, 3, 3] -> [B, 3, 3]"""
    return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)


def svd3_jacobi(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """SVD of 3x3 matrices with proper rotations, by element-wise torch operations only.

    V: eigenvectors of A^T A by cyclic Jacobi rotations, sorted by eigenvalue (descending),
    det V = +1; then Givens QR of A V = U R gives U (a product of rotations, det +1) and the
    singular values diag(R) (the last one carries the sign of det A), as in McAdams et al.,
    "Computing the singular value decomposition of 3x3 matrices with minimal branching and
    elementary floating point operations" (2011).  Same convention as the LAPACK path it
    replaces (CONTRACTS.md): sig descending in magnitude, sig[2] < 0 iff det A < 0.

    Args:
        A: [B, 3, 3] float64.

    Returns:
        U [B, 3, 3], sig [B, 3], V [B, 3, 3] with A = U diag(sig) V^T.
    """
    n = A.shape[0]
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    AtA = _mm(A.transpose(-1, -2), A)  # [B, 3, 3] symmetric
    S = [[AtA[:, i, j] for j in range(3)] for i in range(3)]  # entries [B]
    one, zero = torch.ones_like(S[0][0]), torch.zeros_like(S[0][0])
    Vl = [[one if i == j else zero for j in range(3)] for i in range(3)]
    for _ in range(JACOBI_SWEEPS):
        for p, q in ((0, 1), (0, 2), (1, 2)):
            theta = 0.5 * torch.atan2(2.0 * S[p][q], S[q][q] - S[p][p])  # zeroes S[p][q]
            c, s = torch.cos(theta), torch.sin(theta)
            for M in (S, Vl):  # M <- M J (columns p, q)
                for i in range(3):
                    mp, mq = M[i][p], M[i][q]
                    M[i][p], M[i][q] = c * mp - s * mq, s * mp + c * mq
            for j in range(3):  # S <- J^T S (rows p, q)
                mp, mq = S[p][j], S[q][j]
                S[p][j], S[q][j] = c * mp - s * mq, s * mp + c * mq
    V = torch.stack([torch.stack(row, -1) for row in Vl], -2)  # [B, 3, 3]
    lam = torch.stack([S[0][0], S[1][1], S[2][2]], -1)  # [B, 3] eigenvalues sig^2
    order = torch.argsort(lam, dim=-1, descending=True)  # [B, 3]
    V = torch.gather(V, 2, order[:, None, :].expand(n, 3, 3))
    V[:, :, 2] = torch.where((det3(V) < 0)[:, None], -V[:, :, 2], V[:, :, 2])
    R = _mm(A, V)  # [B, 3, 3] -> upper triangular by Givens rotations from the left
    U = eye.expand(n, 3, 3).clone()
    tiny = torch.finfo(A.dtype).tiny
    for p, q, col in ((0, 1, 0), (0, 2, 0), (1, 2, 1)):
        a, b = R[:, p, col], R[:, q, col]
        r = torch.sqrt(a * a + b * b)
        ok = r > tiny
        c = torch.where(ok, a / torch.where(ok, r, 1.0), 1.0)[:, None]
        s = torch.where(ok, b / torch.where(ok, r, 1.0), 0.0)[:, None]
        Rp, Rq = R[:, p, :].clone(), R[:, q, :].clone()
        R[:, p, :], R[:, q, :] = c * Rp + s * Rq, -s * Rp + c * Rq
        Up, Uq = U[:, :, p].clone(), U[:, :, q].clone()
        U[:, :, p], U[:, :, q] = c * Up + s * Uq, -s * Up + c * Uq
    return U, torch.diagonal(R, dim1=-2, dim2=-1).clone(), V


def svd3_lapack(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`svd3_jacobi`'s result from ``torch.linalg.svd`` (LAPACK; cuSOLVER on CUDA) and
    the sign fix.  # A [B, 3, 3] float64 -> U [B, 3, 3], sig [B, 3], V [B, 3, 3]"""
    U, S, Vh = torch.linalg.svd(A)
    V = Vh.transpose(-1, -2).clone()
    U = U.clone()
    fu = det3(U) < 0
    fv = det3(V) < 0
    U[..., :, 2] = torch.where(fu[:, None], -U[..., :, 2], U[..., :, 2])
    V[..., :, 2] = torch.where(fv[:, None], -V[..., :, 2], V[..., :, 2])
    S = S.clone()
    S[:, 2] = torch.where(fu ^ fv, -S[:, 2], S[:, 2])
    return U, S, V


def svd3_method(device: torch.device) -> str:
    """``jacobi`` or ``lapack``: ``PHYSGS_SVD3`` when set, else Jacobi on CUDA (no cuSOLVER to
    load: its first call costs seconds per process; ~10 kernel launches per rotation instead)
    and LAPACK on the CPU (faster there)."""
    import os

    want = os.environ.get("PHYSGS_SVD3", "auto").strip().lower()
    if want in ("jacobi", "lapack"):
        return want
    return "jacobi" if device.type == "cuda" else "lapack"


class _SVD3(torch.autograd.Function):
    """Batched 3x3 SVD ``F = U diag(sig) V^T`` with U, V proper rotations (det +1).

    The forward pass runs in float64: :func:`svd3_jacobi` on CUDA (element-wise torch only: no
    cuSOLVER, whose loading made the first BGDO update of a GPU process seconds slower),
    :func:`svd3_lapack` on the CPU (``torch.linalg.svd`` plus the sign fix of CONTRACTS.md, a
    reflection moving into the last singular value); they agree to float64 round-off
    (tests/test_bgdo.py; ``PHYSGS_SVD3=jacobi|lapack`` picks one). The backward pass
    is the closed-form SVD derivative with the factor ``1 / (s_j^2 - s_i^2)`` kept finite for
    repeated singular values (F = I is the most common state in a simulation; torch's own
    backward returns NaN there).
    """

    @staticmethod
    def forward(ctx, F):  # F [B, 3, 3]
        A = F.detach().to(torch.float64)
        U, S, V = (svd3_jacobi if svd3_method(A.device) == "jacobi" else svd3_lapack)(A)
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
    J = det3(F)
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
    friction_angle: torch.Tensor  # [B] degrees (Drucker-Prager, Mohr-Coulomb)
    cohesion: torch.Tensor        # [B] dimensionless log-strain offset (Drucker-Prager, Mohr-Coulomb)
    j_min: torch.Tensor           # [B] (J-clamp)
    j_max: torch.Tensor           # [B] (J-clamp)
    fracture_strain: torch.Tensor     # [B] tension cut-off of tearing materials (inf: no tearing)
    fracture_softening: torch.Tensor  # [B] inelastic strain over which the damage grows to 1

    def subset(self, idx: torch.Tensor) -> "PlasticParams":
        return PlasticParams(*(getattr(self, k)[idx] for k in PLASTIC_KEYS))


PLASTIC_KEYS = ("yield_stress", "friction_angle", "cohesion", "j_min", "j_max", "fracture_strain", "fracture_softening")


# Plasticity models that return in principal space (U and V of the trial F kept; the Taichi
# models with svd_mode "needs"): their return map's plastic strain feeds a tearing material's ep.
PRINCIPAL_PLASTICITY = ("von_mises", "drucker_prager", "mohr_coulomb")
D_MAX = 0.95  # largest damage: a broken particle keeps 5% of its tensile stress (mpm/materials.py)


def fracture_step(F_ret: torch.Tensor, ep: torch.Tensor, pp: PlasticParams, F_trial: torch.Tensor | None = None,
                  principal: torch.Tensor | None = None) -> tuple:
    """Tearing after the return map (mpm/materials.py, class Fracture): the return map's
    equivalent plastic strain ``sqrt(2/3) |log sig(F_trial) - log sig(F_ret)|`` (rows where
    ``principal`` [B] bool: a PRINCIPAL_PLASTICITY model, and whose returned state is in mean
    tension, ``sum(log sig(F_ret)) > 0``) is added to ``ep``, then principal
    elastic Hencky strains above ``fracture_strain`` are cut off and added to ``ep``; the
    damage is ``min(ep / fracture_softening, D_MAX)``.
    F_ret  # [B, 3, 3]; ep  # [B]  ->  F  # [B, 3, 3], ep  # [B], d  # [B]"""
    U, sig, V = svd3(F_ret)
    e = torch.log(torch.clamp(sig, min=SIG_FLOOR))
    if F_trial is not None and principal is not None:
        e_trial = torch.log(torch.clamp(svd3(F_trial)[1], min=SIG_FLOOR))
        dp = math.sqrt(2.0 / 3.0) * torch.linalg.vector_norm(e_trial - e, dim=-1)
        ep = ep + torch.where(principal & (e.sum(-1) > 0.0), dp, torch.zeros_like(dp))
    cap = pp.fracture_strain[:, None]
    ep = ep + torch.clamp(e - cap, min=0.0).sum(-1)
    e = torch.minimum(e, cap)
    d = torch.clamp(ep / pp.fracture_softening, max=D_MAX)
    return U @ torch.diag_embed(torch.exp(e)) @ V.transpose(-1, -2), ep, d


def degrade(tau: torch.Tensor, F: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Stress of damaged particles: the tensile principal stresses fade by (1 - d), compression
    stays (principal frame U of F, where the isotropic models' tau is diagonal).
    tau, F  # [B, 3, 3], d  # [B] -> [B, 3, 3]"""
    U, _, _ = svd3(F)
    t = torch.diagonal(U.transpose(-1, -2) @ tau @ U, dim1=-2, dim2=-1)
    t = torch.clamp(t, max=0.0) + (1.0 - d)[:, None] * torch.clamp(t, min=0.0)
    return U @ torch.diag_embed(t) @ U.transpose(-1, -2)


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
        J = det3(F)
        Jc = torch.minimum(torch.maximum(J, pp.j_min), pp.j_max)
        return _signed_cbrt(Jc)[:, None, None] * I
    if model == "fluid":
        J = det3(F)
        return _signed_cbrt(J)[:, None, None] * I
    U, sig, V = svd3(F)
    eps = torch.log(torch.clamp(sig, min=SIG_FLOOR))
    if model == "von_mises":
        eps_hat = eps - eps.mean(-1, keepdim=True)
        n, unit = _safe_unit(eps_hat)
        dg = n - pp.yield_stress / (2.0 * mu)
        eps = torch.where((dg > 0)[:, None], eps - dg[:, None] * unit, eps)
        return U @ torch.diag_embed(torch.exp(eps)) @ V.transpose(-1, -2)
    if model == "mohr_coulomb":
        c = pp.cohesion[:, None]
        e = eps - c
        sphi = torch.tan(torch.deg2rad(pp.friction_angle))  # material.mc_sin_phi
        tr = e.sum(-1)
        e_hat = e - e.mean(-1, keepdim=True)
        hi, lo = e_hat.max(-1).values, e_hat.min(-1).values
        p = (2.0 * mu / 3.0 + lam) * tr  # mean Kirchhoff stress (< 0: compression)
        D = 2.0 * mu * ((hi - lo) + sphi * (hi + lo))
        scale = -2.0 * p * sphi / torch.where(D > 0, D, torch.ones_like(D))
        shrink = (D > 0) & (scale < 1.0)
        e_proj = torch.where(shrink[:, None], (tr / 3.0)[:, None] + scale[:, None] * e_hat, e)
        e = torch.where((tr >= 0)[:, None], torch.zeros_like(e), e_proj)
        return U @ torch.diag_embed(torch.exp(e + c)) @ V.transpose(-1, -2)
    # drucker_prager
    c = pp.cohesion[:, None]
    e = eps - c
    alpha = math.sqrt(2.0) / 3.0 * torch.tan(torch.deg2rad(pp.friction_angle))  # material.dp_alpha
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
    face  # [P] or None: how far in front of its centre each particle's face lies, domain units
    (where wall contact starts; colliders.face_half_width); None: half the cube root of its volume
    """

    label: torch.Tensor
    vol: torch.Tensor
    nu: torch.Tensor
    density: torch.Tensor
    elasticity: list
    plasticity: list
    plastic: PlasticParams
    names: list = field(default_factory=list)
    rigid: list = field(default_factory=list)   # K bools: instance moves as one rigid body
    fixed: list = field(default_factory=list)   # K bools: static geometry (callers leave its rows out)
    face: torch.Tensor | None = None             # [P] domain units (None: 0.5 vol^(1/3), lattice material)

    def is_rigid(self, k: int) -> bool:
        return bool(self.rigid[k]) if self.rigid else False

    @property
    def n_instances(self) -> int:
        return int(self.nu.shape[0])

    def select(self, idx: torch.Tensor) -> "InstanceTable":
        """The same instances with only the particles ``idx``  # [P'] int64."""
        return InstanceTable(self.label[idx], self.vol[idx], self.nu, self.density, list(self.elasticity),
                             list(self.plasticity), self.plastic, list(self.names), list(self.rigid), list(self.fixed),
                             None if self.face is None else self.face[idx])

    def to(self, device) -> "InstanceTable":
        p = self.plastic
        return InstanceTable(self.label.to(device), self.vol.to(device), self.nu.to(device), self.density.to(device),
                             list(self.elasticity), list(self.plasticity),
                             PlasticParams(*(getattr(p, k).to(device) for k in PLASTIC_KEYS)),
                             list(self.names), list(self.rigid), list(self.fixed),
                             None if self.face is None else self.face.to(device))

    @property
    def fractures(self) -> list:
        """Per instance: whether it tears (a finite fracture_strain)."""
        return [bool(math.isfinite(float(v))) for v in self.plastic.fracture_strain]


_PLASTIC_DEFAULTS = {"yield_stress": math.inf, "friction_angle": 30.0, "cohesion": 0.0, "j_min": 0.05, "j_max": 1.2,
                     "fracture_strain": math.inf, "fracture_softening": 0.2}


def instance_table(instances: list[dict], label, vol, dtype=torch.float32, device="cpu", source: str = "params.json",
                   rigid_bodies: bool = True, filled=None) -> InstanceTable:
    """Build the table from params.json ``instances`` (sorted by ``label``) and particle arrays.

    label  # [P] int instance id per particle (0..K-1)
    vol  # [P] particle volume, domain units^3
    filled  # [P] bool or None: particles.h5 ``filled``; a row that is not filled is a visible
    gaussian on the material's surface, its face at its centre (``face`` 0; colliders.py
    "Boundary placement", as the Taichi solver built by simulate.build_solver); None: every row
    is lattice material (face half its volume's cube root in front of its centre)
    rigid_bodies: honour the instances' ``rigid``/``fixed`` flags (sim.rigid_bodies; false is
    the ``no_rigid`` ablation: free rigid instances are deformable, fixed ones stay static).
    """
    from ..errors import InputError

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
    nu, rho, el, pl, names, rigid, fixed = [], [], [], [], [], [], []
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
        fixed.append(bool(inst.get("fixed")) and bool(inst.get("rigid")))
        rigid.append(bool(inst.get("rigid")) and (rigid_bodies or fixed[-1]))
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
    face = None
    if filled is not None:
        filled = np.asarray(filled, bool)
        if filled.shape != label_np.shape:
            raise InputError(source, f"filled has shape {filled.shape}, expected {label_np.shape} (one flag per particle)")
        face = t(face_half_width(vol, ~filled))
    return InstanceTable(
        label=torch.as_tensor(label_np.astype(np.int64), device=device),
        vol=t(vol), nu=t(nu), density=t(rho), elasticity=el, plasticity=pl,
        plastic=PlasticParams(*(t(pvals[k]) for k in PLASTIC_KEYS)),
        names=names, rigid=rigid, fixed=fixed, face=face,
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
    boundary: 'slip' | 'sticky' domain walls, planes ``wall_margin`` domain units inside the
    faces of the unit cube (physgs_steps.mpm.colliders).
    """

    n_grid: int
    domain_size: float = 1.0
    gravity: tuple = (0.0, 0.0, -9.8)
    boundary: str = "slip"
    wall_margin: float = 0.1


_OFFSETS = torch.tensor(list(itertools.product(range(3), repeat=3)), dtype=torch.int64)  # [27, 3]


def particle_stress(F: torch.Tensor, log_E_p: torch.Tensor, table: InstanceTable,
                    ep: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Kirchhoff stress of every particle from its instance's elasticity model, degraded by
    the damage of tearing instances.

    F  # [P, 3, 3]; log_E_p  # [P] log Young's modulus of each particle's instance;
    ep  # [P] accumulated inelastic strain (None: intact)
    returns tau  # [P, 3, 3] Pa, mu  # [P], lam  # [P]
    """
    E_p = torch.exp(log_E_p).to(F.dtype)
    mu, lam = lame(E_p, table.nu[table.label])
    tau = F.new_zeros(F.shape)  # rigid instances carry no stress
    for model in sorted(set(table.elasticity)):
        ks = [k for k, m in enumerate(table.elasticity) if m == model and not table.is_rigid(k)]
        idx = torch.nonzero(torch.isin(table.label, torch.as_tensor(ks, device=F.device)), as_tuple=True)[0]
        if idx.numel():
            tau = tau.index_copy(0, idx, kirchhoff(F[idx], mu[idx], lam[idx], model))
    idx = _fracturing(table, F.device)
    if ep is not None and idx.numel():
        pp = table.plastic.subset(table.label[idx])
        d = torch.clamp(ep[idx] / pp.fracture_softening, max=D_MAX)
        tau = tau.index_copy(0, idx, degrade(tau[idx], F[idx], d))
    return tau, mu, lam


def _fracturing(table: InstanceTable, device) -> torch.Tensor:
    """Indices of the particles of tearing instances.  # -> [P'] int64"""
    ks = [k for k, f in enumerate(table.fractures) if f]
    if not ks:
        return torch.zeros(0, dtype=torch.int64, device=device)
    return torch.nonzero(torch.isin(table.label, torch.as_tensor(ks, device=device)), as_tuple=True)[0]


def plastic_projection(F: torch.Tensor, mu: torch.Tensor, lam: torch.Tensor, table: InstanceTable) -> torch.Tensor:
    """Each particle's plasticity return map.  # F [P, 3, 3], mu, lam [P] -> [P, 3, 3]"""
    out = F
    pp = table.plastic.subset(table.label)
    for model in sorted(set(table.plasticity)):
        if model == "identity":
            continue
        ks = [k for k, m in enumerate(table.plasticity) if m == model and not table.is_rigid(k)]
        idx = torch.nonzero(torch.isin(table.label, torch.as_tensor(ks, device=F.device)), as_tuple=True)[0]
        if idx.numel():
            out = out.index_copy(0, idx, return_map(F[idx], mu[idx], lam[idx], pp.subset(idx), model))
    return out


def mpm_step(x, v, C, F, tau, p_mass, p_vol, dt: float, grid: GridSpec, rigid=None, body=None, cover=None,
             flip=None, p_face=None):
    """One MLS-MPM/APIC substep after the stress (CONTRACTS.md steps 1-4, without plasticity).

    All in SI: x  # [P, 3] m, v  # [P, 3] m/s at the state's time, C  # [P, 3, 3] 1/s,
    F  # [P, 3, 3], tau  # [P, 3, 3] Pa, p_mass  # [P] kg, p_vol  # [P] m^3.
    Leapfrog like the Taichi solver: the velocities are staggered by -dt/2 g before P2G, the
    grid kicks them by dt g, x drifts with the half-step velocity, and the returned v is the
    half-step velocity plus dt/2 g (the velocity at the new state's time).
    rigid  # [P] bool or None: these particles read the grid velocity before the wall
    conditions and are not projected onto the walls (rigid bodies meet boundaries as bodies).
    body  # [P] long: the rigid body of each row (-1: deformable), cover  # [B] kg: each body's
    covering node mass; with them the grid nodes the bodies cover move with them
    (:func:`_rigid_grid`, the Taichi solver's coupling) and rigid rows read their body's field.
    flip  # [P] or None: each row's FLIP share (CONTRACTS step 4, ``materials.FLIP_RATIO``; 0 for
    rigid rows): the velocity gains flip (v - the pre-force grid field at x).
    p_face  # [P] m or None: how far in front of its centre each particle's face lies (wall contact
    starts there; colliders.face_half_width); None: half the cube root of p_vol (lattice material).
    returns x, v, C, F_trial (each like the input)
    """
    P = x.shape[0]
    dev, dtp = x.device, x.dtype
    g = torch.as_tensor(grid.gravity, dtype=dtp, device=dev)
    v = v - 0.5 * dt * g
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
    gv = torch.where(has_mass[:, None], gv + dt * g, torch.zeros_like(gv))
    field = None
    covered = None
    if body is not None and bool((body >= 0).any()):
        gv, field, covered = _rigid_grid(gv, grid_m, uniq, inv.reshape(P, 27), weight, mom, p_mass, body, cover, G,
                                         dx, dt, g)
    # a wall acts on the nodes of (deformable) particles that touch it: a particle's face (p_face
    # beyond its centre: half its volume's cube root, 0 on the surface) within TOUCH cells of it (colliders.py)
    phi_p = torch.stack([sgn * (x[:, a] - pos) for a, sgn, pos in _wall_planes(G, dx, grid)], -1).min(-1).values
    if p_face is None:
        p_face = 0.5 * torch.pow(p_vol, 1.0 / 3.0)
    touch = phi_p - p_face < TOUCH * dx
    if rigid is not None:
        touch = touch & ~rigid
    engaged = torch.zeros(M, dtype=torch.bool, device=dev)
    if bool(touch.any()):
        engaged[inv.reshape(P, 27)[touch].reshape(-1)] = True
    gv_b = _walls(gv, grid_m, uniq, G, dx, grid, engaged, covered)
    gvp = gv_b[inv].reshape(P, 27, 3)
    if rigid is not None and bool(rigid.any()):
        gvp = torch.where(rigid[:, None, None], (gv if field is None else field)[inv].reshape(P, 27, 3), gvp)
    new_v = (weight[..., None] * gvp).sum(1)
    new_C = 4.0 * inv_dx * inv_dx * torch.einsum("pk,pki,pkj->pij", weight, gvp, dpos)
    new_x = x + dt * new_v
    if flip is not None and bool((flip > 0).any()):
        kin = p_mass[:, None, None] * (v[:, None, :] + torch.einsum("pij,pkj->pki", C, dpos))  # [P, 27, 3]
        grid_o = x.new_zeros((M, 3)).index_add(0, inv, (weight[..., None] * kin).reshape(-1, 3))
        v_o = grid_o / torch.where(has_mass, grid_m, torch.ones_like(grid_m))[:, None]
        v_old = (weight[..., None] * v_o[inv].reshape(P, 27, 3)).sum(1)
        new_v = new_v + flip.to(dtp)[:, None] * (v - v_old)
    new_x, new_v = _project_walls(new_x, new_v, rigid, dx, G, grid)
    I = _eye(P, F)
    F_trial = (I + dt * new_C) @ F
    return new_x, new_v + 0.5 * dt * g, new_C, F_trial


def _rigid_grid(gv, grid_m, uniq, inv, weight, mom, p_mass, body, cover, G: int, dx: float, dt: float, g):
    """The rigid bodies' grid projection of the Taichi solver (kernels.py, rigid.py "Coupling").

    gv  # [M, 3] node velocities (gravity applied), grid_m  # [M], uniq  # [M] node keys,
    inv  # [P, 27] node of each stencil entry, weight  # [P, 27], mom  # [P, 27, 3] the momenta
    transferred, body  # [P] long (-1: deformable), cover  # [B] kg.
    returns gv  # [M, 3] (the body's nodes: the soft material's own velocity, the body's field
    where there is none), field  # [M, 3] (the owning body's field; gv elsewhere) and covered  # [M] bool."""
    r = body >= 0
    idx = inv[r].reshape(-1)
    M = gv.shape[0]
    own = torch.zeros(M, dtype=torch.long, device=gv.device)
    own = own.scatter_reduce(0, idx, (body[r] + 1)[:, None].expand(-1, 27).reshape(-1), reduce="amax")
    rm = gv.new_zeros(M).index_add(0, idx, (weight[r] * p_mass[r, None]).reshape(-1))
    rmom = gv.new_zeros((M, 3)).index_add(0, idx, (weight[r][..., None] * mom[r]).reshape(-1, 3))
    rv = torch.where((rm > 0)[:, None], rmom / torch.where(rm > 0, rm, torch.ones_like(rm))[:, None] + dt * g,
                     torch.zeros_like(rmom))
    covered = (own > 0) & (rm >= cover[(own - 1).clamp(min=0)])
    xn = torch.stack([uniq // (G * G), (uniq // G) % G, uniq % G], -1).to(gv.dtype) * dx  # [M, 3]
    # the body's field from its own mass and momentum alone (the soft material on its nodes keeps
    # its own velocity; the Taichi solver's contact of soft material with the body, its level
    # set and reaction, kernels.py _body_contact, is not mirrored, as the bodies' contacts)
    m_n, v_n = rm, rv
    field = gv.clone()
    for b in range(int(cover.shape[0])):
        sel = own == b + 1
        if not bool(sel.any()):
            continue
        m, xb, vb = m_n[sel], xn[sel], v_n[sel]
        Mb = m.sum()
        c0 = (m[:, None] * xb).sum(0) / Mb
        rr = xb - c0
        Pb = (m[:, None] * vb).sum(0)
        Lc = (m[:, None] * torch.cross(rr, vb, dim=-1)).sum(0)
        eye = torch.eye(3, dtype=gv.dtype, device=gv.device)
        Ic = (m[:, None, None] * ((rr * rr).sum(-1)[:, None, None] * eye - rr[:, :, None] * rr[:, None, :])).sum(0)
        w = torch.linalg.solve(Ic, Lc)
        rel = xn - c0
        field = torch.where(sel[:, None], Pb / Mb + torch.cross(w.expand_as(rel), rel, dim=-1), field)
    soft = grid_m - rm
    own_soft = (grid_m[:, None] * gv - rm[:, None] * rv) / torch.where(soft > 0, soft, torch.ones_like(soft))[:, None]
    own_v = torch.where((soft > FRINGE_SOFT * grid_m)[:, None], own_soft, field)
    gv = torch.where((own > 0)[:, None], own_v, gv)
    return gv, field, covered


def _wall_planes(G: int, dx: float, grid: GridSpec):
    """The 6 walls in the Taichi solver's slot order: (axis, sign of the normal, plane position m)."""
    L = G * dx
    m = grid.wall_margin * grid.domain_size
    return [(a, s_, m if s_ > 0 else L - m) for a in range(3) for s_ in (1.0, -1.0)]


def _walls(gv: torch.Tensor, gm: torch.Tensor, uniq: torch.Tensor, G: int, dx: float, grid: GridSpec,
           engaged: torch.Tensor, covered: torch.Tensor | None = None) -> torch.Tensor:
    """Domain walls on the grid velocities with the ghost treatment of
    physgs_steps.mpm.colliders (linear extrapolation from the mirror point's velocity).
    gv  # [M, 3] velocities before the walls, gm  # [M] masses, uniq  # [M] node keys,
    engaged  # [M] bool: nodes a particle touching a wall transfers to (only they feel walls)."""
    dev, dtp = gv.device, gv.dtype
    idx = torch.stack([uniq // (G * G), (uniq // G) % G, uniq % G], dim=-1)  # [M, 3]
    xn = idx.to(dtp) * dx
    has = gm > 0
    dense_v = gv.new_zeros((G * G * G, 3)).index_copy(0, uniq, gv)
    # the mirror leaves out the nodes a free rigid body covers (kernels.py collider_funcs.ghost)
    dense_m = gv.new_zeros((G * G * G,)).index_copy(0, uniq, gm if covered is None else torch.where(covered, 0.0 * gm, gm))
    sticky = grid.boundary == "sticky"
    out = gv
    corners = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=dev)  # [8, 3]
    for a, sgn, pos in _wall_planes(G, dx, grid):
        n = torch.zeros(3, dtype=dtp, device=dev)
        n[a] = sgn
        phi = sgn * (xn[:, a] - pos)  # [M]
        near = has & engaged & (phi < FRONT_BAND * dx)  # behind the wall, or in front within the band
        if not bool(near.any()):
            continue
        behind = near & (phi < 0)
        # plain rule (fallback): sticky -> 0; slip walls are "separate" without friction
        un_own = out @ n
        plain = torch.zeros_like(out) if sticky else out - torch.clamp(un_own, max=0.0)[:, None] * n
        # ghost: mirror sample (trilinear over nodes with mass)
        d = (FRONT_BAND + 1.0) * dx  # axis-aligned: the mirror cube lies beyond the band
        xm = xn + (d - phi)[:, None] * n
        gpos = xm / dx
        b0 = torch.floor(gpos).long()
        fr = gpos - b0.to(dtp)
        nodes = b0[:, None, :] + corners[None]  # [M, 8, 3]
        inside = ((nodes >= 0) & (nodes < G)).all(-1)
        nk = (nodes[..., 0].clamp(0, G - 1) * G + nodes[..., 1].clamp(0, G - 1)) * G + nodes[..., 2].clamp(0, G - 1)
        wcor = torch.where(corners[None].bool(), fr[:, None, :], 1.0 - fr[:, None, :]).prod(-1)  # [M, 8]
        wcor = wcor * (inside & (dense_m[nk] > 0)).to(dtp)
        wsum = wcor.sum(1)
        ok = wsum > 1e-6
        # a ghost node reads its mirror only where the mirror's mean node mass is MIRROR_MASS of its own
        ok = ok & ((phi >= 0) | ((wcor * dense_m[nk]).sum(1) >= MIRROR_MASS * gm * wsum))
        vm = (wcor[..., None] * dense_v[nk]).sum(1) / torch.where(ok, wsum, torch.ones_like(wsum))[:, None]
        q = (phi / d)[:, None]
        un = vm @ n
        if sticky:
            ghost = q * vm
            front = q * vm
        else:
            ut = vm - un[:, None] * n
            approach = ut + q * un[:, None] * n  # no friction on the walls
            # leaving: the mirror's normal velocity, but no faster than the node's own (before any
            # wall): a ghost node does not pull material off the wall that still presses on it
            leave = ut + torch.minimum(un, torch.clamp(gv @ n, min=0.0))[:, None] * n
            ghost = torch.where((un < 0)[:, None], approach, leave)
            # in front: the normal part pushed up to the line through 0 and the mirror's (pushes only)
            target = q[:, 0] * torch.clamp(un, max=0.0)
            front = out + torch.clamp(target - un_own, min=0.0)[:, None] * n
        use_ghost = near & ok & (phi > -GHOST_BAND * dx)
        out = torch.where(use_ghost[:, None], torch.where(behind[:, None], ghost, front),
                          torch.where(near[:, None], plain, out))
    return out


def _project_walls(x, v, rigid, dx: float, G: int, grid: GridSpec):
    """Deformable particles behind a wall go back onto it and lose their velocity into it
    (sticky walls: all of it).  x, v  # [P, 3] m, m/s."""
    keep = torch.ones(x.shape[0], dtype=torch.bool, device=x.device) if rigid is None else ~rigid
    for a, sgn, pos in _wall_planes(G, dx, grid):
        phi = sgn * (x[:, a] - pos)
        hit = keep & (phi < 0)
        if not bool(hit.any()):
            continue
        x = x.clone()
        x[:, a] = torch.where(hit, x[:, a] - sgn * phi, x[:, a])
        if grid.boundary == "sticky":
            v = torch.where(hit[:, None], torch.zeros_like(v), v)
        else:
            un = sgn * v[:, a]
            v = v.clone()
            v[:, a] = torch.where(hit & (un < 0), v[:, a] - sgn * un, v[:, a])
    return x, v


def _skew(w: torch.Tensor) -> torch.Tensor:
    """[B, 3] -> [B, 3, 3] cross-product matrices."""
    z = torch.zeros_like(w[:, 0])
    return torch.stack([torch.stack([z, -w[:, 2], w[:, 1]], -1), torch.stack([w[:, 2], z, -w[:, 0]], -1),
                        torch.stack([-w[:, 1], w[:, 0], z], -1)], -2)


def rigid_projection(x_old, x, v, C, F, p_mass, dt: float, dx: float, label, bodies, F_old=None):
    """The rigid-body step of physgs_steps.mpm.rigid without contacts: each body's particles
    (rows of ``bodies``' instances) move with the body's rigid motion.

    x_old  # [P, 3] positions at the start of the substep (m; a rigid state), x, v, C  # after
    G2P (positions, velocities, affine matrices), F  # [P, 3, 3] after G2P (rows of other instances kept),
    F_old  # [P, 3, 3] at the start of the substep (the bodies' rotations; default F), p_mass  # [P].
    returns x, v, C, F  # the projected state of every particle (others unchanged)."""
    F_old = F if F_old is None else F_old
    x_new, v_new, C_new, F_new = x.clone(), v.clone(), C.clone(), F.clone()
    for k in bodies:
        sel = torch.nonzero(label == k, as_tuple=True)[0]
        if sel.numel() == 0:
            continue
        m = p_mass[sel]
        M = m.sum()
        c = (m[:, None] * x_old[sel]).sum(0) / M
        r = x_old[sel] - c
        vp, Cp = v[sel], C[sel]
        P_ = (m[:, None] * vp).sum(0)
        axial = torch.stack([Cp[:, 2, 1] - Cp[:, 1, 2], Cp[:, 0, 2] - Cp[:, 2, 0], Cp[:, 1, 0] - Cp[:, 0, 1]], -1)
        Lm = (m[:, None] * torch.cross(r, vp, dim=-1)).sum(0) + (m[:, None] * dx * dx / 4.0 * axial).sum(0)
        eye = torch.eye(3, dtype=x_old.dtype, device=x_old.device)
        I = (m[:, None, None] * ((r * r).sum(-1)[:, None, None] * eye - r[:, :, None] * r[:, None, :])).sum(0)
        I = I + M * dx * dx / 2.0 * eye
        V = P_ / M
        w = torch.linalg.solve(I, Lm)
        th = torch.linalg.norm(w) * dt
        Q = eye.clone()
        if float(th) > 1e-14:
            kx = _skew((w / torch.linalg.norm(w))[None])[0]
            Q = eye + torch.sin(th) * kx + (1.0 - torch.cos(th)) * kx @ kx
        r_new = r @ Q.T
        w_new = Q @ torch.linalg.solve(I, Q.T @ Lm)  # (Q I Q^T)^-1 L: angular momentum kept in the new pose
        x_new[sel] = c + dt * V + r_new
        v_new[sel] = V + torch.cross(w_new.expand_as(r_new), r_new, dim=-1)
        C_new[sel] = _skew(w_new[None]).expand(sel.numel(), 3, 3)
        F_new[sel] = Q @ F_old[sel]
    return x_new, v_new, C_new, F_new


def pseudo_step(state: dict, dt: float, log_E: torch.Tensor, table: InstanceTable, grid: GridSpec) -> dict:
    """One differentiable MPM substep from a stored state, log E per instance as the leaf.

    state: domain units, each a tensor: x  # [P, 3], v  # [P, 3], C  # [P, 3, 3], F  # [P, 3, 3],
    optional ep  # [P] accumulated inelastic strain of tearing instances (default 0)
    log_E  # [K] natural log of Young's modulus (Pa) per instance
    returns {"x", "v", "C", "F", "ep"} after the substep (domain units) and "tau"  # [P, 3, 3] Pa, the
    Kirchhoff stress of the input state; "mu", "lam"  # [P]; "log_E_p"  # [P] = log_E[label]
    (differentiate with respect to it for per-particle derivatives).  Rigid instances carry no
    stress and move with their body's rigid motion (:func:`rigid_projection`); rows of fixed
    instances (static geometry, not in the MPM) must be left out by the caller.
    """
    L = float(grid.domain_size)
    F = state["F"]
    ep = state.get("ep")
    ep = F.new_zeros(F.shape[0]) if ep is None else ep.to(F.dtype)
    log_E_p = log_E[table.label]
    tau, mu, lam = particle_stress(F, log_E_p, table, ep)
    p_vol = table.vol * L ** 3
    p_mass = table.density[table.label] * p_vol
    bodies = [k for k in range(table.n_instances) if table.is_rigid(k)]
    rigid = torch.isin(table.label, torch.as_tensor(bodies, dtype=table.label.dtype, device=F.device)) if bodies else None
    x0 = state["x"] * L
    body = cover = None
    if bodies:
        body = torch.full_like(table.label, -1)
        for b, k in enumerate(bodies):
            body = torch.where(table.label == k, torch.full_like(body, b), body)
        dx = L / grid.n_grid
        cover = torch.stack([COVER * table.density[k] * dx ** 3 for k in bodies]).to(F.dtype)
    ratio = torch.as_tensor([0.0 if table.is_rigid(k) else FLIP_RATIO.get(table.plasticity[k], 0.0)
                             for k in range(table.n_instances)], dtype=F.dtype, device=F.device)
    p_face = None if table.face is None else table.face * L
    x, v, C, F_trial = mpm_step(x0, state["v"] * L, state["C"], F, tau, p_mass, p_vol, dt, grid, rigid, body, cover,
                                ratio[table.label], p_face)
    F_new = plastic_projection(F_trial, mu, lam, table)
    idx = _fracturing(table, F.device)
    if idx.numel():
        ks = [k for k, m in enumerate(table.plasticity) if m in PRINCIPAL_PLASTICITY]
        principal = torch.isin(table.label[idx], torch.as_tensor(ks, dtype=table.label.dtype, device=F.device))
        F_f, ep_f, _ = fracture_step(F_new[idx], ep[idx], table.plastic.subset(table.label[idx]), F_trial[idx],
                                     principal)
        F_new = F_new.index_copy(0, idx, F_f)
        ep = ep.index_copy(0, idx, ep_f)
    if bodies:
        # the bodies move with the half-step velocity (as rigid.py's advance); a uniform shift
        # changes no body's angular momentum about its centre of mass
        half = 0.5 * dt * torch.as_tensor(grid.gravity, dtype=v.dtype, device=v.device)
        x, v, C, F_new = rigid_projection(x0, x, v - half, C, F_new, p_mass, dt, L / grid.n_grid, table.label, bodies, F)
        v = v + half
    return {"x": x / L, "v": v / L, "C": C, "F": F_new, "ep": ep, "tau": tau, "mu": mu, "lam": lam,
            "log_E_p": log_E_p}
