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

The metrics are :mod:`.metrics`' (the same SSIM as the training loss, with valid windows instead of zero-padded
borders). Identical images have an infinite PSNR; every PSNR here is capped at :data:`PSNR_CAP` (100 dB, an MSE
of 1e-10) so that reports stay finite, standard JSON. Averages are means of the per-frame values (the usual convention).
Predictions are clamped to [0, 1] before scoring.

The report file (``report=``) names files relative to its own folder, others by their name alone
(:func:`relative_paths`): a training job's report is served to API clients, and the machine's absolute paths are
none of their business. The returned dict keeps the paths as given.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..atomic import atomic_path
from ..avatar import Avatar
from ..errors import DatasetError, OptionError
from .metrics import PSNR_CAP, psnr, psnr_masked, ssim
from .plot import PlotsUnavailable, write_contact_sheet

log = logging.getLogger(__name__)

SHEET_FRAMES = 4  # frames in the contact sheet
SPLITS = ("test", "train", "all")


# ----------------------------------------------------------------------------------------------------- LPIPS
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


# ------------------------------------------------------------------------------------------------- the file
def relative_path(path: str | os.PathLike | None, base: str | os.PathLike) -> str | None:
    """``path`` as the reader of a file in ``base`` may see it: relative to ``base`` when it is inside it (e.g.
    ``contact_sheet.png``), else its name alone (the dataset's folder name, the bundle's file name). None stays
    None."""
    if path is None:
        return None
    target, folder = Path(path).resolve(), Path(base).resolve()
    try:
        return target.relative_to(folder).as_posix() or "."
    except ValueError:
        return target.name


def relative_paths(record: dict, base: str | os.PathLike, keys=("bundle", "data", "report", "contact_sheet",
                                                               "curves", "workdir")) -> dict:
    """A copy of a JSON record (a report, a summary) with the file names under ``keys``, at any depth, made
    relative to ``base`` (:func:`relative_path`); and in text (``notes``), the LPIPS weights' path (a file of the
    machine's, from ``BLENDSPLAT_LPIPS_WEIGHTS``) replaced by its name."""
    from .lpips import ENV

    weights = os.environ.get(ENV, "").strip()

    def walk(value, key=None):
        if isinstance(value, dict):
            return {k: walk(v, k) for k, v in value.items()}
        if isinstance(value, list):
            return [walk(v) for v in value]
        if isinstance(value, str):
            if key in keys:
                return relative_path(value, base)
            if weights and weights in value:
                return value.replace(weights, Path(weights).name)
        return value

    return walk(record)


# ------------------------------------------------------------------------------------------------- evaluation
def split_indices(dataset, split: str) -> np.ndarray:
    """The frame indices of ``split``: "test" (held out), "train" or "all"."""
    if split not in SPLITS:
        raise OptionError(f"must be one of {', '.join(SPLITS)}, got {split!r}", field="split")
    if split == "all":
        return np.arange(len(dataset), dtype=np.int64)
    return np.asarray(getattr(dataset.tracking, split), dtype=np.int64).reshape(-1)


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _prediction(rgb: Tensor) -> Tensor:
    """A render as scored: float64 on the CPU, clamped to [0, 1]."""
    return rgb.detach().to("cpu", torch.float64).clamp(0.0, 1.0)


def _score(pred: Tensor, gt: Tensor, mask: Tensor) -> dict[str, list]:
    """Per-frame psnr, ssim and psnr_head of B predictions (float64, as :func:`_prediction` gives them)."""
    gt, mask = gt.to(torch.float64), mask.to(torch.float64)
    return {"psnr": [psnr(p, g) for p, g in zip(pred, gt, strict=True)],
            "ssim": ssim(pred, gt, reduction="none").tolist(),
            "psnr_head": [psnr_masked(p, g, m) for p, g, m in zip(pred, gt, mask, strict=True)]}


def _aligned_inputs(avatar: Avatar, frame, cams, target: Tensor, iterations: int, expressions: bool):
    """The frame and cameras after test-time alignment (:func:`.align.align_frames`)."""
    from ..camera import Cameras
    from .align import align_frames

    a = align_frames(avatar, frame, cams, target.to(torch.float32), iterations=iterations, expressions=expressions)
    frame = type(frame)(torch.from_numpy(a.expression), frame.joint_rotations, frame.eyelids)
    return frame, Cameras(cams.K, torch.from_numpy(a.R), torch.from_numpy(a.t), cams.width, cams.height)


