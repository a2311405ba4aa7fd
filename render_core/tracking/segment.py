"""The head matte: MediaPipe's selfie segmentation (a person's probability per pixel), cut to the head.

The model sees the whole frame stretched to 256x256 (aspect not kept), RGB in [0, 1], and returns the probability
that each pixel shows a person (already a probability: no activation to apply); it is stretched back to the frame
by bilinear sampling. :func:`head_matte` keeps the head of it: in the face's own frame (x along the line between
the outer eye corners, y down the face; unit: the face's height, brow-to-chin extent of the landmarks), the matte is
faded to zero over ``fade`` below ``neck`` face heights under the chin, and beyond ``side`` face widths from the
face's centre line above the chin and ``neck_side`` below it (ears and hair stay; shoulders, collars and the body
below the neck go). The selfie model sees a person even where there is only a head: on ``data synth``'s floating
heads it paints shoulders under the chin, and the narrower limit below the chin took the matte's share on the
rendered head from 0.65 to 0.78 (its share of the head 1.000 -> 0.999; seeds 223 and 602, every 15th frame).
"""

from __future__ import annotations

import numpy as np

from .geometry import resize
from .mesh import eye_angle
from .runner import load_model

SIZE = 256


def person_probability(rgb: np.ndarray) -> np.ndarray:
    """``[H, W]`` float32 in [0, 1]: the selfie model's person probability for each pixel of ``rgb [H, W, 3]``."""
    H, W = rgb.shape[:2]
    x = resize(rgb, SIZE, SIZE) * (1.0 / 255.0)
    prob = load_model("selfie_segmentation")(x[None])[0].reshape(SIZE, SIZE)
    return np.clip(resize(prob, W, H), 0.0, 1.0)


def head_matte(prob: np.ndarray, landmarks: np.ndarray, neck: float = 0.2, side: float = 0.9,
               neck_side: float = 0.45, fade: float = 0.1) -> np.ndarray:
    """``prob [H, W]`` limited to the head of the face with ``landmarks [468, 3]`` (module docstring)."""
    H, W = prob.shape
    a = eye_angle(landmarks)
    c, s = float(np.cos(a)), float(np.sin(a))
    pts = landmarks[:, :2]
    u, v = pts @ np.array([c, s]), pts @ np.array([-s, c])
    height, width = float(v.max() - v.min()), float(u.max() - u.min())
    centre_u, chin_v = float((u.max() + u.min()) / 2), float(v.max())
    xs = np.arange(W, dtype=np.float32)[None, :] + 0.5
    ys = np.arange(H, dtype=np.float32)[:, None] + 0.5
    # float32 throughout (Python floats keep the arrays' precision)
    pu = np.abs(xs * c + ys * s - centre_u) * (1.0 / width)
    pv = (ys * c - xs * s - chin_v) * (1.0 / height)
    keep = 1.0 - np.clip((pv - neck) * (1.0 / fade), 0.0, 1.0)
    limit = np.where(pv < 0, np.float32(side), np.float32(neck_side))  # the head's width, then the neck's
    keep *= 1.0 - np.clip((pu - limit) * (1.0 / fade), 0.0, 1.0)
    return (prob * keep).astype(np.float32, copy=False)
