"""Image metrics: the one PSNR and the one SSIM of the project (docs/method.md sections 5 and 10).

The training loss (:func:`render_core.train.losses.total_loss`, D-SSIM = 1 - SSIM) and the held-out evaluation
(:mod:`.report`) both call :func:`ssim`; they differ only in the border convention they ask for:

- ``padding="same"`` (training, as 3DGS computes its D-SSIM): the images are zero-padded by half a window, so there
  is one SSIM value per pixel;
- ``padding="valid"`` (evaluation, the usual reporting convention): only window positions that lie entirely inside
  the image count.

Conventions shared by every function here:

- images are channels-last, ``[..., H, W, C]`` (RGB: C = 3), values in ``[0, data_range]`` (by default 1 for
  floating-point images, the dtype's maximum for integer ones: 255 for uint8);
- :func:`ssim` is plain torch and differentiable: it keeps its inputs' dtype and device, so it runs on the GPU
  inside the training graph. The PSNR functions are metrics, not losses: they return Python floats computed in
  float64 (on the inputs' device) and accept numpy arrays too;
- identical images have an infinite PSNR; every PSNR here is capped at :data:`PSNR_CAP` (100 dB, an MSE of
  1e-10 for a data range of 1) so that logs and reports stay finite, standard JSON.

Example::

    >>> import torch
    >>> from render_core.evaluation.metrics import psnr, ssim
    >>> a = torch.rand(2, 64, 64, 3, generator=torch.Generator().manual_seed(0))
    >>> round(psnr(a, a.roll(1, dims=2)), 1)  # PSNR of the pooled MSE of the batch
    7.8
    >>> round(float(ssim(a, a)), 6)
    1.0
    >>> ssim(a, a.flip(1), reduction="none").shape  # one SSIM per image
    torch.Size([2])
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

PSNR_CAP = 100.0  # dB reported for identical images (MSE below 1e-10 * data_range^2)
HEAD_THRESHOLD = 0.5  # a pixel is inside the head where the ground-truth mask exceeds this
SSIM_WINDOW = 11  # Gaussian window side, pixels
SSIM_SIGMA = 1.5  # Gaussian window standard deviation, pixels
SSIM_K1, SSIM_K2 = 0.01, 0.03  # C1 = (K1 * data_range)^2, C2 = (K2 * data_range)^2


# ------------------------------------------------------------------------------------------------------- PSNR
def _tensor(x) -> Tensor:
    """``x`` as a tensor: tensors as they are, anything else (numpy, read-only or strided views) copied."""
    return x if isinstance(x, Tensor) else torch.from_numpy(np.array(x))


def _default_range(t: Tensor, data_range: float | None) -> float:
    """``data_range``, or when None the range of ``t``'s dtype: 1 for floating point, the maximum for integers."""
    if data_range is not None:
        return float(data_range)
    if t.is_floating_point() or t.dtype == torch.bool:
        return 1.0
    return float(torch.iinfo(t.dtype).max)


def _float64(t: Tensor, device: torch.device | None = None) -> Tensor:
    """A detached float64 copy of ``t`` on ``device`` (default: where ``t`` is)."""
    return t.detach().to(device=device if device is not None else t.device, dtype=torch.float64)


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    """PSNR in dB of a mean squared error: ``10 log10(data_range^2 / mse)``, capped at :data:`PSNR_CAP`.

    Args:
        mse: The mean squared error, finite and non-negative. An MSE of 0 gives ``PSNR_CAP``, not inf.
        data_range: The largest possible pixel value (1 for images in [0, 1], 255 for 8-bit images).

    Raises:
        ValueError: ``mse`` is negative or not finite.

    Example::

        >>> psnr_from_mse(0.01)
        20.0
    """
    if not math.isfinite(mse) or mse < 0:
        raise ValueError(f"MSE must be finite and non-negative, got {mse}")
    if mse <= data_range ** 2 * 10.0 ** (-PSNR_CAP / 10.0):
        return PSNR_CAP
    return min(PSNR_CAP, 10.0 * math.log10(data_range ** 2 / mse))


