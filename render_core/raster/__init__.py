"""Rasterizer backends behind one entry point, :func:`render`.

Every backend implements docs/method.md section 9 with the same signature and semantics
(:mod:`render_core.raster.splats`: it takes :class:`ShadedSplats` and returns a :class:`RasterOutput`):
``reference`` (pure torch, differentiable; the oracle the others are tested against), ``native`` (the C++ CPU
backend, the default when it is built) and ``cuda`` (gsplat 1.5.x's CUDA kernels, differentiable; registered where
torch sees a CUDA device and gsplat is installed). Asking for a backend that is not available here is an error that
says why.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ..camera import Cameras
from ..deform import Splats
from ..errors import OptionError, ShapeError
from . import gsplat_backend, native, reference
from .splats import RasterOutput, ShadedSplats

__all__ = ["BACKENDS", "KNOWN_BACKENDS", "RasterOutput", "ShadedSplats", "render", "backend_names", "default_backend",
           "check_backend", "unavailable_reason", "DIFFERENTIABLE", "differentiable"]

Backend = Callable[[ShadedSplats, Cameras, Tensor | None, str], RasterOutput]

KNOWN_BACKENDS: tuple[str, ...] = ("cuda", "native", "reference")
BACKENDS: dict[str, Backend] = {"reference": reference.rasterize}
if native.available():
    BACKENDS["native"] = native.rasterize
if gsplat_backend.available():
    BACKENDS["cuda"] = gsplat_backend.rasterize


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
    """The backend to use for ``name`` (None: the default); OptionError naming the available ones, and for a known
    backend that cannot run here, why (no CUDA device, gsplat not installed, native extension not built)."""
    name = name or default_backend()
    if name not in BACKENDS:
        available = ", ".join(backend_names())
        if name in KNOWN_BACKENDS:
            raise OptionError(f"{name!r} is unavailable here: {unavailable_reason(name)}; available: {available}",
                              field="backend")
        raise OptionError(f"unknown backend {name!r}; available: {available}", field="backend")
    return name


# The differentiable rasterization step of training, per backend: rgb [B, H, W, 3] and alpha [B, H, W] on the
# background, differentiable w.r.t. the posed splats and their colours (``threads``: the CPU's, where it applies).
Differentiable = Callable[..., tuple[Tensor, Tensor]]


def _native_differentiable(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
                           mode: str = "classic", *, threads: int = 0) -> tuple[Tensor, Tensor]:
    return native.rasterize_differentiable(splats, cameras, background, mode, threads=threads)


def _cuda_differentiable(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
                         mode: str = "classic", *, threads: int = 0) -> tuple[Tensor, Tensor]:
    return gsplat_backend.rasterize_differentiable(splats, cameras, background, mode)


DIFFERENTIABLE: dict[str, Differentiable] = {"native": _native_differentiable, "cuda": _cuda_differentiable}


def differentiable(name: str) -> Differentiable:
    """The differentiable rasterization step of backend ``name`` (for training); the errors of
    :func:`check_backend` where it cannot run here, an OptionError for a backend without one."""
    name = check_backend(name)
    if name not in DIFFERENTIABLE:
        raise OptionError(f"{name!r} has no differentiable step for training; those that have: "
                          f"{', '.join(sorted(DIFFERENTIABLE))}", field="backend")
    return DIFFERENTIABLE[name]


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
    home = splats.means.device
    if backend == "cuda":  # shading runs on the GPU too; the outputs come back to the splats' device
        gpu = home if home.type == "cuda" else gsplat_backend.device()
        splats, cameras = splats.to(device=gpu), cameras.to(device=gpu)
    out = BACKENDS[backend](ShadedSplats.from_splats(splats, cameras), cameras, background, mode)
    return gsplat_backend.moved(out, home)
