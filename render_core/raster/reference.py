"""The pure-torch reference rasterizer: docs/method.md section 9 exactly (gsplat 1.5.3 "classic" semantics), and the
"antialiased" mode. Differentiable through autograd; the oracle every faster backend is tested against.

How it works: every (Gaussian, pixel) pair that section 9 evaluates (every pixel of every 16x16 tile that the
Gaussian's opacity-aware box overlaps) is enumerated, the eligibility rule (sigma >= 0, alpha >= 1/255) is applied
without autograd, the surviving pairs are sorted by (pixel, depth, Gaussian index), and each pixel is composited
front to back with a segmented cumulative product of (1 - alpha) computed in the log domain in float64. Pairs at
and after a pixel's transmittance stop (next T <= 1e-4) are dropped, then the kept pairs are evaluated again with
autograd so gradients flow to means, rotations, scales, opacities and colours.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..avatar import check_raster_mode
from ..camera import Cameras
from ..rotation import quat_to_matrix
from .splats import RasterOutput, ShadedSplats

TILE = 16
NEAR = 0.01
EPS2D = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
T_STOP = 1e-4
EXTENT_MAX = 3.33
# Pairs enumerated per chunk while testing eligibility (bounds the temporary memory to a few hundred MB).
PAIR_CHUNK = 1 << 23


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities for B cameras (docs/method.md section 9, steps 1-3)."""

    means2d: Tensor  # [B, N, 2] pixel coordinates (x right, y down)
    conics: Tensor  # [B, N, 3] inverse 2D covariance (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy
    depths: Tensor  # [B, N] camera z
    opacities: Tensor  # [B, N] opacity used for compositing (times the compensation in antialiased mode)
    radii: Tensor  # [B, N, 2] int32 box half-extents in pixels, 0 where culled
    visible: Tensor  # [B, N] bool


def project(
    means: Tensor,  # [B, N, 3]
    quats: Tensor,  # [B, N, 4] wxyz
    scales: Tensor,  # [B, N, 3]
    opacities: Tensor,  # [B, N]
    cameras: Cameras,  # B cameras
    mode: str = "classic",
) -> Projection:
    """Project 3D Gaussians to 2D: cull by depth (z < 0.01), EWA 2D covariance with the clamped Jacobian, 0.3 px
    blur (antialiased mode: opacity times sqrt(det / det_blurred)), opacity-aware extent and box culling."""
    dtype = means.dtype
    K, Rw, tw = cameras.K.to(dtype), cameras.R.to(dtype), cameras.t.to(dtype)
    W, H = cameras.width, cameras.height
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]

    p = torch.einsum("bij,bnj->bni", Rw, means) + tw[:, None]
    x, y, z = p.unbind(-1)
    in_front = z >= NEAR
    zs = torch.where(in_front, z, torch.ones_like(z))  # keep culled entries finite (no inf/nan in gradients)

    # Jacobian of the perspective projection at the clamped view-space position.
    lim_x_pos = (W - cx) / fx + 0.3 * (0.5 * W / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * W / fx)
    lim_y_pos = (H - cy) / fy + 0.3 * (0.5 * H / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * H / fy)
    tx = zs * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x / zs))
    ty = zs * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y / zs))
    zero = torch.zeros_like(zs)
    J = torch.stack(
        [fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2], dim=-1
    ).reshape(*zs.shape, 2, 3)

    M = quat_to_matrix(quats) * scales[..., None, :]
    cov_cam = Rw[:, None] @ (M @ M.transpose(-1, -2)) @ Rw[:, None].transpose(-1, -2)
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    c00, c01, c11 = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det_raw = c00 * c11 - c01 * c01
    c00, c11 = c00 + EPS2D, c11 + EPS2D
    det = c00 * c11 - c01 * c01
    ok = in_front & (det > 0)
    det_s = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_s, -c01 / det_s, c00 / det_s], dim=-1)

    check_raster_mode(mode)
    opac = opacities
    if mode == "antialiased":
        opac = opac * torch.sqrt(torch.clamp(det_raw / det_s, min=0.0))
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    with torch.no_grad():
        ok = ok & (opac >= ALPHA_MIN)
        extent = torch.clamp(torch.sqrt(2.0 * torch.log(opac.clamp_min(ALPHA_MIN) / ALPHA_MIN)), max=EXTENT_MAX)
        rx = torch.ceil(extent * torch.sqrt(c00.clamp_min(0)))
        ry = torch.ceil(extent * torch.sqrt(c11.clamp_min(0)))
        mx, my = means2d.unbind(-1)
        ok = ok & (rx > 0) & (ry > 0)
        ok = ok & ~((mx + rx <= 0) | (mx - rx >= W) | (my + ry <= 0) | (my - ry >= H))
        ok = ok & torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        radii = torch.where(ok[..., None], torch.stack([rx, ry], -1), 0).to(torch.int32)
    return Projection(means2d, conics, torch.where(in_front, z, zero), opac, radii, ok)


