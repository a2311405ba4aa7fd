"""Held-out evaluation of an avatar on a tracked-video dataset (docs/method.md section 10, the paper's protocol).

Every frame of the split (the dataset's held-out ``test`` frames by default) is rendered over a black background
with the frame's tracking and camera and compared with the ground truth whose background is masked to black:

- ``psnr``: over the full frame (all pixels, all channels), in dB;
- ``ssim``: over the full frame, the standard 11x11 Gaussian window with sigma 1.5, constants K1 = 0.01 and
  K2 = 0.03, data range 1, valid (unpadded) windows, computed per RGB channel and averaged over channels and
  window positions;
- ``psnr_head``: the MSE over the pixels inside the ground-truth head mask only (mask > 0.5), in dB; frames whose
  mask is empty have none;
- ``lpips``: LPIPS (AlexNet v0.1, :mod:`.lpips`) only when its weights are in the local file named by
  ``BLENDSPLAT_LPIPS_WEIGHTS`` (nothing is ever downloaded); otherwise null, with the reason in ``notes``.

Identical images have an infinite PSNR; every PSNR here is capped at :data:`PSNR_CAP` (100 dB, an MSE of 1e-10)
so that reports stay finite, standard JSON. Averages are means of the per-frame values (the usual convention).
Predictions are clamped to [0, 1] before scoring.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..avatar import Avatar
from ..errors import DatasetError

PSNR_CAP = 100.0  # dB reported for identical images (MSE below 1e-10)
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03
HEAD_THRESHOLD = 0.5  # a pixel is inside the head where the ground-truth mask exceeds this
SHEET_FRAMES = 4  # frames in the contact sheet
SPLITS = ("test", "train", "all")


# ---------------------------------------------------------------------------------------------------- metrics
def _as_tensor(x) -> Tensor:
    t = x if isinstance(x, Tensor) else torch.from_numpy(np.asarray(x))
    return t.detach().to("cpu", torch.float64)


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    """10 log10(range^2 / MSE) in dB, capped at :data:`PSNR_CAP` (so an MSE of 0 gives PSNR_CAP, not inf)."""
    if not math.isfinite(mse) or mse < 0:
        raise ValueError(f"MSE must be finite and non-negative, got {mse}")
    if mse <= data_range ** 2 * 10.0 ** (-PSNR_CAP / 10.0):
        return PSNR_CAP
    return min(PSNR_CAP, 10.0 * math.log10(data_range ** 2 / mse))


def psnr(pred, target, data_range: float = 1.0) -> float:
    """PSNR (dB, capped) of two images of the same shape, e.g. [H, W, 3], over every pixel and channel."""
    a, b = _as_tensor(pred), _as_tensor(target)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return psnr_from_mse(float(((a - b) ** 2).mean()), data_range)


def psnr_masked(pred, target, mask, data_range: float = 1.0) -> float | None:
    """PSNR (dB, capped) over the pixels where ``mask`` [H, W] > 0.5 only (all channels of those pixels); images are
    [H, W, C]. None when the mask has no pixel."""
    a, b, m = _as_tensor(pred), _as_tensor(target), _as_tensor(mask)
    if a.shape != b.shape or a.shape[:-1] != m.shape:
        raise ValueError(f"shapes differ: {tuple(a.shape)}, {tuple(b.shape)} and mask {tuple(m.shape)}")
    inside = m > HEAD_THRESHOLD
    if not bool(inside.any()):
        return None
    return psnr_from_mse(float(((a - b)[inside] ** 2).mean()), data_range)


def _gaussian_window(size: int, sigma: float) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
    return g / g.sum()


def ssim_batch(pred, target, data_range: float = 1.0, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> Tensor:
    """SSIM of B image pairs [B, H, W, C] -> [B] (float64), averaged over channels and valid window positions.

    The window shrinks to the smaller image side when an image is smaller than ``window`` pixels."""
    a, b = _as_tensor(pred), _as_tensor(target)
    if a.shape != b.shape or a.dim() != 4:
        raise ValueError(f"expected two [B, H, W, C] batches of one shape, got {tuple(a.shape)}, {tuple(b.shape)}")
    bsz, h, w, c = a.shape
    size = min(window, h, w)
    g = _gaussian_window(size, sigma)
    gy = g.view(1, 1, size, 1).expand(c, 1, size, 1)
    gx = g.view(1, 1, 1, size).expand(c, 1, 1, size)

    def blur(x: Tensor) -> Tensor:  # separable Gaussian filter per channel, valid positions only
        return torch.nn.functional.conv2d(torch.nn.functional.conv2d(x, gy, groups=c), gx, groups=c)

    x, y = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x ** 2
    syy = blur(y * y) - mu_y ** 2
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))
    return s.mean(dim=(1, 2, 3))


def ssim(pred, target, data_range: float = 1.0) -> float:
    """SSIM of two images [H, W, C] (or [H, W]): 11x11 Gaussian window, sigma 1.5, averaged over channels."""
    a, b = _as_tensor(pred), _as_tensor(target)
    if a.dim() == 2:
        a, b = a[..., None], b[..., None]
    return float(ssim_batch(a[None], b[None], data_range)[0])


def _lpips_metric(width: int, height: int):
    """(callable(pred [B,H,W,3], gt) -> [B] or None, note). Never downloads: LPIPS (:mod:`render_core.evaluation.lpips`)
    needs its AlexNet weights in the local file named by ``BLENDSPLAT_LPIPS_WEIGHTS``."""
    from . import lpips

    if min(width, height) < lpips.MIN_SIZE:
        return None, f"lpips is null: the frames ({width} x {height}) are smaller than LPIPS's {lpips.MIN_SIZE} px"
    model, note = lpips.from_environment()
    if model is None:
        return None, note

    def fn(pred: Tensor, gt: Tensor) -> Tensor:
        return model(pred, gt).double()

    return fn, note


# ------------------------------------------------------------------------------------------------- evaluation
def split_indices(dataset, split: str) -> np.ndarray:
    """The frame indices of ``split``: "test" (held out), "train" or "all"."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    if split == "all":
        return np.arange(len(dataset), dtype=np.int64)
    return np.asarray(getattr(dataset.tracking, split), dtype=np.int64).reshape(-1)


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def evaluate(bundle_or_avatar, data_dir, split: str = "test", batch: int = 4, contact_sheet=None, report=None, *,
             backend: str | None = None, sheet_frames: int = SHEET_FRAMES) -> dict:
    """Render every frame of ``split`` of the dataset at ``data_dir`` and score it against the masked ground truth.

    ``bundle_or_avatar``: a bundle path or an :class:`Avatar`. ``batch``: frames rendered per call. Writes the
    result as JSON to ``report`` and a contact sheet PNG (prediction | ground truth, ``sheet_frames`` frames evenly
    spaced over the split) to ``contact_sheet`` when given. Returns {"psnr", "ssim", "psnr_head", "lpips",
    "frames", "split", "per_frame": [{"index", "psnr", "ssim", "psnr_head", "lpips"}, ...], "bundle", "data",
    "width", "height", "backend", "notes", "seconds"}; "bundle" is None when an Avatar was given.

    Raises DatasetError when the dataset is malformed, does not animate this avatar (other expression or joint
    names) or has no frame in ``split``; BundleError for an unreadable bundle; ValueError for a bad argument."""
    from ..bundle import read_bundle
    from ..data.frames import check_compatible, frame_inputs, targets
    from ..data.portable import read_dataset
    from ..renderer import AvatarRenderer

    t_start = time.perf_counter()
    if batch < 1:
        raise ValueError(f"batch must be at least 1, got {batch}")
    if isinstance(bundle_or_avatar, Avatar):
        avatar, bundle = bundle_or_avatar, None
    else:
        bundle = str(bundle_or_avatar)
        avatar = read_bundle(bundle)
    ds = read_dataset(data_dir)
    try:
        check_compatible(avatar, ds.tracking)
    except DatasetError as e:
        what = f"the avatar {bundle}" if bundle else "the avatar"
        raise DatasetError(f"{what} cannot be evaluated on {data_dir}: {e.detail}", field=e.field) from None
    indices = split_indices(ds, split)
    if indices.size == 0:
        raise DatasetError(f"the dataset {data_dir} has no {split} frames to evaluate", field=split)

    renderer = AvatarRenderer(avatar, backend)
    background = torch.zeros(3)
    lpips_fn, lpips_note = _lpips_metric(int(ds.tracking.width), int(ds.tracking.height))
    notes = [lpips_note, f"psnr values are capped at {PSNR_CAP:g} dB (identical images)",
             "psnr_head: MSE over the pixels where the ground-truth mask > 0.5"]
    want = set()
    if contact_sheet is not None:
        picks = np.linspace(0, indices.size - 1, num=min(max(sheet_frames, 1), indices.size))
        want = {int(indices[int(round(p))]) for p in picks}
    sheet: list[tuple[int, np.ndarray, np.ndarray, float]] = []
    per_frame = []
    for start in range(0, indices.size, batch):
        chunk = indices[start:start + batch]
        frame, cams = frame_inputs(avatar, ds.tracking, chunk)
        out = renderer.render(frame, cams, background=background)
        pred = out.rgb.detach().to("cpu", torch.float64).clamp(0.0, 1.0)
        gt, mask = targets(ds, chunk)
        gt, mask = gt.to(torch.float64), mask.to(torch.float64)
        ssims = ssim_batch(pred, gt)
        lp = lpips_fn(pred, gt) if lpips_fn is not None else None
        for k, i in enumerate(chunk.tolist()):
            rec = {"index": int(i), "psnr": psnr(pred[k], gt[k]), "ssim": float(ssims[k]),
                   "psnr_head": psnr_masked(pred[k], gt[k], mask[k]),
                   "lpips": float(lp[k]) if lp is not None else None}
            per_frame.append(rec)
            if i in want:
                sheet.append((int(i), pred[k].numpy(), gt[k].numpy(), rec["psnr"]))

    result = {
        "psnr": _mean(r["psnr"] for r in per_frame),
        "ssim": _mean(r["ssim"] for r in per_frame),
        "psnr_head": _mean(r["psnr_head"] for r in per_frame),
        "lpips": _mean(r["lpips"] for r in per_frame),
        "frames": len(per_frame),
        "split": split,
        "bundle": bundle,
        "data": str(data_dir),
        "width": int(ds.tracking.width),
        "height": int(ds.tracking.height),
        "backend": renderer.backend,
        "notes": notes,
        "per_frame": per_frame,
    }
    if contact_sheet is not None:
        result["contact_sheet"] = str(write_contact_sheet(sheet, contact_sheet))
    result["seconds"] = round(time.perf_counter() - t_start, 3)
    if report is not None:
        report = Path(report)
        report.parent.mkdir(parents=True, exist_ok=True)
        result["report"] = str(report)
        tmp = report.with_name(report.name + ".tmp")
        tmp.write_text(json.dumps(result, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, report)
    return result


def write_contact_sheet(rows: list[tuple[int, np.ndarray, np.ndarray, float]], out_png) -> Path:
    """One row per (index, prediction [H, W, 3], ground truth [H, W, 3], psnr): prediction | ground truth, under
    a caption with the frame index and its PSNR (OpenImageIO PNG)."""
    from .plot import GLYPH_H, draw_text, write_png

    if not rows:
        raise ValueError("the contact sheet needs at least one frame")
    h, w = rows[0][1].shape[:2]
    scale = 1 if w < 160 else 2
    cap = (GLYPH_H + 4) * scale
    pad = 2
    sheet = np.full((cap + pad + len(rows) * (h + cap + pad), 2 * w + 3 * pad, 3), 40, dtype=np.uint8)
    draw_text(sheet, pad, 2 * scale, "prediction", (230, 230, 230), scale)
    draw_text(sheet, 2 * pad + w, 2 * scale, "ground truth", (230, 230, 230), scale)
    for r, (index, pred, gt, value) in enumerate(rows):
        y = cap + pad + r * (h + cap + pad)
        draw_text(sheet, pad, y + scale, f"frame {index}  psnr {value:.2f}", (255, 210, 90), scale)
        y += cap
        for c, img in enumerate((pred, gt)):
            x = pad + c * (w + pad)
            sheet[y:y + h, x:x + w] = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return write_png(out_png, sheet)


def _fmt(v: float | None, digits: int) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def run_eval(bundle, data, *, as_json: bool = False, split: str = "test", batch: int = 4, report=None,
             contact_sheet=None) -> int:
    """``blendsplat eval --bundle BUNDLE --data DATA [--json]``: print the evaluation (one JSON object with
    ``--json``, else one summary line) to stdout; exit status 0."""
    result = evaluate(bundle, data, split=split, batch=batch, contact_sheet=contact_sheet, report=report)
    if as_json:
        sys.stdout.write(json.dumps(result, indent=2, allow_nan=False) + "\n")
    else:
        sys.stdout.write(f"{bundle} on {data} ({result['frames']} {split} frames): PSNR {_fmt(result['psnr'], 2)} dB, "
                         f"SSIM {_fmt(result['ssim'], 4)}, head PSNR {_fmt(result['psnr_head'], 2)} dB, "
                         f"LPIPS {_fmt(result['lpips'], 4)}\n")
    sys.stdout.flush()
    return 0
