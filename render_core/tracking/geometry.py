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
    k x k blocks of the region it covers (no aliasing). Only that region is converted to float. The sampling grid is
    affine in the crop's pixels: built from its first row and column, not mapped point by point."""
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
    # float in numpy's [h, w, C] order, then viewed as [1, C, h, w] (a copy to channels first is 4x slower here)
    region = box_shrink(torch.from_numpy(src[y0:y1, x0:x1].astype(np.float32)).permute(2, 0, 1)[None], k)
    h, w = region.shape[2:]
    # crop pixel (u, v) -> image rect.to_image(u, v) = centre + s w ax / 2 + t h ay / 2 with s = 2 (u + 1/2) / out_w
    # - 1 and t likewise (pixel centres); the region's grid coordinate of an image point x is 2 (x - x0) / (k w) - 1
    ax, ay = rect.axes()
    s = np.arange(0.5, out_w) * (2.0 / out_w) - 1
    t = np.arange(0.5, out_h)[:, None] * (2.0 / out_h) - 1
    gx = (2 * (rect.cx - x0 + s * (rect.w * ax[0] / 2) + t * (rect.h * ay[0] / 2)) / (k * w) - 1)
    gy = (2 * (rect.cy - y0 + s * (rect.w * ax[1] / 2) + t * (rect.h * ay[1] / 2)) / (k * h) - 1)
    grid = torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32))[None]
    out = F.grid_sample(region, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def box_shrink(images: torch.Tensor, k: int) -> torch.Tensor:
    """``[..., H, W]`` -> the means of its whole k x k blocks ``[..., H // k, W // k]`` (as ``avg_pool2d(images,
    k)``, 3-4x faster on the CPU): sums of k strided rows, then of k strided columns."""
    if k == 1:
        return images
    images = images[..., :images.shape[-2] // k * k, :images.shape[-1] // k * k]
    rows = sum(images[..., i::k, :] for i in range(k))
    return sum(rows[..., i::k] for i in range(k)) * (1.0 / (k * k))


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
