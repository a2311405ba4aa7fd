"""Rasterizer backends behind one entry point, :func:`render`.

Every backend implements METHOD.md section 9 with the same signature and semantics: ``reference`` (pure torch,
differentiable; the oracle the others are tested against) and ``native`` (the C++ CPU backend, the default when
it is built).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..camera import Cameras
from ..deform import Splats, shade
from ..errors import ShapeError
from . import native, reference
from .reference import RasterOutput

__all__ = ["BACKENDS", "RasterOutput", "render", "backend_names", "default_backend"]

Backend = Callable[[Splats, Cameras, Tensor | None, str], RasterOutput]


def _reference_backend(splats: Splats, cameras: Cameras, background: Tensor | None, mode: str) -> RasterOutput:
    colors = shade(splats, cameras.centres.to(splats.means.dtype))
    return reference.rasterize(splats.means, splats.quats, splats.scales, splats.opacities, colors, cameras,
                               background, mode)


def _native_backend(splats: Splats, cameras: Cameras, background: Tensor | None, mode: str) -> RasterOutput:
    colors = shade(splats, cameras.centres.to(splats.means.dtype))
    rgb, alpha, depth, timings = native.rasterize(splats.means, splats.quats, splats.scales, splats.opacities,
                                                  colors, cameras, background, mode)
    return RasterOutput(rgb, alpha, depth, timings=timings)


BACKENDS: dict[str, Backend] = {"reference": _reference_backend}
if native.available():
    BACKENDS["native"] = _native_backend


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def default_backend() -> str:
    """``native`` where it is built, else ``reference``."""
    return "native" if "native" in BACKENDS else "reference"


def check_backend(name: str | None) -> str:
    """The backend to use for ``name`` (None: the default); ValueError naming the available ones."""
    name = name or default_backend()
    if name not in BACKENDS:
        raise ValueError(f"unknown or unavailable backend {name!r}; available: {', '.join(backend_names())}")
    return name


def render(
    splats: Splats,  # B (or 1) deformed Gaussian sets
    cameras: Cameras,  # B (or 1) cameras
    *,
    backend: str | None = None,
    background: Tensor | None = None,  # [3] or [B, 3], default black
    mode: str = "classic",
) -> RasterOutput:
    """Render deformed Gaussians (see :func:`render_core.deform.deform`) from B cameras.

    One set of splats may be seen by B cameras, or B sets by one camera (broadcast), or B by B pairwise.
    ``mode`` is the bundle's raster mode ("classic" or "antialiased"); ``backend`` None picks
    :func:`default_backend`. Returns RGB [B, H, W, 3] over the background, alpha [B, H, W] and alpha-composited
    depth [B, H, W]. Only the reference backend is differentiable here (for a native forward and backward of
    posed Gaussians, see :func:`render_core.raster.native.rasterize_differentiable`).

    Example::

        splats = deform(avatar, Frame.neutral(avatar))
        out = render(splats, front_camera(512, 512), mode=avatar.raster_mode)
    """
    backend = check_backend(backend)
    bs, bc = splats.means.shape[0], len(cameras)
    if bs != bc:
        if bs == 1:
            splats = splats.expand(bc)
        elif bc == 1:
            cameras = cameras.expand(bs)
        else:
            raise ShapeError(f"{bs} splat sets cannot pair with {bc} cameras", field="cameras")
    if background is not None and not torch.isfinite(background).all():
        raise ShapeError("must be finite", field="background")
    return BACKENDS[backend](splats, cameras, background, mode)
