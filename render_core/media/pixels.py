"""Float pixels to bytes: the one float -> uint8 rounding (:func:`to_uint8`) and the one RGBA8 conversion
(:func:`to_rgba8`) that every writer, encoder and the service use; and RGBA8 to the YUV 4:2:0 planes video encoders
take (:func:`rgba8_to_i420`)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..raster import native


def to_uint8(pixels: Tensor | np.ndarray) -> np.ndarray:
    """Floats in [0, 1] (any shape) -> uint8 on the host: clamped to [0, 1], then x * 255 + 0.5 truncated (rounded
    half up), in the input's dtype. A tensor is converted where it lives (a GPU frame crosses to the host as bytes)."""
    t = pixels.detach() if isinstance(pixels, Tensor) else torch.from_numpy(np.array(pixels))
    return (t.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def to_rgba8(rgb: Tensor, alpha: Tensor) -> np.ndarray:
    """[B, H, W, 3] colour and [B, H, W] alpha in [0, 1] -> [B, H, W, 4] uint8 RGBA on the host, rounded as
    :func:`to_uint8` does (on the CPU by the native converter where it is built, bit for bit the same)."""
    if native.available() and rgb.device.type == "cpu":
        return native.to_rgba8(rgb, alpha)
    return to_uint8(torch.cat([rgb, alpha[..., None]], -1))


def rgba8_to_i420(rgba: np.ndarray, y: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
    """[H, W, 4] uint8 RGBA (alpha ignored) into the planes of a YUV 4:2:0 frame: BT.601 studio range, FFmpeg's
    default for RGB to YUV (what a decoder assumes of a stream that does not say). Y per pixel,
    ``((66 R + 129 G + 25 B + 128) >> 8) + 16``; U and V from the sums of each 2x2 block (an odd last row or column
    counted twice), ``((-38 R - 74 G + 112 B + 512) >> 10) + 128`` and ``((112 R - 94 G - 18 B + 512) >> 10) + 128``.
    ``y`` is [H, >= W], ``u`` and ``v`` [(H + 1) // 2, >= (W + 1) // 2] (rows may be padded, as FFmpeg's planes are;
    the padding is left alone), all uint8 and C-ordered. The native converter where it is built (about 0.1 ms a
    512x512 frame), else numpy: the same integers."""
    h, w = rgba.shape[0], rgba.shape[1]
    ch, cw = (h + 1) // 2, (w + 1) // 2
    if (rgba.ndim != 3 or rgba.shape[2] != 4 or y.shape[0] != h or y.shape[1] < w or u.shape[0] != ch
            or u.shape[1] < cw or v.shape[0] != ch or v.shape[1] < cw):
        raise ValueError(f"rgba8_to_i420: planes {y.shape}, {u.shape}, {v.shape} do not fit a {h}x{w} frame")
    if native.available():
        return native.rgba8_to_i420(np.ascontiguousarray(rgba), y, u, v)
    c = rgba[..., :3].astype(np.int32)
    r, g, b = c[..., 0], c[..., 1], c[..., 2]
    y[:, :w] = ((66 * r + 129 * g + 25 * b + 128) >> 8) + 16
    rows = np.minimum(np.arange(2 * ch), h - 1)
    cols = np.minimum(np.arange(2 * cw), w - 1)
    s = c[rows][:, cols].reshape(ch, 2, cw, 2, 3).sum((1, 3))
    r, g, b = s[..., 0], s[..., 1], s[..., 2]
    u[:, :cw] = ((-38 * r - 74 * g + 112 * b + 512) >> 10) + 128
    v[:, :cw] = ((112 * r - 94 * g - 18 * b + 512) >> 10) + 128
