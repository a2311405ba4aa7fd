"""Closest surface points and per-blendshape displacement magnitudes (METHOD.md sections 3 and 4).

``d_{i,k}`` is the displacement magnitude, from M0 to M_k, of the neutral-mesh point closest to Gaussian i: the
barycentric interpolation, at that point, of the vertices' ``|expression_basis[k]|``. Computed per Gaussian
directly (no 256^3 grid): the closest point is searched among the triangles incident to the point's few nearest
vertices, which finds the true closest triangle for points on or near the surface (every Gaussian at
initialisation; densified children copy their parent's values instead of looking them up).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..facemodel import FaceModel


def _closest_on_segment(p: Tensor, a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Closest point of segments ab to p ([..., 3]) and its parameter t in [0, 1]."""
    ab = b - a
    t = ((p - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-30)
    t = t.clamp(0.0, 1.0)
    return a + t[..., None] * ab, t


def closest_points(vertices: Tensor, faces: Tensor, points: Tensor, *, neighbours: int = 16,
                   chunk: int = 4096) -> tuple[Tensor, Tensor]:
    """For each point, the closest triangle of the mesh and the barycentric coordinates of the closest point on it.

    Candidates: the triangles incident to the ``neighbours`` nearest vertices (exact for points on or near the
    surface; an approximation far from it). Computed in float64.

    Returns:
        (triangle index [P] int64, barycentric [P, 3] float64, summing to 1, all >= 0).
    """
    v = vertices.double()
    f = faces.long()
    nv = v.shape[0]
    # Vertex -> incident triangles, padded with -1.
    vert_of = f.flatten()
    tri_of = torch.arange(f.shape[0]).repeat_interleave(3)
    order = torch.argsort(vert_of, stable=True)
    vert_sorted, tri_sorted = vert_of[order], tri_of[order]
    counts = torch.bincount(vert_sorted, minlength=nv)
    valence = int(counts.max()) if counts.numel() else 0
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(vert_sorted)) - start[vert_sorted]
    incident = torch.full((nv, max(valence, 1)), -1, dtype=torch.long)
    incident[vert_sorted, slot] = tri_sorted

    tri_out, bary_out = [], []
    for p in points.double().split(chunk):
        near = torch.cdist(p, v).topk(min(neighbours, nv), largest=False).indices  # [c, n]
        cand = incident[near].reshape(len(p), -1)  # [c, n * valence]
        valid = cand >= 0
        cand_safe = cand.clamp_min(0)
        tri = v[f[cand_safe]]  # [c, m, 3 corners, 3]
        a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
        q = p[:, None, :].expand_as(a)
        # Projection onto the plane, barycentric by areas.
        e0, e1 = b - a, c - a
        d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
        w = q - a
        d20, d21 = (w * e0).sum(-1), (w * e1).sum(-1)
        den = (d00 * d11 - d01 * d01).clamp_min(1e-30)
        bv = (d11 * d20 - d01 * d21) / den
        bw = (d00 * d21 - d01 * d20) / den
        bu = 1 - bv - bw
        inside = (bu >= 0) & (bv >= 0) & (bw >= 0)
        best_bary = torch.stack([bu, bv, bw], -1)
        best_pt = a + bv[..., None] * e0 + bw[..., None] * e1
        best_d = torch.where(inside, (best_pt - q).square().sum(-1), torch.inf)
        # Edges (for projections outside the triangle).
        for (i0, i1), (x0, x1) in (((0, 1), (a, b)), ((1, 2), (b, c)), ((0, 2), (a, c))):
            pt, t = _closest_on_segment(q, x0, x1)
            dist = (pt - q).square().sum(-1)
            better = ~inside & (dist < best_d)
            eb = torch.zeros_like(best_bary)
            eb[..., i0] = 1 - t
            eb[..., i1] = t
            best_bary = torch.where(better[..., None], eb, best_bary)
            best_d = torch.where(better, dist, best_d)
        best_d = torch.where(valid, best_d, torch.inf)
        j = best_d.argmin(1)
        rows = torch.arange(len(p))
        tri_out.append(cand_safe[rows, j])
        bary_out.append(best_bary[rows, j].clamp_min(0.0))
    tri_idx = torch.cat(tri_out) if tri_out else torch.zeros(0, dtype=torch.long)
    bary = torch.cat(bary_out) if bary_out else torch.zeros(0, 3, dtype=torch.float64)
    bary = bary / bary.sum(1, keepdim=True).clamp_min(1e-30)
    return tri_idx, bary


def displacement_magnitudes(model: FaceModel, points: Tensor) -> Tensor:
    """d [K, P]: per blendshape k, |displacement| of the neutral-mesh point closest to each point (barycentric
    interpolation of the vertices' displacement norms, float32)."""
    tri, bary = closest_points(model.template, model.faces, points)
    corners = model.faces.long()[tri]  # [P, 3]
    mag = model.expression_basis.double().norm(dim=-1)  # [K, V]
    return (mag[:, corners] * bary[None]).sum(-1).float()


def consistency_range(model: FaceModel) -> tuple[float, float]:
    """(eps, d_max) of f(x) = (x - eps) / (d_max - eps) (METHOD.md section 4).

    The reference code takes eps = 0.1 x the largest vertex displacement of the *last* blendshape and d_max = the
    largest of the *first*, relying on FLAME's components being sorted by variance (first = largest motion, last =
    smallest). Face models whose blendshapes are not sorted (the open head's ARKit targets are alphabetical) need
    the order-free form used here: eps = 0.1 x min_k max_v |dB_k(v)| and d_max = max_k max_v |dB_k(v)|. For a
    variance-sorted basis this is the reference's choice whenever the first component moves most and the last
    least. No alignment of the targets to the back of the head and no neck zeroing (the open head's targets do
    not move the skull); no upper clamp (f <= 1 anyway, since d <= d_max).
    """
    per = model.expression_basis.double().norm(dim=-1).amax(dim=1)  # [K]
    moving = per[per > 0]
    if moving.numel() == 0:
        return 1e-5, 1.0
    eps = 0.1 * float(moving.min())
    d_max = float(moving.max())
    if d_max <= eps:
        d_max = eps + 1e-9
    return eps, d_max


def consistency_weights(d: Tensor, eps: float, d_max: float) -> Tensor:
    """max(f(d), 0) with f(x) = (x - eps) / (d_max - eps)."""
    return ((d - eps) / (d_max - eps)).clamp_min(0.0)
