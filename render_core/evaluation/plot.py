"""Training curves as PNG without matplotlib: a small numpy line-plot renderer and a built-in 3x5 bitmap font.

:func:`plot_curves` reads a training log (``log.jsonl``: one JSON object per line with ``iteration`` and the logged
values, e.g. ``loss``, ``l1``, ``ssim``, ``alpha``, ``psnr``, ``seconds``) and draws one panel per key, stacked
vertically: the curve against the iteration, axes, a grid at round tick values with their labels, and a title
line with the key's last, minimum and maximum values (and the iterations where the extremes occur).

:func:`draw_text` and :func:`write_png` are shared with the evaluation's contact sheet.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

# 3x5 glyphs, rows top to bottom ('#' = ink). Text is drawn upper-case; unknown characters draw as '?'.
_GLYPHS = {
    "A": (".#.", "#.#", "###", "#.#", "#.#"), "B": ("##.", "#.#", "##.", "#.#", "##."),
    "C": (".##", "#..", "#..", "#..", ".##"), "D": ("##.", "#.#", "#.#", "#.#", "##."),
    "E": ("###", "#..", "##.", "#..", "###"), "F": ("###", "#..", "##.", "#..", "#.."),
    "G": (".##", "#..", "#.#", "#.#", ".##"), "H": ("#.#", "#.#", "###", "#.#", "#.#"),
    "I": ("###", ".#.", ".#.", ".#.", "###"), "J": ("..#", "..#", "..#", "#.#", ".#."),
    "K": ("#.#", "#.#", "##.", "#.#", "#.#"), "L": ("#..", "#..", "#..", "#..", "###"),
    "M": ("#.#", "###", "###", "#.#", "#.#"), "N": ("##.", "#.#", "#.#", "#.#", "#.#"),
    "O": (".#.", "#.#", "#.#", "#.#", ".#."), "P": ("##.", "#.#", "##.", "#..", "#.."),
    "Q": (".#.", "#.#", "#.#", "##.", ".##"), "R": ("##.", "#.#", "##.", "#.#", "#.#"),
    "S": (".##", "#..", ".#.", "..#", "##."), "T": ("###", ".#.", ".#.", ".#.", ".#."),
    "U": ("#.#", "#.#", "#.#", "#.#", "###"), "V": ("#.#", "#.#", "#.#", "#.#", ".#."),
    "W": ("#.#", "#.#", "###", "###", "#.#"), "X": ("#.#", "#.#", ".#.", "#.#", "#.#"),
    "Y": ("#.#", "#.#", ".#.", ".#.", ".#."), "Z": ("###", "..#", ".#.", "#..", "###"),
    "0": ("###", "#.#", "#.#", "#.#", "###"), "1": (".#.", "##.", ".#.", ".#.", "###"),
    "2": ("##.", "..#", ".#.", "#..", "###"), "3": ("##.", "..#", ".#.", "..#", "##."),
    "4": ("#.#", "#.#", "###", "..#", "..#"), "5": ("###", "#..", "##.", "..#", "##."),
    "6": (".##", "#..", "###", "#.#", "###"), "7": ("###", "..#", ".#.", ".#.", ".#."),
    "8": ("###", "#.#", "###", "#.#", "###"), "9": ("###", "#.#", "###", "..#", "##."),
    ".": ("...", "...", "...", "...", ".#."), ",": ("...", "...", "...", ".#.", "#.."),
    "-": ("...", "...", "###", "...", "..."), "+": ("...", ".#.", "###", ".#.", "..."),
    ":": ("...", ".#.", "...", ".#.", "..."), "=": ("...", "###", "...", "###", "..."),
    "_": ("...", "...", "...", "...", "###"), "/": ("..#", "..#", ".#.", "#..", "#.."),
    "(": (".#.", "#..", "#..", "#..", ".#."), ")": (".#.", "..#", "..#", "..#", ".#."),
    "|": (".#.", ".#.", ".#.", ".#.", ".#."), "%": ("#.#", "..#", ".#.", "#..", "#.#"),
    "#": ("#.#", "###", "#.#", "###", "#.#"), "?": ("##.", "..#", ".#.", "...", ".#."),
    " ": ("...", "...", "...", "...", "..."),
}
_FONT = {c: np.array([[ch == "#" for ch in row] for row in rows], dtype=bool) for c, rows in _GLYPHS.items()}
GLYPH_W, GLYPH_H = 3, 5  # pixels at scale 1; characters advance by GLYPH_W + 1

WHITE = (255, 255, 255)
BLACK = (0, 0, 0)
GRID = (225, 225, 225)
AXIS = (60, 60, 60)
TEXT = (30, 30, 30)
COLOURS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (23, 190, 207))


def text_width(text: str, scale: int = 1) -> int:
    """Pixel width of ``text`` drawn by :func:`draw_text` at ``scale``."""
    return max(0, len(text) * (GLYPH_W + 1) - 1) * scale


def draw_text(img: np.ndarray, x: int, y: int, text: str, colour=TEXT, scale: int = 1) -> None:
    """Draw ``text`` into ``img`` [H, W, 3] uint8 with its top-left corner at (x, y); clipped at the edges."""
    h, w = img.shape[:2]
    for k, ch in enumerate(text.upper()):
        glyph = _FONT.get(ch, _FONT["?"])
        if scale > 1:
            glyph = glyph.repeat(scale, 0).repeat(scale, 1)
        gx = x + k * (GLYPH_W + 1) * scale
        ys, xs = np.nonzero(glyph)
        ys, xs = ys + y, xs + gx
        keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        img[ys[keep], xs[keep]] = colour


def draw_polyline(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, colour, thickness: int = 2) -> None:
    """Connect the points (xs[i], ys[i]) (pixel coordinates, floats) with straight segments."""
    xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
    if xs.size == 0:
        return
    if xs.size == 1:
        px, py = xs, ys
    else:
        steps = np.maximum(np.ceil(np.maximum(np.abs(np.diff(xs)), np.abs(np.diff(ys)))), 1).astype(np.int64)
        seg = np.repeat(np.arange(steps.size), steps)
        t = (np.arange(seg.size) - np.repeat(np.cumsum(steps) - steps, steps)) / steps[seg]
        px = np.concatenate([xs[seg] + t * (xs[seg + 1] - xs[seg]), xs[-1:]])
        py = np.concatenate([ys[seg] + t * (ys[seg + 1] - ys[seg]), ys[-1:]])
    px, py = np.rint(px).astype(np.int64), np.rint(py).astype(np.int64)
    h, w = img.shape[:2]
    for dy in range(thickness):
        for dx in range(thickness):
            qx, qy = px + dx - thickness // 2, py + dy - thickness // 2
            keep = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
            img[qy[keep], qx[keep]] = colour


def nice_ticks(lo: float, hi: float, count: int = 5) -> np.ndarray:
    """Round tick values (1, 2 or 5 times a power of ten apart) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return np.zeros(0)
    if hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / max(count - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1.0, 2.0, 5.0, 10.0) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = np.arange(first, hi + step * 1e-9, step)
    return ticks[(ticks >= lo - step * 1e-9) & (ticks <= hi + step * 1e-9)]


