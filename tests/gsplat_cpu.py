"""gsplat's ``rasterization`` on the CPU, for checking the cuda backend's conventions without a GPU.

``gsplat.rasterization`` (gsplat/rendering.py) is plain torch around four CUDA entry points. Here they are replaced:
projection and tile binning by gsplat's own pure-torch twins (``gsplat.cuda._torch_impl``), and the per-tile
compositing by :func:`rasterize_to_pixels` below, our own vectorised statement of what gsplat 1.5.3's forward
kernel computes (per tile, the Gaussians in bin order; sigma, alpha = min(0.999, o exp(-sigma)), skip sigma < 0
or alpha < 1/255, stop before the transmittance would fall to 1e-4; out = sum + T background). Everything else -
argument checks, the batch and camera dimensions, opacity compensation, the "RGB+D" depth channel and its zero
background, the output layout - is gsplat's own code, fed by our conversion (render_core.raster.gsplat_backend).

Differences from the CUDA kernels that cannot change an image: the torch projection bounds a splat by 3.33 sigma
instead of the opacity-aware extent and does not cull opacity < 1/255 (pixels outside the opacity-aware box have
alpha < 1/255 and are skipped either way).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

ALPHA_MIN = 1.0 / 255.0


def fully_fused_projection(means, covars, quats, scales, viewmats, Ks, width, height, eps2d=0.3, near_plane=0.01,
                           far_plane=1e10, radius_clip=0.0, packed=False, sparse_grad=False,
                           calc_compensations=False, camera_model="pinhole", opacities=None):
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    assert not packed and covars is None and radius_clip == 0.0
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    return _fully_fused_projection(means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane,
                                   calc_compensations, camera_model)


def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, sort=True, segmented=False,
                packed=False, n_images=None, image_ids=None, gaussian_ids=None):
    from gsplat.cuda._torch_impl import _isect_tiles

    assert not packed
    tiles_per_gauss, isect_ids, flatten_ids = _isect_tiles(means2d, radii, depths, tile_size, tile_width,
                                                           tile_height, sort=False)
    # The CUDA path sorts with a stable radix sort: equal depths keep the Gaussian order.
    isect_ids, order = torch.sort(isect_ids, stable=True)
    return tiles_per_gauss, isect_ids, flatten_ids[order]


def isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
    from gsplat.cuda._torch_impl import _isect_offset_encode

    return _isect_offset_encode(isect_ids, n_images, tile_width, tile_height)


def rasterize_to_pixels(means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor, image_width: int,
                        image_height: int, tile_size: int, isect_offsets: Tensor, flatten_ids: Tensor,
                        backgrounds: Tensor | None = None, masks=None, packed: bool = False, absgrad: bool = False):
    """gsplat's forward compositing kernel, per tile with torch ops (differentiable; float64 transmittance)."""
    assert not packed and masks is None
    image_dims = means2d.shape[:-2]
    n, ch = means2d.shape[-2], colors.shape[-1]
    images = math.prod(image_dims)
    tiles_h, tiles_w = isect_offsets.shape[-2:]
    m2 = means2d.reshape(images * n, 2)
    cn = conics.reshape(images * n, 3)
    col = colors.reshape(images * n, ch)
    op = opacities.reshape(images * n)
    offsets = isect_offsets.reshape(-1).tolist() + [len(flatten_ids)]
    out_c = torch.zeros(images, image_height, image_width, ch, dtype=colors.dtype)
    out_a = torch.zeros(images, image_height, image_width, dtype=colors.dtype)
    for tile in range(images * tiles_h * tiles_w):
        start, end = offsets[tile], offsets[tile + 1]
        if start == end:
            continue
        img, ty, tx = tile // (tiles_h * tiles_w), (tile // tiles_w) % tiles_h, tile % tiles_w
        ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, image_height))
        xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, image_width))
        if len(ys) == 0 or len(xs) == 0:
            continue
        py, px = torch.meshgrid(ys, xs, indexing="ij")
        pix = torch.stack([px.reshape(-1), py.reshape(-1)], -1).to(m2.dtype) + 0.5  # [P, 2]
        g = flatten_ids[start:end].long()  # bin order: depth, then Gaussian index
        d = m2[g][None] - pix[:, None]  # [P, G, 2]
        a, b, c = cn[g].unbind(-1)
        sigma = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
        alpha = torch.clamp(op[g] * torch.exp(-sigma), max=0.999)
        valid = (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
        t_incl = torch.cumprod(1.0 - alpha.double(), dim=1)  # T after each Gaussian
        t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], 1)
        keep = valid & (t_incl > 1e-4)  # T only falls: every Gaussian from the stopping one on is dropped
        w = torch.where(keep, alpha * t_excl.to(alpha.dtype), torch.zeros_like(alpha))
        out_c[img, py, px] = (w @ col[g]).reshape(len(ys), len(xs), ch)
        out_a[img, py, px] = w.sum(1).reshape(len(ys), len(xs))
    if backgrounds is not None:
        out_c = out_c + (1.0 - out_a[..., None]) * backgrounds.reshape(images, 1, 1, ch)
    return (out_c.reshape(*image_dims, image_height, image_width, ch),
            out_a.reshape(*image_dims, image_height, image_width, 1))


def patch_gsplat(monkeypatch) -> None:
    """Make ``gsplat.rasterization`` run on CPU tensors (for this test)."""
    import gsplat.rendering as rendering

    for fn in (fully_fused_projection, isect_tiles, isect_offset_encode, rasterize_to_pixels):
        monkeypatch.setattr(rendering, fn.__name__, fn)


def emulate_cuda_backend(monkeypatch) -> None:
    """Run the cuda backend on the CPU: gsplat patched as above, its device the CPU and ``cuda`` registered in
    ``render()``, so AvatarRenderer, bench and the trainer's CUDA step run their real code paths here."""
    import gsplat.rendering as rendering

    from render_core import raster
    from render_core.raster import gsplat_backend

    patch_gsplat(monkeypatch)
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: rendering.rasterization)
    monkeypatch.setattr(gsplat_backend, "device", lambda: torch.device("cpu"))
    monkeypatch.setattr(gsplat_backend, "device_name", lambda: "cpu (gsplat emulated)")
    monkeypatch.setattr(gsplat_backend, "available", lambda: True)
    monkeypatch.setitem(raster.BACKENDS, "cuda", gsplat_backend.rasterize)
