"""The CUDA backend: gsplat 1.5.x's rasterization kernels (forward and backward) behind ``render()``.

docs/method.md section 9 *is* gsplat 1.5.3's "classic" rasterization (and its "antialiased" mode), so this backend only
translates conventions; it adds no splatting code of its own. Two pieces:

- :func:`gsplat_arguments` turns our :class:`~render_core.raster.splats.ShadedSplats` and
  :class:`~render_core.camera.Cameras` into the keyword arguments of ``gsplat.rasterization`` and
  :func:`from_gsplat` turns its outputs into a :class:`RasterOutput`. Both are plain torch and device-agnostic:
  the CUDA path uses them, and the tests run the very same conversion through gsplat's ``rasterization`` on the
  CPU (its projection and tile binning replaced by gsplat's pure-torch twins) against the reference rasterizer,
  so the conventions are checked on machines without a GPU too.
- :func:`rasterize` / :func:`rasterize_differentiable`: the CUDA path (gsplat's autograd gives the backward).

Conventions carried over (see :mod:`render_core.raster.splats`): world-to-camera ``[R | t]`` as 4x4 ``viewmats``,
K in pixels, colours evaluated beforehand (``sh_degree`` None), near plane 0.01, 0.3 px blur, 16 px tiles, unpacked
layout, and ``render_mode="RGB+D"`` whose fourth channel is the alpha-composited camera depth (its background is
0). B splat sets meet B cameras as gsplat's batch dimension with one camera each (``viewmats [B, 1, 4, 4]``).

Availability: the backend is registered when torch sees a CUDA device and gsplat 1.5.x imports
(``pip install --no-deps 'gsplat>=1.5,<1.6'``; its wheel is pure Python and compiles its CUDA sources with the
local nvcc on first use, which takes minutes once and is cached under ``~/.cache/torch_extensions``). Without
them everything still imports; :func:`unavailable_reason` says why the backend is missing.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from ..avatar import check_raster_mode
from ..camera import Cameras
from .reference import EPS2D, NEAR, TILE
from .splats import RasterOutput, ShadedSplats

GSPLAT_SPEC = "gsplat>=1.5,<1.6"
FAR = 1e10  # gsplat's default far plane (docs/method.md has none)
PACKED = False  # [B, 1, N, ...] outputs: no nnz compaction (most of a head's Gaussians are visible)


@functools.cache
def unavailable_reason() -> str | None:
    """Why the CUDA backend cannot run here (None when it can): no CUDA device, or gsplat missing / not 1.5.x."""
    if not torch.cuda.is_available():
        built = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        return f"no CUDA device (torch.cuda.is_available() is False; torch {torch.__version__} is {built})"
    try:
        import gsplat
    except ImportError as e:
        return f"gsplat is not installed ({e}); install it with pip install --no-deps '{GSPLAT_SPEC}'"
    version = getattr(gsplat, "__version__", "?")
    if not version.startswith("1.5."):
        return f"gsplat {version} is installed but the backend needs {GSPLAT_SPEC}"
    return None


def available() -> bool:
    return unavailable_reason() is None


def device() -> torch.device:
    """Where the backend computes (the current CUDA device)."""
    return torch.device("cuda")


def device_name() -> str:
    """The GPU's name, for reports."""
    return torch.cuda.get_device_name(device())


def require() -> None:
    """RuntimeError naming why the CUDA backend is unavailable (no-op when it is available)."""
    reason = unavailable_reason()
    if reason is not None:
        raise RuntimeError(f"the cuda backend is unavailable: {reason}")


@functools.cache
def _rasterization():
    """gsplat.rasterization, after checking that gsplat's CUDA extension built (the first call compiles it)."""
    require()
    from gsplat.cuda._backend import _C

    if _C is None:
        raise RuntimeError("gsplat imported but its CUDA extension did not build: gsplat found no CUDA toolkit "
                           "(nvcc on PATH or CUDA_HOME) to compile it with; see docs/cuda-gpu-runbook.md")
    from gsplat import rasterization

    return rasterization


def build_extension() -> None:
    """Compile (first time, minutes) or load gsplat's CUDA extension now instead of at the first frame."""
    _rasterization()


def viewmats(cameras: Cameras, device: torch.device | str | None = None) -> Tensor:
    """[B, 4, 4] float32 world-to-camera matrices [[R, t], [0, 0, 0, 1]] (gsplat's ``viewmats``)."""
    device = cameras.R.device if device is None else device
    out = torch.zeros(len(cameras), 4, 4, device=device)
    out[:, :3, :3] = cameras.R
    out[:, :3, 3] = cameras.t
    out[:, 3, 3] = 1.0
    return out