def _pixel_rects(proj: Projection, width: int, height: int) -> Tensor:
    """[V, 4] half-open pixel rectangles (x0, y0, x1, y1) to evaluate for each visible Gaussian.

    Section 9 evaluates every pixel of every 16x16 tile the box (mean +- radius) overlaps, but a pixel can only
    pass the eligibility rule inside an ellipse: alpha >= 1/255 means 0.5 d^T S^-1 d <= ln(255 o), whose bounding
    box is mean +- sqrt(2 ln(255 o) diag S). So only the pixels of the tile rectangle whose centres lie in that
    box (grown by 0.01 px for rounding) are tested - the same image, with several times fewer pairs.
    """
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    vis = proj.visible
    m = proj.means2d.detach()[vis]
    r = proj.radii[vis].to(m.dtype)
    t0 = torch.floor((m - r) / TILE)
    t1 = torch.ceil((m + r) / TILE)
    lim = torch.tensor([tiles_x, tiles_y], dtype=m.dtype)
    t0 = torch.minimum(t0.clamp_min(0), lim).long() * TILE
    t1 = torch.minimum(torch.minimum(t1.clamp_min(0), lim).long() * TILE, torch.tensor([width, height]))
    conic = proj.conics.detach()[vis]
    det = conic[:, 0] * conic[:, 2] - conic[:, 1] ** 2  # S = inverse(conic): S_xx = c / det, S_yy = a / det
    level = 2.0 * torch.log(proj.opacities.detach()[vis] / ALPHA_MIN).clamp_min(0)
    half = torch.sqrt(level[:, None] * torch.stack([conic[:, 2], conic[:, 0]], -1) / det[:, None]) + 0.01
    b0 = torch.ceil(m - half - 0.5).long()  # pixels p with |p + 0.5 - mean| <= half
    b1 = torch.floor(m + half - 0.5).long() + 1
    x0 = torch.maximum(t0, b0)
    return torch.cat([x0, torch.maximum(torch.minimum(t1, b1), x0)], -1)