def evaluate(bundle_or_avatar, data_dir, split: str = "test", batch: int = 4, contact_sheet=None, report=None, *,
             backend: str | None = None, sheet_frames: int = SHEET_FRAMES, align: int = 0,
             align_expressions: bool = False) -> dict:
    """Render every frame of ``split`` of the dataset at ``data_dir`` and score it against the masked ground truth.

    ``bundle_or_avatar``: a bundle path or an :class:`Avatar`. ``batch``: frames rendered per call. Writes the
    result as JSON to ``report`` and a contact sheet PNG (prediction | ground truth, ``sheet_frames`` frames evenly
    spaced over the split) to ``contact_sheet`` when given. Returns {"psnr", "ssim", "psnr_head", "lpips",
    "frames", "split", "per_frame": [{"index", "psnr", "ssim", "psnr_head", "lpips"}, ...], "bundle", "data",
    "width", "height", "backend", "notes", "seconds"}; "bundle" is None when an Avatar was given. With
    ``contact_sheet`` also "contact_sheet" (its path) and "plots" ({"contact_sheet": path}); without matplotlib
    (the ``train`` extra) the sheet is skipped, not an error: "contact_sheet" is None, "plots" is {"skipped":
    reason} and the reason is logged and added to "notes". With ``report`` also "report" (its path); in the file
    itself every path is relative to the report's folder or a name alone (:func:`relative_paths`).

    ``align``: that many steps of test-time alignment (:mod:`.align`: each frame's head pose, and its expressions
    with ``align_expressions``, refined against its own image with this avatar) before scoring; the scores without
    it are kept under "unaligned" ({"psnr", "ssim", "psnr_head"}, and "psnr_head_unaligned" per frame) and the
    result says "aligned": {"iterations", "expressions"}. 0 (the default) scores the dataset's tracking as it is.

    Raises DatasetError when the dataset is malformed, does not animate this avatar (other expression or joint
    names) or has no frame in ``split``; BundleError for an unreadable bundle; ValueError for a bad argument."""
    from ..bundle import read_bundle
    from ..data.frames import check_compatible, frame_inputs, targets
    from ..data.portable import read_dataset
    from ..renderer import AvatarRenderer

    t_start = time.perf_counter()
    if batch < 1:
        raise OptionError(f"must be at least 1, got {batch}", field="batch")
    if align < 0:
        raise OptionError(f"must be at least 0, got {align}", field="align")
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
    per_frame, unaligned_frames = [], []
    for start in range(0, indices.size, batch):
        chunk = indices[start:start + batch]
        frame, cams = frame_inputs(avatar, ds.tracking, chunk)
        gt, mask = targets(ds, chunk)
        unaligned = None
        if align:
            unaligned = _score(_prediction(renderer.render(frame, cams, background=background).rgb), gt, mask)
            frame, cams = _aligned_inputs(avatar, frame, cams, gt, align, align_expressions)
        pred = _prediction(renderer.render(frame, cams, background=background).rgb)
        scores = _score(pred, gt, mask)
        gt = gt.to(torch.float64)
        lp = lpips_fn(pred, gt) if lpips_fn is not None else None
        for k, i in enumerate(chunk.tolist()):
            rec = {"index": int(i), "psnr": scores["psnr"][k], "ssim": scores["ssim"][k],
                   "psnr_head": scores["psnr_head"][k], "lpips": float(lp[k]) if lp is not None else None}
            if unaligned is not None:
                rec["psnr_head_unaligned"] = unaligned["psnr_head"][k]
                unaligned_frames.append({key: unaligned[key][k] for key in unaligned})
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
    if align:
        result["aligned"] = {"iterations": align, "expressions": align_expressions}
        result["unaligned"] = {key: _mean(r[key] for r in unaligned_frames) for key in ("psnr", "ssim", "psnr_head")}
        notes.append("aligned: each frame's head pose%s refined against its own image with this avatar before "
                     "scoring (test-time alignment); the dataset's tracking as it is scores \"unaligned\""
                     % (" and expressions" if align_expressions else ""))
    if contact_sheet is not None:
        try:
            result["contact_sheet"] = str(write_contact_sheet(sheet, contact_sheet))
            result["plots"] = {"contact_sheet": result["contact_sheet"]}
        except PlotsUnavailable as e:
            log.warning("contact sheet skipped: %s", e.reason)
            result["contact_sheet"] = None
            result["plots"] = {"skipped": e.reason}
            notes.append(f"no contact sheet: {e.reason}")
    result["seconds"] = round(time.perf_counter() - t_start, 3)
    if report is not None:
        report = Path(report)
        report.parent.mkdir(parents=True, exist_ok=True)
        result["report"] = str(report)
        saved = relative_paths(result, report.parent)
        with atomic_path(report) as tmp:
            tmp.write_text(json.dumps(saved, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return result
