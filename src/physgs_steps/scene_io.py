"""Reading and writing 3D Gaussian Splatting scene files.

Formats:

* INRIA 3DGS ``.ply`` (read and write): ``binary_little_endian``, one ``vertex`` element
  with the scalar properties ``x y z``, optional ``nx ny nz`` (ignored), ``f_dc_0..2``,
  ``f_rest_0..M-1`` (M = 3 (K - 1), channel-major: ``f_rest_0..K-2`` are the red
  coefficients 1..K-1, then green, then blue), ``opacity`` (logit), ``scale_0..2``
  (log standard deviations) and ``rot_0..3`` (quaternion w x y z).  The SH degree 0..3 is
  inferred from M.  Any other scalar property is returned in ``scene.extras``: integers as
  int32 (a ``uchar`` property named ``filled`` as bool), floating point as float32.
* antimatter15 ``.splat`` (read only): 32 bytes per gaussian, 3 float32 position,
  3 float32 linear scale, 4 uint8 RGBA, 4 uint8 quaternion (w x y z) stored as
  ``q * 128 + 128``.

Validation (every problem raises :class:`~physgs_steps.errors.InputError` naming the file):
truncated data, missing/duplicate/list properties, ASCII or big-endian PLY, NaN/Inf values
(the message names each field, the count and the first index), zero gaussians,
zero-length quaternions, negative ``.splat`` scales, unknown file extensions.

Quaternion policy: a quaternion whose length differs from 1 by more than
``QUAT_UNIT_TOL`` is normalised and the repair is logged (count and largest deviation);
INRIA training leaves raw, unnormalised quaternions in its files, so this is routine.
A quaternion of length below ``QUAT_ZERO_TOL`` has no rotation to recover and is an error
(naming the count and the first index) rather than silently becoming the identity.
Quaternions within the tolerance are kept bit for bit, so ``save`` then ``load`` is exact.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
from numpy.lib import recfunctions as rfn

from .errors import InputError
from .gaussians import SH_C0, GaussianScene, sh_degree_from_k
from .runtime import atomic_path

QUAT_UNIT_TOL = 1e-5  # |‖q‖ - 1| above this -> normalise (logged)
QUAT_ZERO_TOL = 1e-12  # ‖q‖ below this -> error
SPLAT_RECORD = np.dtype([("pos", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rot", "u1", (4,))])
SPLAT_MIN_SCALE = 1e-8  # zero linear scales in .splat files (float underflow) are clamped to this

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_HEADER_LIMIT = 1 << 20
_CORE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
         "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
_IGNORED = {"nx", "ny", "nz"}
_REQUIRED_HINT = "x y z f_dc_0..2 opacity scale_0..2 rot_0..3"

_LOG = logging.getLogger("physgs.scene_io")


# ---------------------------------------------------------------------------- public API
def load_gaussians(path, log: logging.Logger | None = None) -> GaussianScene:
    """Load a 3DGS scene from an INRIA ``.ply`` or an antimatter15 ``.splat`` file.

    Args:
        path: file path; the format is chosen by the extension (``.ply`` / ``.splat``).
        log: logger for repairs (quaternion normalisation); default ``physgs.scene_io``.

    Returns:
        A validated :class:`GaussianScene` with finite values and unit quaternions.

    Raises:
        InputError: missing file, unknown extension, malformed or non-finite content.
    """
    log = log or _LOG
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found" if not path.exists() else "not a regular file")
    suffix = path.suffix.lower()
    with open(path, "rb") as f:
        magic = f.read(4)
    if suffix == ".ply":
        return _load_ply(path, log)
    if suffix == ".splat":
        if magic == b"ply\n" or magic == b"ply\r":
            raise InputError(path, "has the .splat extension but is a PLY file; rename it to .ply")
        return _load_splat(path, log)
    hint = " (the content looks like a PLY file; rename it to .ply)" if magic[:3] == b"ply" else ""
    raise InputError(path, f"unknown 3DGS file format '{path.suffix or '(no extension)'}': "
                           f"expected an INRIA .ply or an antimatter15 .splat{hint}")


def save_gaussians(scene: GaussianScene, path) -> None:
    """Save a scene as a binary little-endian INRIA 3DGS ``.ply`` (atomic write).

    Extras become extra vertex properties after the standard ones: bool arrays as
    ``uchar``, integer arrays as ``int`` (int32), everything else as ``float``.
    Only [N] per-gaussian scalars can be stored; other shapes raise ``InputError``.

    Args:
        scene: the scene (means [N, 3], log_scales [N, 3], quats [N, 4], opacity_logits [N],
            sh [N, K, 3], extras {name: [N]}).
        path: output ``.ply`` path.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise InputError(path, f"cannot write extension '{path.suffix}': only INRIA .ply is written")
    names, columns = _standard_columns(scene)
    extra_fields = []
    for key, arr in scene.extras.items():
        extra_fields.append(_extra_field(path, key, np.asarray(arr), scene.n, set(names)))
    dtype = np.dtype([(n, "<f4") for n in names] + [(k, t) for k, t, _ in extra_fields])
    data = np.empty(scene.n, dtype=dtype)
    for n, col in zip(names, columns):
        data[n] = col
    for key, _, values in extra_fields:
        data[key] = values
    header = _ply_header(scene.n, dtype)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            data.tofile(f)


