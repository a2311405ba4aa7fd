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

The fitted head cuts it further (:func:`mesh_silhouette`, ``head_matte(..., silhouette=)``): the matte is kept only
within a margin of the fitted open head's silhouette: ``hair`` face heights (0.25 above the eyes, 0.1 from the eyes
to the chin: hair, the ears' surroundings) and ``neck_margin`` below the chin (the mesh's neck: the avatar is built
on that mesh and cannot model a body beyond it). The
selfie model's shoulders and its blobs beside the neck otherwise become an opaque black rim that training must
learn (10x weighted alpha loss) and that no held-out frame shows. Measured on ``data synth`` seed 257 (150 frames
at 256 px): IoU with the true head mask 0.80 -> 0.90 (median), the head still covered; then 0.996 with the cut by
colour (:func:`colour_cut`: a pixel near or beyond the silhouette with the colour of the wall beside it is wall);
docs/method.md section 13.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .geometry import resize
from .mesh import OUTER_EYE_CORNERS, eye_angle
from .runner import load_model

SIZE = 256


def person_probability(rgb: np.ndarray) -> np.ndarray:
    """``[H, W]`` float32 in [0, 1]: the selfie model's person probability for each pixel of ``rgb [H, W, 3]``."""
    H, W = rgb.shape[:2]
    x = resize(rgb, SIZE, SIZE) * (1.0 / 255.0)
    prob = load_model("selfie_segmentation")(x[None])[0].reshape(SIZE, SIZE)
    return np.clip(resize(prob, W, H), 0.0, 1.0)


