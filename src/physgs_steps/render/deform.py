"""Simulated frames -> deformed gaussians in the scene's source frame.

PhysGaussian's kinematics (FastPhysGS Eq. 3): a gaussian moves with its particle,
``mu(t) = x_p(t)``, and its covariance follows the particle's deformation gradient,
``Sigma(t) = F(t) Sigma F(t)^T``.

Frames: ``scene.ply`` and ``final.h5`` are in the simulation frame,
``x_sim = s R (x_src - c_src) + c_sim``. Rendering happens in the source frame so that the
capture's own cameras (``cameras.json``) apply unchanged:

* means: ``x_src = R^T (x_sim - c_sim) / s + c_src``;
* deformation gradients: ``F_src = R^T F_sim R`` (the scale cancels);
* covariances: ``Sigma_src(t) = F_src Sigma_src F_src^T`` with ``Sigma_src`` the rest
  covariance in the source frame (the sim-frame covariance divided by ``s^2`` and rotated
  back).

View-dependent colour: the SH coefficients stay in the source (rest) frame. A deformed
gaussian is rotated by the polar rotation ``R_p`` of ``F_src = R_p S``; its colour along a
world view direction ``d`` is the rest radiance along ``R_p^T d``. We rotate the view
directions (see :mod:`physgs_steps.render.sh`), not the coefficients. With SH degree 0
there is no view dependence and the polar decomposition is skipped.

Gaussians of ``scene.ply`` not listed in ``final.h5``'s ``gaussian_index`` are drawn at
rest (F = I); the stage logs how many. Filled (interior) particles are never drawn: they
are not gaussians of ``scene.ply`` and ``gaussian_index`` can only point at those.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..errors import RenderError
from ..gaussians import GaussianScene

NONFINITE_POLICIES = ("error", "hide")
# A gaussian's driver whose prediction lies more than this many carrier spacings (about 1.9 dx
# at 4 particles per cell) from its heaviest driver's has been torn off it (CarrierMap).
TEAR_SPACINGS = 3.0


def matmul3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for [..., 3, 3] stacks (broadcasting). On CUDA written out elementwise:
    cuBLAS's batched 3x3 products took 3.7 ms per product of 1M matrices on an H100 against
    0.4 ms elementwise; on the CPU ``matmul`` is the faster one (158 against 589 ms)."""
    return mul3_elementwise(a, b) if a.is_cuda else a @ b


def mul3_elementwise(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] x [..., 3, 3] products as broadcast multiply-and-sum (no batched GEMM)."""
    return (a[..., :, :, None] * b[..., None, :, :]).sum(dim=-2)


def matvec3(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``a @ v`` for [..., 3, 3] matrices and [..., 3] vectors (see :func:`matmul3`)."""
    return matvec3_elementwise(a, v) if a.is_cuda else (a @ v.unsqueeze(-1)).squeeze(-1)


