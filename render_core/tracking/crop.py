"""Stage 1, last step: frames cropped and scaled to the training resolution, and the pixel mapping that implies.

A :class:`Window` is a region of the upright frame (integer pixels; it may reach outside the frame, where the crop
is black) shown at ``width`` x ``height``: a frame point (u, v) (continuous pixel coordinates, centres at +0.5) lands
at (sx (u - x0), sy (v - y0)) in the crop, so intrinsics K of the frame become ``window.intrinsics(K)``.

:func:`crop_windows` makes them:

- ``fixed`` (the default): one window for the whole video, around the head in every frame - the union of the
  per-frame face boxes (stage 2's landmark boxes; NaN rows, frames without a face, are ignored), widened to the
  head: its centre raised by ``lift`` of the box's height (hair and skull above the brow), its long side scaled by
  ``scale``, at the output's aspect. Constant intrinsics, as a static camera has.
- ``follow``: one window per frame, each box's centre and size smoothed over ``smooth`` frames (a centred moving
  average, missing boxes filled from the nearest frame with one), then widened as above.
- ``none``: the whole frame, scaled uniformly to fit and centred (black bars where the aspects differ), so the
  frame's centre - the principal point a video without calibration is given - is the crop's centre.

A window that fits in the frame is moved inside it; one larger than the frame stays centred on the head.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import TrackingError

MODES = ("fixed", "follow", "none")
MAX_SIZE = 4096


@dataclass(frozen=True)
class Window:
    """The frame region [x0, x0 + w) x [y0, y0 + h) (integers) shown at ``width`` x ``height``."""

    x0: int
    y0: int
    w: int
    h: int
    width: int
    height: int

    @property
    def scale(self) -> tuple[float, float]:
        return self.width / self.w, self.height / self.h

    def affine(self) -> np.ndarray:
        """``[2, 3]``: frame pixel coordinates -> crop pixel coordinates."""
        sx, sy = self.scale
        return np.array([[sx, 0.0, -sx * self.x0], [0.0, sy, -sy * self.y0]])

    def to_crop(self, points: np.ndarray) -> np.ndarray:
        """Points ``[..., 2+]`` in frame pixels -> crop pixels (extra columns, e.g. z, scaled by sx)."""
        sx, sy = self.scale
        out = np.array(points, dtype=np.float64, copy=True)
        out[..., 0] = sx * (out[..., 0] - self.x0)
        out[..., 1] = sy * (out[..., 1] - self.y0)
        out[..., 2:] *= sx
        return out

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """The crop's intrinsics ``[3, 3]`` from the frame's ``K``."""
        A = np.eye(3)
        A[:2] = self.affine()
        return A @ np.asarray(K, dtype=np.float64)


def _check_size(width: int, height: int) -> None:
    for name, v in (("width", width), ("height", height)):
        if not (8 <= int(v) <= MAX_SIZE):
            raise TrackingError(f"the crop's {name} must be in [8, {MAX_SIZE}], got {v}", field="size")


def whole_frame(frame_w: int, frame_h: int, width: int, height: int) -> Window:
    """``none``: the whole frame fitted into width x height, centred."""
    _check_size(width, height)
    s = min(width / frame_w, height / frame_h)
    # even margins: the frame's centre is exactly the window's
    w = frame_w + 2 * max(0, round((width / s - frame_w) / 2))
    h = frame_h + 2 * max(0, round((height / s - frame_h) / 2))
    return Window(-(w - frame_w) // 2, -(h - frame_h) // 2, w, h, width, height)


def _window_around(cx: float, cy: float, side: float, frame_w: int, frame_h: int, width: int,
                   height: int) -> Window:
    """A window at the output's aspect whose long side is ``side``, centred on (cx, cy), moved inside the frame
    where it fits."""
    aspect = width / height
    w, h = (side, side / aspect) if aspect >= 1 else (side * aspect, side)
    w, h = max(2, round(w)), max(2, round(h))
    x0, y0 = round(cx - w / 2), round(cy - h / 2)
    if w <= frame_w:
        x0 = min(max(x0, 0), frame_w - w)
    if h <= frame_h:
        y0 = min(max(y0, 0), frame_h - h)
    return Window(int(x0), int(y0), int(w), int(h), width, height)


def _fill_missing(values: np.ndarray) -> np.ndarray:
    """Rows of ``values [N, C]`` with NaN take the nearest row without."""
    ok = ~np.isnan(values).any(1)
    idx = np.flatnonzero(ok)
    nearest = idx[np.abs(np.arange(len(values))[:, None] - idx[None, :]).argmin(1)]
    return values[nearest]


def crop_windows(boxes: np.ndarray | None, frame_w: int, frame_h: int, width: int, height: int,
                 mode: str = "fixed", scale: float = 2.0, lift: float = 0.15, smooth: int = 9) -> list[Window]:
    """The crop of each frame (module docstring): ``boxes [N, 4]`` (x0, y0, x1, y1; NaN rows for frames without a
    face) -> N windows (the same one N times for ``fixed``). ``boxes`` may be None for ``none``."""
    if mode not in MODES:
        raise TrackingError(f"unknown crop {mode!r}; one of {', '.join(MODES)}", field="crop")
    _check_size(width, height)
    if mode == "none":
        n = 1 if boxes is None else len(boxes)
        return [whole_frame(frame_w, frame_h, width, height)] * n
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if not len(boxes) or np.isnan(boxes).any(1).all():
        raise TrackingError("a head crop needs a face box in at least one frame", field="crop")
    if not (scale > 0 and math.isfinite(scale)):
        raise TrackingError(f"the crop's scale must be positive, got {scale}", field="crop")

    def widen(x0, y0, x1, y1):
        bw, bh = x1 - x0, y1 - y0
        return (x0 + x1) / 2, (y0 + y1) / 2 - lift * bh, scale * max(bw, bh)

    if mode == "fixed":
        found = boxes[~np.isnan(boxes).any(1)]
        cx, cy, side = widen(found[:, 0].min(), found[:, 1].min(), found[:, 2].max(), found[:, 3].max())
        return [_window_around(cx, cy, side, frame_w, frame_h, width, height)] * len(boxes)
    filled = _fill_missing(boxes)
    k = max(1, int(smooth)) | 1
    padded = np.pad(filled, ((k // 2, k // 2), (0, 0)), mode="edge")
    smoothed = np.stack([np.convolve(padded[:, c], np.ones(k) / k, mode="valid") for c in range(4)], 1)
    return [_window_around(*widen(*b), frame_w, frame_h, width, height) for b in smoothed]


def crop_frame(rgb: np.ndarray, window: Window) -> np.ndarray:
    """``rgb [H, W, C]`` uint8 cut to ``window`` and scaled to its size (bilinear, antialiased when shrinking);
    black outside the frame. Returns uint8 ``[height, width, C]``."""
    rgb = np.asarray(rgb, dtype=np.uint8)
    H, W = rgb.shape[:2]
    region = np.zeros((window.h, window.w) + rgb.shape[2:], dtype=rgb.dtype)
    x0, y0 = max(window.x0, 0), max(window.y0, 0)
    x1, y1 = min(window.x0 + window.w, W), min(window.y0 + window.h, H)
    if x1 > x0 and y1 > y0:
        region[y0 - window.y0:y1 - window.y0, x0 - window.x0:x1 - window.x0] = rgb[y0:y1, x0:x1]
    if (window.w, window.h) == (window.width, window.height):
        return region
    t = torch.from_numpy(region.reshape(window.h, window.w, -1)).permute(2, 0, 1)[None]
    shrink = window.w > window.width or window.h > window.height
    out = F.interpolate(t, size=(window.height, window.width), mode="bilinear", align_corners=False,
                        antialias=shrink)  # uint8 in, uint8 out (torch's fast path)
    return out[0].permute(1, 2, 0).numpy().reshape((window.height, window.width) + rgb.shape[2:])
