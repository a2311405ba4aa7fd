"""What every rasterizer backend takes (:class:`ShadedSplats`) and returns (:class:`RasterOutput`).

Each backend module (``reference``, ``native``, ``gsplat_backend``) has the same entry point::

    rasterize(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None, mode: str = "classic")
        -> RasterOutput

It splats B sets of N Gaussians, set b seen by camera b (``len(cameras) == B``), exactly as docs/method.md section 9
defines (gsplat 1.5.3's "classic" rasterization), or with the opacity compensation of section 9 step 7 when
``mode`` is "antialiased". ``background``: the [3] or [B, 3] colour behind the splats, default black. Cameras:
pinhole, world-to-camera ``R``, ``t`` (OpenCV: x right, y down, z forward; ``x_c = R x + t``), ``K`` in pixels,
pixel centres at +0.5. ``rasterize_differentiable`` (native and cuda) takes the same arguments and returns
``(rgb, alpha)`` with gradients for every tensor of the splats and the background.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..camera import Cameras
from ..deform import Splats, shade


@dataclass
class ShadedSplats:
    """Posed Gaussians whose colours are evaluated for the camera that sees them: the input of every backend.

    :func:`render_core.deform.deform` gives :class:`~render_core.deform.Splats` (SH colour, for any view);
    :meth:`from_splats` shades them for B cameras (docs/method.md section 9 step 6).
    """

    means: Tensor  # [B, N, 3] world-space centres
    quats: Tensor  # [B, N, 4] orientations, w first (gsplat's convention); normalised by the backends
    scales: Tensor  # [B, N, 3] standard deviations along the Gaussian's axes (linear, not log)
    opacities: Tensor  # [B, N] in [0, 1] (not logits)
    colors: Tensor  # [B, N, 3] RGB as camera b sees it (evaluated beforehand: no SH here)

    @classmethod
    def from_splats(cls, splats: Splats, cameras: Cameras) -> ShadedSplats:
        """``splats`` (one set per camera) with their view-dependent colours for ``cameras``."""
        return cls(splats.means, splats.quats, splats.scales, splats.opacities, shade(splats, cameras.centres))

    def tensors(self) -> dict[str, Tensor]:
        """The five tensors by field name (gsplat's argument names), in field order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> ShadedSplats:
        """A copy with the tensors cast to ``dtype`` and moved to ``device`` (differentiably)."""
        return ShadedSplats(*(t.to(device=device, dtype=dtype) for t in self.tensors().values()))


@dataclass
class RasterOutput:
    """What a rasterizer returns for B cameras."""

    rgb: Tensor  # [B, H, W, 3] colour composited over the background
    alpha: Tensor  # [B, H, W] accumulated opacity, 1 - final transmittance
    depth: Tensor  # [B, H, W] alpha-composited camera depth (divide by alpha for the expected depth)
    means2d: Tensor | None = None  # [B, N, 2] projected centres (for densification statistics)
    radii: Tensor | None = None  # [B, N, 2] int32, 0 where culled
    timings: dict | None = None  # per-stage milliseconds (blend, lbs, raster) where the backend measures them