def mesh_silhouette(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int,
                    max_side: int = SIZE // 2) -> np.ndarray:
    """``[height, width]`` bool: the pixels that a triangle of the mesh (``vertices [V, 3]`` in camera coordinates,
    in front of it; ``faces [F, 3]``) overlaps, seen through the intrinsics ``K [3, 3]``. Drawn at most
    ``max_side`` pixels on the long side and scaled up (a coarse mask: :func:`head_matte` grows it by a margin),
    each triangle sampled on a barycentric grid about a pixel apart (triangles grouped by their subdivision)."""
    scale = min(1.0, max_side / max(width, height))
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    uv = vertices @ K.T
    uv = uv[:, :2] / uv[:, 2:3] * np.array([w / width, h / height])
    tri = torch.from_numpy(uv[faces]).float()  # [F, 3, 2]
    edge = (tri - tri.roll(1, 1)).norm(dim=-1).amax(-1)
    subdiv = torch.ceil(edge).clamp(1, 256).long()
    out = torch.zeros(h * w, dtype=torch.bool)
    for n in subdiv.unique().tolist():
        i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
        inside = (i + j) <= n
        bary = torch.stack([i[inside], j[inside], n - i[inside] - j[inside]], -1).float() / n
        p = torch.einsum("sk,fkc->fsc", bary, tri[subdiv == n]).reshape(-1, 2)
        x, y = p[:, 0].floor().long(), p[:, 1].floor().long()
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        out[y[ok] * w + x[ok]] = True
    mask = out.reshape(1, 1, h, w).float()
    if (w, h) != (width, height):
        mask = F.interpolate(mask, size=(height, width), mode="nearest")
    return mask[0, 0].numpy() > 0.5


def _max_filter(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """The running maximum of ``a`` over windows of ``2 radius + 1`` along ``axis`` (zero beyond the edges), in
    time independent of the radius (van Herk / Gil-Werman: per block of the window's length, prefix and suffix
    maxima; a window spans at most two blocks)."""
    w = 2 * radius + 1
    a = np.moveaxis(a, axis, -1)
    n = a.shape[-1]
    length = -(-(n + 2 * radius) // w) * w
    padded = np.zeros(a.shape[:-1] + (length,), a.dtype)
    padded[..., radius:radius + n] = a
    blocks = padded.reshape(a.shape[:-1] + (length // w, w))
    prefix = np.maximum.accumulate(blocks, axis=-1).reshape(padded.shape)
    suffix = np.maximum.accumulate(blocks[..., ::-1], axis=-1)[..., ::-1].reshape(padded.shape)
    return np.moveaxis(np.maximum(suffix[..., :n], prefix[..., w - 1:w - 1 + n]), -1, axis)


def _dilated(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask [H, W]`` (bool) grown by ``radius`` pixels (a square neighbourhood: two separable running maxima)."""
    if radius <= 0:
        return mask
    if radius <= 2:  # a few shifted ORs are cheaper than the running maxima
        out = mask.copy()
        for axis in (0, 1):
            grown = out.copy()
            n = out.shape[axis]
            for d in range(1, radius + 1):
                lo, hi = [slice(None)] * 2, [slice(None)] * 2
                lo[axis], hi[axis] = slice(0, n - d), slice(d, n)
                grown[tuple(lo)] |= out[tuple(hi)]
                grown[tuple(hi)] |= out[tuple(lo)]
            out = grown
        return out
    return _max_filter(_max_filter(mask.view(np.uint8), radius, 0), radius, 1).view(bool)


def _grown(mask: np.ndarray, radii: list[int], max_side: int = SIZE // 2) -> list[np.ndarray]:
    """``mask [H, W]`` grown by each radius, computed on a grid of at most ``max_side`` cells a side (a cell is set
    when any of its pixels is): the margins come out up to a cell wider, never narrower."""
    H, W = mask.shape
    s = max(1, -(-max(H, W) // max_side))
    if s == 1:
        return [_dilated(mask, r) for r in radii]
    h, w = -(-H // s), -(-W // s)
    padded = np.zeros((h * s, w * s), bool)
    padded[:H, :W] = mask
    coarse = padded.reshape(h, s, w, s).any(axis=(1, 3))
    rows, cols = np.arange(H) // s, np.arange(W) // s
    return [_dilated(coarse, -(-r // s))[rows[:, None], cols[None, :]] for r in radii]


def _box_sum(a: np.ndarray, radius: int) -> np.ndarray:
    """The sum of ``a [H, W, ...]`` over the ``(2 radius + 1)^2`` square around each pixel (zero beyond the edges),
    from an integral image."""
    H, W = a.shape[:2]
    c = np.zeros((H + 1, W + 1) + a.shape[2:], np.float64)
    c[1:, 1:] = a.cumsum(0).cumsum(1)
    y0, y1 = np.clip(np.arange(H) - radius, 0, H), np.clip(np.arange(H) + radius + 1, 0, H)
    x0, x1 = np.clip(np.arange(W) - radius, 0, W), np.clip(np.arange(W) + radius + 1, 0, W)
    return (c[y1][:, x1] - c[y0][:, x1] - c[y1][:, x0] + c[y0][:, x0]).astype(np.float32)


def _local_mean(rgb: np.ndarray, weight: np.ndarray, radius: int, at: tuple[np.ndarray, np.ndarray],
                max_side: int = SIZE // 2) -> tuple[np.ndarray, np.ndarray]:
    """The mean colour of the pixels of ``rgb [H, W, 3]`` selected by ``weight [H, W]`` within about ``radius`` of
    each pixel, and their count (a normalised box filter), at the pixels ``at`` (row and column indices): ``[M, 3]``
    and ``[M]``. Computed on a grid of at most ``max_side`` cells a side (cell sums: rows of cells added, then their
    columns) and read at each pixel's cell: a smooth estimate, not an exact one."""
    H, W = weight.shape
    s = max(1, -(-max(H, W) // max_side))
    h, w = -(-H // s), -(-W // s)

    def cells(a: np.ndarray) -> np.ndarray:
        padded = np.zeros((h * s, w * s) + a.shape[2:], np.float32)
        padded[:H, :W] = a
        return padded.reshape((h, s, w * s) + a.shape[2:]).sum(1).reshape((h, w, s) + a.shape[2:]).sum(2)

    count = _box_sum(cells(weight), max(1, round(radius / s)))
    total = _box_sum(cells(rgb * weight[..., None]), max(1, round(radius / s)))
    cell = (at[0] // s, at[1] // s)
    return total[cell] / np.maximum(count[cell], 1e-6)[..., None], count[cell]


def colour_cut(matte: np.ndarray, rgb: np.ndarray, silhouette: np.ndarray, height: float, radius: float = 0.3,
               inset: float = 0.03, contrast: tuple[float, float] = (0.05, 0.15),
               background: np.ndarray | None = None) -> np.ndarray:
    """``matte [H, W]`` lowered where, outside the fitted head's ``silhouette`` or within ``inset`` face heights
    of its edge (at least a pixel: the fit's error and the silhouette's coarse grid), the frame ``rgb [H, W, 3]``
    (uint8) has the colour of the background beside it: B, the mean colour of the ``background [H, W]`` (bool;
    default: the pixels the matte gives up) within ``radius`` face heights. A pixel within ``contrast[0]`` of B
    (Euclidean, RGB in [0, 1]) is background, one beyond ``contrast[1]`` keeps its matte, and the matte fades
    linearly between. It only takes away: the selfie model's spill beside the neck and behind the head, where it
    shows the wall, becomes background; hair, ears and anything else of another colour than the wall stay (hair
    of the wall's own colour goes too: colour cannot tell them apart). ``height``: the face's height in pixels."""
    band = (matte > 0) & _dilated(~silhouette, max(1, round(inset * height)))
    if not band.any():
        return matte
    image = rgb.astype(np.float32) * (1.0 / 255.0)
    wall = matte < 0.02 if background is None else background
    at = np.nonzero(band)
    B, count = _local_mean(image, wall.astype(np.float32), max(2, round(radius * height)), at)
    distance = np.sqrt(np.square(image[at] - B).sum(-1))
    keep = np.clip((distance - contrast[0]) / (contrast[1] - contrast[0]), 0.0, 1.0)
    keep[count < 1] = 1.0  # no background in reach: nothing to compare with
    out = matte.astype(np.float32, copy=True)
    out[at] *= keep
    return out


def head_matte(prob: np.ndarray, landmarks: np.ndarray, neck: float = 0.2, side: float = 0.9,
               neck_side: float = 0.45, fade: float = 0.1, silhouette: np.ndarray | None = None,
               hair: tuple[float, float] = (0.25, 0.1), neck_margin: float = 0.03,
               rgb: np.ndarray | None = None) -> np.ndarray:
    """``prob [H, W]`` limited to the head of the face with ``landmarks [468, 3]`` (module docstring); with the
    fitted head's ``silhouette [H, W]`` (bool), also to within ``hair[0]`` face heights of it above the eyes,
    ``hair[1]`` from the eyes to the chin and ``neck_margin`` below the chin; with the frame ``rgb [H, W, 3]`` as
    well, cut by colour near and beyond that silhouette (:func:`colour_cut`)."""
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
    if silhouette is not None:
        eyes = (float(v[list(OUTER_EYE_CORNERS)].mean()) - chin_v) / height  # the eye line, as pv measures it
        radii = [round(r * height) for r in (*hair, neck_margin)]
        above, beside, below = _grown(silhouette, radii)
        keep *= np.where(pv < eyes, above, np.where(pv < 0, beside, below))
    matte = (prob * keep).astype(np.float32, copy=False)
    if silhouette is not None and rgb is not None:
        # the background's colour from what the matte gives up, but not hair above the hair margin
        matte = colour_cut(matte, rgb, silhouette, height, background=(matte < 0.02) & ~((pv < eyes) & (prob > 0.5)))
    return matte


def sharpen_edge(matte: np.ndarray, width: float = 1.0) -> np.ndarray:
    """``matte [H, W]`` (0..1) as a coverage with an edge ``width`` pixels wide: ``clip(0.5 + (m - 0.5) / (width
    |grad m|))``. The selfie model's output is a probability, smooth over several pixels at the person's outline
    (and bilinearly stretched from 256 px), not how much of each pixel the head covers: on ``data synth``'s heads,
    whose true masks are binary, the tracked matte's rim held about 400 soft pixels a 256 px frame. Read as a
    distance to the 0.5 contour (its value over its gradient), it becomes the antialiased edge of that contour:
    seed 223 (150 frames, H.264), soft pixels 406 -> 119 a frame, L1 error against the true masks 122 -> 86 pixels
    a frame, the same IoU (0.996). Flat parts go to 0 or 1 whichever side of 0.5 they are (a faint plateau
    is taken as background, a strong one as head)."""
    m = matte.astype(np.float32, copy=False)
    gy, gx = np.gradient(m)
    slope = np.maximum(np.sqrt(gx * gx + gy * gy) * np.float32(width), np.float32(1e-6))
    return np.clip(np.float32(0.5) + (m - np.float32(0.5)) / slope, 0.0, 1.0).astype(np.float32, copy=False)