def gsplat_arguments(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
                     mode: str = "classic", *, device: torch.device | str | None = None) -> dict:
    """Keyword arguments of ``gsplat.rasterization`` that render docs/method.md section 9 as
    :func:`render_core.raster.reference.rasterize` does (float32, on ``device``, default: that of the splats).

    gsplat's batch dimension carries the B splat sets, each seen by its one camera; colours are already
    evaluated (``sh_degree=None``); ``render_mode="RGB+D"`` appends the alpha-composited depth as a fourth
    channel. Differentiable with respect to every tensor argument (the casts and reshapes are autograd ops).

    Example::

        colors, alphas, meta = gsplat.rasterization(**gsplat_arguments(splats, cams, mode="classic"))
        out = from_gsplat(colors, alphas, meta)
    """
    check_raster_mode(mode)
    B, N = splats.means.shape[:2]
    want = {"means": (B, N, 3), "quats": (B, N, 4), "scales": (B, N, 3), "opacities": (B, N), "colors": (B, N, 3)}
    for name, t in splats.tensors().items():
        assert t.shape == want[name], (name, t.shape)
    assert len(cameras) == B, (len(cameras), B)
    device = splats.means.device if device is None else torch.device(device)

    def f32(t: Tensor) -> Tensor:
        return t.to(device=device, dtype=torch.float32)

    if background is None:
        bg = torch.zeros(B, 1, 3, device=device)
    else:
        bg = f32(background).reshape(-1, 1, 3).expand(B, 1, 3)
    return dict(
        **splats.to(torch.float32, device).tensors(),
        viewmats=viewmats(cameras, device)[:, None], Ks=f32(cameras.K)[:, None],
        width=cameras.width, height=cameras.height, near_plane=NEAR, far_plane=FAR, radius_clip=0.0, eps2d=EPS2D,
        sh_degree=None, packed=PACKED, tile_size=TILE, backgrounds=bg, render_mode="RGB+D", rasterize_mode=mode,
        camera_model="pinhole",
    )


def from_gsplat(
    colors: Tensor,  # [B, 1, H, W, 4]: RGB over the background, then the alpha-composited depth
    alphas: Tensor,  # [B, 1, H, W, 1]
    meta: dict,
) -> RasterOutput:
    """gsplat.rasterization's outputs for :func:`gsplat_arguments` as our RasterOutput ([B, H, W, ...])."""
    out = RasterOutput(rgb=colors[:, 0, ..., :3], alpha=alphas[:, 0, ..., 0], depth=colors[:, 0, ..., 3])
    if meta.get("means2d") is not None:
        out.means2d = meta["means2d"][:, 0]  # zeros where culled (the reference keeps the projection)
        out.radii = meta["radii"][:, 0]
    return out


def moved(out: RasterOutput, device: torch.device) -> RasterOutput:
    """``out`` with its tensors on ``device`` (differentiably; the same object when already there)."""
    if out.rgb.device == device:
        return out
    return RasterOutput(out.rgb.to(device), out.alpha.to(device), out.depth.to(device),
                        None if out.means2d is None else out.means2d.to(device),
                        None if out.radii is None else out.radii.to(device), out.timings)


def rasterize(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
              mode: str = "classic") -> RasterOutput:
    """Splat ``splats`` for ``cameras`` as every backend does (:mod:`render_core.raster.splats`) with gsplat's CUDA
    kernels, in float32 whatever the input dtypes; differentiable (gsplat's backward) with respect to the splats'
    tensors and the background. Splats on the CPU are moved to the GPU and the outputs moved back; splats
    already on the GPU stay there."""
    rasterization = _rasterization()
    home = splats.means.device
    gpu = home if home.type == "cuda" else device()
    colors, alphas, meta = rasterization(**gsplat_arguments(splats, cameras, background, mode, device=gpu))
    return moved(from_gsplat(colors, alphas, meta), home)


def rasterize_differentiable(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
                             mode: str = "classic") -> tuple[Tensor, Tensor]:
    """rgb [B, H, W, 3] and alpha [B, H, W] of :func:`rasterize`: the CUDA twin of
    :func:`render_core.raster.native.rasterize_differentiable` (the same arguments less the CPU options)."""
    out = rasterize(splats, cameras, background, mode)
    return out.rgb, out.alpha
