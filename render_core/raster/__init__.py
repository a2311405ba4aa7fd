"""Rasterizer backends behind one entry point, :func:`render`.

Every backend implements docs/method.md section 9 with the same signature and semantics: ``reference`` (pure torch,
differentiable; the oracle the others are tested against), ``native`` (the C++ CPU backend, the default when
it is built) and ``cuda`` (gsplat 1.5.x's CUDA kernels, differentiable; registered where torch sees a CUDA device
and gsplat is installed). Asking for a backend that is not available here is an error that says why.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..camera import Cameras
from ..deform import Splats, shade
from ..errors import ShapeError
from . import gsplat_backend, native, reference
from .reference import RasterOutput

__all__ = ["BACKENDS", "KNOWN_BACKENDS", "RasterOutput", "render", "backend_names", "default_backend",
           "check_backend", "unavailable_reason"]

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


def _cuda_backend(splats: Splats, cameras: Cameras, background: Tensor | None, mode: str) -> RasterOutput:
    """Shade and splat on the GPU (CPU inputs are moved there and the outputs moved back)."""
    home = splats.means.device
    gpu = home if home.type == "cuda" else gsplat_backend.device()
    splats, cameras = splats.to(device=gpu), cameras.to(device=gpu)
    colors = shade(splats, cameras.centres.to(splats.means.dtype))
    out = gsplat_backend.rasterize(splats.means, splats.quats, splats.scales, splats.opacities, colors, cameras,
                                   background, mode)
    return gsplat_backend.moved(out, home)


KNOWN_BACKENDS: tuple[str, ...] = ("cuda", "native", "reference")
BACKENDS: dict[str, Backend] = {"reference": _reference_backend}
if native.available():
    BACKENDS["native"] = _native_backend
if gsplat_backend.available():
    BACKENDS["cuda"] = _cuda_backend


def backend_names() -> list[str]:
    return sorted(BACKENDS)


def default_backend() -> str:
    """``native`` where it is built, else ``reference``."""
    return "native" if "native" in BACKENDS else "reference"


def unavailable_reason(name: str) -> str | None:
    """Why a known backend is not available here (None when it is, or for an unknown name)."""
    if name in BACKENDS or name not in KNOWN_BACKENDS:
        return None
    if name == "cuda":
        return gsplat_backend.unavailable_reason() or "not registered"
    return f"the native extension is not built ({native.IMPORT_ERROR})"


def check_backend(name: str | None) -> str:
    """The backend to use for ``name`` (None: the default); ValueError naming the available ones, and for a known
    backend that cannot run here, why (no CUDA device, gsplat not installed, native extension not built)."""
    name = name or default_backend()
    if name not in BACKENDS:
        available = ", ".join(backend_names())
        if name in KNOWN_BACKENDS:
            raise ValueError(f"backend {name!r} is unavailable here: {unavailable_reason(name)}; available: "
                             f"{available}")
        raise ValueError(f"unknown backend {name!r}; available: {available}")
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
    depth [B, H, W], on the device of the splats. The reference and cuda backends are differentiable (for a native
    forward and backward of posed Gaussians, see :func:`render_core.raster.native.rasterize_differentiable`).

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
