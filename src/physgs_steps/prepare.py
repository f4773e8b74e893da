"""Stage ``prepare``: load a 3DGS scene (file or built-in) and normalise it into the
simulation domain.

The map from the source frame to the simulation frame (unit cube, z up) is
``x_sim = s * R @ (x_src - c_src) + c_sim`` (docs/CONTRACTS.md):

* ``R = R_up @ R_n @ ... @ R_1``: first the extra rotations of the scene key
  ``transform.rotation_degree`` / ``rotation_axis`` in list order (right-handed, about the
  current x/y/z axes, as PhysGaussian's preprocessing applies them), then ``R_up`` turns
  ``transform.up_axis`` onto +z.
* The bounding box of the rotated centres is trimmed by ``prepare.trim_quantile`` at each
  end of every axis (floaters do not decide the scale); ``s`` makes its largest side
  ``transform.extent`` and its centre lands on ``transform.center``.
* Before that, gaussians outside ``transform.crop_box`` (source frame) and below
  ``prepare.min_opacity`` are dropped.
* ``region.box`` (source frame) chooses what is simulated: the transform is fitted to the
  gaussians inside it; the others are *static surroundings*, kept in scene.ply (extra
  vertex property ``static`` = 1), never clustered, filled or simulated, and drawn at rest
  in every frame. They may lie anywhere, also outside the domain.

Gaussians: means are mapped, log-scales get ``+ log s``, quaternions are pre-multiplied by
the quaternion of R, SH coefficients stay in the source frame, extras are kept.  Every
simulated centre must then lie inside the domain less a wall margin of 3 cells of a 64^3 grid;
otherwise a ConfigError names ``transform.extent`` or ``transform.center`` and the numbers
(or, with ``prepare.drop_outside``, those gaussians are dropped).

Sanity checks that cost nothing here and save a whole simulation that would render an
empty video (:func:`check_appearance`, :func:`check_resolution`):

* every gaussian with opacity below 1/255 (nothing would be drawn): InputError;
* gaussians whose standard deviation exceeds ``MAX_SIM_SIGMA`` (1 domain unit, twice the
  scene's largest side; e.g. a scale of 1e30) would each cover the whole view: they are
  dropped and logged (``dropped.oversized``); when that is every gaussian, InputError;
* centres so far from the origin that float32 (the type of 3DGS positions) cannot resolve
  the scene (a capture 1e9 units away spanning a few units): InputError saying so.
"""
from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field

import numpy as np

from .errors import ConfigError, InputError
from .gaussians import GaussianScene, rotmat_to_quat
from .runtime import read_json_input, write_json
from .scene_io import load_gaussians, save_gaussians

MARGIN_GRID = 64  # the wall margin is MARGIN_CELLS cells of a grid of this many cells per axis
MARGIN_CELLS = 3
MARGIN = MARGIN_CELLS / MARGIN_GRID
ALPHA_VISIBLE = 1.0 / 255.0  # below this opacity a gaussian is never drawn (both renderers)
MAX_SIM_SIGMA = 1.0  # domain units: a gaussian wider than this covers the whole view
FLOAT32_STEPS = 100  # the scene must span at least this many float32 steps of its coordinates
FAR_FROM_ORIGIN = 1e3  # a scene without extent this far out is probably quantised (the message says so)
BUILTIN_PREFIX = "builtin:"
_AXES = {"x": 0, "y": 1, "z": 2, 0: 0, 1: 1, 2: 2}


