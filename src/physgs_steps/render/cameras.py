"""Pinhole cameras in the OpenCV convention (x right, y down, z forward), like gsplat.

A :class:`Camera` holds the world-to-camera matrix (gsplat's ``viewmats``), the
intrinsics ``K`` and the image size. Cameras come from an orbit description (the scene
file's ``camera:`` block, see ``workflow/schemas/scene_camera.schema.yaml``) or from the
``cameras.json`` an INRIA 3DGS training run writes next to its point cloud.

All positions are in the scene's *source* frame (the frame of the input ``.ply``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError, RenderError
from ..runtime import read_json_input


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    Attributes:
        viewmat: [4, 4] float64 world-to-camera transform, OpenCV axes.
        K: [3, 3] float64 intrinsics (fx, fy, cx, cy in pixels; pixel centres at +0.5).
        width: image width in pixels (>= 1).
        height: image height in pixels (>= 1).
        name: free label (image name of an INRIA camera, ``orbit_0012``...).
    """

    viewmat: np.ndarray
    K: np.ndarray
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        vm = np.asarray(self.viewmat, dtype=np.float64)
        k = np.asarray(self.K, dtype=np.float64)
        object.__setattr__(self, "viewmat", vm)
        object.__setattr__(self, "K", k)
        label = self.name or "camera"
        if vm.shape != (4, 4) or k.shape != (3, 3):
            raise RenderError(f"{label}: viewmat must be [4,4] and K [3,3], got {vm.shape} and {k.shape}")
        if not (np.isfinite(vm).all() and np.isfinite(k).all()):
            raise RenderError(f"{label}: viewmat or K contains NaN/inf")
        if int(self.width) < 1 or int(self.height) < 1:
            raise RenderError(f"{label}: image size {self.width}x{self.height} is empty (width and height must be >= 1)")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise RenderError(f"{label}: focal lengths must be positive, got fx={k[0, 0]}, fy={k[1, 1]}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def c2w(self) -> np.ndarray:
        """[4, 4] camera-to-world transform."""
        return np.linalg.inv(self.viewmat)

    @property
    def position(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        r, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -r.T @ t

    @property
    def forward(self) -> np.ndarray:
        """[3] unit viewing direction (camera +z) in world coordinates."""
        return self.viewmat[2, :3] / np.linalg.norm(self.viewmat[2, :3])

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera rendering an image of another size (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        k = self.K.copy()
        k[0] *= sx
        k[1] *= sy
        return Camera(self.viewmat, k, width, height, self.name)


def intrinsics_from_fov(fov_deg: float, width: int, height: int) -> np.ndarray:
    """[3, 3] K of a centred pinhole with vertical field of view ``fov_deg`` and square pixels."""
    if not 0.0 < fov_deg < 180.0:
        raise ConfigError("camera.fov_deg", f"must be in (0, 180), got {fov_deg}")
    fy = 0.5 * height / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[fy, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] world-to-camera matrix of a camera at ``eye`` looking at ``target``.

    Args:
        eye: [3] camera centre.
        target: [3] point on the optical axis.
        up: [3] world direction that appears upwards in the image.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    fwd = target - eye
    dist = np.linalg.norm(fwd)
    if dist < 1e-12:
        raise RenderError(f"camera at {eye.tolist()} coincides with its look-at point")
    fwd /= dist
    right = np.cross(fwd, up)
    if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-30):
        raise RenderError(f"camera looks along its up vector {up.tolist()} (elevation of +-90 deg?)")
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r_c2w = np.stack([right, down, fwd], axis=1)
    vm = np.eye(4)
    vm[:3, :3] = r_c2w.T
    vm[:3, 3] = -r_c2w.T @ eye
    return vm


def _horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (e1, e2, u) with u = up; for up = +z, e1 = +x and e2 = +y."""
    u = np.asarray(up, dtype=np.float64)
    n = np.linalg.norm(u)
    if n < 1e-12:
        raise ConfigError("camera.up", "up vector has zero length")
    u = u / n
    ref = np.array([0.0, 1.0, 0.0]) if abs(u[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = ref - (ref @ u) * u
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    return e1, e2, u


def orbit_position(center, radius: float, azimuth_deg: float, elevation_deg: float, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[3] point at ``radius`` from ``center``; azimuth 0 lies along +x (for up = +z), counter-clockwise seen from above."""
    e1, e2, u = _horizontal_basis(np.asarray(up, dtype=np.float64))
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    d = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * u
    return np.asarray(center, dtype=np.float64) + radius * d


def orbit_cameras(center, radius: float, n: int, elevation_deg: float, fov_deg: float, width: int, height: int,
                  *, azimuth_deg: float = 0.0, azimuth_step_deg: float | None = None,
                  elevation_step_deg: float = 0.0, radius_step: float = 0.0,
                  up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """``n`` cameras looking at ``center``.

    By default they are spread evenly over a full turn (``azimuth_step_deg = 360 / n``);
    a video trajectory passes its per-frame deltas instead.

    Args:
        center: [3] look-at point.
        radius: distance of the first camera from ``center`` (> 0).
        n: number of cameras (>= 1).
        elevation_deg: angle above the horizontal plane (perpendicular to ``up``).
        fov_deg: vertical field of view.
        width, height: image size in pixels.
        azimuth_deg: azimuth of the first camera (0 = +x for up = +z).
        azimuth_step_deg, elevation_step_deg, radius_step: change per camera.
        up: [3] world up.
    Returns:
        list of ``n`` :class:`Camera`.
    """
    if n < 1:
        raise ConfigError("camera.n", f"need at least one camera, got {n}")
    if int(width) < 1 or int(height) < 1:
        raise ConfigError("render.width/height", f"image size {width}x{height} is empty")
    step = 360.0 / n if azimuth_step_deg is None else azimuth_step_deg
    k = intrinsics_from_fov(fov_deg, int(width), int(height))
    cams = []
    for i in range(n):
        r = radius + i * radius_step
        el = elevation_deg + i * elevation_step_deg
        if r <= 0:
            raise ConfigError("camera.radius", f"orbit radius becomes {r:.4g} <= 0 at camera {i}")
        if abs(el) >= 89.9:
            raise ConfigError("camera.elevation_deg", f"elevation reaches {el:.2f} deg at camera {i}; keep it within +-89.9")
        eye = orbit_position(center, r, azimuth_deg + i * step, el, up)
        cams.append(Camera(look_at(eye, center, up), k, int(width), int(height), f"orbit_{i:04d}"))
    return cams


def load_inria_cameras(path) -> list[Camera]:
    """Cameras of an INRIA 3DGS training run (``cameras.json``, source frame).

    Each entry has ``position`` [3] (camera centre), ``rotation`` [3][3] (camera-to-world
    rotation, OpenCV axes), ``fx``, ``fy``, ``width``, ``height``; the principal point is the
    image centre (as in the INRIA renderer).
    """
    path = Path(path)
    data = read_json_input(path, "cameras file")
    if not isinstance(data, list) or not data:
        raise InputError(path, "expected a non-empty JSON list of camera entries")
    cams = []
    for i, e in enumerate(data):
        cams.append(_inria_entry(path, i, e))
    return cams


def _inria_entry(path: Path, i: int, e) -> Camera:
    if not isinstance(e, dict):
        raise InputError(path, f"entry {i} is not an object")
    missing = [k for k in ("position", "rotation", "fx", "fy", "width", "height") if k not in e]
    if missing:
        raise InputError(path, f"entry {i} lacks {', '.join(missing)}")
    try:
        pos = np.asarray(e["position"], dtype=np.float64)
        rot = np.asarray(e["rotation"], dtype=np.float64)
        fx, fy = float(e["fx"]), float(e["fy"])
        w, h = int(e["width"]), int(e["height"])
    except (TypeError, ValueError) as err:
        raise InputError(path, f"entry {i}: bad value ({err})") from None
    if pos.shape != (3,) or rot.shape != (3, 3):
        raise InputError(path, f"entry {i}: position must be [3] and rotation [3][3], got {pos.shape}, {rot.shape}")
    if not (np.isfinite(pos).all() and np.isfinite(rot).all() and math.isfinite(fx) and math.isfinite(fy)):
        raise InputError(path, f"entry {i}: non-finite numbers")
    if np.abs(rot @ rot.T - np.eye(3)).max() > 1e-3 or np.linalg.det(rot) < 0:
        raise InputError(path, f"entry {i}: rotation is not a proper rotation matrix")
    if w < 1 or h < 1 or fx <= 0 or fy <= 0:
        raise InputError(path, f"entry {i}: width/height must be >= 1 and fx/fy > 0, got {w}x{h}, fx={fx}, fy={fy}")
    vm = np.eye(4)
    vm[:3, :3] = rot.T
    vm[:3, 3] = -rot.T @ pos
    k = np.array([[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(vm, k, w, h, str(e.get("img_name", f"inria_{i:04d}")))


def stack_cameras(cameras: list[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """([C, 4, 4] viewmats, [C, 3, 3] Ks) of cameras that share one image size."""
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise RenderError(f"cameras of one batch must share an image size, got {sorted(sizes)}")
    return np.stack([c.viewmat for c in cameras]), np.stack([c.K for c in cameras])


@dataclass
class ViewCheck:
    """How a set of gaussian centres sits relative to one camera.

    Attributes:
        n: number of centres checked.
        frac_behind: fraction with camera depth below the near plane (or behind the camera).
        inside_box: whether the camera centre lies inside the 2nd-98th percentile box of the
            centres; None where no centre lies behind the near plane (the box is then not
            computed: it only matters for telling a camera inside the object from one that
            clips a few gaussians, and the percentiles were most of a frame's check).
        frac_in_view: fraction in front of the near plane that project inside the image.
    """

    n: int
    frac_behind: float
    inside_box: bool | None
    frac_in_view: float


def check_view(means, camera: Camera, near: float, max_rows: int = 20000) -> ViewCheck:
    """Where the gaussians are relative to ``camera`` (:func:`check_views` of one view).

    Args:
        means: [N, 3] torch tensor or array of centres in the camera's world frame.
        camera: the camera.
        near: near-plane distance.
    """
    return check_views([means], [camera], near, max_rows)[0]


def check_views(means: list, cameras: list[Camera], near: float, max_rows: int = 20000) -> list[ViewCheck]:
    """Where the gaussians ``means[i]`` are relative to ``cameras[i]``, for a batch of frames.

    Each set of centres is subsampled (strided, at most ``max_rows``); the work stays on the
    centres' device (float64), with one read-back of the fractions of all frames; the
    percentile box is computed only for frames where some centre lies behind the near plane.

    Args:
        means: B [N_i, 3] torch tensors or arrays of centres in the cameras' world frame (one
            device); sets of one size are stacked and checked in one pass.
        cameras: B cameras.
        near: near-plane distance.
    Returns:
        B :class:`ViewCheck`.
    """
    import torch

    if len(means) != len(cameras):
        raise ValueError(f"{len(means)} sets of centres but {len(cameras)} cameras")
    ms = []
    for m in means:
        m = torch.as_tensor(m)
        if m.shape[0] > max_rows:
            m = m[:: int(math.ceil(m.shape[0] / max_rows))]
        ms.append(m.detach())
    checks: list[ViewCheck | None] = [ViewCheck(0, 0.0, None, 0.0) if m.shape[0] == 0 else None for m in ms]
    todo = [i for i, c in enumerate(checks) if c is None]
    if not todo:
        return checks
    dev = ms[todo[0]].device
    views = torch.as_tensor(np.stack([cameras[i].viewmat for i in todo]), dtype=torch.float64, device=dev)  # [B, 4, 4]
    ks = torch.as_tensor(np.stack([cameras[i].K for i in todo]), dtype=torch.float64, device=dev)  # [B, 3, 3]
    size = torch.as_tensor([[cameras[i].width, cameras[i].height] for i in todo], dtype=torch.float64, device=dev)  # [B, 2]
    if len({tuple(ms[i].shape) for i in todo}) == 1:  # one pass over the stack [B, n, 3]
        fracs = _view_fractions(torch.stack([ms[i] for i in todo]).to(torch.float64), views, ks, size, near)
    else:  # frames with rows left out (hidden): one pass each, still one read-back
        fracs = torch.cat([_view_fractions(ms[i].to(torch.float64)[None], views[k:k + 1], ks[k:k + 1],
                                           size[k:k + 1], near) for k, i in enumerate(todo)])
    for i, (frac_front, frac_in) in zip(todo, fracs.tolist()):  # the one read-back
        frac_behind = 1.0 - frac_front
        inside = None
        if frac_behind > 0.0:
            m = ms[i].to(torch.float64)
            q = torch.tensor([0.02, 0.98], dtype=torch.float64, device=m.device)
            lo, hi = torch.quantile(m, q, dim=0).cpu().numpy()  # linear interpolation, as np.percentile
            pos = cameras[i].position
            inside = bool(((pos >= lo) & (pos <= hi)).all())
        checks[i] = ViewCheck(int(ms[i].shape[0]), frac_behind, inside, frac_in)
    return checks


def _view_fractions(m, views, ks, size, near: float):
    """[B, 2] (fraction in front of the near plane, fraction projecting inside the image) of
    centres m [B, n, 3] (float64) seen by cameras with viewmats [B, 4, 4], K [B, 3, 3] and
    image (width, height) [B, 2]."""
    import torch

    pc = m @ views[:, :3, :3].transpose(1, 2) + views[:, None, :3, 3]  # [B, n, 3] camera frame
    z = pc[..., 2]  # [B, n]
    front = z >= near
    zf = torch.clamp_min(z, near)
    u = ks[:, 0, 0, None] * pc[..., 0] / zf + ks[:, 0, 2, None]  # [B, n] pixels
    v = ks[:, 1, 1, None] * pc[..., 1] / zf + ks[:, 1, 2, None]
    in_img = front & (u >= 0) & (u < size[:, 0, None]) & (v >= 0) & (v < size[:, 1, None])
    return torch.stack([front.double().mean(dim=1), in_img.double().mean(dim=1)], dim=1)