def matvec3_elementwise(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[..., 3, 3] x [..., 3] products as broadcast multiply-and-sum."""
    return (a * v[..., None, :]).sum(dim=-1)


@dataclass
class Gaussians:
    """Gaussians ready to render (one frame), torch tensors on one device.

    Attributes:
        means: [N, 3] centres.
        covars: [N, 3, 3] covariances.
        opacities: [N] in [0, 1].
        sh: [N, K, 3] SH coefficients in each gaussian's rest frame.
        rotations: [N, 3, 3] rest -> current rotation per gaussian, or None (= identity).
    """

    means: torch.Tensor
    covars: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    rotations: torch.Tensor | None = None

    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    @staticmethod
    def from_scene(scene: GaussianScene, device="cpu") -> "Gaussians":
        """Static gaussians of a scene, in the scene's own frame."""
        return Gaussians(
            means=torch.from_numpy(scene.means).to(device),
            covars=torch.from_numpy(scene.covariances().astype(np.float32)).to(device),
            opacities=torch.from_numpy(scene.opacities).to(device),
            sh=torch.from_numpy(scene.sh).to(device),
        )


@dataclass
class SourceMap:
    """Similarity map back from the simulation frame: ``x_src = R^T (x_sim - c_sim) / s + c_src``.

    Attributes:
        R: [3, 3] rotation source -> sim.
        scale: s.
        src_center: [3] c_src.
        sim_center: [3] c_sim.
    """

    R: np.ndarray
    scale: float
    src_center: np.ndarray
    sim_center: np.ndarray

    @staticmethod
    def from_transform(t) -> "SourceMap":
        """From a :class:`physgs_steps.prepare.SceneTransform` (``load_transform``)."""
        return SourceMap(np.asarray(t.R, np.float64), float(t.scale), np.asarray(t.src_center, np.float64),
                         np.asarray(t.sim_center, np.float64))

    @staticmethod
    def identity() -> "SourceMap":
        return SourceMap(np.eye(3), 1.0, np.zeros(3), np.zeros(3))

    def _tensors(self, dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(R, c_sim, c_src) as tensors, made once per dtype and device (a host-to-device copy
        each otherwise: three a frame)."""
        cache = self.__dict__.setdefault("_cache", {})
        key = (dtype, str(device))
        if key not in cache:
            cache[key] = tuple(torch.as_tensor(a, dtype=dtype, device=device)
                               for a in (self.R, self.sim_center, self.src_center))
        return cache[key]

    def points(self, x: torch.Tensor) -> torch.Tensor:
        """[..., 3] sim-frame points -> source frame."""
        R, c_sim, c_src = self._tensors(x.dtype, x.device)
        return (x - c_sim) @ R / self.scale + c_src

    def linear(self, F: torch.Tensor) -> torch.Tensor:
        """[..., 3, 3] sim-frame linear maps (deformation gradients) -> ``R^T F R``."""
        R = self._tensors(F.dtype, F.device)[0]
        return matmul3(matmul3(R.T, F), R)

    def covariances(self, cov: torch.Tensor) -> torch.Tensor:
        """[..., 3, 3] sim-frame covariances -> ``R^T C R / s^2``."""
        return self.linear(cov) / (self.scale ** 2)


def rest_gaussians(scene_sim: GaussianScene, smap: SourceMap, device="cpu") -> Gaussians:
    """The undeformed scene (given in the simulation frame) in the source frame."""
    g = Gaussians.from_scene(scene_sim, device)
    g.means = smap.points(g.means.double()).float()
    g.covars = smap.covariances(g.covars.double()).float()
    return g


def polar_rotation(F: torch.Tensor, max_iter: int = 30) -> torch.Tensor:
    """Rotation part ``R = U V^T`` of ``F = U diag(sig) V^T`` with U, V proper rotations.

    Rows with det F > 0 use Higham's scaled Newton iteration
    ``X <- (g X + X^-T / g) / 2``, ``g = |det X|^(-1/3)`` (elementwise 3x3 algebra, fast on
    CPU and GPU, quadratic convergence); rows with det F <= 0 (inverted or degenerate
    elements) and rows that have not converged use the SVD, where for an inverted F the last
    singular value is taken negative, as in docs/CONTRACTS.md.

    A stack of frames [B, N, 3, 3] iterates together, each frame until its own rows have
    converged (then it stops changing), so every frame gets the bits it gets alone: the
    iteration is elementwise per row and only the convergence test looks across a frame's rows.
    One read-back per iteration for all frames.

    Args:
        F: [N, 3, 3], or [B, N, 3, 3] (B frames).
        max_iter: Newton iterations at most.
    Returns:
        rotations (det +1) of F's shape.
    """
    Fb = F if F.dim() == 4 else F.unsqueeze(0)  # [B, N, 3, 3]
    tol = 1e-12 if F.dtype == torch.float64 else 1e-6
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    det = (Fb[..., 0, :] * torch.linalg.cross(Fb[..., 1, :], Fb[..., 2, :])).sum(dim=-1)  # [B, N] by cofactors: no cuSOLVER/MAGMA start-up
    good = det > 1e-12 * Fb.flatten(-2).abs().amax(dim=-1).clamp_min(1e-30) ** 3  # [B, N]
    X = torch.where(good[..., None, None], Fb, eye.expand_as(Fb))  # [B, N, 3, 3]
    active = list(range(Fb.shape[0]))  # frames still iterating
    for _ in range(max_iter):
        Xa = X if len(active) == X.shape[0] else X[active]  # [A, N, 3, 3]
        inv_t, d = _inverse_transpose(Xa)
        g = _inv_cbrt(d)[..., None, None]
        nxt = 0.5 * (g * Xa + inv_t / g)
        change = (nxt - Xa).abs().flatten(1).amax(dim=1)  # [A] largest change of each frame
        if len(active) == X.shape[0]:
            X = nxt
        else:
            X[active] = nxt
        done = (change.double() < tol).tolist()  # the read-back of this iteration, compared in float64 as float()
        active = [f for f, ok in zip(active, done) if not ok]
        if not active:
            break
    redo = ~good  # [B, N]
    for f in active:  # frames that have not converged: their rows far from a rotation
        err = (X[f] @ X[f].transpose(1, 2) - eye).abs().flatten(1).amax(dim=1)
        redo[f] |= err > 100 * tol
    some = redo.any(dim=1).tolist()  # [B]
    if any(some):
        X = X.clone()
        for f in (f for f, s_ in enumerate(some) if s_):  # per frame: a batched SVD may pick another algorithm
            X[f][redo[f]] = _polar_svd(Fb[f][redo[f]])
    return X if F.dim() == 4 else X[0]


def _inv_cbrt(d: torch.Tensor) -> torch.Tensor:
    """[A, N] -> ``|d|^(-1/3)``, each frame (row) raised on its own on the CPU: the CPU's vectorised
    ``pow`` and its scalar loop over a tensor's last elements round differently, so an
    element's bits depend on where it sits in the tensor, and a frame of a stack would not get
    the bits it gets alone. CUDA computes every element alike: one pass for the stack."""
    if d.is_cuda:
        return d.abs().pow(-1.0 / 3.0)
    return torch.stack([r.abs().pow(-1.0 / 3.0) for r in d])


def _inverse_transpose(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """([..., 3, 3] X^-T, [...] det X) from cofactors: the rows of X^-T are r1 x r2, r2 x r0, r0 x r1 over det."""
    r0, r1, r2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
    cof = torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], dim=-2)
    det = (r0 * cof[..., 0, :]).sum(dim=-1)
    return cof / det[..., None, None], det


def _polar_svd(F: torch.Tensor) -> torch.Tensor:
    """Polar rotation through the SVD with proper U, V (works for any F)."""
    U, _, Vh = torch.linalg.svd(F)
    U = U.clone()
    Vh = Vh.clone()
    U[torch.det(U) < 0, :, 2] *= -1
    Vh[torch.det(Vh) < 0, 2, :] *= -1
    return U @ Vh


def check_frame(frame: int, x: np.ndarray | torch.Tensor, F: np.ndarray | torch.Tensor, policy: str) -> torch.Tensor | None:
    """Non-finite rows of one frame.

    Args:
        frame: frame number (for the message).
        x: [Nv, 3] positions; F: [Nv, 3, 3] deformation gradients, or F - I (the render stage
            passes final.h5's float16 F - I: non-finite exactly where F is).
        policy: ``error`` raises :class:`RenderError`; ``hide`` returns the [Nv] bool mask of bad rows.
    Returns:
        None when every row is finite, else the mask (policy ``hide``).
    """
    if isinstance(x, np.ndarray) and isinstance(F, np.ndarray) and \
            np.isfinite(np.sum(x, dtype=np.float64) + np.sum(F, dtype=np.float64)):
        # a finite float64 sum has no NaN/inf term (float32 terms cannot overflow it): the one
        # pass a finite frame costs (the per-row masks below took 3 ms a frame of 60k rows on
        # the GPU machine's host)
        return None
    x = torch.as_tensor(x)
    F = torch.as_tensor(F)
    bad = ~(torch.isfinite(x).all(dim=1) & torch.isfinite(F).flatten(1).all(dim=1))
    n_bad = int(bad.sum())
    if n_bad == 0:
        return None
    if policy == "error" or n_bad == bad.numel():
        raise RenderError(
            f"frame {frame}: {n_bad} of {bad.numel()} particles have NaN/inf position or deformation gradient "
            "(the simulation diverged; lower the time step or stiffness, or set render.on_nonfinite: hide "
            "to draw the frame without them)")
    return bad


def covers_all(index: torch.Tensor, n: int) -> bool:
    """Whether ``index`` [Nv] is exactly 0..n-1 in order (every gaussian simulated, in row order)."""
    return index.numel() == n and bool((index == torch.arange(n, device=index.device)).all())


def deform(rest: Gaussians, index: torch.Tensor, x_sim: torch.Tensor, F_sim: torch.Tensor, smap: SourceMap | None,
           with_rotation: bool, hide: torch.Tensor | None = None, full: bool | None = None) -> Gaussians:
    """Gaussians of one simulated frame, in the source frame (:func:`deform_frames` of one frame).

    Args:
        rest: [N] rest gaussians in the source frame (:func:`rest_gaussians`).
        index: [Nv] int64 rows of ``rest`` that the simulation moved (``gaussian_index``).
        x_sim: [Nv, 3] simulated positions (sim frame).
        F_sim: [Nv, 3, 3] deformation gradients (sim frame).
        smap: the map back to the source frame; None where ``x_sim`` and ``F_sim`` are in the
            source frame already (the render stage maps the stored particles before the
            carrier spreads them over the gaussians: the map then runs on thousands of rows,
            not on every gaussian).
        with_rotation: compute the polar rotations for view-dependent SH (degree > 0).
        hide: optional [Nv] bool rows to leave out of this frame (drawn with opacity 0).
        full: ``covers_all(index, rest.n)`` where the caller knows it.
    Returns:
        :class:`Gaussians` with N rows (rows not in ``index`` stay at rest).
    """
    dev = rest.means.device
    if smap is None:
        x, Fs = x_sim.to(dev, torch.float32), F_sim.to(dev, torch.float32)
    else:
        x = smap.points(x_sim.to(dev, torch.float64)).float()
        Fs = smap.linear(F_sim.to(dev, torch.float32))  # float32: R is orthonormal, |F| ~ 1
    return deform_frames(rest, index, x[None], Fs[None], with_rotation, None if hide is None else hide[None], full)[0]


def deform_frames(rest: Gaussians, index: torch.Tensor, x: torch.Tensor, F: torch.Tensor, with_rotation: bool,
                  hide: torch.Tensor | None = None, full: bool | None = None) -> list[Gaussians]:
    """Gaussians of B simulated frames at once, in the source frame.

    Every operation is elementwise or a product per row (no reduction across rows, the
    polar rotations converge per frame), so each frame gets the bits it gets alone
    (tests/test_render_batch.py checks it); the stack costs the launches of one frame.

    Args:
        rest: [N] rest gaussians in the source frame (:func:`rest_gaussians`).
        index: [Nv] int64 rows of ``rest`` that the simulation moved.
        x: [B, Nv, 3] positions in the source frame.
        F: [B, Nv, 3, 3] deformation gradients in the source frame.
        with_rotation: compute the polar rotations for view-dependent SH (degree > 0).
        hide: optional [B, Nv] bool rows to leave out (drawn with opacity 0).
        full: ``covers_all(index, rest.n)`` where the caller knows it (the render stage computes
            it once: it is a host synchronisation per call otherwise).
    Returns:
        B :class:`Gaussians` with N rows each (rows not in ``index`` stay at rest), views into
        [B, N, ...] tensors.
    """
    dev = rest.means.device
    x, Fs = x.to(dev, torch.float32), F.to(dev, torch.float32)  # [B, Nv, 3], [B, Nv, 3, 3]
    b = x.shape[0]
    if hide is not None:
        hide = hide.to(dev)  # [B, Nv]
        x = torch.where(hide[..., None], torch.zeros_like(x), x)
        Fs = torch.where(hide[..., None, None], torch.eye(3, device=dev).expand_as(Fs), Fs)
    if full is None:
        full = covers_all(index, rest.n)
    idx = index.to(dev)
    cov_rows = matmul3(matmul3(Fs, rest.covars if full else rest.covars[idx]), Fs.transpose(-1, -2))  # [B, Nv, 3, 3] F Sigma F^T
    rot_rows = polar_rotation(Fs) if with_rotation else None  # [B, Nv, 3, 3]
    if full:
        means, covars, rots = x, cov_rows, rot_rows
    else:
        means = rest.means.repeat(b, 1, 1)  # [B, N, 3]
        means[:, idx] = x
        covars = rest.covars.repeat(b, 1, 1, 1)  # [B, N, 3, 3]
        covars[:, idx] = cov_rows
        rots = None
        if rot_rows is not None:
            rots = torch.eye(3, device=dev).repeat(b, rest.n, 1, 1)  # [B, N, 3, 3]
            rots[:, idx] = rot_rows
    opac = [rest.opacities] * b  # [N] each
    if hide is not None:
        o = rest.opacities.repeat(b, 1)  # [B, N]
        o[:, idx] = torch.where(hide, torch.zeros_like(o[:, idx]), o[:, idx])
        opac = list(o)
    return [Gaussians(means=means[f], covars=covars[f], opacities=opac[f], sh=rest.sh,
                      rotations=None if rots is None else rots[f]) for f in range(b)]


@dataclass
class CarrierMap:
    """The carrier (:mod:`physgs_steps.carrier`) resolved against one final.h5, on one device.

    Simulated gaussian ``rows[i]`` is driven by the stored particles ``index[i]`` (final.h5
    columns) with ``weight[i]``:
    ``x = sum_k w_k (x_k + F_k d_k)``, ``F = sum_k w_k F_k``, ``d_k = x_g(0) - x_k(0)``
    (sim frame). Identity carriers (one driver, weight 1, ``sim.particles: gaussians``) skip
    the offsets: x = x_k, F = F_k.

    Torn drivers: a driver whose prediction ``x_k + F_k d_k`` lies farther than ``cut``
    (TEAR_SPACINGS carrier spacings) from the prediction of the gaussian's heaviest driver
    no longer moves with it (a tear or a gap opened between them) and drops out of that
    frame's blend (the remaining weights renormalised).  Without this a gaussian next to a
    tear, driven from both sides, was drawn in the gap between the pieces, at the weighted
    mean of the two sides (the torn bread's "crumb" band).  In intact material the drivers'
    predictions agree to well within a spacing, and nothing changes.

    Attributes:
        rows: [Ns] int64 rows of scene.ply that move (the others are drawn at rest).
        index: [Ns, K] int64 final.h5 columns (0 where the weight is 0).
        weight: [Ns, K] float32, rows sum to 1.
        offset: [Ns, K, 3] float32 rest offsets, or None for an identity carrier.
    """

    rows: torch.Tensor
    index: torch.Tensor
    weight: torch.Tensor
    offset: torch.Tensor | None
    chunk: int = 1 << 19  # gaussians per pass of apply (300k in one: fewer launches)
    cut: float = math.inf  # sim-frame distance beyond which a driver's prediction counts as torn off

    @property
    def identity(self) -> bool:
        return self.offset is None

    @staticmethod
    def build(carrier, particle_index: np.ndarray, rest_means_sim: np.ndarray, x0: np.ndarray,
              device="cpu", length_scale: float = 1.0) -> "CarrierMap":
        """Resolve a :class:`~physgs_steps.carrier.Carrier` against final.h5.

        Args:
            carrier: the carrier (index into ``carrier.drivers``).
            particle_index: [M] rows of particles.h5 stored in final.h5 (its columns).
            rest_means_sim: [N, 3] scene.ply centres (sim frame).
            x0: [M, 3] stored positions at frame 0 (sim frame).
            length_scale: lengths of the frame ``rest_means_sim`` and ``x0`` are given in per
                sim-frame unit (the tear distance is the carrier's spacing times this): 1 in
                the sim frame, ``1 / s`` where both are given in the source frame
                (:class:`SourceMap`), and :meth:`apply` then takes source-frame states.
        Drivers that final.h5 does not store (instances the simulation left out) count as
        absent: a gaussian without any stored driver is drawn at rest.
        The work is [N, K] gathers, done on ``device`` (1M gaussians x 8 drivers: numpy took
        2.5 s of a 10 s render stage on the GPU machine).
        """
        dev = torch.device(device)
        pidx = torch.from_numpy(np.ascontiguousarray(particle_index, np.int64)).to(dev)  # [M]
        order = torch.argsort(pidx)
        sorted_idx = pidx[order]
        drivers = torch.from_numpy(np.ascontiguousarray(carrier.drivers, np.int64)).to(dev)  # [D]
        pos = torch.searchsorted(sorted_idx, drivers).clamp_max(max(len(order) - 1, 0))
        stored = sorted_idx[pos] == drivers
        col_of_driver = torch.where(stored, order[pos], torch.full_like(pos, -1))  # [D] final.h5 column of each driver
        idx = torch.from_numpy(np.ascontiguousarray(carrier.index)).to(dev).long()  # [N, K]
        col = torch.where(idx >= 0, col_of_driver[idx.clamp_min(0)], torch.full_like(idx, -1))  # [N, K]
        w = torch.from_numpy(np.ascontiguousarray(carrier.weight)).to(dev).double()
        w = torch.where(col >= 0, w, torch.zeros_like(w))
        tot = w.sum(dim=1)  # [N]
        rows = torch.nonzero(tot > 0).squeeze(1)  # [Ns]
        w = (w[rows] / tot[rows, None]).float()
        col = col[rows].clamp_min(0)
        offset = None
        if col.shape[1] != 1:
            means = torch.from_numpy(np.ascontiguousarray(rest_means_sim)).to(dev).double()  # [N, 3]
            xs0 = torch.from_numpy(np.ascontiguousarray(x0)).to(dev).double()  # [M, 3]
            offset = (means[rows, None, :] - xs0[col]).float()  # [Ns, K, 3]
        spacing = float(getattr(carrier, "spacing", 0.0) or 0.0)
        cut = TEAR_SPACINGS * spacing * float(length_scale) if spacing > 0 else math.inf
        return CarrierMap(rows=rows, index=col, weight=w, offset=offset, cut=cut)

    def apply(self, x: torch.Tensor, F: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Stored states x [B, M, 3], F [B, M, 3, 3] of B frames, or x [M, 3], F [M, 3, 3] of one
        -> ([B, Ns, 3] centres, [B, Ns, 3, 3] deformation gradients) of the moving gaussians
        (sim frame; without B for one frame). Every gaussian's blend is its own (gathers,
        products and sums over its K drivers), so a frame gets the same bits in a stack as alone."""
        if self.identity:
            i = self.index[:, 0]
            return x[..., i, :], F[..., i, :, :]
        if x.dim() == 2:
            xs, Fs = self.apply(x[None], F[None])
            return xs[0], Fs[0]
        nb, ns = x.shape[0], self.rows.shape[0]
        xs = torch.empty((nb, ns, 3), dtype=x.dtype, device=x.device)
        Fs = torch.empty((nb, ns, 3, 3), dtype=F.dtype, device=F.device)
        fb = self.frames_per_pass(x)
        step = max(1, self.chunk // fb)  # gaussians per pass: the temporaries of one frame's pass
        for f0 in range(0, nb, fb):
            fr = slice(f0, f0 + fb)
            for a in range(0, ns, step):
                b = min(a + step, ns)
                i = self.index[a:b]  # [c, K]
                w, d = self.weight[a:b].to(x.dtype), self.offset[a:b].to(x.dtype)  # [c, K], [c, K, 3]
                Fk = F[fr][:, i]  # [fb, c, K, 3, 3]
                pred = x[fr][:, i] + matvec3(Fk, d)  # [fb, c, K, 3]
                if math.isfinite(self.cut):  # drivers torn off the heaviest one leave the blend
                    head = pred.gather(2, w.argmax(dim=1)[None, :, None, None].expand(Fk.shape[0], -1, 1, 3))  # [fb, c, 1, 3]
                    w = torch.where(((pred - head) ** 2).sum(-1) <= self.cut ** 2, w, torch.zeros_like(w))  # [fb, c, K]
                    w = w / w.sum(dim=-1, keepdim=True)
                xs[fr, a:b] = (w.unsqueeze(-1) * pred).sum(dim=-2)
                Fs[fr, a:b] = torch.einsum("...ck,...ckij->...cij", w.to(F.dtype), Fk)
        return xs, Fs

    @staticmethod
    def frames_per_pass(x: torch.Tensor) -> int:
        """Frames of the stack x [B, M, 3] that :meth:`apply` blends in one pass: all on CUDA (the
        launches of one frame); one on the CPU, where a stack's [B, c, K, 3, 3] temporaries leave
        the cache (16 frames of 20k gaussians took 0.48 s in one pass, 0.31 s frame by frame)."""
        return int(x.shape[0]) if x.is_cuda else 1

    def hidden(self, bad: torch.Tensor) -> torch.Tensor:
        """[Ns] bool moving gaussians with a non-finite driver, from the [M] driver mask."""
        b = bad.to(self.index.device)[self.index]  # [Ns, K]
        return (b & (self.weight > 0)).any(dim=1)
