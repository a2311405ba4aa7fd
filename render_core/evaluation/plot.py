"""Figures of training and evaluation, drawn with matplotlib's Agg backend: the training curves and the contact sheet.

matplotlib is optional (the ``train`` extra: ``pip install 'blendsplat[train]'``; the render service does not need
it). It is imported only when a figure is drawn, and only through ``matplotlib.figure.Figure`` with an explicit
``FigureCanvasAgg``: no pyplot, no global backend or figure state, so drawing is safe from worker threads.

Without matplotlib every drawing function raises :class:`PlotsUnavailable`, whose ``reason`` says why and how to
install it; :func:`training_plots` and the evaluation record that reason (``{"skipped": reason}``) and log it
instead of failing, so a run still writes all of its numbers.

- :func:`plot_curves` / :func:`curves_figure`: a training log (``log.jsonl``) as one panel per logged key against
  the iteration.
- :func:`write_contact_sheet` / :func:`contact_sheet_figure`: prediction | ground truth per evaluated frame,
  each row captioned with the frame index and its PSNR.

Example::

    >>> from render_core.evaluation.plot import PlotsUnavailable, plot_curves
    >>> try:
    ...     plot_curves("run/log.jsonl", "run/curves.png", keys=("loss", "psnr"))
    ... except PlotsUnavailable as e:
    ...     print("plots skipped:", e.reason)
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..atomic import atomic_path
from ..media.pixels import to_uint8

if TYPE_CHECKING:  # matplotlib is optional: imported lazily by _matplotlib()
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'blendsplat[train]'"
DPI = 100  # pixels per inch of every figure: sizes below are in pixels

# Curves: how each logged key is labelled and which way is better.
LABELS = {"loss": "loss", "l1": "L1", "ssim": "SSIM", "alpha": "alpha MSE", "mouth": "mouth cylinder",
          "psnr": "PSNR (dB)", "psnr_head": "head PSNR (dB)", "gaussians": "Gaussians", "seconds": "seconds"}
HIGHER_IS_BETTER = frozenset({"psnr", "psnr_head", "ssim"})
LOG_SPAN = 10.0  # a panel whose values are all positive and span at least this factor gets a log y axis
COLOURS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:cyan")

# Contact sheet: pixels.
SHEET_MIN_WIDTH = 192  # smaller frames are enlarged (nearest neighbour, integer factor) to at least this width
SHEET_PAD = 6
SHEET_HEADER = 26  # the column titles
SHEET_CAPTION = 24  # a row's caption
SHEET_BACKGROUND = (0.16, 0.16, 0.16)


class PlotsUnavailable(RuntimeError):
    """matplotlib cannot be imported, so no figure can be drawn; ``reason`` says why and how to install it."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def _matplotlib():
    """(Figure, FigureCanvasAgg), imported on first use; PlotsUnavailable without a usable matplotlib."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:
        if isinstance(e, ModuleNotFoundError) and (e.name or "").split(".")[0] == "matplotlib":
            raise PlotsUnavailable(f"matplotlib is not installed: {INSTALL_HINT}") from None
        raise PlotsUnavailable(f"matplotlib cannot be imported ({e}): {INSTALL_HINT}") from None
    return Figure, FigureCanvasAgg


def unavailable() -> str | None:
    """Why figures cannot be drawn here (matplotlib missing or broken), or None when they can."""
    try:
        _matplotlib()
    except PlotsUnavailable as e:
        return e.reason
    return None


def _figure(width: int, height: int, **kwargs) -> Figure:
    """A ``width`` x ``height`` pixel figure with its own Agg canvas (no pyplot)."""
    fig_cls, canvas_cls = _matplotlib()
    fig = fig_cls(figsize=(width / DPI, height / DPI), dpi=DPI, **kwargs)
    canvas_cls(fig)
    return fig


def save_figure(fig: Figure, out_png: str | os.PathLike) -> Path:
    """Write ``fig`` as a PNG (RGBA, the figure's pixel size) to ``out_png``, atomically; returns the path."""
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return out_png


# ---------------------------------------------------------------------------------------------------- curves
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


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _series(records: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(iterations, values) of the records with a finite number under ``key`` (the record's position when it has
    no usable ``iteration``)."""
    xs, ys = [], []
    for n, rec in enumerate(records):
        v, it = rec.get(key), rec.get("iteration", n)
        if _number(v):
            xs.append(float(it) if _number(it) else float(n))
            ys.append(float(v))
    return np.asarray(xs), np.asarray(ys)


def _short(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.3e}"


def curves_figure(records: list[dict], keys: Sequence[str] | str = ("loss", "psnr"), *, width: int = 640,
                  panel_height: int = 200, title: str = "training curves") -> Figure:
    """The figure :func:`plot_curves` saves: one panel per key of ``records`` (log records), sharing the x axis.

    Each panel plots the key against the iteration, with a legend naming the curve and its last value and marking
    the best value (the maximum for PSNR and SSIM, the minimum otherwise), a y-axis label with units and a grid;
    a panel whose values are all positive and span at least a factor :data:`LOG_SPAN` (a loss over a long run)
    gets a log y axis. A key absent from the records gets an empty panel reading "no data". The bottom panel's x
    axis reads "iteration"; ``title`` heads the figure. The figure is ``width`` x ``panel_height * len(keys)``
    pixels. Raises PlotsUnavailable without matplotlib, ValueError for no key or a figure under 160 x 60 per
    panel."""
    keys = [keys] if isinstance(keys, str) else list(keys)
    if not keys:
        raise ValueError("plot_curves needs at least one key")
    if width < 160 or panel_height < 60:
        raise ValueError(f"the plot is too small ({width} x {panel_height} per panel): at least 160 x 60")
    fig = _figure(width, panel_height * len(keys), layout="constrained")
    axes = fig.subplots(len(keys), 1, sharex=True, squeeze=False)[:, 0]
    for k, (ax, key) in enumerate(zip(axes, keys, strict=True)):
        xs, ys = _series(records, key)
        colour = COLOURS[k % len(COLOURS)]
        if ys.size:
            ax.plot(xs, ys, color=colour, linewidth=1.5, label=f"{key} (last {_short(ys[-1])})")
            higher = key in HIGHER_IS_BETTER
            best = int(np.argmax(ys) if higher else np.argmin(ys))
            ax.plot(xs[best], ys[best], "o", color=colour, markersize=5,
                    label=f"{'max' if higher else 'min'} {_short(ys[best])} at {xs[best]:.0f}")
            if ys.min() > 0 and ys.max() >= LOG_SPAN * ys.min():
                ax.set_yscale("log")
            ax.legend(loc="best", fontsize="small", framealpha=0.8)
        else:
            ax.text(0.5, 0.5, f"{key}: no data", transform=ax.transAxes, ha="center", va="center", color="grey")
        ax.set_ylabel(LABELS.get(key, key), fontsize="small")
        ax.tick_params(labelsize="small")
        ax.grid(True, which="major", alpha=0.35)
    axes[-1].set_xlabel("iteration", fontsize="small")
    fig.suptitle(title, fontsize="medium")
    return fig


def plot_curves(log_jsonl_path: str | os.PathLike, out_png: str | os.PathLike,
                keys: Sequence[str] | str = ("loss", "psnr"), *, width: int = 640, panel_height: int = 200) -> Path:
    """Plot ``keys`` of a training log (``log.jsonl``) against the iteration into ``out_png``: one panel per key
    (see :func:`curves_figure`), ``width`` x ``panel_height * len(keys)`` pixels. Returns the PNG's path.

    Raises PlotsUnavailable without matplotlib, ValueError for no key or a too small figure, OSError when the log
    cannot be read."""
    fig = curves_figure(read_log(log_jsonl_path), keys, width=width, panel_height=panel_height,
                        title=f"training curves: {Path(log_jsonl_path).parent.name or Path(log_jsonl_path).name}")
    return save_figure(fig, out_png)


def training_plots(log_jsonl_path: str | os.PathLike, out_png: str | os.PathLike,
                   keys: Sequence[str] | str = ("loss", "psnr")) -> dict:
    """The training run's figures for its summary: ``{"curves": path}``, or ``{"skipped": reason}`` (logged as a
    warning) when matplotlib is not installed, so that training still finishes and writes its numbers."""
    try:
        return {"curves": str(plot_curves(log_jsonl_path, out_png, keys))}
    except PlotsUnavailable as e:
        log.warning("training curves skipped: %s", e.reason)
        return {"skipped": e.reason}


# --------------------------------------------------------------------------------------------- contact sheet
def caption(index: int, psnr: float) -> str:
    """A contact-sheet row's caption, e.g. "frame 12  PSNR 27.31 dB"."""
    return f"frame {index}  PSNR {psnr:.2f} dB"


def contact_sheet_figure(rows: Sequence[tuple[int, np.ndarray, np.ndarray, float]]) -> Figure:
    """The figure :func:`write_contact_sheet` saves.

    ``rows``: (frame index, prediction [H, W, 3], ground truth [H, W, 3], PSNR in dB), images in [0, 1]. Under the
    column titles "prediction" and "ground truth", each row is captioned by :func:`caption` and shows the two
    images side by side, pixel for pixel (enlarged by an integer factor to at least :data:`SHEET_MIN_WIDTH` pixels
    wide, nearest neighbour), on a dark background. Raises ValueError for no row or images of different sizes,
    PlotsUnavailable without matplotlib."""
    if not rows:
        raise ValueError("the contact sheet needs at least one frame")
    h, w = np.asarray(rows[0][1]).shape[:2]
    for index, pred, gt, _ in rows:
        if np.asarray(pred).shape[:2] != (h, w) or np.asarray(gt).shape[:2] != (h, w):
            raise ValueError(f"frame {index}: the images are not all {w} x {h}")
    s = max(1, math.ceil(SHEET_MIN_WIDTH / w))
    hs, ws = h * s, w * s
    width = 2 * ws + 3 * SHEET_PAD
    height = SHEET_HEADER + len(rows) * (SHEET_CAPTION + hs + SHEET_PAD)
    fig = _figure(width, height, facecolor=SHEET_BACKGROUND)

    def text(x: float, top: float, line: str, colour: str, size: float) -> None:  # pixels from the top-left
        fig.text(x / width, 1.0 - top / height, line, color=colour, fontsize=size, ha="left", va="center")

    text(SHEET_PAD, SHEET_HEADER / 2, "prediction", "#e6e6e6", 10)
    text(2 * SHEET_PAD + ws, SHEET_HEADER / 2, "ground truth", "#e6e6e6", 10)
    top = SHEET_HEADER
    for index, pred, gt, value in rows:
        text(SHEET_PAD, top + SHEET_CAPTION / 2, caption(index, value), "#ffd25a", 9)
        top += SHEET_CAPTION
        for c, img in enumerate((pred, gt)):
            pixels = to_uint8(img)[..., :3].repeat(s, axis=0).repeat(s, axis=1)
            fig.figimage(pixels, xo=SHEET_PAD + c * (ws + SHEET_PAD), yo=height - top - hs, origin="upper")
        top += hs + SHEET_PAD
    return fig


def write_contact_sheet(rows: Sequence[tuple[int, np.ndarray, np.ndarray, float]], out_png) -> Path:
    """Draw :func:`contact_sheet_figure` of ``rows`` into the PNG ``out_png``; returns its path. Raises
    PlotsUnavailable without matplotlib."""
    return save_figure(contact_sheet_figure(rows), out_png)