# ---------------------------------------------------------------------------- transform
@dataclass
class SceneTransform:
    """The similarity map source frame <-> simulation frame.

    Attributes:
        R: [3, 3] rotation (source -> sim), float64.
        scale: s > 0, sim units per source unit.
        src_center: [3] point of the source frame mapped to ``sim_center``.
        sim_center: [3] its image in the simulation frame.
        record: the full transform.json content (empty when built in memory).
    """

    R: np.ndarray
    scale: float
    src_center: np.ndarray
    sim_center: np.ndarray
    record: dict = field(default_factory=dict)

    def to_sim(self, points) -> np.ndarray:
        """[M, 3] source-frame points -> [M, 3] float64 simulation-frame points."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p - self.src_center) @ self.R.T + self.sim_center

    def to_source(self, points) -> np.ndarray:
        """[M, 3] simulation-frame points -> [M, 3] float64 source-frame points."""
        p = np.asarray(points, dtype=np.float64)
        return (p - self.sim_center) @ self.R / self.scale + self.src_center

    def rotate_quats(self, quats, inverse: bool = False) -> np.ndarray:
        """[M, 4] (w, x, y, z) orientations -> [M, 4] float32 orientations q_R * q
        (source -> sim), or q_R^-1 * q with ``inverse`` (sim -> source)."""
        qr = rotmat_to_quat(self.R[None])[0].astype(np.float64)  # [4]
        if inverse:
            qr = qr * np.array([1.0, -1.0, -1.0, -1.0])
        return quat_multiply(qr, np.asarray(quats, dtype=np.float64)).astype(np.float32)

    def to_sim_scene(self, scene: GaussianScene) -> GaussianScene:
        """A copy of ``scene`` in the simulation frame (SH left in the source frame)."""
        return self._map_scene(scene, self.to_sim(scene.means), np.log(self.scale), False)

    def to_source_scene(self, scene: GaussianScene) -> GaussianScene:
        """A copy of a simulation-frame ``scene`` mapped back to the source frame."""
        return self._map_scene(scene, self.to_source(scene.means), -np.log(self.scale), True)

    def _map_scene(self, scene: GaussianScene, means: np.ndarray, dlog: float, inverse: bool) -> GaussianScene:
        return GaussianScene(
            means=means.astype(np.float32),
            log_scales=(scene.log_scales.astype(np.float64) + dlog).astype(np.float32),
            quats=self.rotate_quats(scene.quats, inverse=inverse),
            opacity_logits=scene.opacity_logits.copy(),
            sh=scene.sh.copy(),
            extras={k: np.array(v, copy=True) for k, v in scene.extras.items()},
        )

    def to_dict(self) -> dict:
        """The four contract keys of transform.json."""
        return {"scale": float(self.scale), "rotation": self.R.tolist(),
                "src_center": self.src_center.tolist(), "sim_center": self.sim_center.tolist()}


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions a [4] or [M, 4] and b [M, 4] -> [M, 4]."""
    aw, ax, ay, az = np.moveaxis(np.broadcast_to(a, b.shape), -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def load_transform(path) -> SceneTransform:
    """Read a transform.json written by :func:`run`.

    Raises:
        InputError: missing keys, wrong shapes, a non-rotation matrix or a scale <= 0.
    """
    rec = read_json_input(path, "transform file")
    missing = [k for k in ("scale", "rotation", "src_center", "sim_center") if k not in rec]
    if missing:
        raise InputError(path, f"transform is missing keys {missing}")
    try:
        R = np.asarray(rec["rotation"], dtype=np.float64)
        src_c = np.asarray(rec["src_center"], dtype=np.float64)
        sim_c = np.asarray(rec["sim_center"], dtype=np.float64)
        scale = float(rec["scale"])
    except (TypeError, ValueError) as e:
        raise InputError(path, f"transform values are not numeric: {e}") from None
    if R.shape != (3, 3) or src_c.shape != (3,) or sim_c.shape != (3,):
        raise InputError(path, f"transform shapes: rotation {R.shape} (need 3x3), src_center {src_c.shape}, "
                               f"sim_center {sim_c.shape} (need 3)")
    if not (np.isfinite(R).all() and np.isfinite(src_c).all() and np.isfinite(sim_c).all()) \
            or not np.isfinite(scale) or scale <= 0:
        raise InputError(path, f"transform has non-finite values or scale {scale} <= 0")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
        raise InputError(path, "transform 'rotation' is not a proper rotation matrix")
    return SceneTransform(R=R, scale=scale, src_center=src_c, sim_center=sim_c, record=rec)


# ---------------------------------------------------------------------------- config
def _validated(name: str, key: str, value, source: str | None) -> dict:
    """A copy of ``value`` validated against ``<name>.schema.yaml`` with defaults filled;
    errors are ConfigErrors naming ``key.<sub key>`` and ``source``."""
    from . import config

    value = {} if value is None else copy.deepcopy(value)
    return config.validate(value, config.load_schema(f"{name}.schema.yaml"), source or name, key)


def transform_config(scene_cfg: dict) -> dict:
    """The scene's ``transform`` dict validated and merged with the defaults."""
    tcfg = _validated("scene_transform", "transform", scene_cfg.get("transform"), scene_cfg.get("_path"))
    if len(tcfg["rotation_degree"]) != len(tcfg["rotation_axis"]):
        raise ConfigError("transform.rotation_axis",
                          f"has {len(tcfg['rotation_axis'])} entries but transform.rotation_degree has "
                          f"{len(tcfg['rotation_degree'])}; give one axis per angle", scene_cfg.get("_path"))
    box = tcfg["crop_box"]
    if box is not None and not (np.asarray(box[0]) < np.asarray(box[1])).all():
        raise ConfigError("transform.crop_box", f"min {box[0]} must be below max {box[1]} on every axis",
                          scene_cfg.get("_path"))
    return tcfg


def region_config(scene_cfg: dict) -> dict:
    """The scene's ``region`` dict validated and merged with the defaults (scene_region.schema.yaml)."""
    rcfg = _validated("scene_region", "region", scene_cfg.get("region"), scene_cfg.get("_path"))
    box = rcfg["box"]
    if box is not None and not (np.asarray(box[0]) < np.asarray(box[1])).all():
        raise ConfigError("region.box", f"min {box[0]} must be below max {box[1]} on every axis", scene_cfg.get("_path"))
    return rcfg


def prepare_config(cfg: dict) -> dict:
    """The ``prepare`` section validated and merged with the defaults."""
    return _validated("prepare", "prepare", cfg.get("prepare"), None)


# ---------------------------------------------------------------------------- geometry
def axis_rotation(degrees: float, axis) -> np.ndarray:
    """[3, 3] right-handed rotation by ``degrees`` about axis 0/1/2 or 'x'/'y'/'z'."""
    t = np.deg2rad(float(degrees))
    c, s = np.cos(t), np.sin(t)
    i = _AXES[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    r = np.eye(3)
    r[j, j], r[j, k], r[k, j], r[k, k] = c, -s, s, c
    return r


def up_rotation(up_axis: str) -> np.ndarray:
    """[3, 3] proper rotation taking the unit vector of ``up_axis`` (x, y, z, -x, -y, -z) to +z."""
    table = {
        "z": np.eye(3),
        "-z": axis_rotation(180, "x"),
        "y": axis_rotation(90, "x"),
        "-y": axis_rotation(-90, "x"),
        "x": axis_rotation(-90, "y"),
        "-x": axis_rotation(90, "y"),
    }
    return np.round(table[up_axis], 12) + 0.0


def scene_rotation(tcfg: dict) -> np.ndarray:
    """[3, 3] R = R_up @ R_n @ ... @ R_1 from a validated transform config."""
    r = np.eye(3)
    for deg, axis in zip(tcfg["rotation_degree"], tcfg["rotation_axis"]):
        r = axis_rotation(deg, axis) @ r
    return up_rotation(tcfg["up_axis"]) @ r


def fit_transform(means: np.ndarray, tcfg: dict, trim_quantile: float, source="scene") -> SceneTransform:
    """The transform placing the trimmed bounding box of ``means`` [N, 3] as ``tcfg`` says.

    Raises:
        InputError: the trimmed box has zero size (e.g. a single gaussian).
    """
    R = scene_rotation(tcfg)
    rotated = np.asarray(means, dtype=np.float64) @ R.T  # [N, 3]
    if trim_quantile > 0:
        lo, hi = np.quantile(rotated, [trim_quantile, 1.0 - trim_quantile], axis=0)
    else:
        lo, hi = rotated.min(axis=0), rotated.max(axis=0)
    size = float((hi - lo).max())
    far = float(np.abs(rotated).max())
    if not size > 1e-12 * max(1.0, far):
        hint = ("" if far < FAR_FROM_ORIGIN else f"; they lie {far:.3g} units from the origin, where float32 positions "
                f"resolve only {float(np.spacing(np.float32(far))):.3g} units: re-export the capture centred near the "
                "origin")
        raise InputError(source, f"the {len(rotated)} gaussian centres have no spatial extent "
                                 f"(trimmed box {lo.tolist()}..{hi.tolist()}); cannot scale the scene{hint}")
    check_resolution(means, size, source)
    return SceneTransform(R=R, scale=float(tcfg["extent"]) / size, src_center=R.T @ ((lo + hi) / 2),
                          sim_center=np.asarray(tcfg["center"], dtype=np.float64))


# ---------------------------------------------------------------------------- normalise
def normalise_scene(scene: GaussianScene, tcfg: dict, pcfg: dict, source="scene",
                    log: logging.Logger | None = None, region_box=None) -> tuple[GaussianScene, SceneTransform, dict]:
    """Filter ``scene`` and map it into the simulation domain.

    Args:
        scene: source-frame scene (N gaussians).
        tcfg: validated ``transform`` config (:func:`transform_config`).
        pcfg: validated ``prepare`` config (:func:`prepare_config`).
        source: name of the source for messages.
        region_box: [[min], [max]] source-frame box of what is simulated (``region.box``),
            or None for everything.

    Returns:
        (scene in the sim frame with N_kept gaussians, transform, info) where info holds
        ``dropped`` (counts for ``crop_box``, ``min_opacity``, ``outside``), ``bounds_src``
        (``{"min", "max"}`` of the kept simulated centres in the source frame) and
        ``n_static`` (gaussians outside ``region_box``, marked by the extra ``static``).
    """
    log = log or logging.getLogger("physgs.prepare")
    dropped = {"crop_box": 0, "min_opacity": 0, "outside": 0, "oversized": 0}
    if "static" in scene.extras:  # a scene.ply of an earlier run as the source: the region is decided anew
        scene = GaussianScene(scene.means, scene.log_scales, scene.quats, scene.opacity_logits, scene.sh,
                              {k: v for k, v in scene.extras.items() if k != "static"})
    check_appearance(scene, source, log)
    if tcfg["crop_box"] is not None:
        lo, hi = np.asarray(tcfg["crop_box"], dtype=np.float64)
        keep = ((scene.means >= lo) & (scene.means <= hi)).all(axis=1)
        dropped["crop_box"] = int((~keep).sum())
        if not keep.any():
            raise ConfigError("transform.crop_box", f"box {lo.tolist()}..{hi.tolist()} contains none of the "
                                                    f"{scene.n} gaussians of {source} (bounds "
                                                    f"{_fmt(scene.means.min(0))}..{_fmt(scene.means.max(0))})")
        scene = scene.subset(keep) if dropped["crop_box"] else scene
    if pcfg["min_opacity"] > 0:
        keep = scene.opacities >= pcfg["min_opacity"]
        dropped["min_opacity"] = int((~keep).sum())
        if not keep.any():
            raise ConfigError("prepare.min_opacity", f"{pcfg['min_opacity']} drops all {scene.n} gaussians of "
                                                     f"{source} (largest opacity {float(scene.opacities.max()):.4g})")
        scene = scene.subset(keep) if dropped["min_opacity"] else scene
    static = np.zeros(scene.n, bool)
    if region_box is not None:
        lo, hi = np.asarray(region_box, dtype=np.float64)
        static = ~((scene.means >= lo) & (scene.means <= hi)).all(axis=1)
        if static.all():
            raise ConfigError("region.box", f"box {lo.tolist()}..{hi.tolist()} contains none of the {scene.n} "
                                            f"gaussians of {source} (bounds {_fmt(scene.means.min(0))}.."
                                            f"{_fmt(scene.means.max(0))})")
    tf = fit_transform(scene.means[~static], tcfg, pcfg["trim_quantile"], source)
    sim = tf.to_sim_scene(scene)
    sigma = np.exp(sim.log_scales.astype(np.float64)).max(axis=1)  # [N] largest std, domain units
    huge = ~(sigma <= MAX_SIM_SIGMA)
    if huge.any():
        biggest = float(np.max(np.exp(scene.log_scales.astype(np.float64))))
        if huge.all():
            raise InputError(source, f"every gaussian is larger than the whole scene (standard deviations up to "
                                     f"{biggest:.3g} source units, {float(sigma.max()):.3g} x the simulation domain): "
                                     "the scale_0..2 properties must hold the natural log of the standard deviation "
                                     "(INRIA 3DGS convention), not linear scales")
        dropped["oversized"] = int(huge.sum())
        log.warning("dropped %d gaussians wider than the domain (standard deviation above %g domain units, largest "
                    "%.3g source units): each would cover the whole view", dropped["oversized"], MAX_SIM_SIGMA, biggest)
        sim, scene, static = sim.subset(~huge), scene.subset(~huge), static[~huge]
    outside = ((sim.means < MARGIN) | (sim.means > 1.0 - MARGIN)).any(axis=1) & ~static
    if outside.any():
        if not pcfg["drop_outside"]:
            _raise_outside(sim.means[~static], tcfg, source)
        dropped["outside"] = int(outside.sum())
        if outside.sum() == (~static).sum():
            raise ConfigError("transform.center", f"every gaussian of {source} lies outside the domain margin")
        log.warning("dropped %d gaussians outside the domain [%.4f, %.4f]^3 (prepare.drop_outside)",
                    dropped["outside"], MARGIN, 1.0 - MARGIN)
        sim = sim.subset(~outside)
        scene = scene.subset(~outside)
        static = static[~outside]
    if static.any():
        sim.extras["static"] = static
    return sim, tf, {"dropped": dropped, "bounds_src": _bounds(scene.means[~static]), "n_static": int(static.sum())}


def check_appearance(scene: GaussianScene, source, log: logging.Logger) -> None:
    """Raise when no gaussian of ``scene`` would be visible (every opacity below 1/255)."""
    op = scene.opacities
    invisible = op < ALPHA_VISIBLE
    if invisible.all():
        raise InputError(source, f"every one of the {scene.n} gaussians has opacity below 1/255 (largest "
                                 f"{float(op.max()):.3g}): nothing would be drawn. The `opacity` property of a 3DGS "
                                 "file holds logits (opacity = sigmoid(value)); a file storing linear opacities in "
                                 "[0, 1] must be converted")
    if invisible.any():
        log.info("%d of %d gaussians have opacity below 1/255 (never drawn)", int(invisible.sum()), scene.n)


def check_resolution(means: np.ndarray, size: float, source) -> None:
    """Raise when float32 centres ``means`` [N, 3] are too far from the origin to resolve a
    scene of ``size`` (source units): at |x| = 1e9 float32 steps are 64 units."""
    far = float(np.abs(np.asarray(means, np.float64)).max())
    step = float(np.spacing(np.float32(far)))
    if size < FLOAT32_STEPS * step:
        raise InputError(source, f"the gaussian centres lie up to {far:.3g} source units from the origin, where "
                                 f"float32 positions (3DGS files) resolve only {step:.3g} units, but the scene spans "
                                 f"{size:.3g} units: its positions are quantised. Re-export the capture centred near "
                                 "the origin (subtract its centre from x, y, z)")


def _raise_outside(means: np.ndarray, tcfg: dict, source) -> None:
    """Raise the ConfigError explaining why the normalised scene does not fit the domain."""
    lo, hi = means.min(axis=0).astype(np.float64), means.max(axis=0).astype(np.float64)
    width = 1.0 - 2.0 * MARGIN
    size = hi - lo
    hint = ("; floaters far from the object also cause this: crop with transform.crop_box, raise "
            "prepare.min_opacity or prepare.trim_quantile, or set prepare.drop_outside: true")
    where = (f"normalised scene of {source} spans {_fmt(lo)}..{_fmt(hi)} (size {_fmt(size)}) but must lie in "
             f"[{MARGIN:.4f}, {1 - MARGIN:.4f}]^3 (a {MARGIN_CELLS}-cell wall margin of a {MARGIN_GRID}^3 grid)")
    if (size > width).any():
        fit = float(tcfg["extent"]) * width / float(size.max())
        raise ConfigError("transform.extent", f"{tcfg['extent']} is too large: {where}; the size fits with an "
                                              f"extent of at most {fit:.4g}{hint}")
    c = np.asarray(tcfg["center"], dtype=np.float64)
    ok_lo, ok_hi = c + (MARGIN - lo), c + (1.0 - MARGIN - hi)
    raise ConfigError("transform.center", f"{c.tolist()} places the scene outside the domain: {where}; "
                                          f"a center within {_fmt(ok_lo)}..{_fmt(ok_hi)} fits{hint}")


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.4g}" for x in np.ravel(v)) + "]"


