"""Closest surface points and per-blendshape displacement magnitudes (docs/method.md sections 3 and 4).

``d_{i,k}`` is the displacement magnitude, from M0 to M_k, of the neutral-mesh point closest to Gaussian i: the
barycentric interpolation, at that point, of the vertices' ``|expression_basis[k]|``; the LBS weights of a point
are the same interpolation of the vertices' weights. :func:`surface_values` computes both per point directly (every
Gaussian at initialisation) with an exact closest-point search (:func:`closest_points`). Densified and moved
Gaussians get them from the 256^3 lookup grid of :mod:`.grids`, whose nodes use the same search
(:class:`Triangles`, :func:`closest_among`) with candidates shared by a brick of nodes.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..facemodel import FaceModel

SLACK = 1e-7  # metres added to the candidate bounds (covers the rounding of matrix-product distances)


def compact(keep: Tensor) -> tuple[Tensor, Tensor]:
    """The column indices of the True entries of each row of ``keep`` [R, C], moved to the front (in order) and
    padded with 0 to the longest row: (indices [R, m], valid [R, m]), m >= 1."""
    rows, cols = keep.nonzero(as_tuple=True)
    count = torch.bincount(rows, minlength=keep.shape[0])
    width = max(int(count.max()) if len(count) else 0, 1)
    slot = torch.arange(len(rows)) - (torch.cumsum(count, 0) - count)[rows]
    idx = torch.zeros(keep.shape[0], width, dtype=torch.long)
    valid = torch.zeros(keep.shape[0], width, dtype=torch.bool)
    idx[rows, slot] = cols
    valid[rows, slot] = True
    return idx, valid


class Triangles:
    """A mesh's triangles prepared for closest-point queries (float64, one contiguous array per scalar).

    With w = q - a, e0 = b - a, e1 = c - a, the squared distance from q to the triangle's plane foot and to each
    edge is a function of the dot products ww, w.e0, w.e1 (per query) and e0.e0, e0.e1, e1.e1 (per triangle), so
    a query touches 9 numbers per candidate triangle and no 3-vectors.
    """

    def __init__(self, vertices: Tensor, faces: Tensor):
        v = vertices.detach().double().cpu()
        f = faces.detach().long().cpu()
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        e0, e1 = b - a, c - a
        self.vertices, self.faces = v, f
        self.a = a.t().contiguous()  # [3, F]
        self.e0 = e0.t().contiguous()
        self.e1 = e1.t().contiguous()
        self.d00 = (e0 * e0).sum(1)
        self.d01 = (e0 * e1).sum(1)
        self.d11 = (e1 * e1).sum(1)
        centroid = (a + b + c) / 3
        self.centroid = centroid
        self.radius = torch.stack([a, b, c]).sub(centroid).norm(dim=-1).amax(0)  # bounding sphere per triangle

    def __len__(self) -> int:
        return int(self.faces.shape[0])

    def _dots(self, points: Tensor, tri: Tensor) -> tuple[Tensor, ...]:
        """(ww, w.e0, w.e1, d00, d01, d11) for points [P, 3] and triangles [P] or [P, m]."""
        q = points.double()
        shape = (-1,) + (1,) * (tri.dim() - 1)
        w = [q[:, i].reshape(shape) - self.a[i][tri] for i in range(3)]
        ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        d20 = w[0] * self.e0[0][tri] + w[1] * self.e0[1][tri] + w[2] * self.e0[2][tri]
        d21 = w[0] * self.e1[0][tri] + w[1] * self.e1[1][tri] + w[2] * self.e1[2][tri]
        return ww, d20, d21, self.d00[tri], self.d01[tri], self.d11[tri]

    @staticmethod
    def _options(ww, d20, d21, d00, d01, d11):
        """Squared distances and parameters of the four closest-point options: the plane foot (inside or not) and
        the edges ab, bc, ac (each clamped to its segment)."""
        den = (d00 * d11 - d01 * d01).clamp_min(1e-30)
        bv = (d11 * d20 - d01 * d21) / den
        bw = (d00 * d21 - d01 * d20) / den
        inside = (bv >= 0) & (bw >= 0) & (bv + bw <= 1)
        foot = ww - bv * d20 - bw * d21  # |w - (bv e0 + bw e1)|^2 at the plane foot
        t_ab = (d20 / d00.clamp_min(1e-30)).clamp(0, 1)
        ab = ww - 2 * t_ab * d20 + t_ab * t_ab * d00
        t_ac = (d21 / d11.clamp_min(1e-30)).clamp(0, 1)
        ac = ww - 2 * t_ac * d21 + t_ac * t_ac * d11
        qb = ww - 2 * d20 + d00  # |q - b|^2
        dot = d21 - d20 - d01 + d00  # (q - b).(c - b)
        e2 = d11 - 2 * d01 + d00  # |c - b|^2
        t_bc = (dot / e2.clamp_min(1e-30)).clamp(0, 1)
        bc = qb - 2 * t_bc * dot + t_bc * t_bc * e2
        return inside, foot, (bv, bw), (ab, t_ab), (bc, t_bc), (ac, t_ac)

    def near(self, centres: Tensor, half: Tensor | float = 0.0) -> tuple[Tensor, Tensor]:
        """The triangles that can hold the closest surface point of a point within ``half`` of each centre [U, 3]
        (``half`` [U] or a number; 0: the centre itself): (candidates [U, m], valid [U, m]).

        Exact: the closest triangle of such a point lies within D + 2 half of the centre, D being the centre's
        distance to the surface. A bounding-sphere prefilter against every triangle (the nearest vertex bounds D
        from above), then :meth:`refine`."""
        c = centres.double()
        half = torch.as_tensor(half, dtype=torch.float64).expand(len(c))
        m = torch.cdist(c, self.vertices).amin(1)  # >= D
        lower = torch.cdist(c, self.centroid) - self.radius  # <= the distance to each triangle
        cand, valid = compact(lower <= (m + 2 * half + SLACK)[:, None])
        return self.refine(c, half, cand, valid)

    def refine(self, centres: Tensor, half: Tensor, cand: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
        """Keep the candidates [U, m] within D + 2 half of each centre, D being the centre's distance to its nearest
        candidate: exact (see :meth:`near`) when the candidates held every triangle that can be closest to a point
        within ``half`` of the centre, and the centre's own closest triangle."""
        dist = torch.where(valid, self.distances(centres, cand), torch.inf).sqrt()
        bound = dist.amin(1) + 2 * half + SLACK
        keep = valid & (dist <= bound[:, None])
        idx, ok = compact(keep)
        return cand.gather(1, idx), ok

    def distances(self, points: Tensor, candidates: Tensor) -> Tensor:
        """Squared distance [P, m] from each point [P, 3] to each of its candidate triangles [P, m]."""
        inside, foot, _, (ab, _), (bc, _), (ac, _) = self._options(*self._dots(points, candidates))
        return torch.where(inside, foot, torch.minimum(torch.minimum(ab, bc), ac)).clamp_min(0.0)

    def closest(self, points: Tensor, tri: Tensor) -> tuple[Tensor, Tensor]:
        """The closest point of triangle ``tri[i]`` [P] to point i [P, 3]: (barycentric [P, 3], squared distance)."""
        inside, foot, (bv, bw), (ab, t_ab), (bc, t_bc), (ac, t_ac) = self._options(*self._dots(points, tri))
        zero = torch.zeros_like(ab)
        best = torch.where(inside, foot, torch.inf)
        bary = torch.stack([1 - bv - bw, bv, bw], -1)
        for dist, b in ((ab, (1 - t_ab, t_ab, zero)), (bc, (zero, 1 - t_bc, t_bc)), (ac, (1 - t_ac, zero, t_ac))):
            better = ~inside & (dist < best)
            bary = torch.where(better[:, None], torch.stack(b, -1), bary)
            best = torch.where(better, dist, best)
        bary = bary.clamp_min(0.0)
        return bary / bary.sum(1, keepdim=True).clamp_min(1e-30), best.clamp_min(0.0)


