"""Training losses (docs/method.md section 5): L = (0.8 L1 + 0.2 D-SSIM) + 10 L_alpha + 100 L_reg.

Images are [B, H, W, 3] (RGB) and [B, H, W] (alpha, mask) in [0, 1]. The SSIM (zero-padded "same" borders here)
and the PSNR are :mod:`render_core.evaluation.metrics`'s, the ones evaluation reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..evaluation.metrics import ssim

RGB_L1, RGB_DSSIM = 0.8, 0.2
ALPHA_WEIGHT = 10.0
MOUTH_WEIGHT = 100.0


def l1(pred: Tensor, target: Tensor) -> Tensor:
    return (pred - target).abs().mean()


def alpha_mse(alpha: Tensor, mask: Tensor) -> Tensor:
    """Accumulated opacity vs the foreground head mask, mean squared error (the reference code)."""
    return (alpha - mask).square().mean()


@dataclass
class MouthCylinder:
    """The cylinder the mouth-interior Gaussians must stay in (rest space, metres).

    Defined from the mouth Gaussians' initial rest positions: the axis runs along x (left-right, across the
    mouth) through the centre of their bounding box; the radius is the largest distance of an initial mouth
    Gaussian from that axis (in y-z) plus ``margin``; the half-length is half the x-extent plus ``margin``. So
    every initial mouth Gaussian is inside (the regulariser starts at exactly 0) and may move up to ``margin``
    (default 5 mm) beyond its initial extent for free.
    """

    centre: Tensor  # [3]
    radius: float
    half_length: float

    @classmethod
    def from_points(cls, x: Tensor, margin: float = 0.005) -> MouthCylinder:
        x = x.detach().float()
        lo, hi = x.amin(0), x.amax(0)
        centre = (lo + hi) / 2
        r = float((x[:, 1:] - centre[1:]).norm(dim=1).max()) if len(x) else 0.0
        return cls(centre, r + margin, float(hi[0] - lo[0]) / 2 + margin)

    def sdf(self, x: Tensor) -> Tensor:
        """Signed distance of points [M, 3] to the capped cylinder (negative inside)."""
        p = x - self.centre.to(x)
        d_rad = p[:, 1:].norm(dim=1) - self.radius
        d_ax = p[:, 0].abs() - self.half_length
        d = torch.stack([d_rad, d_ax], dim=1)
        return d.amax(1).clamp_max(0.0) + d.clamp_min(0.0).norm(dim=1)

    def loss(self, x: Tensor) -> Tensor:
        """mean(max(SDF(x), 0)^2)."""
        if x.shape[0] == 0:
            return x.sum() * 0
        return self.sdf(x).clamp_min(0.0).square().mean()

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "radius": self.radius, "half_length": self.half_length}

    @classmethod
    def from_dict(cls, d: dict) -> MouthCylinder:
        return cls(torch.tensor(d["centre"], dtype=torch.float32), float(d["radius"]), float(d["half_length"]))


def total_loss(rgb: Tensor, alpha: Tensor, target: Tensor, mask: Tensor, mouth_means: Tensor,
               cylinder: MouthCylinder) -> tuple[Tensor, dict[str, Tensor]]:
    """The training loss and its terms (l1, ssim (the SSIM, not D-SSIM), alpha, mouth)."""
    t_l1 = l1(rgb, target)
    t_ssim = ssim(rgb, target, padding="same")  # zero-padded borders, as 3DGS computes D-SSIM
    t_alpha = alpha_mse(alpha, mask)
    t_mouth = cylinder.loss(mouth_means)
    loss = RGB_L1 * t_l1 + RGB_DSSIM * (1 - t_ssim) + ALPHA_WEIGHT * t_alpha + MOUTH_WEIGHT * t_mouth
    return loss, {"l1": t_l1, "ssim": t_ssim, "alpha": t_alpha, "mouth": t_mouth}