# ---------------------------------------------------------------------------- stage
# The last built-in scene generated in this process, by (name, make_scene arguments): generation
# is deterministic and takes seconds at 10^6 gaussians, and the warm stage worker (worker.py)
# runs prepare again for every run of the same scene.
_BUILTIN_CACHE: dict = {}


def _copy_scene(scene: GaussianScene) -> GaussianScene:
    """A copy whose arrays the caller may change without touching the cached scene."""
    return GaussianScene(means=scene.means.copy(), log_scales=scene.log_scales.copy(), quats=scene.quats.copy(),
                         opacity_logits=scene.opacity_logits.copy(), sh=scene.sh.copy(),
                         extras={k: np.array(v, copy=True) for k, v in scene.extras.items()})


def load_source(inputs: dict, scene_cfg: dict, log: logging.Logger) -> tuple[GaussianScene, str]:
    """The source-frame scene and its name: a built-in (``builtin:<name>``) or a file."""
    source = scene_cfg.get("source")
    if not isinstance(source, str) or not source:
        raise ConfigError("source", f"must be a .ply/.splat path or 'builtin:<name>', got {source!r}", scene_cfg.get("_path"))
    if source.startswith(BUILTIN_PREFIX):
        from .builtin_scenes import make_scene

        name = source[len(BUILTIN_PREFIX):]
        kwargs = scene_cfg.get("builtin") or {}
        if not isinstance(kwargs, dict):
            raise ConfigError("builtin", f"must be a mapping of make_scene arguments, got {kwargs!r}", scene_cfg.get("_path"))
        key = (name, repr(sorted(kwargs.items())))
        cached = _BUILTIN_CACHE.get(key)
        if cached is None:
            scene, _ground_truth = make_scene(name, **kwargs)
            _BUILTIN_CACHE.clear()
            _BUILTIN_CACHE[key] = scene
        else:  # the same deterministic scene as the last one this process generated (the warm worker)
            scene = cached
        scene = _copy_scene(scene)
        log.info("built-in scene %s (%s): %d gaussians%s", name, kwargs, scene.n,
                 "" if cached is None else " (generated earlier in this process)")
        return scene, source
    path = inputs.get("source") or source
    scene = load_gaussians(path, log=log)
    log.info("loaded %s: %d gaussians, SH degree %d, extras %s", path, scene.n, scene.sh_degree,
             sorted(scene.extras))
    return scene, str(path)


