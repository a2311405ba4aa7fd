"""Test-time alignment: each evaluated frame's head pose refined against its image with the avatar itself.

A tracked dataset's held-out frames carry the tracker's estimate of the pose, and on a detailed face a one-pixel
error of that estimate alone costs about 7 dB of PSNR (docs/method.md section 13), whatever the avatar's quality.
To score the avatar rather than the tracking, :func:`align_frames` refines, per frame, a rigid motion of the head
(rotation ``w`` about the head's centre, translation ``u``) and optionally the expression coefficients, by Adam on
the L1 distance between the differentiable render and the masked frame, then returns the frames' cameras and
expressions so refined. The motion is folded into the camera exactly::

    X' = Q (X - c) + c + u    (Q = exp(w))   seen by (R, t)   ==   X seen by (R Q, t + R (c - Q c + u))

so the colours are shaded from the moved camera's centre and the refined tracking renders the same image with
any backend. Only the pose (and expressions when asked) moves: the avatar is never changed, so a frame's image
informs its own pose and nothing else. This is the protocol of test-time pose optimisation used to evaluate
novel-view synthesis from estimated poses; ``eval --align`` reports both figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..avatar import Avatar
from ..camera import Cameras
from ..deform import Frame, Splats, blend, shade, skin
from ..errors import OptionError
from ..raster import ShadedSplats, differentiable
from ..rotation import axis_angle_to_matrix, matrix_to_quat, quat_multiply

ROTATION_LR = 2e-3  # radians per Adam step
TRANSLATION_LR = 5e-4  # metres per Adam step
EXPRESSION_LR = 1e-2
EXPRESSION_PRIOR = 1e-3  # weight of |d expression|^2 against the mean L1 image residual


@dataclass(frozen=True)
class Aligned:
    """The refined tracking of the aligned frames (in the order given): cameras ``R [B, 3, 3]``, ``t [B, 3]`` and
    expressions ``[B, K]`` in the avatar's expression order."""

    R: np.ndarray
    t: np.ndarray
    expression: np.ndarray


def moved_camera(cams: Cameras, w: Tensor, u: Tensor, centre: Tensor) -> tuple[Tensor, Tensor]:
    """(R Q, t + R (c - Q c + u)): the camera that sees the unmoved head as ``cams`` sees the moved one."""
    Q = axis_angle_to_matrix(w)
    R = cams.R @ Q
    t = cams.t + (cams.R @ (centre - (Q @ centre[..., None])[..., 0] + u)[..., None])[..., 0]
    return R, t


def moved_splats(splats: Splats, cams: Cameras, w: Tensor, u: Tensor) -> ShadedSplats:
    """The posed head ``splats`` moved by (w [B, 3], u [B, 3]) about its centre, shaded for ``cams``: what
    ``cams`` sees is the unmoved head seen by the moved camera (:func:`moved_camera`). Differentiable in w, u
    and the splats."""
    centre = splats.means.mean(1).detach()  # [B, 3]: the head's centre, the rotation's pivot
    Q = axis_angle_to_matrix(w)
    means = ((splats.means - centre[:, None]) @ Q.transpose(1, 2)) + centre[:, None] + u[:, None]
    quats = quat_multiply(matrix_to_quat(Q)[:, None].expand_as(splats.quats), splats.quats)
    R, t = moved_camera(cams, w, u, centre)
    colours = shade(splats, -(R.transpose(1, 2) @ t[..., None])[..., 0])
    return ShadedSplats(means, quats, splats.scales, splats.opacities, colours)


def _render(avatar: Avatar, cams: Cameras, splats: Splats, w: Tensor, u: Tensor, rasterize) -> Tensor:
    rgb, _ = rasterize(moved_splats(splats, cams, w, u), cams, None, avatar.raster_mode)
    return rgb


def align_frames(avatar: Avatar, frame: Frame, cams: Cameras, target: Tensor, *, iterations: int = 40,
                 expressions: bool = False, backend: str = "native") -> Aligned:
    """Refine B frames (``frame``, ``cams``) against ``target`` [B, H, W, 3] (masked to black, in [0, 1]) for
    ``iterations`` Adam steps; see the module docstring."""
    if iterations < 1:
        raise OptionError(f"must be at least 1, got {iterations}", field="iterations")
    avatar = avatar.to(torch.float32)
    rasterize = differentiable(backend)
    b = frame.batch_size
    w = torch.zeros(b, 3, requires_grad=True)
    u = torch.zeros(b, 3, requires_grad=True)
    de = torch.zeros_like(frame.expression, requires_grad=True)
    groups = [{"params": [w], "lr": ROTATION_LR}, {"params": [u], "lr": TRANSLATION_LR}]
    if expressions:
        groups.append({"params": [de], "lr": EXPRESSION_LR})
    opt = torch.optim.Adam(groups)
    with torch.no_grad():
        fixed = skin(avatar, blend(avatar, frame.expression), frame)  # the head, when its expressions stay
    for _ in range(iterations):
        opt.zero_grad(set_to_none=True)
        splats = skin(avatar, blend(avatar, frame.expression + de), frame) if expressions else fixed
        rgb = _render(avatar, cams, splats, w, u, rasterize)
        loss = (rgb - target).abs().mean() * b + EXPRESSION_PRIOR * de.square().sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        final = skin(avatar, blend(avatar, frame.expression + de), frame) if expressions else fixed
        centre = final.means.mean(1)
        R, t = moved_camera(cams, w, u, centre)
    return Aligned(R.numpy().astype(np.float32), t.numpy().astype(np.float32),
                   (frame.expression + de).detach().numpy().astype(np.float32))