# ---------------------------------------------------------------------------- PLY reading
def _load_ply(path: Path, log: logging.Logger) -> GaussianScene:
    n, dtype, start = _ply_layout(path)
    data = np.fromfile(path, dtype=dtype, count=n, offset=start)
    return _scene_from_vertices(path, data, log)


def _ply_layout(path: Path) -> tuple[int, np.dtype, int]:
    """(vertex count, vertex dtype, byte offset of the vertex data) of a 3DGS ``.ply``, after
    checking the header and that the file holds exactly the declared vertex data."""
    header, data_start = _read_header(path)
    elements = _parse_header(path, header)
    vertex_offset, (n, props) = _locate_vertex(path, elements)
    dtype = _vertex_dtype(path, props)
    _check_schema(path, [p for p, _ in props])
    if n == 0:
        raise InputError(path, "contains zero gaussians (element vertex 0)")
    start = data_start + vertex_offset
    need = n * dtype.itemsize
    have = path.stat().st_size - start
    if have < need:
        raise InputError(path, f"truncated: the header declares {n} vertices of {dtype.itemsize} bytes "
                               f"({need} bytes) but only {max(have, 0)} bytes of vertex data follow")
    if have > need and elements[-1][0] == "vertex":
        extra = have - need
        whole = f" ({extra // dtype.itemsize} more whole vertices)" if extra >= dtype.itemsize else ""
        raise InputError(path, f"{extra} bytes follow the {n} vertices the header declares{whole}: the header's "
                               "'element vertex' count is smaller than the data (or the file has trailing "
                               "bytes); fix the count in the header")
    return n, dtype, start


def probe(path) -> dict:
    """What a scene file holds, without reading its gaussians: ``{"format": "ply" | "splat",
    "n": gaussian count, "bytes": file size}``. Raises InputError on a missing file, an
    unknown extension or a malformed header / size (the checks of :func:`load_gaussians`
    that need no data)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found" if not path.exists() else "not a regular file")
    suffix = path.suffix.lower()
    size = path.stat().st_size
    if suffix == ".ply":
        n, _, _ = _ply_layout(path)
        return {"format": "ply", "n": n, "bytes": size}
    if suffix == ".splat":
        if size == 0 or size % SPLAT_RECORD.itemsize:
            raise InputError(path, f"size {size} bytes is not a positive multiple of the {SPLAT_RECORD.itemsize}-byte "
                                   ".splat record (truncated or not a .splat file)")
        return {"format": "splat", "n": size // SPLAT_RECORD.itemsize, "bytes": size}
    raise InputError(path, f"unknown 3DGS file format '{path.suffix or '(no extension)'}': "
                           "expected an INRIA .ply or an antimatter15 .splat")


def _read_header(path: Path) -> tuple[list[str], int]:
    """Return the header lines and the byte offset where the binary data starts."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_LIMIT)
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise InputError(path, "not a PLY file: it does not start with the line 'ply'")
    match = re.search(rb"\nend_header\r?\n", head)
    if match is None:
        raise InputError(path, f"PLY header has no 'end_header' line within the first {_HEADER_LIMIT} bytes")
    end = (match.start(), match.end())
    try:
        text = head[: end[0]].decode("ascii")
    except UnicodeDecodeError as e:
        raise InputError(path, f"PLY header contains non-ASCII bytes at offset {e.start}") from None
    return [line.strip() for line in text.splitlines()], end[1]


