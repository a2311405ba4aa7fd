"""Pruning by contribution (docs/method.md section 6): fewer face Gaussians for (nearly) the same image.

The contribution of face Gaussian i is the sum, over a fixed sample of training frames and over their pixels, of
its blending weight w_ip = alpha_ip T_ip (its alpha at pixel p times the transmittance in front of it: its share of
that pixel's colour). The image is linear in the colours, rgb_p = sum_i w_ip c_i (+ T_p x background), so the
gradient of the summed image with respect to one colour channel of Gaussian i is exactly sum_p w_ip: one forward
and backward of the training rasterizer per frame (:func:`contribution`), with whatever step the training device
uses (the native C++ backward on the CPU, gsplat's on CUDA), the pairs it skips (alpha < 1/255, past the
transmittance stop) excluded as they are from the image. With refined poses (:mod:`.poses`) each frame's head is
moved by its correction, as training renders it.

:class:`ContributionPruner` owns the schedule (preset ``prune_at``, ``prune_fraction``, ``prune_frames``): at each
iteration of ``prune_at`` it scores the face Gaussians on ``prune_frames`` training frames (evenly spaced: no
random draw, so a resumed run scores the same frames) and removes the lowest-scoring ones through
:func:`.densify.reindex` (survivors keep their Adam moments, their blendshape pairs and LBS weights; the
densification statistics follow them); training then continues and fine-tunes the rest. ``prune_fraction`` is
the fraction of face Gaussians removed over the whole schedule: each of the m pruning iterations removes
1 - (1 - f)^(1/m) of those present. With ``prune_mouth`` (the default) the mouth interior loses the same fraction,
its Gaussians ranked among themselves (:func:`prune_mouth_lowest`; their scores lie far below the face's, so one
ranking would take nearly all of them). Off when ``prune_at`` is empty or ``prune_fraction`` is 0.

``prune_by`` (``train --prune-by``) chooses the score: the contribution itself, or ``"efficiency"``: the
contribution per pixel the Gaussian costs to render (:func:`footprints`, its alpha >= 1/255 ellipse, plus
:data:`FIXED_PIXELS` a frame), so that big faint Gaussians go before small bright ones; or ``"peak"``: the largest
of its per-frame weights instead of their sum, so that a Gaussian that one expression needs (teeth behind parted
lips, a crease of a smile) stays beside the ones every frame shows a little of: a blendshape avatar is judged on
expressions it was not trained on, and a sum over the sampled frames ranks such Gaussians by how often their
expression happened to be sampled.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .. import raster
from ..camera import Cameras
from ..deform import Frame, Splats, skin
from ..evaluation.align import moved_splats
from ..raster.reference import ALPHA_MIN, EXTENT_MAX, project
from .densify import DensifyStrategy, reindex, swap_parameter
from .model import TrainableAvatar
from .poses import corrected
from .presets import Preset

PRUNE_BY = ("contribution", "efficiency", "peak")
FIXED_PIXELS = 32.0  # what a Gaussian costs a frame beyond its pixels (blend, skinning, projection, binning), in pixels


def blend_weights(splats: Splats | raster.ShadedSplats, cameras: Cameras, rasterize: raster.Differentiable,
                  mode: str = "classic", *, threads: int = 0) -> Tensor:
    """[B, N]: for each of the B sets of posed splats (set b seen by camera b; their SH is not read), each splat's
    sum over the pixels of its blending weight alpha T, read as the gradient of the summed red channel with respect
    to its red colour (exact: the image is linear in the colours, whose values do not matter)."""
    colors = torch.zeros_like(splats.means, requires_grad=True)
    shaded = raster.ShadedSplats(splats.means.detach(), splats.quats.detach(), splats.scales.detach(),
                                 splats.opacities.detach(), colors)
    rgb, _ = rasterize(shaded, cameras, None, mode, threads=threads)
    (grad,) = torch.autograd.grad(rgb[..., 0].sum(), colors)
    return grad[..., 0]


def check_prune_by(by: str) -> None:
    """Refuse a score that is not one of :data:`PRUNE_BY`, by name."""
    if by not in PRUNE_BY:
        raise ValueError(f"prune_by must be one of {PRUNE_BY}, got {by!r}")


def footprints(splats: Splats, cameras: Cameras, mode: str = "classic") -> Tensor:
    """[B, N]: each splat's screen area in pixels where its alpha reaches 1/255 (the ellipse of its opacity-aware
    extent, at most 3.33 sigma, as the rasterizer bounds it), 0 where it is culled: the pixels compositing pays
    for when nothing in front has saturated them."""
    with torch.no_grad():
        proj = project(splats.means.detach(), splats.quats.detach(), splats.scales.detach(),
                       splats.opacities.detach(), cameras.to(splats.means.dtype), mode)
        a, b, c = proj.conics.unbind(-1)
        extent2 = torch.clamp(2.0 * torch.log(proj.opacities.clamp_min(ALPHA_MIN) / ALPHA_MIN), max=EXTENT_MAX ** 2)
        area = torch.pi * extent2 / (a * c - b * b).clamp_min(1e-30).sqrt()
        return torch.where(proj.visible, area, 0.0)


def contribution(model: TrainableAvatar, frames: Frame, cameras: Cameras, rasterize: raster.Differentiable, *,
                 motions: Tensor | None = None, threads: int = 0, by: str = "contribution",
                 mouth: bool = False) -> Tensor:
    """Per face Gaussian [N] (float64, on the model's device): :func:`blend_weights` summed over the B frames
    (``frames``, ``cameras``: one camera per frame), one frame at a time. ``motions``: [B, 6 (+ K)] rigid
    corrections (w, u) of the frames' heads and their expression corrections (:mod:`.poses`, as training renders
    them), or None. ``by="efficiency"``: that sum divided by what the Gaussian costs to render over the frames,
    :data:`FIXED_PIXELS` a frame plus its :func:`footprints` (the blending weight per pixel paid for);
    ``by="peak"``: the largest of the B weights instead of their sum. ``mouth``: [N + M], the M mouth-interior
    Gaussians' scores after the face's."""
    check_prune_by(by)
    n = model.num_gaussians + (int(model.mouth_means.shape[0]) if mouth else 0)
    score = torch.zeros(n, dtype=torch.float64, device=model.means.device)
    cost = torch.full_like(score, FIXED_PIXELS * len(frames))
    with torch.no_grad():
        avatar = model.avatar(0, detach=True, deltas=False)  # the colours do not change the weights
    for j in range(len(frames)):
        frame, motion = Frame(frames.expression[j:j + 1], frames.joint_rotations[j:j + 1],
                              None if frames.eyelids is None else frames.eyelids[j:j + 1]), None
        if motions is not None:
            frame, motion = corrected(frame, motions[j:j + 1])
        with torch.no_grad():
            splats = skin(avatar, model.blend(frame.expression, 0), frame)
            if motion is not None:
                splats = moved_splats(splats, cameras.index(j), *motion)
        w = blend_weights(splats, cameras.index(j), rasterize, avatar.raster_mode, threads=threads)
        if by == "peak":
            torch.maximum(score, w[0, :n].to(score.dtype), out=score)
        else:
            score += w[0, :n].to(score.dtype)
        if by == "efficiency":
            cost += footprints(splats, cameras.index(j), avatar.raster_mode)[0, :n].to(cost.dtype)
    return score / cost if by == "efficiency" else score


def prune_lowest(model: TrainableAvatar, opt: torch.optim.Optimizer, score: Tensor, count: int,
                 strategy: DensifyStrategy | None = None) -> dict:
    """Remove the ``count`` face Gaussians with the lowest ``score`` [N] (ties: the later index goes first), keeping
    the order, Adam moments and blendshape entries of the rest (and ``strategy``'s statistics of them). Returns
    the counts: before, after, pruned, mass_kept (the fraction of the score the survivors hold), unseen (Gaussians
    with a zero score)."""
    n = model.num_gaussians
    count = min(max(int(count), 0), n - 1)
    with torch.no_grad():
        order = torch.argsort(score, descending=True, stable=True)
        keep = order[: n - count].sort().values
        total = float(score.sum())
        kept = float(score[keep].sum())
        if count:
            reindex(model, opt, keep, torch.zeros(len(keep), dtype=torch.bool, device=keep.device))
            if strategy is not None:
                strategy.select(keep)
    return {"before": n, "after": model.num_gaussians, "pruned": count,
            "mass_kept": round(kept / total, 6) if total > 0 else 1.0, "unseen": int((score <= 0).sum())}


def prune_mouth_lowest(model: TrainableAvatar, opt: torch.optim.Optimizer, score: Tensor, count: int) -> dict:
    """Remove the ``count`` mouth-interior Gaussians with the lowest ``score`` [M] (ties: the later index goes
    first; at least one stays), keeping the order and Adam moments of the rest and their jaw or upper-head group.
    Returns the counts: mouth_before, mouth_after."""
    m = int(model.mouth_means.shape[0])
    count = min(max(int(count), 0), m - 1)
    if count:
        with torch.no_grad():
            keep = torch.argsort(score, descending=True, stable=True)[: m - count].sort().values
            for name, value in list(model.named_parameters()):
                if name.startswith("mouth_"):
                    swap_parameter(model, opt, name, value.detach()[keep], lambda v: v[keep])
            model.register_buffer("mouth_group", model.mouth_group[keep])
    return {"mouth_before": m, "mouth_after": int(model.mouth_means.shape[0])}


def step_fraction(fraction: float, steps: int) -> float:
    """What each of ``steps`` prunings removes so that ``fraction`` of the Gaussians go in all."""
    if steps <= 0 or fraction <= 0:
        return 0.0
    return 1.0 - (1.0 - min(fraction, 1.0)) ** (1.0 / steps)


class ContributionPruner:
    """The preset's contribution-pruning schedule (:meth:`from_preset`); :meth:`due` says when,
    :meth:`prune` does it. Holds no state of its own: the schedule is the preset's, the sample fixed."""

    def __init__(self, at: tuple[int, ...] = (), fraction: float = 0.0, frames: int = 24, by: str = "contribution",
                 mouth: bool = False):
        check_prune_by(by)  # at the trainer's start, not at the first pruning
        self.by, self.mouth = by, bool(mouth)
        self.at = tuple(sorted({int(i) for i in at})) if fraction > 0 else ()
        self.fraction, self.frames = float(fraction), max(int(frames), 1)
        self.each = step_fraction(self.fraction, len(self.at))

    @classmethod
    def from_preset(cls, preset: Preset) -> ContributionPruner:
        return cls(preset.prune_at, preset.prune_fraction, preset.prune_frames, preset.prune_by, preset.prune_mouth)

    @property
    def enabled(self) -> bool:
        return bool(self.at)

    def due(self, iteration: int) -> bool:
        return iteration in self.at

    def sample(self, count: int) -> np.ndarray:
        """Indices into the ``count`` training frames to score on (evenly spaced, at most ``frames``)."""
        return np.unique(np.linspace(0, count - 1, min(self.frames, count)).round().astype(np.int64))

    def prune(self, model: TrainableAvatar, opt: torch.optim.Optimizer, strategy: DensifyStrategy | None,
              frames: Frame, cameras: Cameras, rasterize: raster.Differentiable, *, motions: Tensor | None = None,
              threads: int = 0) -> dict:
        """Score the face Gaussians on the sample of the training ``frames`` (``cameras``: one per frame;
        ``motions``: their [F, 6 (+ K)] corrections, :attr:`.poses.FramePoses.wu`, or None) and remove this step's
        share; the counts of :func:`prune_lowest` and ``frames`` (how many were scored)."""
        pick = torch.from_numpy(self.sample(len(frames))).to(frames.expression.device)
        sub = Frame(frames.expression[pick], frames.joint_rotations[pick],
                    None if frames.eyelids is None else frames.eyelids[pick])
        cams = Cameras(cameras.K[pick], cameras.R[pick], cameras.t[pick], cameras.width, cameras.height)
        moved = None if motions is None else motions[pick]
        score = contribution(model, sub, cams, rasterize, motions=moved, threads=threads, by=self.by,
                             mouth=self.mouth)
        n = model.num_gaussians
        counts = prune_lowest(model, opt, score[:n], int(round(self.each * n)), strategy)
        if self.mouth:  # the mouth interior by the same fraction, ranked among itself
            counts.update(prune_mouth_lowest(model, opt, score[n:], int(round(self.each * (len(score) - n)))))
        return {**counts, "frames": len(pick)}