def psnr(pred, target, data_range: float | None = None) -> float:
    """PSNR in dB (capped at :data:`PSNR_CAP`) over every pixel and channel of two images or batches.

    Args:
        pred: ``[..., H, W, C]`` (or any shape) tensor or array: the rendered image(s).
        target: The same shape as ``pred``: the reference image(s); moved to ``pred``'s device.
        data_range: The largest possible pixel value; None: 1 for floating-point images, the dtype's maximum for
            integer ones (255 for uint8).

    Returns:
        ``psnr_from_mse(mean((pred - target)^2))``, computed in float64. A batch gives one PSNR of the pooled
        MSE, not the mean of per-image PSNRs.

    Raises:
        ValueError: The shapes differ.

    Example::

        >>> round(psnr(torch.zeros(8, 8, 3), torch.full((8, 8, 3), 0.1)), 6)  # MSE 0.01
        20.0
        >>> round(psnr(np.zeros((8, 8, 3), np.uint8), np.full((8, 8, 3), 51, np.uint8)), 6)  # over 0..255
        13.9794
    """
    p = _tensor(pred)
    a = _float64(p)
    b = _float64(_tensor(target), a.device)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return psnr_from_mse(float((a - b).square().mean()), _default_range(p, data_range))


def psnr_masked(pred, target, mask, data_range: float | None = None) -> float | None:
    """PSNR in dB (capped) over the pixels inside ``mask`` only: the evaluation's ``psnr_head``.

    Args:
        pred: ``[..., H, W, C]`` tensor or array: the rendered image(s).
        target: The same shape as ``pred``: the reference image(s).
        mask: ``[..., H, W]``: a pixel counts (all of its C channels) where ``mask > HEAD_THRESHOLD`` (0.5), so a
            boolean mask or a soft [0, 1] matte both work.
        data_range: The largest possible pixel value; None: from ``pred``'s dtype, as for :func:`psnr`.

    Returns:
        The PSNR of the MSE over the masked pixels, or None when the mask selects no pixel.

    Raises:
        ValueError: The shapes do not match.

    Example::

        >>> mask = torch.zeros(10, 10); mask[:2] = 1  # 20 pixels
        >>> gt = torch.zeros(10, 10, 3); pred = gt.clone(); pred[:2] = 0.1; pred[2:] = 0.5
        >>> round(psnr_masked(pred, gt, mask), 6)  # the error outside the mask does not count
        20.0
    """
    p = _tensor(pred)
    a = _float64(p)
    b, m = _float64(_tensor(target), a.device), _float64(_tensor(mask), a.device)
    if a.shape != b.shape or a.shape[:-1] != m.shape:
        raise ValueError(f"shapes differ: {tuple(a.shape)}, {tuple(b.shape)} and mask {tuple(m.shape)}")
    inside = m > HEAD_THRESHOLD
    if not bool(inside.any()):
        return None
    return psnr_from_mse(float((a - b)[inside].square().mean()), _default_range(p, data_range))