def _parse_header(path: Path, lines: list[str]) -> list[tuple[str, int, list[tuple[str, str]]]]:
    """Parse header lines into [(element name, count, [(property, numpy type)])]."""
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for lineno, line in enumerate(lines[1:], start=2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else ""
            _check_format(path, fmt)
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise InputError(path, f"PLY header line {lineno} is malformed: '{line}'")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise InputError(path, f"PLY header line {lineno}: property before any element")
            _parse_property(path, lineno, line, tok, elements[-1])
        else:
            raise InputError(path, f"PLY header line {lineno} is not understood: '{line}'")
    if fmt is None:
        raise InputError(path, "PLY header has no 'format' line")
    return elements


def _check_format(path: Path, fmt: str) -> None:
    if fmt == "binary_little_endian":
        return
    if fmt == "ascii":
        raise InputError(path, "is an ASCII PLY (format ascii), not a binary 3DGS file: a 3DGS .ply is "
                               f"binary_little_endian with vertex properties {_REQUIRED_HINT}")
    if fmt == "binary_big_endian":
        raise InputError(path, "is a big-endian PLY (format binary_big_endian); 3DGS .ply files are "
                               "binary_little_endian: convert it first")
    raise InputError(path, f"unknown PLY format '{fmt}'")


def _parse_property(path: Path, lineno: int, line: str, tok: list[str], element) -> None:
    name, _, props = element
    if len(tok) >= 2 and tok[1] == "list":
        if name == "vertex":
            raise InputError(path, f"vertex property '{tok[-1]}' is a list property (line {lineno}); "
                                   "a 3DGS .ply has only scalar vertex properties")
        props.append((tok[-1], "list"))
        return
    if len(tok) != 3:
        raise InputError(path, f"PLY header line {lineno} is malformed: '{line}'")
    if tok[1] not in _PLY_TYPES:
        raise InputError(path, f"PLY header line {lineno}: unknown property type '{tok[1]}'")
    props.append((tok[2], _PLY_TYPES[tok[1]]))


def _locate_vertex(path: Path, elements) -> tuple[int, tuple[int, list[tuple[str, str]]]]:
    """Byte offset of the vertex data after the header, and (count, properties)."""
    offset = 0
    for name, count, props in elements:
        if name == "vertex":
            return offset, (count, props)
        if any(t == "list" for _, t in props):
            raise InputError(path, f"element '{name}' with list properties precedes 'vertex'; "
                                   "not a 3DGS .ply")
        offset += count * sum(np.dtype(t).itemsize for _, t in props)
    raise InputError(path, "PLY has no 'vertex' element (not a 3DGS .ply)")


def _vertex_dtype(path: Path, props: list[tuple[str, str]]) -> np.dtype:
    seen = set()
    for p, _ in props:
        if p in seen:
            raise InputError(path, f"vertex property '{p}' appears twice")
        seen.add(p)
    return np.dtype([(p, "<" + t) for p, t in props])


def _check_schema(path: Path, names: list[str]) -> None:
    """Check the required 3DGS properties and the f_rest numbering."""
    missing = [p for p in _CORE if p not in names]
    if missing:
        raise InputError(path, f"not a 3DGS .ply: vertex properties {missing} are missing "
                               f"(found {names[:20]}{' ...' if len(names) > 20 else ''}); "
                               f"required: {_REQUIRED_HINT}")
    rest = [p for p in names if p.startswith("f_rest_")]
    expect = [f"f_rest_{i}" for i in range(len(rest))]
    if sorted(rest, key=_rest_index) != expect:
        raise InputError(path, f"f_rest_* properties are not numbered 0..{len(rest) - 1}: {rest}")
    m = len(rest)
    if m % 3 or (m // 3 + 1) not in (1, 4, 9, 16):
        raise InputError(path, f"{m} f_rest_* properties do not match SH degree 0..3 "
                               "(expected 0, 9, 24 or 45)")


def _rest_index(name: str) -> int:
    tail = name[len("f_rest_"):]
    return int(tail) if tail.isdigit() else -1


def _columns(data: np.ndarray, names: list[str]) -> np.ndarray:
    """[N, len(names)] float32 copy of the named fields of a structured array."""
    if not names:
        return np.zeros((data.shape[0], 0), np.float32)
    return rfn.structured_to_unstructured(data[names], dtype=np.float32, copy=True)


def _scene_from_vertices(path: Path, data: np.ndarray, log: logging.Logger) -> GaussianScene:
    names = list(data.dtype.names)
    _check_finite(path, data)
    _check_float32_range(path, data)
    n = data.shape[0]
    m = sum(1 for p in names if p.startswith("f_rest_"))
    k = m // 3 + 1
    sh = np.empty((n, k, 3), np.float32)
    sh[:, 0] = _columns(data, ["f_dc_0", "f_dc_1", "f_dc_2"])
    if m:
        rest = _columns(data, [f"f_rest_{i}" for i in range(m)])  # [N, 3 (K-1)] channel-major
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    quats = _checked_quats(path, _columns(data, ["rot_0", "rot_1", "rot_2", "rot_3"]), log)
    extras = {}
    for p in names:
        if p in _CORE or p in _IGNORED or p.startswith("f_rest_"):
            continue
        extras[p] = _extra_from_ply(p, data[p])
    return GaussianScene(
        means=_columns(data, ["x", "y", "z"]),
        log_scales=_columns(data, ["scale_0", "scale_1", "scale_2"]),
        quats=quats,
        opacity_logits=np.ascontiguousarray(data["opacity"], dtype=np.float32),
        sh=sh,
        extras=extras,
    )


def _extra_from_ply(name: str, values: np.ndarray) -> np.ndarray:
    """[N] extra property -> int32 / bool (uchar 'filled') / float32."""
    if values.dtype.kind in "iu":
        if name == "filled" and values.dtype.itemsize == 1:
            return values != 0
        return values.astype(np.int32)
    return values.astype(np.float32)


def _check_finite(path: Path, data: np.ndarray) -> None:
    """Raise naming every floating-point field with NaN/Inf, its count and first index."""
    problems = []
    for p in data.dtype.names:
        if data.dtype[p].kind != "f":
            continue
        bad = ~np.isfinite(data[p])
        if bad.any():
            problems.append(f"'{p}': {int(bad.sum())} values (first at index {int(np.argmax(bad))})")
    if problems:
        raise InputError(path, "non-finite (NaN/Inf) values in " + "; ".join(problems))


def _check_float32_range(path: Path, data: np.ndarray) -> None:
    """Float64 properties are stored as float32: raise naming every field whose finite values
    overflow float32 (they would become inf after the cast), its count and first index."""
    big = float(np.finfo(np.float32).max)
    problems = []
    for p in data.dtype.names:
        if data.dtype[p].kind != "f" or data.dtype[p].itemsize <= 4:
            continue
        bad = np.abs(data[p]) > big
        if bad.any():
            problems.append(f"'{p}': {int(bad.sum())} values (first at index {int(np.argmax(bad))}, "
                            f"{float(data[p][np.argmax(bad)]):.4g})")
    if problems:
        raise InputError(path, f"double-precision values beyond the float32 range (|x| > {big:.4g}) in "
                               + "; ".join(problems) + ": they cannot be represented in single precision")


def _checked_quats(path: Path, q: np.ndarray, log: logging.Logger, quantized: bool = False) -> np.ndarray:
    """[N, 4] quaternions -> [N, 4] unit quaternions (see the module docstring's policy)."""
    norm = np.sqrt(np.einsum("ij,ij->i", q.astype(np.float64), q.astype(np.float64)))  # [N]
    zero = norm < QUAT_ZERO_TOL
    if zero.any():
        raise InputError(path, f"{int(zero.sum())} zero-length quaternions (rot_0..3 all zero), "
                               f"first at index {int(np.argmax(zero))}: these gaussians have no orientation")
    off = np.abs(norm - 1.0) > QUAT_UNIT_TOL
    if off.any():
        q = q.copy()
        q[off] = (q[off].astype(np.float64) / norm[off, None]).astype(np.float32)
        level = logging.DEBUG if quantized else logging.INFO
        log.log(level, "%s: normalised %d of %d quaternions (largest | |q| - 1 | = %.3g)",
                path, int(off.sum()), q.shape[0], float(np.abs(norm - 1.0).max()))
    return q


# ---------------------------------------------------------------------------- .splat
def _load_splat(path: Path, log: logging.Logger) -> GaussianScene:
    size = path.stat().st_size
    if size == 0:
        raise InputError(path, "contains zero gaussians (empty .splat file)")
    if size % SPLAT_RECORD.itemsize:
        raise InputError(path, f"size {size} bytes is not a multiple of the {SPLAT_RECORD.itemsize}-byte "
                               f".splat record (truncated or not a .splat file)")
    rec = np.fromfile(path, dtype=SPLAT_RECORD)
    problems = []
    for field in ("pos", "scale"):
        bad = ~np.isfinite(rec[field]).all(axis=1)
        if bad.any():
            problems.append(f"'{field}': {int(bad.sum())} values (first at index {int(np.argmax(bad))})")
    if problems:
        raise InputError(path, "non-finite (NaN/Inf) values in " + "; ".join(problems))
    return GaussianScene(
        means=rec["pos"],
        log_scales=_splat_log_scales(path, rec["scale"], log),
        quats=_checked_quats(path, (rec["rot"].astype(np.float32) - 128.0) / 128.0, log, quantized=True),
        opacity_logits=_alpha_to_logit(rec["rgba"][:, 3]),
        sh=((rec["rgba"][:, None, :3].astype(np.float32) / 255.0 - 0.5) / SH_C0),
    )


def _splat_log_scales(path: Path, scale: np.ndarray, log: logging.Logger) -> np.ndarray:
    """[N, 3] linear scales -> [N, 3] log scales (zero clamped to SPLAT_MIN_SCALE, logged)."""
    neg = (scale < 0).any(axis=1)
    if neg.any():
        raise InputError(path, f"{int(neg.sum())} gaussians have negative scales, "
                               f"first at index {int(np.argmax(neg))}")
    small = scale < SPLAT_MIN_SCALE
    if small.any():
        log.warning("%s: %d scale values below %g clamped to it", path, int(small.sum()), SPLAT_MIN_SCALE)
    return np.log(np.maximum(scale, SPLAT_MIN_SCALE)).astype(np.float32)


def _alpha_to_logit(a: np.ndarray) -> np.ndarray:
    """[N] uint8 alpha -> [N] float32 logit, alpha clamped to [0.5/255, 1 - 0.5/255]."""
    eps = 0.5 / 255.0
    p = np.clip(a.astype(np.float64) / 255.0, eps, 1.0 - eps)
    return np.log(p / (1.0 - p)).astype(np.float32)


# ---------------------------------------------------------------------------- PLY writing
def _standard_columns(scene: GaussianScene) -> tuple[list[str], list[np.ndarray]]:
    """Property names in INRIA order and their [N] float32 columns."""
    n, k = scene.n, scene.sh.shape[1]
    sh_degree_from_k(k)
    rest = scene.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # [N, 3 (K-1)] channel-major
    zeros = np.zeros(n, np.float32)
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    cols = [scene.means[:, 0], scene.means[:, 1], scene.means[:, 2], zeros, zeros, zeros,
            scene.sh[:, 0, 0], scene.sh[:, 0, 1], scene.sh[:, 0, 2]]
    names += [f"f_rest_{i}" for i in range(rest.shape[1])]
    cols += [rest[:, i] for i in range(rest.shape[1])]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    cols += [scene.opacity_logits] + [scene.log_scales[:, i] for i in range(3)] + \
            [scene.quats[:, i] for i in range(4)]
    return names, cols


def _extra_field(path: Path, key: str, arr: np.ndarray, n: int, taken: set) -> tuple[str, str, np.ndarray]:
    """(name, little-endian type, [N] values) of one extra for writing."""
    if not key or any(c.isspace() for c in key) or not key.isascii():
        raise InputError(path, f"extra '{key}' is not a valid PLY property name")
    if key in taken or key in _CORE:
        raise InputError(path, f"extra '{key}' clashes with a standard 3DGS property")
    if arr.shape != (n,):
        raise InputError(path, f"extra '{key}' has shape {arr.shape}; only [N] per-gaussian scalars "
                               "can be stored in a .ply")
    if arr.dtype == np.bool_:
        return key, "u1", arr.astype(np.uint8)
    if arr.dtype.kind in "iu":
        info = np.iinfo(np.int32)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise InputError(path, f"extra '{key}' has values outside the int32 range")
        return key, "<i4", arr.astype(np.int32)
    return key, "<f4", arr.astype(np.float32)


def _ply_header(n: int, dtype: np.dtype) -> bytes:
    type_names = {"f4": "float", "i4": "int", "u1": "uchar"}
    lines = ["ply", "format binary_little_endian 1.0", "comment written by physgs_steps",
             f"element vertex {n}"]
    for name in dtype.names:
        lines.append(f"property {type_names[dtype[name].str[1:]]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")
