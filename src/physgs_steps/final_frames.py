"""final.h5: the simulated frames, written by final_sim and read once by render.

Layout (format ``physgs-final/2``; docs/CONTRACTS.md):

* ``particle_index`` [M] int64: rows of particles.h5 whose states are stored, in column
  order (the carrier's drivers: the particles that carry the visible gaussians).
* ``time`` [T] float64: time of every frame (frame k at k / fps).
* ``frame_row`` [T] int32: the stored row of each frame. Frames held at rest
  (:mod:`physgs_steps.mpm.rest`) repeat the row of the frame where rest began, so a
  scene that settles after 2 s of a 5 s clip stores 60 rows, not 150.
* ``x`` [S, M, 3] float32: positions (sim frame, domain units) of the S stored rows.
* ``F_minus_I`` [S, M, 3, 3] float16: deformation gradient minus the identity.
* attributes ``format``, ``stats``, ``params``, ``sim_config`` (JSON), ``physical`` (the
  plausibility figures accumulated while simulating, :mod:`physgs_steps.physical`) and
  ``motion_box`` (JSON {"frame": "source" | "sim", "box": [[lo], [hi]]}: the union over
  frames of the 1-99 % box of the stored positions, in the capture's source frame when
  final_sim had transform.json; the render stage fits its camera to it without reading
  frames).

Chunks hold one stored row (the renderer reads whole frames, one after another); no
compression filter by default (``sim.compression``; measured in
``benchmarks/bench_final_h5.py``: gzip cost more time than the bytes it saved).

Error budget of the float16 storage: the renderer uses F only as ``Sigma(t) = F Sigma F^T``.
Storing ``F - I`` in float16 (11-bit significand, round to nearest) gives per entry
``|F_read - F| <= 2^-11 |F - I| + 2^-25`` (the second term: float16 subnormal spacing), so a
gaussian's axes change by at most 0.05 % of their deformation, e.g. 0.0005 px on a
100-px-wide gaussian stretched by 10 %. Positions stay float32: the reader's budget for
them is a fraction of a pixel at any output size, which float16's 2^-11 of a domain unit
(0.2 px on a 512-px view of the domain) would not meet. |F - I| beyond float16's range
(65504) cannot be stored: final_sim stops with a SimulationError (such a run has exploded).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .errors import InputError, SimulationError
from .runtime import json_text

FORMAT = "physgs-final/2"
F16_MAX = 65504.0
F16_BOUND_REL = 2.0 ** -11   # |F_read - F| <= F16_BOUND_REL |F - I| + F16_BOUND_ABS per entry
F16_BOUND_ABS = 2.0 ** -25
MOTION_ROWS = 4096  # positions per frame used for the motion box (a strided subset)
CODECS = ("none", "gzip", "lz4")


def codec_options(name: str, level: int = 1) -> dict:
    """h5py ``create_dataset`` keywords of a codec: ``none``, ``gzip`` (with byte shuffling)
    or ``lz4`` (Blosc LZ4 through the optional package hdf5plugin)."""
    if name == "none":
        return {}
    if name == "gzip":
        return {"compression": "gzip", "compression_opts": int(level), "shuffle": True}
    if name == "lz4":
        try:
            import hdf5plugin
        except ImportError:
            from .errors import ConfigError

            raise ConfigError("sim.compression", "lz4 needs the package hdf5plugin (pip install hdf5plugin)") from None
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=int(level), shuffle=hdf5plugin.Blosc.SHUFFLE))
    raise ValueError(f"unknown codec {name!r}; known: {CODECS}")


# float32 -> float16 bits, round to nearest even, done in blocks that stay in the CPU's cache
# (numpy's astype converts one element at a time: 2.2-4 ms for 60k particles' F - I on the
# 2-core CPU; this 0.6-1 ms; benchmarks/bench_final_h5.py --callback)
_H_REBIAS = np.uint32(((15 - 127) << 23) + 0xFFF + (1 << 32))  # exponent 127 -> 15, plus the rounding offset
_H_MIN_NORMAL = np.uint32(113 << 23)                            # 2^-14: float16's smallest normal number
_H_HALF = np.float32(0.5)                                       # aligns a subnormal's 10 bits at the bottom
_H_HALF_BITS = np.uint32(126 << 23)                             # its bits
_F16_BLOCK = 1 << 16


def to_float16(a: np.ndarray) -> np.ndarray:
    """``a.astype(np.float16)``, bit for bit, for a float32 array whose entries are all finite
    and below F16_MAX in magnitude (callers check; NaN, inf and overflow take numpy's path).

    Normal results: rebias the exponent and round the 13 dropped bits to nearest, ties to even
    (add 0xFFF plus the lowest kept bit, shift). Subnormal results (|a| < 2^-14): add 0.5 in
    float32, whose rounding (to nearest even at 2^-24, float16's subnormal spacing) leaves the
    float16 significand in the low bits. tests/test_carrier.py compares it with astype on every
    float16 value, the midpoints between neighbours and their float32 neighbours."""
    a = np.ascontiguousarray(a, np.float32)
    u = a.reshape(-1).view(np.uint32)
    n = len(u)
    res = np.empty(n, np.uint16)
    b = min(n, _F16_BLOCK)
    mag, o, t = np.empty(b, np.uint32), np.empty(b, np.uint32), np.empty(b, np.uint32)
    s, small = np.empty(b, np.float32), np.empty(b, bool)
    for i in range(0, n, b):
        j = min(n, i + b)
        k = j - i
        ui, mg, oo, tt, ss, sm = u[i:j], mag[:k], o[:k], t[:k], s[:k], small[:k]
        np.bitwise_and(ui, np.uint32(0x7FFFFFFF), out=mg)
        np.right_shift(mg, 13, out=oo)          # the lowest kept bit: ties go to even
        oo &= np.uint32(1)
        oo += mg
        oo += _H_REBIAS
        oo >>= 13
        np.add(mg.view(np.float32), _H_HALF, out=ss)
        sb = ss.view(np.uint32)
        sb -= _H_HALF_BITS
        np.less(mg, _H_MIN_NORMAL, out=sm)
        np.copyto(oo, sb, where=sm)
        np.right_shift(ui, 16, out=tt)
        tt &= np.uint32(0x8000)
        oo |= tt
        res[i:j] = oo
    return res.view(np.float16).reshape(a.shape)


def f_minus_identity(F: np.ndarray, eye: np.ndarray | None = None) -> np.ndarray:
    """F - I of [M, 3, 3] float32 as one contiguous subtraction of ``eye`` (:func:`tiled_identity`
    of M; made here when not given): the broadcast ``F - np.eye(3)`` runs 3-element inner loops
    and takes 3x as long. The same value for every entry (x - 0 is x, -0 included)."""
    F = np.ascontiguousarray(F, np.float32)
    if eye is None:
        eye = tiled_identity(len(F))
    return (F.reshape(-1) - eye).reshape(F.shape)


def tiled_identity(m: int) -> np.ndarray:
    """[9 M] float32: M flattened 3x3 identities."""
    return np.tile(np.eye(3, dtype=np.float32).reshape(-1), int(m))


class FinalWriter:
    """Writes final.h5 frame by frame into an open, empty h5py.File.

    Args:
        h5: the file (opened for writing).
        particle_index: [M] rows of particles.h5 that are stored.
        time: [T] frame times in s.
        codec: h5py dataset keywords (:func:`codec_options`).
        to_source: optional map of [K, 3] sim-frame points to the source frame (the motion
            box is then recorded in the source frame, as the camera needs it).
    """

    def __init__(self, h5, particle_index: np.ndarray, time: np.ndarray, codec: dict | None = None,
                 to_source=None):
        self.h5 = h5
        self.m = int(len(particle_index))
        self.n_frames = int(len(time))
        self.rows = 0
        self.frame_row = np.full(self.n_frames, -1, np.int32)
        m, n = self.m, self.n_frames
        h5.create_dataset("particle_index", data=np.asarray(particle_index, np.int64))
        h5.create_dataset("time", data=np.asarray(time, np.float64))
        # room for every frame, shrunk to the stored rows in finish(): a chunk is allocated when
        # it is written, so rows never written (frames held at rest) take no space in the file
        self.dx = h5.create_dataset("x", (n, m, 3), np.float32, maxshape=(None, m, 3), chunks=(1, m, 3), **(codec or {}))
        self.dF = h5.create_dataset("F_minus_I", (n, m, 3, 3), np.float16, maxshape=(None, m, 3, 3),
                                    chunks=(1, m, 3, 3), **(codec or {}))
        # without a filter a row's chunk is its bytes: written with H5Dwrite_chunk (no selection,
        # no conversion); with a codec through h5py's ordinary path (HDF5 compresses)
        self._direct = not codec
        self._eye = tiled_identity(m)
        self.lo, self.hi = np.full(3, np.inf), np.full(3, -np.inf)
        self._stride = max(1, int(math.ceil(m / MOTION_ROWS)))
        self._to_source = to_source

    def frame(self, k: int, x: np.ndarray, F: np.ndarray) -> np.ndarray | None:
        """Store frame k: x [M, 3], F [M, 3, 3] (sim frame, float32).

        Returns F - I as float32 [M, 3, 3] when every entry of F is finite (the
        ``f_minus_i`` of :meth:`PhysicalFigures.add`, which then need not compute it), else None."""
        x_in = x
        try:   # whole rows, C order: the bytes of a chunk (h5py's write broadcast too)
            x = np.ascontiguousarray(np.broadcast_to(np.asarray(x, np.float32), (self.m, 3)))
            F = np.ascontiguousarray(np.broadcast_to(np.asarray(F, np.float32), (self.m, 3, 3)))
        except ValueError:
            raise ValueError(f"frame {k}: x {np.shape(x)} and F {np.shape(F)} do not fit ({self.m}, 3) and "
                             f"({self.m}, 3, 3)") from None
        dev = f_minus_identity(F, self._eye)
        # one min and one max instead of |dev| >= F16_MAX per entry: both inside the float16
        # range means every entry is finite and storable; otherwise (NaN, inf, huge) the exact
        # entry-wise check below decides
        fast = dev.size == 0 or bool(-F16_MAX < dev.min() and dev.max() < F16_MAX)
        if fast:
            dev16 = to_float16(dev)
        else:
            dev = F - np.eye(3, dtype=np.float32)   # the reference expression (NaN payloads as before)
            big = np.abs(dev) >= F16_MAX
            if big.any():
                raise SimulationError(f"frame {k}: {int(big.any(axis=(1, 2)).sum())} particles have |F - I| >= {F16_MAX:g} "
                                      "(the simulation exploded); final.h5 stores F - I in float16")
            dev16 = dev.astype(np.float16)
        r = self.rows
        if r >= self.n_frames:
            raise ValueError(f"frame {k}: all {self.n_frames} rows are written")
        if self._direct:
            self.dx.id.write_direct_chunk((r, 0, 0), x)
            self.dF.id.write_direct_chunk((r, 0, 0, 0), dev16)
        else:
            self.dx[r] = x
            self.dF[r] = dev16
        self.frame_row[k] = r
        self.rows += 1
        sub = np.asarray(x_in)[:: self._stride].astype(np.float64)
        if not np.isfinite(sub.sum()):   # a finite sum: every entry is finite
            sub = sub[np.isfinite(sub).all(axis=1)]
        if self._to_source is not None and sub.shape[0]:
            sub = np.asarray(self._to_source(sub), np.float64)
        if sub.shape[0]:
            b = np.percentile(sub, [1.0, 99.0], axis=0)
            self.lo, self.hi = np.minimum(self.lo, b[0]), np.maximum(self.hi, b[1])
        return dev if fast else None

    def hold(self, k: int) -> None:
        """Frame k repeats the newest stored row (the state is held at rest)."""
        if self.rows == 0:
            raise ValueError("hold() before any frame was stored")
        self.frame_row[k] = self.rows - 1

    def truncate(self, n: int) -> None:
        """Keep frames 0..n-1 only (an unstable run kept with ``sim.on_unstable: keep``)."""
        n = int(n)
        if not 1 <= n <= self.n_frames:
            raise ValueError(f"truncate({n}) outside 1..{self.n_frames}")
        time = np.asarray(self.h5["time"][:n], np.float64)
        del self.h5["time"]
        self.h5.create_dataset("time", data=time)
        self.frame_row = self.frame_row[:n]
        self.n_frames = n

    def finish(self, attrs: dict) -> None:
        """Write ``frame_row`` and the attributes (dicts become JSON). Every frame must be set."""
        missing = np.flatnonzero(self.frame_row < 0)
        if missing.size:
            raise SimulationError(f"final.h5: frames {missing[:10].tolist()} were never written")
        self.h5.create_dataset("frame_row", data=self.frame_row)
        self.dx.resize(self.rows, axis=0)   # the rows never written (held frames, truncate) go
        self.dF.resize(self.rows, axis=0)
        self.h5.attrs["format"] = FORMAT
        box = None
        if np.isfinite(self.lo).all():
            box = {"frame": "sim" if self._to_source is None else "source", "box": [self.lo.tolist(), self.hi.tolist()]}
        self.h5.attrs["motion_box"] = json_text(box)
        for k, v in attrs.items():
            self.h5.attrs[k] = v if isinstance(v, str) else json_text(v, default=str)


READ_BLOCK_BYTES = 16 << 20  # FinalFrames reads rows in blocks of about this size


class FinalFrames:
    """Read access to final.h5 (module docstring). A context manager.

    Attributes:
        n_frames: T; m: stored particles M; rows: stored rows S.
        particle_index: [M] int64; time: [T] float64; frame_row: [T] int32.
    """

    def __init__(self, path):
        import h5py

        self.path = Path(path)
        self._b0, self._bx, self._bf = None, None, None  # the block of rows read last (_block)
        if not self.path.is_file():
            raise InputError(self.path, "frames file not found")
        try:
            self.h5 = h5py.File(self.path, "r")
        except OSError as e:
            raise InputError(self.path, f"not a readable HDF5 file: {e}") from None
        try:
            self._check()
        except BaseException:
            self.close()
            raise

    def _check(self) -> None:
        h = self.h5
        fmt = h.attrs.get("format")
        if fmt != FORMAT:
            raise InputError(self.path, f"format {fmt!r} is not {FORMAT!r} (a final.h5 of an older version: "
                                        "re-run final_sim)")
        missing = [k for k in ("x", "F_minus_I", "particle_index", "time", "frame_row") if k not in h]
        if missing:
            raise InputError(self.path, f"missing datasets {missing}")
        x, f = h["x"], h["F_minus_I"]
        self.rows, self.m = int(x.shape[0]), int(x.shape[1]) if x.ndim == 3 else -1
        self.particle_index = np.asarray(h["particle_index"][...], np.int64)
        self.time = np.asarray(h["time"][...], np.float64)
        self.frame_row = np.asarray(h["frame_row"][...], np.int64)
        self.n_frames = int(self.time.shape[0])
        problems = []
        if x.ndim != 3 or x.shape[2] != 3:
            problems.append(f"x has shape {x.shape}, expected [S, M, 3]")
        elif f.shape != (self.rows, self.m, 3, 3):
            problems.append(f"F_minus_I has shape {f.shape}, expected {(self.rows, self.m, 3, 3)}")
        elif self.rows < 1 or self.m < 1:
            problems.append(f"no stored frames or particles (x has shape {x.shape})")
        elif self.particle_index.shape != (self.m,):
            problems.append(f"particle_index has shape {self.particle_index.shape}, expected ({self.m},)")
        elif self.frame_row.shape != (self.n_frames,) or self.n_frames < 1:
            problems.append(f"frame_row has shape {self.frame_row.shape}, time has {self.n_frames} frames")
        elif self.frame_row.min() < 0 or self.frame_row.max() >= self.rows:
            problems.append(f"frame_row spans [{self.frame_row.min()}, {self.frame_row.max()}] but {self.rows} rows are stored")
        if problems:
            raise InputError(self.path, "; ".join(problems))

    def __enter__(self) -> "FinalFrames":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def row(self, t: int) -> int:
        """The stored row of frame t."""
        return int(self.frame_row[t])

    def _block(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """(x, F_minus_I) of stored row r, from the block of rows read with it.

        A miss reads rows r .. r + B - 1 of both datasets in one call each (B: READ_BLOCK_BYTES
        worth of rows, at least 1), so a reader going forward through the frames (the render
        stage) makes one HDF5 read per block instead of two per frame (about 1.4 ms a frame of
        4.5k particles on the GPU machine's host, mostly h5py's per-call work)."""
        b0 = self._b0
        if b0 is None or not b0 <= r < b0 + len(self._bx):
            n = max(1, min(self.rows - r, READ_BLOCK_BYTES // max(1, self.m * (3 * 4 + 9 * 2))))
            self._bx = np.asarray(self.h5["x"][r:r + n], dtype=np.float32)
            self._bf = self.h5["F_minus_I"][r:r + n]
            self._b0 = b0 = r
        return self._bx[r - b0], self._bf[r - b0]

    def x(self, t: int) -> np.ndarray:
        """[M, 3] float32 positions of frame t (a copy of :meth:`x_view`)."""
        return self.x_view(t).copy()

    def x_view(self, t: int) -> np.ndarray:
        """[M, 3] float32 positions of frame t: a view into the block of rows read with it (no
        copy; do not write to it)."""
        return self._block(self.row(t))[0]

    def F_minus_I(self, t: int) -> np.ndarray:
        """[M, 3, 3] float16 ``F - I`` of frame t as stored: a view into the block of rows read
        with it (no copy; do not write to it). ``F(t)`` is this in float32 plus the identity."""
        return self._block(self.row(t))[1]

    def F(self, t: int) -> np.ndarray:
        """[M, 3, 3] float32 deformation gradients of frame t (within the float16 error budget)."""
        return self.F_minus_I(t).astype(np.float32) + np.eye(3, dtype=np.float32)

    def attr(self, name: str):
        """A JSON attribute decoded (None when absent)."""
        raw = self.h5.attrs.get(name)
        if raw is None:
            return None
        try:
            return json.loads(raw)
        except (TypeError, ValueError) as e:
            raise InputError(self.path, f"attribute {name!r} is not valid JSON: {e}") from None

    @property
    def motion_box(self) -> tuple[str, np.ndarray, np.ndarray] | None:
        """(frame "source" or "sim", [3] lo, [3] hi) of the motion, or None."""
        rec = self.attr("motion_box")
        if rec is None:
            return None
        return rec["frame"], np.asarray(rec["box"][0], float), np.asarray(rec["box"][1], float)

    def close(self) -> None:
        self.h5.close()