def format_number(v: float) -> str:
    """Short label for a tick or a value: up to 4 significant digits, scientific when very large or small."""
    if v == 0 or not math.isfinite(v):
        return "0" if v == 0 else str(v)
    a = abs(v)
    if a >= 1e5 or a < 1e-3:
        return f"{v:.1e}".replace("e-0", "e-").replace("e+0", "e")
    return f"{v:.4g}"


def write_png(path: str | os.PathLike, pixels: np.ndarray) -> Path:
    """Write an [H, W, 3] uint8 image with OpenImageIO (the format follows the extension)."""
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pixels = np.ascontiguousarray(pixels, dtype=np.uint8)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    ok = out.open(str(path), oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], "uint8"))
    ok = ok and out.write_image(pixels)
    err = out.geterror()
    out.close()
    if not ok:
        raise OSError(f"cannot write {path}: {err}")
    return path


def read_log(path: str | os.PathLike) -> list[dict]:
    """The records of a ``log.jsonl`` (blank and malformed lines are skipped: a run may be writing the last one)."""
    records = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict):
                records.append(rec)
    return records


def _series(records: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, values) of the records with a finite number under ``key``."""
    xs, ys = [], []
    for n, rec in enumerate(records):
        v, it = rec.get(key), rec.get("iteration", n)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            continue
        if isinstance(it, bool) or not isinstance(it, (int, float)) or not math.isfinite(it):
            it = n
        xs.append(float(it))
        ys.append(float(v))
    return np.asarray(xs), np.asarray(ys)


def _panel(img: np.ndarray, top: int, height: int, key: str, xs: np.ndarray, ys: np.ndarray, colour,
           x_range: tuple[float, float], scale: int) -> None:
    w = img.shape[1]
    ch = (GLYPH_H + 2) * scale  # a text line
    left, right = text_width("000000", scale) + 8, w - text_width("00000", scale) // 2 - 6  # room for tick labels
    y0, y1 = top + ch + 6, top + height - 2 * ch - 4  # plot area rows (inclusive); below: ticks, axis name
    if ys.size:
        i_min, i_max = int(np.argmin(ys)), int(np.argmax(ys))
        title = (f"{key}  last {format_number(ys[-1])}  min {format_number(ys[i_min])} at {xs[i_min]:.0f}"
                 f"  max {format_number(ys[i_max])} at {xs[i_max]:.0f}")
    else:
        title = f"{key}  (no data)"
    draw_text(img, left, top + 2, title, colour, scale)
    lo_x, hi_x = x_range
    lo_y, hi_y = (float(ys.min()), float(ys.max())) if ys.size else (0.0, 1.0)
    if hi_y - lo_y < 1e-12 * max(1.0, abs(hi_y)):
        pad = max(abs(hi_y) * 0.05, 1e-6)
        lo_y, hi_y = lo_y - pad, hi_y + pad
    else:
        pad = 0.05 * (hi_y - lo_y)
        lo_y, hi_y = lo_y - pad, hi_y + pad

    def px(x):
        return left + (np.asarray(x) - lo_x) / max(hi_x - lo_x, 1e-12) * (right - left)

    def py(y):
        return y1 - (np.asarray(y) - lo_y) / (hi_y - lo_y) * (y1 - y0)

    for t in nice_ticks(lo_y, hi_y, max(2, (y1 - y0) // (ch * 3))):
        r = int(round(float(py(t))))
        img[r, left:right + 1] = GRID
        label = format_number(float(t))
        draw_text(img, left - 4 - text_width(label, scale), r - GLYPH_H * scale // 2, label, TEXT, scale)
    for t in nice_ticks(lo_x, hi_x, max(2, (right - left) // (text_width("000000", scale) * 2))):
        c = int(round(float(px(t))))
        img[y0:y1 + 1, c] = GRID
        label = format_number(float(t))
        draw_text(img, c - text_width(label, scale) // 2, y1 + 3, label, TEXT, scale)
    img[y0:y1 + 1, left] = AXIS
    img[y1, left:right + 1] = AXIS
    if ys.size:
        draw_polyline(img, px(xs), py(ys), colour, thickness=max(1, scale))


def plot_curves(log_jsonl_path: str | os.PathLike, out_png: str | os.PathLike, keys=("loss", "psnr"), *,
                width: int = 640, panel_height: int = 200, scale: int = 1) -> Path:
    """Plot ``keys`` of a training log against the iteration, one panel per key, into ``out_png``.

    The image is ``width`` x ``panel_height * len(keys)`` pixels; a key absent from the log gets an empty panel
    titled "(no data)". ``scale`` enlarges the text. Returns the PNG's path."""
    keys = [keys] if isinstance(keys, str) else list(keys)
    if not keys:
        raise ValueError("plot_curves needs at least one key")
    if width < 160 or panel_height < 60:
        raise ValueError(f"the plot is too small ({width} x {panel_height} per panel): at least 160 x 60")
    records = read_log(log_jsonl_path)
    series = [_series(records, k) for k in keys]
    all_x = np.concatenate([xs for xs, _ in series]) if series else np.zeros(0)
    lo_x, hi_x = (float(all_x.min()), float(all_x.max())) if all_x.size else (0.0, 1.0)
    if hi_x <= lo_x:
        hi_x = lo_x + 1.0
    img = np.full((panel_height * len(keys), width, 3), WHITE, dtype=np.uint8)
    for k, (key, (xs, ys)) in enumerate(zip(keys, series, strict=True)):
        _panel(img, k * panel_height, panel_height, key, xs, ys, COLOURS[k % len(COLOURS)], (lo_x, hi_x), scale)
        if k:
            img[k * panel_height, :] = AXIS
    draw_text(img, width - 8 - text_width("iteration", scale), img.shape[0] - (GLYPH_H + 2) * scale, "iteration",
              TEXT, scale)
    return write_png(out_png, img)
