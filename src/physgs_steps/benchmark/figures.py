"""The benchmark's figures: small contact sheets (one row of frames per scene x variant), the
BGDO side-by-side, and the stress-vs-E plot. PNGs, written atomically."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..runtime import atomic_path


def video_frames(video: str, n: int) -> tuple[list[np.ndarray], list[int], int]:
    """``n`` frames evenly spaced over a video (first and last included): (frames, indices, total)."""
    from ..metrics import read_video_frames

    info, frames = read_video_frames(video, n)
    return frames, list(info["sampled_frames"]), int(info["n_frames"])


def _fit(img: np.ndarray, height: int):
    from PIL import Image

    h, w = img.shape[:2]
    return Image.fromarray(img).resize((max(1, int(round(w * height / h))), height), Image.BILINEAR)


def strip_sheet(rows: list[tuple[str, list[np.ndarray] | None, str | None]], path: str | Path, height: int = 96,
                caption: str | None = None) -> None:
    """A PNG with one row per entry: a label, then its frames scaled to ``height`` pixels.

    rows: (label, frames or None, note shown instead of / under the frames, e.g. "no video: ...").
    """
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default(size=max(10, height // 8))
    pad, label_w = 4, max(160, height * 2)
    tiles = [[_fit(f, height) for f in (frames or [])] for _, frames, _ in rows]
    width = label_w + max([sum(t.width + pad for t in ts) for ts in tiles] + [height * 4]) + pad
    row_h = height + pad
    top = int(font.size * 1.8) if caption else 0
    sheet = Image.new("RGB", (width, top + len(rows) * row_h + pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    if caption:
        draw.text((pad, pad), caption, fill=(0, 0, 0), font=font)
    for i, ((label, _, note), ts) in enumerate(zip(rows, tiles)):
        y = top + pad + i * row_h
        draw.multiline_text((pad, y + 2), _wrap(label, label_w, font), fill=(0, 0, 0), font=font)
        x = label_w
        for t in ts:
            sheet.paste(t, (x, y))
            x += t.width + pad
        if note:
            draw.multiline_text((x + pad if ts else label_w, y + height // 3), _wrap(note, width - x - 2 * pad, font),
                                fill=(160, 0, 0), font=font)
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")


def _wrap(text: str, width_px: int, font) -> str:
    words, lines, cur = str(text).split(), [], ""
    for w in words:
        trial = (cur + " " + w).strip()
        if cur and font.getlength(trial) > width_px:
            lines.append(cur)
            cur = w
        else:
            cur = trial
    if cur:
        lines.append(cur)
    return "\n".join(lines[:4])


def difference_frames(a: list[np.ndarray], b: list[np.ndarray], gain: float = 4.0) -> list[np.ndarray]:
    """|a - b| per frame (amplified, inverted so that equal pixels are white)."""
    out = []
    for fa, fb in zip(a, b):
        if fa.shape != fb.shape:
            continue
        d = np.abs(fa.astype(np.int16) - fb.astype(np.int16)).max(axis=2, keepdims=True)
        d = np.clip(d * gain, 0, 255).astype(np.uint8)
        out.append(np.repeat(255 - d, 3, axis=2))
    return out


def stress_plot(rows: list[dict], band, path: str | Path, title: str) -> None:
    """Per-particle stress (median, 10-90 % band, mean) and the BGDO step against initial E."""
    from .. import reporting as R

    rows = sorted(rows, key=lambda r: r["E"])
    E = np.array([r["E"] for r in rows], float)
    with R.figure(path, size=(7.5, 7.0), nrows=2, sharex=True) as (fig, axes):
        ax1, ax2 = axes
        ax1.set_xscale("log")
        ax1.set_yscale("log")
        have = [i for i, r in enumerate(rows) if (r.get("stress") or {}).get("n")]
        if have:
            st = [rows[i]["stress"] for i in have]
            lo = np.maximum([s["p10"] for s in st], 1e-3)
            hi = np.maximum([s["p90"] for s in st], 1e-3)
            ax1.fill_between(E[have], lo, hi, alpha=0.25, label="per-particle 10-90 %")
            ax1.plot(E[have], np.maximum([s["median"] for s in st], 1e-3), "o-", ms=3, label="per-particle median")
            ax1.plot(E[have], np.maximum([s["mean"] for s in st], 1e-3), "s", ms=2.5, label="per-particle mean")
        ylo, yhi = ax1.get_ylim()
        for fate, marker, y, text in (("exploded", "rx", yhi / 2, "forward run exploded"),
                                      ("broken", "kv", ylo * 2, "forward run collapsed")):
            idx = [i for i, r in enumerate(rows) if r.get("fate") == fate]
            if idx:
                ax1.plot(E[idx], np.full(len(idx), y), marker, ms=5, label=text)
        ax1.set_ylim(ylo, yhi)
        ax1.set_ylabel("|d||tau_p|| / dlog E| = ||tau_p|| [Pa]")
        ax1.set_title(title, fontsize=8)
        ax1.legend(loc="upper left", fontsize=7)
        G = np.array([np.nan if r.get("G") is None else -float(r["G"]) for r in rows])
        ax2.plot(E, G, "o-", ms=3, color="C3", label="BGDO step -G (change of log E)")
        ax2.axhline(0.0, color="k", lw=0.6)
        ax2.set_ylabel("change of log E")
        ax2.set_xlabel("initial Young's modulus E [Pa]")
        ax3 = ax2.twinx()
        d = np.array([np.nan if r.get("delta") is None else float(r["delta"]) for r in rows])
        ax3.plot(E, d, "^", ms=3, color="C2", label="mean deformation delta")
        ax3.set_ylabel("delta (key frames)", color="C2")
        if band:
            for a in (ax1, ax2):
                a.axvspan(band[0], band[1], color="C1", alpha=0.12)
        h1, l1 = ax2.get_legend_handles_labels()
        h2, l2 = ax3.get_legend_handles_labels()
        ax2.legend(h1 + h2, l1 + l2, loc="lower left", fontsize=7)
