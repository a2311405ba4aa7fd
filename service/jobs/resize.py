"""A dataset at a job's ``resolution`` (the longest image side to train at).

The Trainer trains at its dataset's size (``tracking.width`` x ``tracking.height``: the targets it decodes and the
cameras it renders with). A job whose ``resolution`` is smaller than the dataset's longest side therefore trains on
a resampled copy, written once into its work folder (``dataset_<width>x<height>/``, the portable format) and reused
when the job resumes:

- the size keeps the aspect ratio: each side scaled by ``resolution / longest side`` and rounded (at least 1);
- frames and masks are low-pass filtered and resampled (a triangle filter widened by the reduction factor, what
  image libraries call antialiased bilinear), so fine detail averages instead of aliasing; a mask's edge becomes
  fractional, as the area it covers is;
- the intrinsics are scaled per axis (``fx``, ``cx`` by the width ratio, ``fy``, ``cy`` by the height's): pixel
  coordinates have their origin at the top-left corner of the top-left pixel (docs/tracked-video-format.md), so a
  point keeps its place in the picture; poses, expressions and the split are unchanged;
- frames are written lossless (PNG; EXR for a dataset of EXR frames), masks as PNG.

A ``resolution`` at or above the dataset's longest side trains at the dataset's own size (no upsampling: it would
add no detail).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from render_core.data.portable import MANIFEST, Dataset, read_dataset, write_dataset


def training_size(width: int, height: int, resolution: int | None) -> tuple[int, int]:
    """The size a ``width`` x ``height`` dataset trains at for ``resolution`` (None: its own)."""
    longest = max(width, height)
    if resolution is None or resolution >= longest:
        return width, height
    scale = resolution / longest
    return max(1, round(width * scale)), max(1, round(height * scale))


def resample(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """An image ([H, W, C] or [H, W], float in [0, 1]) at ``width`` x ``height``: antialiased bilinear (a triangle
    filter scaled to the reduction), pixel centres at +0.5 (``align_corners=False``). float32 in [0, 1]."""
    import torch
    import torch.nn.functional as F

    image = torch.from_numpy(np.ascontiguousarray(pixels, dtype=np.float32))
    planar = image[None, None] if image.ndim == 2 else image.permute(2, 0, 1)[None]
    if planar.shape[-2:] == (height, width):
        return image.numpy()
    out = F.interpolate(planar, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    out = out[0, 0] if image.ndim == 2 else out[0].permute(1, 2, 0)
    return out.clamp_(0.0, 1.0).contiguous().numpy()


def scaled_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics [N, 3, 3] for an image scaled by ``sx`` horizontally and ``sy`` vertically (the first row, fx and
    cx, times sx; the second, fy and cy, times sy)."""
    out = np.array(K, dtype=np.float32, copy=True)
    out[:, 0, :] *= sx
    out[:, 1, :] *= sy
    return out


def _frames(dataset: Dataset, width: int, height: int) -> Iterator[np.ndarray]:
    for i in range(len(dataset)):
        yield resample(dataset.frame(i), width, height)


def _masks(dataset: Dataset, width: int, height: int) -> Iterator[np.ndarray]:
    for i in range(len(dataset)):
        yield resample(dataset.mask(i), width, height)


def dataset_at(data_dir: Path, resolution: int | None, workdir: Path) -> tuple[Path, tuple[int, int], tuple[int, int]]:
    """The dataset to train on for ``resolution``: ``data_dir`` itself, or its resampled copy in ``workdir``
    (written now, or an earlier attempt's: the writer publishes a complete folder only). Returns the folder, the
    training size and the dataset's own size (each width, height). DatasetError for a dataset that cannot be
    read."""
    dataset = read_dataset(data_dir)
    tracking = dataset.tracking
    own = (int(tracking.width), int(tracking.height))
    width, height = training_size(*own, resolution)
    if (width, height) == own:
        return data_dir, own, own
    out = workdir / f"dataset_{width}x{height}"
    if (out / MANIFEST).is_file():
        return out, (width, height), own
    resized = dataclasses.replace(tracking, width=width, height=height,
                                  K=scaled_intrinsics(tracking.K, width / own[0], height / own[1]))
    pattern = dataset.manifest.get("frame_files") or ""
    image_format = "exr" if pattern.lower().endswith(".exr") else "png"
    write_dataset(out, _frames(dataset, width, height), _masks(dataset, width, height), resized,
                  image_format=image_format)
    return out, (width, height), own
