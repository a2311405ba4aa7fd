"""Float pixels to bytes: the one float -> uint8 rounding (:func:`to_uint8`) and the one RGBA8 conversion
(:func:`to_rgba8`) that every writer, encoder and the service use."""

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