# ------------------------------------------------------------------------------------------------------- SSIM
@functools.cache
def _gaussian_window(size: int, sigma: float) -> Tensor:
    """The normalised 1-D Gaussian ``[size]`` (float64, CPU) of the separable SSIM window."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def ssim(pred, target, *, data_range: float | None = None, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA,
         padding: Literal["valid", "same"] = "valid", reduction: Literal["mean", "none"] = "mean") -> Tensor:
    """Structural similarity (Wang et al. 2004) with a Gaussian window, per channel, differentiable.

    For each channel and window position: ``((2 mu_x mu_y + C1) (2 s_xy + C2)) / ((mu_x^2 + mu_y^2 + C1)
    (s_xx + s_yy + C2))``, where the means and (biased) variances are Gaussian-weighted over the window
    (``window`` x ``window``, standard deviation ``sigma``, applied separably, horizontal then vertical),
    ``C1 = (0.01 data_range)^2`` and ``C2 = (0.03 data_range)^2``. The map is then averaged over positions and
    channels.

    Args:
        pred: ``[B, H, W, C]`` batch, ``[H, W, C]`` image or ``[H, W]`` greyscale image (tensor or array).
            A tensor keeps its dtype, device and autograd graph.
        target: The same shape as ``pred``; converted to ``pred``'s dtype and device.
        data_range: The largest possible pixel value; None: 1 for floating-point images, the dtype's maximum for
            integer ones (255 for uint8; they are scored in float64).
        window: Side of the Gaussian window in pixels (11). With ``padding="valid"`` it shrinks to the smaller
            image side when an image is smaller than that; with ``"same"`` it must be odd.
        sigma: Standard deviation of the window in pixels (1.5).
        padding: ``"valid"``: only window positions entirely inside the image (the evaluation's convention).
            ``"same"``: zero padding by ``window // 2`` so every pixel has a value (the training loss's
            convention, as in 3DGS). The two SSIM maps differ only within ``window // 2`` pixels of a border.
        reduction: ``"mean"``: one scalar ``[]`` over the batch, channels and positions. ``"none"``: one value per
            image, ``[B]`` for a batch (``[]`` for a single image).

    Returns:
        The SSIM, in [-1, 1] (1 for identical images), as a tensor of ``pred``'s dtype.

    Raises:
        ValueError: Shapes differ or are not 2-, 3- or 4-D, or an unknown ``padding`` / ``reduction``, or an even
            ``window`` with ``"same"`` padding.

    Example::

        >>> a, b = torch.rand(4, 32, 32, 3), torch.rand(4, 32, 32, 3, requires_grad=True)
        >>> loss = 1 - ssim(a, b, padding="same")  # the training D-SSIM term
        >>> loss.backward()
        >>> ssim(a.double(), b.detach().double(), reduction="none").shape  # evaluation: one value per frame
        torch.Size([4])
    """
    if padding not in ("valid", "same"):
        raise ValueError(f"padding must be 'valid' or 'same', got {padding!r}")
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    x = _tensor(pred)
    data_range = _default_range(x, data_range)
    if not x.is_floating_point():
        x = x.to(torch.float64)
    y = _tensor(target).to(device=x.device, dtype=x.dtype)
    if x.shape != y.shape or x.dim() not in (2, 3, 4):
        raise ValueError(f"expected two [B, H, W, C], [H, W, C] or [H, W] images of one shape, got "
                         f"{tuple(x.shape)} and {tuple(y.shape)}")
    single = x.dim() < 4
    if x.dim() == 2:
        x, y = x[..., None], y[..., None]
    if single:
        x, y = x[None], y[None]
    _, h, w, c = x.shape
    x, y = x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2)  # [B, C, H, W]
    if padding == "same":
        if window % 2 == 0:
            raise ValueError(f"'same' padding needs an odd window, got {window}")
        size, pad = window, window // 2
    else:
        size, pad = min(window, h, w), 0
    g = _gaussian_window(size, sigma).to(device=x.device, dtype=x.dtype)
    gh = g.reshape(1, 1, 1, size).expand(5 * c, 1, 1, size).contiguous()
    gv = g.reshape(1, 1, size, 1).expand(5 * c, 1, size, 1).contiguous()

    # One pass over the five maps x, y, x^2, y^2, xy, stacked on the channels.
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    blurred = F.conv2d(F.conv2d(stack, gh, padding=(0, pad), groups=5 * c), gv, padding=(pad, 0), groups=5 * c)
    mu_x, mu_y, xx, yy, xy = blurred.split(c, dim=1)
    sxx, syy, sxy = xx - mu_x * mu_x, yy - mu_y * mu_y, xy - mu_x * mu_y
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2))
    if reduction == "mean":
        return s.mean()
    per_image = s.mean(dim=(1, 2, 3))
    return per_image[0] if single else per_image
