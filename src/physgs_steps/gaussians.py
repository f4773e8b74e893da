"""The one in-memory type for a 3D Gaussian Splatting scene.

Shapes use fixed letters: N gaussians, K spherical-harmonic coefficients per colour
channel (K = (degree + 1) ** 2, degree 0..3).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SH_C0 = 0.28209479177387814  # real SH basis constant for degree 0


def sh_degree_from_k(k: int) -> int:
    deg = int(round(np.sqrt(k))) - 1
    if (deg + 1) ** 2 != k or not 0 <= deg <= 3:
        raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for d in 0..3")
    return deg


@dataclass
class GaussianScene:
    """A 3DGS scene.

    Attributes:
        means: [N, 3] float32 gaussian centres.
        log_scales: [N, 3] float32 natural-log standard deviations along the local axes.
        quats: [N, 4] float32 rotations as (w, x, y, z); unit length after validation.
        opacity_logits: [N] float32, opacity = sigmoid(logit).
        sh: [N, K, 3] float32 SH coefficients; sh[:, 0] is the DC term (f_dc_*).
        extras: optional per-gaussian arrays, each with leading dimension N, e.g.
            ``label`` [N] int32 instance id (-1 = none), ``filled`` [N] bool.
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        n = self.means.shape[0]
        expect = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
        }
        for name, shape in expect.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"GaussianScene.{name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianScene.sh has shape {self.sh.shape}, expected [N, K, 3]")
        try:
            sh_degree_from_k(self.sh.shape[1])
        except ValueError as e:
            raise ValueError(f"GaussianScene.sh: {e}") from None
        for key, arr in self.extras.items():
            if np.asarray(arr).shape[:1] != (n,):
                raise ValueError(f"GaussianScene.extras['{key}'] has leading dim {np.asarray(arr).shape[:1]}, expected {n}")

    # ------------------------------------------------------------------ views
    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_k(self.sh.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        """[N] opacity in (0, 1)."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64))).astype(np.float32)

    @property
    def scales(self) -> np.ndarray:
        """[N, 3] standard deviations."""
        return np.exp(self.log_scales)

    def rotation_matrices(self) -> np.ndarray:
        """[N, 3, 3] rotation matrices of the (normalised) quaternions."""
        return quat_to_rotmat(self.quats)

    def covariances(self) -> np.ndarray:
        """[N, 3, 3] covariance R S S^T R^T."""
        r = self.rotation_matrices()
        m = r * self.scales[:, None, :]
        return m @ np.swapaxes(m, 1, 2)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds of the means: ([3] min, [3] max)."""
        return self.means.min(axis=0), self.means.max(axis=0)

    def subset(self, index) -> "GaussianScene":
        """A new scene with the gaussians selected by a boolean mask or an index array."""
        return GaussianScene(
            means=self.means[index],
            log_scales=self.log_scales[index],
            quats=self.quats[index],
            opacity_logits=self.opacity_logits[index],
            sh=self.sh[index],
            extras={k: np.asarray(v)[index] for k, v in self.extras.items()},
        )

    @staticmethod
    def concat(scenes: list["GaussianScene"]) -> "GaussianScene":
        """Concatenate scenes; SH is padded with zeros to the highest degree; extras must match."""
        k = max(s.sh.shape[1] for s in scenes)
        shs = []
        for s in scenes:
            pad = np.zeros((s.n, k, 3), np.float32)
            pad[:, : s.sh.shape[1]] = s.sh
            shs.append(pad)
        keys = set(scenes[0].extras)
        for s in scenes[1:]:
            if set(s.extras) != keys:
                raise ValueError("GaussianScene.concat: scenes have different extras")
        return GaussianScene(
            means=np.concatenate([s.means for s in scenes]),
            log_scales=np.concatenate([s.log_scales for s in scenes]),
            quats=np.concatenate([s.quats for s in scenes]),
            opacity_logits=np.concatenate([s.opacity_logits for s in scenes]),
            sh=np.concatenate(shs),
            extras={k_: np.concatenate([np.asarray(s.extras[k_]) for s in scenes]) for k_ in keys},
        )

    def base_colors(self) -> np.ndarray:
        """[N, 3] view-independent RGB from the DC term, clipped to [0, 1]."""
        return np.clip(self.sh[:, 0] * SH_C0 + 0.5, 0.0, 1.0)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """[N, 4] (w, x, y, z) quaternions -> [N, 3, 3] rotation matrices (normalises first)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    ).reshape(q.shape[:-1] + (3, 3))
    return r.astype(np.float32)


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotation matrices -> [N, 4] (w, x, y, z) unit quaternions with w >= 0."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(np.asarray(r, dtype=np.float64)).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    wxyz *= np.where(wxyz[:, :1] < 0, -1.0, 1.0)
    return wxyz.astype(np.float32)