def run(inputs: dict, outputs: dict, cfg: dict, log: logging.Logger) -> dict:
    """Stage entry point (see the module docstring).

    inputs: ``{"source": path}`` for file scenes, nothing for built-ins.
    outputs: ``{"scene": .../scene.ply, "transform": .../transform.json}``.
    cfg: ``{"scene": {...}, "prepare": {...}}``.
    """
    scene_cfg = cfg.get("scene") or {}
    tcfg = transform_config(scene_cfg)
    rcfg = region_config(scene_cfg)
    pcfg = prepare_config(cfg)
    import time

    t0 = time.perf_counter()
    scene, source = load_source(inputs, scene_cfg, log)
    t1 = time.perf_counter()
    n_input = scene.n
    bounds_src_in = _bounds(scene.means)
    sim, tf, info = normalise_scene(scene, tcfg, pcfg, source, log, rcfg["box"])
    t2 = time.perf_counter()
    dropped = info["dropped"]
    simulated = ~np.asarray(sim.extras.get("static", np.zeros(sim.n, bool)), bool)
    bounds_sim = _bounds(sim.means[simulated])
    record = tf.to_dict()
    record.update({
        "source": source, "n_input": n_input, "n_kept": sim.n, "dropped": dropped,
        "bounds_src": info["bounds_src"], "bounds_src_input": bounds_src_in, "bounds_sim": bounds_sim,
        "up_axis": tcfg["up_axis"], "extent": float(tcfg["extent"]),
        "trim_quantile": float(pcfg["trim_quantile"]), "min_opacity": float(pcfg["min_opacity"]),
        "margin": MARGIN, "sh_degree": sim.sh_degree, "extras": sorted(sim.extras),
        "region_box": rcfg["box"], "n_static": info["n_static"],
    })
    save_gaussians(sim, outputs["scene"])
    write_json(outputs["transform"], record)
    timings = {"load": round(t1 - t0, 3), "normalise": round(t2 - t1, 3), "write": round(time.perf_counter() - t2, 3)}
    log.info("normalised %s: kept %d of %d gaussians (dropped %s; %d of them static surroundings outside "
             "region.box), scale %.6g, rotation %s, simulated bounds %s..%s", source, sim.n, n_input, dropped,
             info["n_static"], tf.scale, np.round(tf.R, 6).tolist(), _fmt(bounds_sim["min"]), _fmt(bounds_sim["max"]))
    log.info("wrote %s and %s", outputs["scene"], outputs["transform"])
    return {"n_input": n_input, "n_kept": sim.n, "dropped": dropped, "n_static": info["n_static"], "scale": tf.scale,
            "timings": timings}


def _bounds(points: np.ndarray) -> dict:
    """{"min": [3], "max": [3]} of points [M, 3]."""
    return {"min": points.min(axis=0).astype(float).tolist(), "max": points.max(axis=0).astype(float).tolist()}