def closest_among(mesh: Triangles, points: Tensor, candidates: Tensor,
                  valid: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The closest point to each point among its candidate triangles.

    Args:
        mesh: the prepared triangles; points: [P, 3].
        candidates: [P, m] triangle indices (any value where not ``valid``).
        valid: [P, m] bool, or None (all valid). Every row needs at least one valid candidate.

    Returns:
        (triangle index [P] int64, barycentric [P, 3] float64 (>= 0, summing to 1), squared distance [P]).
    """
    cand = candidates.clamp(0, len(mesh) - 1) if valid is not None else candidates
    dist = mesh.distances(points, cand)
    if valid is not None:
        dist = torch.where(valid, dist, torch.inf)
    j = dist.argmin(1)
    tri = cand.gather(1, j[:, None]).squeeze(1)
    bary, d2 = mesh.closest(points, tri)
    return tri, bary, d2


def closest_points(vertices: Tensor, faces: Tensor, points: Tensor, *, chunk: int = 512) -> tuple[Tensor, Tensor]:
    """For each point, the closest triangle of the mesh and the barycentric coordinates of the closest point on it.

    Exact (:meth:`Triangles.near` picks every triangle that can be the closest, :func:`closest_among` the closest),
    anywhere in space; ties go to the lower triangle index. Computed in float64.

    Returns:
        (triangle index [P] int64, barycentric [P, 3] float64, summing to 1, all >= 0).
    """
    mesh = Triangles(vertices, faces)
    tri_out, bary_out = [], []
    for p in points.detach().double().cpu().split(chunk):
        cand, valid = mesh.near(p)
        tri, bary, _ = closest_among(mesh, p, cand, valid)
        tri_out.append(tri)
        bary_out.append(bary)
    tri_idx = torch.cat(tri_out) if tri_out else torch.zeros(0, dtype=torch.long)
    bary = torch.cat(bary_out) if bary_out else torch.zeros(0, 3, dtype=torch.float64)
    return tri_idx, bary


def values_at(model: FaceModel, tri: Tensor, bary: Tensor) -> tuple[Tensor, Tensor]:
    """LBS weights [P, J] (rows normalised to sum 1) and displacement magnitudes d [K, P] of the surface points
    (triangle [P], barycentric [P, 3]): the barycentric interpolation of the vertices' values, float32."""
    corners = model.faces.long()[tri]  # [P, 3]
    b = bary.double()
    lbs = (model.lbs_weights.double()[corners] * b[..., None]).sum(1)
    lbs = lbs / lbs.sum(1, keepdim=True).clamp_min(1e-30)
    mag = model.expression_basis.double().norm(dim=-1)  # [K, V]
    d = (mag[:, corners] * b[None]).sum(-1)
    return lbs.float(), d.float()


def surface_values(model: FaceModel, points: Tensor) -> tuple[Tensor, Tensor]:
    """(LBS weights [P, J], d [K, P]) of the neutral-mesh point closest to each point [P, 3] (computed directly)."""
    tri, bary = closest_points(model.template, model.faces, points)
    return values_at(model, tri, bary)


def displacement_magnitudes(model: FaceModel, points: Tensor) -> Tensor:
    """d [K, P]: per blendshape k, |displacement| of the neutral-mesh point closest to each point (barycentric
    interpolation of the vertices' displacement norms, float32)."""
    return surface_values(model, points)[1]


def consistency_range(model: FaceModel) -> tuple[float, float]:
    """(eps, d_max) of f(x) = (x - eps) / (d_max - eps) (docs/method.md section 4).

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
