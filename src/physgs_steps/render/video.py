"""Video (H.264 mp4), PNG frames and a contact sheet, all written atomically.

The mp4 is written through imageio-ffmpeg's bundled ffmpeg: libx264, yuv420p (plays
everywhere), constant quality ``-crf``. yuv420p needs even image sizes: an odd width or
height is padded by repeating the last column/row (and logged by the caller).
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np

from ..errors import RenderError
from ..runtime import atomic_path


def even_size(width: int, height: int) -> tuple[int, int]:
    """The video size for an image size (each side rounded up to even)."""
    return width + (width % 2), height + (height % 2)


def pad_even(img: np.ndarray) -> np.ndarray:
    """[H, W, 3] uint8 -> the same image padded by edge repetition to even H and W."""
    h, w = img.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return img
    return np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


class VideoWriter:
    """Stream frames into an H.264 mp4; the file appears only when :meth:`close` succeeds.

    Frames go to ffmpeg from a background thread through a bounded queue (``queue`` frames), so
    the caller renders the next frames while ffmpeg encodes (a pipe write blocks while the
    encoder is behind; at 1080p x264 is slower than gsplat).  ``wait_seconds`` is the time
    :meth:`append` spent blocked on a full queue and ``close_seconds`` the encoding left after the
    last frame: together, what encoding added to the stage.

    Use as a context manager; an exception inside the block leaves no file behind.
    """

    def __init__(self, path, width: int, height: int, fps: float, crf: int = 18, preset: str = "medium",
                 queue: int = 8):
        import queue as _queue
        import threading

        import imageio_ffmpeg

        if width < 1 or height < 1:
            raise RenderError(f"{path}: cannot write a {width}x{height} video")
        self.path = Path(path)
        self.size = even_size(width, height)
        self._atomic = atomic_path(self.path)
        self._tmp = self._atomic.__enter__()
        self.n_frames = 0
        self.wait_seconds = 0.0
        self.close_seconds = 0.0
        self._gen = imageio_ffmpeg.write_frames(
            str(self._tmp), self.size, pix_fmt_in="rgb24", pix_fmt_out="yuv420p", fps=float(fps),
            codec="libx264", quality=None, macro_block_size=2, ffmpeg_log_level="error",
            output_params=["-crf", str(int(crf)), "-preset", str(preset), "-movflags", "+faststart"])
        self._gen.send(None)
        self._q: _queue.Queue = _queue.Queue(maxsize=max(1, int(queue)))
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._feed, name="physgs-video", daemon=True)
        self._thread.start()

    def _feed(self) -> None:
        while True:
            img = self._q.get()
            if img is None:
                return
            if self._error is None:
                try:
                    self._gen.send(img)
                except BaseException as e:  # ffmpeg died: reported by the next append/close
                    self._error = e

    def _check(self) -> None:
        if self._error is not None:
            raise RenderError(f"{self.path}: the video encoder failed: {self._error}")

    def append(self, img: np.ndarray) -> None:
        """Add one [H, W, 3] uint8 frame (the size given at construction, before even padding)."""
        import time

        img = pad_even(np.ascontiguousarray(img, dtype=np.uint8))
        if (img.shape[1], img.shape[0]) != self.size:
            raise RenderError(f"{self.path}: frame of size {img.shape[1]}x{img.shape[0]}, video is {self.size[0]}x{self.size[1]}")
        self._check()
        t0 = time.perf_counter()
        self._q.put(img)
        self.wait_seconds += time.perf_counter() - t0
        self.n_frames += 1

    def _stop_thread(self) -> None:
        if self._thread.is_alive():
            self._q.put(None)
            self._thread.join()

    def close(self) -> None:
        """Finish encoding and move the file into place."""
        import time

        if self.n_frames == 0:
            self.abort()
            raise RenderError(f"{self.path}: no frames were rendered")
        t0 = time.perf_counter()
        self._stop_thread()
        if self._error is not None:
            self.abort()
            raise RenderError(f"{self.path}: the video encoder failed: {self._error}")
        self._gen.close()
        self.close_seconds = time.perf_counter() - t0
        self._atomic.__exit__(None, None, None)

    def abort(self) -> None:
        """Stop encoding and delete the partial file."""
        self._error = self._error or RenderError("aborted")  # the feeder drops what is still queued
        try:
            self._stop_thread()
        except Exception:
            pass
        try:
            self._gen.close()
        except Exception:  # ffmpeg may already be gone; the partial file is removed below
            pass
        err = RenderError(f"{self.path}: video writing aborted")
        try:
            self._atomic.__exit__(RenderError, err, None)
        except RenderError:
            pass

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False


def read_video(path) -> np.ndarray:
    """[T, H, W, 3] uint8 frames of a video file (for checks and tests)."""
    import imageio_ffmpeg

    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    w, h = meta["size"]
    frames = [np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 3) for buf in gen]
    return np.stack(frames) if frames else np.zeros((0, h, w, 3), np.uint8)


def write_png(path, img: np.ndarray) -> None:
    """Write one [H, W, 3] uint8 image as PNG (atomically)."""
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)).save(tmp, format="PNG")


class FrameDir:
    """PNG frames ``frame_00000.png``... written into a hidden folder and moved into place at the end."""

    def __init__(self, path):
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.part")
        if self.tmp.exists():
            shutil.rmtree(self.tmp)
        self.tmp.mkdir(parents=True)
        self.n = 0

    def add(self, frame: int, img: np.ndarray) -> None:
        from PIL import Image

        Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)).save(self.tmp / f"frame_{frame:05d}.png", format="PNG")
        self.n += 1

    def commit(self) -> None:
        if self.path.exists():
            shutil.rmtree(self.path)
        os.replace(self.tmp, self.path)

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)


def sheet_indices(n_frames: int, n_tiles: int) -> list[int]:
    """Positions (0..n_frames-1) of the frames a contact sheet shows: evenly spaced, first and last included."""
    if n_frames <= 0:
        return []
    k = min(n_tiles, n_frames)
    return sorted({int(round(i * (n_frames - 1) / max(k - 1, 1))) for i in range(k)})


def contact_sheet(images: list[np.ndarray], labels: list[str], columns: int, tile_width: int,
                  background=(255, 255, 255)) -> np.ndarray:
    """A grid of downscaled frames with a caption under each.

    Args:
        images: list of [H, W, 3] uint8 frames (one size).
        labels: one caption per image.
        columns: images per row.
        tile_width: width of each thumbnail in pixels (height keeps the aspect ratio).
    Returns:
        [H_sheet, W_sheet, 3] uint8.
    """
    from PIL import Image, ImageDraw, ImageFont

    if not images:
        raise RenderError("contact sheet: no frames")
    h, w = images[0].shape[:2]
    tw = int(tile_width)
    th = max(1, int(round(h * tw / w)))
    font = ImageFont.load_default(size=max(10, tw // 16))
    cap = int(font.size * 1.6)
    gap = 4
    cols = max(1, min(columns, len(images)))
    rows = (len(images) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * (tw + gap) + gap, rows * (th + cap + gap) + gap), tuple(background))
    draw = ImageDraw.Draw(sheet)
    for i, (img, label) in enumerate(zip(images, labels)):
        r, c = divmod(i, cols)
        x0, y0 = gap + c * (tw + gap), gap + r * (th + cap + gap)
        # reducing_gap: a box reduction to 3x the thumbnail first, then Lanczos (Pillow's own
        # option; 8 frames of 1920x1080 to 320 wide: 0.29 -> 0.11 s on the 2-core machine)
        thumb = Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8)).resize((tw, th), Image.LANCZOS,
                                                                                  reducing_gap=3.0)
        sheet.paste(thumb, (x0, y0))
        draw.rectangle([x0, y0, x0 + tw - 1, y0 + th - 1], outline=(128, 128, 128))
        draw.text((x0 + 2, y0 + th + 2), label, fill=(0, 0, 0), font=font)
    return np.asarray(sheet)


def final_frames_sheet(videos: list, labels: list[str], out, columns: int = 2, tile_width: int = 320) -> np.ndarray:
    """A contact sheet of the last frame of each video (e.g. one scene before and after a
    change, side by side), written to ``out`` (PNG) and returned ([H, W, 3] uint8)::

        python -c "from physgs_steps.render.video import final_frames_sheet as f; f(['a.mp4', 'b.mp4'], ['main', 'branch'], 'sheet.png')"
    """
    if len(videos) != len(labels) or not videos:
        raise RenderError(f"final_frames_sheet: {len(videos)} videos and {len(labels)} labels (one label per video)")
    frames = []
    for v in videos:
        fr = read_video(v)
        if len(fr) == 0:
            raise RenderError(f"{v}: no frames")
        frames.append(fr[-1])
    sizes = {f.shape for f in frames}
    if len(sizes) != 1:
        raise RenderError(f"final_frames_sheet: the videos' frame sizes differ: {sorted(sizes)}")
    sheet = contact_sheet(frames, list(labels), columns, tile_width)
    write_png(out, sheet)
    return sheet
