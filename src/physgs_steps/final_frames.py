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
        m = self.m
        h5.create_dataset("particle_index", data=np.asarray(particle_index, np.int64))
        h5.create_dataset("time", data=np.asarray(time, np.float64))
        self.dx = h5.create_dataset("x", (0, m, 3), np.float32, maxshape=(None, m, 3), chunks=(1, m, 3), **(codec or {}))
        self.dF = h5.create_dataset("F_minus_I", (0, m, 3, 3), np.float16, maxshape=(None, m, 3, 3),
                                    chunks=(1, m, 3, 3), **(codec or {}))
        self.lo, self.hi = np.full(3, np.inf), np.full(3, -np.inf)
        self._stride = max(1, int(math.ceil(m / MOTION_ROWS)))
        self._to_source = to_source

    def frame(self, k: int, x: np.ndarray, F: np.ndarray) -> None:
        """Store frame k: x [M, 3], F [M, 3, 3] (sim frame, float32)."""
        dev = np.asarray(F, np.float32) - np.eye(3, dtype=np.float32)
        big = np.abs(dev) >= F16_MAX
        if big.any():
            raise SimulationError(f"frame {k}: {int(big.any(axis=(1, 2)).sum())} particles have |F - I| >= {F16_MAX:g} "
                                  "(the simulation exploded); final.h5 stores F - I in float16")
        r = self.rows
        self.dx.resize(r + 1, axis=0)
        self.dF.resize(r + 1, axis=0)
        self.dx[r] = np.asarray(x, np.float32)
        self.dF[r] = dev.astype(np.float16)
        self.frame_row[k] = r
        self.rows += 1
        sub = np.asarray(x, np.float64)[:: self._stride]
        sub = sub[np.isfinite(sub).all(axis=1)]
        if self._to_source is not None and sub.shape[0]:
            sub = np.asarray(self._to_source(sub), np.float64)
        if sub.shape[0]:
            b = np.percentile(sub, [1.0, 99.0], axis=0)
            self.lo, self.hi = np.minimum(self.lo, b[0]), np.maximum(self.hi, b[1])

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
        b0 = getattr(self, "_b0", None)
        if b0 is None or not b0 <= r < b0 + len(self._bx):
            n = max(1, min(self.rows - r, READ_BLOCK_BYTES // max(1, self.m * (3 * 4 + 9 * 2))))
            self._bx = np.asarray(self.h5["x"][r:r + n], dtype=np.float32)
            self._bf = self.h5["F_minus_I"][r:r + n]
            self._b0 = b0 = r
        return self._bx[r - b0], self._bf[r - b0]

    def x(self, t: int) -> np.ndarray:
        """[M, 3] float32 positions of frame t."""
        return self._block(self.row(t))[0].copy()

    def F(self, t: int) -> np.ndarray:
        """[M, 3, 3] float32 deformation gradients of frame t (within the float16 error budget)."""
        return self._block(self.row(t))[1].astype(np.float32) + np.eye(3, dtype=np.float32)

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
