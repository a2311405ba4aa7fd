"""Rotated crops: the regions the models see, cut out of a frame by bilinear sampling, and their points mapped back.

A :class:`Rect` is a (possibly rotated, possibly mirrored) rectangle in image pixels (x right, y down; continuous
coordinates, pixel centres at +0.5). Its crop of ``out_w`` x ``out_h`` pixels maps crop coordinates (u, v) in
[0, out_w] x [0, out_h] to ``centre + (u / out_w - 1/2) w ax + (v / out_h - 1/2) h ay``, where ``ax`` = (cos a, sin a)
(the crop's x axis in the image: ``angle`` a, clockwise on screen) and ``ay`` = (-sin a, cos a); ``mirror`` flips
``ax`` (a horizontally mirrored crop, as the iris model wants for one eye). Outside the image the crop is zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class Rect:
    cx: float
    cy: float
    w: float
    h: float
    angle: float = 0.0  # radians
    mirror: bool = False

    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The crop's unit x and y axes in image coordinates."""
        c, s = math.cos(self.angle), math.sin(self.angle)
        ax = np.array([c, s])
        return (-ax if self.mirror else ax), np.array([-s, c])

    def to_image(self, uv: np.ndarray, out_w: float, out_h: float) -> np.ndarray:
        """Crop coordinates ``[..., 2]`` (pixels of an ``out_w`` x ``out_h`` crop) -> image pixels ``[..., 2]``."""
        ax, ay = self.axes()
        du = (np.asarray(uv[..., 0], dtype=np.float64) / out_w - 0.5) * self.w
        dv = (np.asarray(uv[..., 1], dtype=np.float64) / out_h - 0.5) * self.h
        return np.stack([self.cx + du * ax[0] + dv * ay[0], self.cy + du * ax[1] + dv * ay[1]], -1)

    def scaled(self, sx: float, sy: float | None = None, square_long: bool = False) -> Rect:
        """The same centre and angle, sides scaled (after making it square on its long side when asked)."""
        w, h = (max(self.w, self.h),) * 2 if square_long else (self.w, self.h)
        return replace(self, w=w * sx, h=h * (sx if sy is None else sy))

    def corners(self) -> np.ndarray:
        """[4, 2] image coordinates of the corners."""
        return self.to_image(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]), 1.0, 1.0)


def rect_from_points(points: np.ndarray, angle: float, scale: float = 1.0, square_long: bool = True) -> Rect:
    """The rectangle at ``angle`` around ``points [N, 2]`` (their extent along its axes), scaled by ``scale``."""
    r = Rect(0.0, 0.0, 1.0, 1.0, angle)
    ax, ay = r.axes()
    u, v = points @ ax, points @ ay
    cu, cv = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    centre = cu * ax + cv * ay
    rect = Rect(float(centre[0]), float(centre[1]), float(u.max() - u.min()), float(v.max() - v.min()), angle)
    return rect.scaled(scale, square_long=square_long)


def crop(img: np.ndarray, rect: Rect, out_w: int, out_h: int) -> np.ndarray:
    """The ``out_h`` x ``out_w`` crop of ``img [H, W]`` or ``[H, W, C]`` (any dtype) as float32 ``[out_h, out_w, C]``
    in the input's units, bilinear, zero outside the image. A crop shrinking the image by k >= 2 first averages
    k x k blocks of the region it covers (no aliasing). Only that region is converted to float."""
    src = img[..., None] if img.ndim == 2 else img
    H, W = src.shape[:2]
    c = rect.corners()
    k = max(1, int(min(rect.w / out_w, rect.h / out_h)))
    x0 = int(np.clip(math.floor(c[:, 0].min()) - 2 * k, 0, W))
    y0 = int(np.clip(math.floor(c[:, 1].min()) - 2 * k, 0, H))
    x1 = int(np.clip(math.ceil(c[:, 0].max()) + 2 * k, 0, W))
    y1 = int(np.clip(math.ceil(c[:, 1].max()) + 2 * k, 0, H))
    x0, y0 = x0 - x0 % k, y0 - y0 % k
    if x1 - x0 < k or y1 - y0 < k:  # entirely outside the image
        return np.zeros((out_h, out_w, src.shape[2]), dtype=np.float32)
    region = torch.from_numpy(np.ascontiguousarray(src[y0:y1, x0:x1])).permute(2, 0, 1)[None].float()
    if k >= 2:
        region = F.avg_pool2d(region, k)
    u = torch.arange(out_w, dtype=torch.float64) + 0.5
    v = torch.arange(out_h, dtype=torch.float64) + 0.5
    xy = torch.from_numpy(rect.to_image(np.stack(np.meshgrid(u.numpy(), v.numpy()), -1), out_w, out_h))
    h, w = region.shape[2:]
    grid = torch.stack([2 * (xy[..., 0] - x0) / (k * w) - 1, 2 * (xy[..., 1] - y0) / (k * h) - 1], -1)
    out = F.grid_sample(region, grid[None].float(), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def resize(img: np.ndarray, out_w: int, out_h: int) -> np.ndarray:
    """``img [H, W]`` or ``[H, W, C]`` stretched to ``out_h`` x ``out_w``: float32, bilinear, antialiased when
    shrinking (uint8 pictures take torch's uint8 path, several times faster, rounded to integers)."""
    src = img[..., None] if img.ndim == 2 else img
    t = torch.from_numpy(np.ascontiguousarray(src)).permute(2, 0, 1)[None]
    if t.dtype != torch.uint8:
        t = t.float()
    shrink = out_w < src.shape[1] or out_h < src.shape[0]
    out = F.interpolate(t, size=(out_h, out_w), mode="bilinear", align_corners=False, antialias=shrink)
    out = out[0].permute(1, 2, 0).numpy().astype(np.float32, copy=False)
    return out[..., 0] if img.ndim == 2 else out


def letterbox(img: np.ndarray, size: int) -> tuple[np.ndarray, Rect]:
    """``img [H, W, C]`` scaled to fit a ``size`` x ``size`` square (aspect kept), centred, zero around it: float32
    ``[size, size, C]``, and the square's :class:`Rect` in the image (its crop coordinates map back to pixels)."""
    H, W = img.shape[:2]
    s = size / max(W, H)
    w, h = max(1, round(W * s)), max(1, round(H * s))
    ox, oy = (size - w) // 2, (size - h) // 2
    out = np.zeros((size, size, img.shape[2]), dtype=np.float32)
    out[oy:oy + h, ox:ox + w] = resize(img, w, h)
    # crop pixel (u, v) <- image (u - ox) W / w, (v - oy) H / h: a rect of side size W / w centred accordingly
    sx, sy = W / w, H / h
    return out, Rect((size / 2 - ox) * sx, (size / 2 - oy) * sy, size * sx, size * sy)