def _alpha(means2d: Tensor, conics: Tensor, opac: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
    """sigma and clamped alpha of Gaussians (rows of the arguments) at pixel centres (px + 0.5, py + 0.5)."""
    dx = means2d[..., 0] - (px.to(means2d.dtype) + 0.5)
    dy = means2d[..., 1] - (py.to(means2d.dtype) + 0.5)
    a, b, c = conics.unbind(-1)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    return sigma, torch.clamp(opac * torch.exp(-sigma), max=ALPHA_MAX)


def _eligible_pairs(proj: Projection, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """(flat Gaussian index b * N + n, flat pixel index b * H * W + y * W + x, alpha) of every evaluated pair that
    passes the eligibility rule (sigma >= 0 and alpha >= 1/255); no autograd."""
    B, N = proj.visible.shape
    flat = torch.nonzero(proj.visible.reshape(-1)).squeeze(1)
    rects = _pixel_rects(proj, width, height)
    wx, wy = rects[:, 2] - rects[:, 0], rects[:, 3] - rects[:, 1]
    counts = wx * wy
    # One row per visible Gaussian: what the pair loop gathers (one gather per chunk instead of several).
    geom = torch.stack([rects[:, 0], rects[:, 1], wx, (flat // N) * (height * width)], -1)
    params = torch.cat([proj.means2d.detach().reshape(B * N, 2)[flat], proj.conics.detach().reshape(B * N, 3)[flat],
                        proj.opacities.detach().reshape(B * N, 1)[flat]], -1)
    gids, pids, alphas = [], [], []
    ends = torch.cumsum(counts, 0)
    start = 0
    while start < len(flat):
        # Largest run of Gaussians whose pairs fit one chunk (always at least one Gaussian).
        base = int(ends[start - 1]) if start else 0
        stop = max(int(torch.searchsorted(ends, base + PAIR_CHUNK, right=True)), start + 1)
        c = counts[start:stop]
        local = torch.repeat_interleave(torch.arange(start, stop), c)
        k = torch.arange(base, int(ends[stop - 1])) - (ends[local] - counts[local])
        x0, y0, w, img = geom[local].unbind(-1)
        dy = torch.div(k, w, rounding_mode="floor")
        px, py = x0 + (k - dy * w), y0 + dy
        p = params[local]
        sigma, alpha = _alpha(p[:, 0:2], p[:, 2:5], p[:, 5], px, py)
        keep = (sigma >= 0) & (alpha >= ALPHA_MIN)
        gids.append(flat[local[keep]])
        pids.append((img + py * width + px)[keep])
        alphas.append(alpha[keep])
        start = stop
    if not gids:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty, torch.zeros(0, dtype=params.dtype)
    return torch.cat(gids), torch.cat(pids), torch.cat(alphas)


def _segment_exclusive_log_cumsum(values: Tensor, segment_start: Tensor) -> Tensor:
    """Exclusive cumulative sum of ``values`` within consecutive segments (``segment_start`` marks firsts)."""
    incl = torch.cumsum(values, 0)
    excl = incl - values
    seg = torch.cumsum(segment_start.long(), 0) - 1
    return excl - excl[segment_start][seg]


def rasterize(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
              mode: str = "classic") -> RasterOutput:
    """Splat ``splats`` for ``cameras`` as every backend does (:mod:`render_core.raster.splats`), differentiable
    through autograd with respect to the splats' tensors and the background."""
    B, N = splats.means.shape[:2]
    W, H = cameras.width, cameras.height
    dtype = splats.means.dtype
    proj = project(splats.means, splats.quats, splats.scales, splats.opacities, cameras, mode)
    with torch.no_grad():
        gid, pid, alpha = _eligible_pairs(proj, W, H)
        # Order by (pixel, depth, Gaussian index): rank Gaussians by (depth, index), then sort the pair keys.
        rank = torch.empty(B * N, dtype=torch.long)
        rank[torch.sort(proj.depths.detach().reshape(-1), stable=True).indices] = torch.arange(B * N)
        order = torch.argsort(pid * (B * N) + rank[gid])
        gid, pid, alpha = gid[order], pid[order], alpha[order]
        first = torch.ones_like(pid, dtype=torch.bool)
        first[1:] = pid[1:] != pid[:-1]
        log_t = torch.log1p(-alpha.double())
        log_t_before = _segment_exclusive_log_cumsum(log_t, first)
        # Keep pairs until the transmittance stop; a prefix of every pixel's list (T only decreases), so the
        # kept pairs' transmittances are unchanged by dropping the rest.
        keep = torch.exp(log_t_before + log_t) > T_STOP
        gid, pid, first, alpha, log_t_before = gid[keep], pid[keep], first[keep], alpha[keep], log_t_before[keep]

    if torch.is_grad_enabled() and any(t.requires_grad for t in splats.tensors().values()):
        # Differentiable composite of the kept pairs: alpha and T again, with autograd.
        _, alpha = _alpha(proj.means2d.reshape(-1, 2)[gid], proj.conics.reshape(-1, 3)[gid],
                          proj.opacities.reshape(-1)[gid], pid % W, (pid // W) % H)
        log_t_before = _segment_exclusive_log_cumsum(torch.log1p(-alpha.double()), first)
    w = alpha * torch.exp(log_t_before).to(dtype)
    num_pix = B * H * W
    acc_a = torch.zeros(num_pix, dtype=dtype).index_add(0, pid, w)
    acc_c = torch.zeros(num_pix, 3, dtype=dtype).index_add(0, pid, w[:, None] * splats.colors.reshape(-1, 3)[gid])
    acc_d = torch.zeros(num_pix, dtype=dtype).index_add(0, pid, w * proj.depths.reshape(-1)[gid])
    if background is None:
        background = torch.zeros(3, dtype=dtype)
    bg = background.to(dtype).reshape(-1, 1, 3).expand(B, 1, 3)
    acc_c = acc_c.reshape(B, H * W, 3) + (1.0 - acc_a.reshape(B, H * W, 1)) * bg
    return RasterOutput(
        rgb=acc_c.reshape(B, H, W, 3),
        alpha=acc_a.reshape(B, H, W),
        depth=acc_d.reshape(B, H, W),
        means2d=proj.means2d,
        radii=proj.radii,
    )
