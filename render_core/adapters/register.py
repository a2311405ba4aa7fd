"""Dense correspondence between two face models of different topologies (docs/method.md section 12).

Both neutral meshes are heads in metres, y up, facing +z. :func:`register` finds, for every target vertex, a
point on the source surface (a triangle and barycentric coordinates):

1. rigid alignment: a similarity transform (Umeyama/Procrustes) on the landmarks both models have (the rest
   positions of joints with the same name, e.g. eye_l, eye_r, jaw, neck), else on the centroids, refined by
   rigid ICP (point to closest surface point, Kabsch);
2. non-rigid ICP: a per-vertex offset field u of the aligned target, smooth along the target's edges, pulled to
   the closest source points: minimise sum_v w_v |x_v + u_v - c_v|^2 + alpha sum_(i,j) |u_i - u_j|^2 (+ the
   landmarks' terms), solved by conjugate gradients, re-matching c and lowering the stiffness alpha each round;
   matches farther than a threshold (or across opposite normals) get w_v = 0;
3. closest-point projection of the deformed target vertices onto the source triangles: barycentric coordinates.

:func:`transfer` then carries any per-vertex field of the source (expression displacements) to the target.
Everything is numpy/torch (float64); no scipy.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ..facemodel.model import FaceModel

LANDMARK_JOINTS = ("neck", "head", "jaw", "eye_l", "eye_r")


@dataclass
class Correspondence:
    """For each target vertex: the source triangle (``faces`` row) and barycentric weights of its closest point,
    the distance (metres) after registration, and whether the match is trusted. ``rotation``/``scale``/``shift``:
    the similarity that maps source coordinates into the target's frame (x_t = scale R x_s + shift)."""

    triangles: np.ndarray  # [Vt] int64 index into the source faces
    vertices: np.ndarray  # [Vt, 3] int64 source vertex indices of those triangles
    weights: np.ndarray  # [Vt, 3] barycentric
    distance: np.ndarray  # [Vt]
    valid: np.ndarray  # [Vt] bool
    rotation: np.ndarray  # [3, 3]
    scale: float
    shift: np.ndarray  # [3]

    def transfer(self, field: np.ndarray) -> np.ndarray:
        """A source per-vertex vector field [..., Vs, 3] -> the target's [..., Vt, 3] (interpolated, rotated into
        the target's frame; lengths kept: a 1 cm motion stays 1 cm)."""
        f = np.asarray(field, dtype=np.float64)
        out = np.einsum("...vkc,vk->...vc", f[..., self.vertices, :], self.weights)
        return out @ self.rotation.T


def _closest_on_triangles(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Closest points of points p [N, 3] on triangles (a, b, c) [N, 3] each: (points [N, 3], barycentric [N, 3]).
    The region tests of Ericson, Real-Time Collision Detection, 5.1.5, vectorised (degenerate triangles fall to
    an edge or a vertex)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    eps = 1e-30
    zero, one = torch.zeros_like(d1), torch.ones_like(d1)
    denom = va + vb + vc
    denom = torch.where(denom.abs() < eps, torch.full_like(denom, eps), denom)
    v, w = vb / denom, vc / denom
    bary = torch.stack([1 - v - w, v, w], -1)  # interior; the regions below take precedence, last one first

    def region(mask: torch.Tensor, value: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
        return torch.where(mask[:, None], value, current)

    t_bc = ((d4 - d3) / ((d4 - d3) + (d5 - d6)).clamp_min(eps)).clamp(0, 1)
    bary = region((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), torch.stack([zero, 1 - t_bc, t_bc], -1), bary)
    t_ac = (d2 / (d2 - d6).clamp_min(eps)).clamp(0, 1)
    bary = region((vb <= 0) & (d2 >= 0) & (d6 <= 0), torch.stack([1 - t_ac, zero, t_ac], -1), bary)
    bary = region((d6 >= 0) & (d5 <= d6), torch.stack([zero, zero, one], -1), bary)
    t_ab = (d1 / (d1 - d3).clamp_min(eps)).clamp(0, 1)
    bary = region((vc <= 0) & (d1 >= 0) & (d3 <= 0), torch.stack([1 - t_ab, t_ab, zero], -1), bary)
    bary = region((d3 >= 0) & (d4 <= d3), torch.stack([zero, one, zero], -1), bary)
    bary = region((d1 <= 0) & (d2 <= 0), torch.stack([one, zero, zero], -1), bary)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


class SurfaceIndex:
    """Closest-point queries on a triangle mesh: candidates are the triangles whose centroids are the ``k`` nearest
    to the query (brute-force distances in chunks), then exact point-triangle distances on those."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, k: int = 12):
        self.v = torch.as_tensor(np.asarray(vertices, np.float64))
        self.f = torch.as_tensor(np.asarray(faces, np.int64))
        tri = self.v[self.f]
        self.centroids = tri.mean(1)
        self.centroids32 = self.centroids.float()
        n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = torch.nn.functional.normalize(n, dim=1)
        self.k = min(k, len(self.f))

    def candidates(self, points: np.ndarray | torch.Tensor, chunk: int = 2048) -> torch.Tensor:
        """[N, k] candidate triangles per point: those with the k nearest centroids (float32 distances)."""
        p_all = torch.as_tensor(np.asarray(points)).float() if not torch.is_tensor(points) else points.float()
        c2 = (self.centroids32 ** 2).sum(1)
        out = []
        for s in range(0, len(p_all), chunk):
            p = p_all[s:s + chunk]
            d = torch.addmm(c2[None], p, self.centroids32.T, alpha=-2.0)  # |c|^2 - 2 p.c (|p|^2 is constant)
            out.append(d.topk(self.k, dim=1, largest=False).indices)
        return torch.cat(out)

    def query(self, points: np.ndarray | torch.Tensor, cand: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(closest points [N, 3], triangle [N], barycentric [N, 3], distance [N]) among ``cand`` ([N, k], default
        :meth:`candidates` of the points; a caller whose points move little may reuse them)."""
        p = torch.as_tensor(np.asarray(points, np.float64)) if not torch.is_tensor(points) else points.double()
        cand = self.candidates(p) if cand is None else cand
        k = cand.shape[1]
        tri = self.f[cand]  # [n, k, 3]
        pe = p[:, None].expand(-1, k, -1).reshape(-1, 3)
        a, b, c = (self.v[tri[..., i]].reshape(-1, 3) for i in range(3))
        q, bary = _closest_on_triangles(pe, a, b, c)
        d = (q - pe).norm(dim=1).reshape(-1, k)
        best = d.argmin(1)
        rows = torch.arange(len(p))
        return (q.reshape(-1, k, 3)[rows, best], cand[rows, best], bary.reshape(-1, k, 3)[rows, best],
                d[rows, best])


def similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, scale: bool = True
               ) -> tuple[np.ndarray, float, np.ndarray]:
    """(R, s, t) minimising sum w |s R src + t - dst|^2 (Umeyama 1991; Kabsch when ``scale`` is False)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    cov = (xd * w[:, None]).T @ xs
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2] = -1
    r = u @ np.diag(d) @ vt
    var = (w * (xs ** 2).sum(1)).sum()
    s = float((sig * d).sum() / var) if scale and var > 0 else 1.0
    return r, s, mu_d - s * r @ mu_s


def _laplacian(faces: np.ndarray, n: int) -> torch.Tensor:
    """The graph Laplacian (sparse [n, n]) of the mesh's edges: sum over edges (i, j) of |u_i - u_j|^2 = u^T L u."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    i, j = torch.as_tensor(e[:, 0]), torch.as_tensor(e[:, 1])
    deg = torch.zeros(n, dtype=torch.float64).index_add_(0, i, torch.ones(len(i), dtype=torch.float64)).index_add_(
        0, j, torch.ones(len(j), dtype=torch.float64))
    rows = torch.cat([i, j, torch.arange(n)])
    cols = torch.cat([j, i, torch.arange(n)])
    vals = torch.cat([-torch.ones(2 * len(i), dtype=torch.float64), deg])
    coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (n, n), check_invariants=False).coalesce()
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the product below is all we use
        warnings.simplefilter("ignore")
        return coo.to_sparse_csr()


def _cg(apply, b: torch.Tensor, x0: torch.Tensor, iters: int = 60, tol: float = 1e-5, atol: float = 1e-7
        ) -> torch.Tensor:
    """Conjugate gradients for an SPD operator, columns of b [n, 3] solved together (stops at a residual
    ``tol`` relative to b, or ``atol`` metres RMS per vertex)."""
    x = x0.clone()
    r = b - apply(x)
    p = r.clone()
    rs = (r * r).sum(0)
    b_norm = torch.maximum(tol * tol * (b * b).sum(0), torch.tensor(atol * atol * len(b), dtype=b.dtype))
    for _ in range(iters):
        if bool((rs <= b_norm).all()):
            break
        ap = apply(p)
        alpha = rs / (p * ap).sum(0).clamp_min(1e-300)
        x = x + alpha * p
        r = r - alpha * ap
        rs_new = (r * r).sum(0)
        p = r + (rs_new / rs.clamp_min(1e-300)) * p
        rs = rs_new
    return x


def landmarks(source: FaceModel, target: FaceModel) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Rest positions of the joints both models have (by name, from LANDMARK_JOINTS): (source [L, 3], target
    [L, 3], names)."""
    names = [n for n in LANDMARK_JOINTS if n in source.joint_names and n in target.joint_names]
    s = np.array([source.joint_positions[source.joint_names.index(n)].double().numpy() for n in names]).reshape(-1, 3)
    t = np.array([target.joint_positions[target.joint_names.index(n)].double().numpy() for n in names]).reshape(-1, 3)
    return s, t, names


def register(source: FaceModel, target: FaceModel, *, rigid_iterations: int = 10, nonrigid_iterations: int = 4,
             stiffness: tuple[float, float] = (50.0, 1.0), max_distance: float = 0.01,
             use_landmarks: bool = True) -> Correspondence:
    """Dense correspondence from every target vertex to the source surface (steps 1-3 of the module docstring).

    ``max_distance`` (metres): matches farther than this after registration are marked invalid (the fit ignores
    them; e.g. a neck the source does not have)."""
    vs = source.template.double().numpy()
    vt = target.template.double().numpy()
    ft = target.faces.numpy()
    index = SurfaceIndex(vs, source.faces.numpy())

    # 1. Rigid: target -> source frame (x_s = s R x_t + t), landmarks first, then ICP.
    ls, lt, names = landmarks(source, target)
    if use_landmarks and len(names) >= 3:
        r, s, t = similarity(lt, ls)
    else:
        r, s, t = np.eye(3), 1.0, vs.mean(0) - vt.mean(0)
    x = (s * vt @ r.T) + t
    cand = index.candidates(x)  # reused while the target moves little (ICP and non-rigid rounds)
    for _ in range(rigid_iterations):
        q, _, _, d = index.query(x, cand)
        q, d = q.numpy(), d.numpy()
        keep = d <= max(np.median(d) * 3, 1e-6)
        r2, s2, t2 = similarity(x[keep], q[keep], scale=True)
        x = s2 * x @ r2.T + t2
        r, s, t = r2 @ r, s2 * s, s2 * r2 @ t + t2
        if np.abs(r2 - np.eye(3)).max() < 1e-7 and abs(s2 - 1) < 1e-7 and np.abs(t2).max() < 1e-8:
            break

    # 2. Non-rigid ICP: smooth offsets u of the aligned target vertices.
    n = len(x)
    lap = _laplacian(ft, n)
    lm_idx = None
    if use_landmarks and len(names):
        # landmark vertices: the target vertex nearest each target joint... joints sit inside the head, so the
        # landmark term acts on the joints through the offset of their nearest vertices (kept where they map).
        lt_aligned = s * lt @ r.T + t
        lm_idx = np.argmin(((x[None] - lt_aligned[:, None]) ** 2).sum(-1), axis=1)
        lm_goal = x[lm_idx] + (ls - lt_aligned)
    u = torch.zeros(n, 3, dtype=torch.float64)
    xt = torch.as_tensor(x)
    for alpha in np.geomspace(stiffness[0], stiffness[1], nonrigid_iterations):
        q, tri, _, d = index.query(xt + u, cand)
        # normals: a match across opposite-facing surfaces (inside vs outside) is dropped; the two meshes' winding
        # may be opposite (the sign that most close matches agree on is taken as "facing the same way")
        w = (d <= max_distance).double()
        facing = torch.as_tensor((_vertex_normals(x + u.numpy(), ft) * index.normals[tri].numpy()).sum(1))
        if float(facing[w > 0].median()) < 0 if bool((w > 0).any()) else False:
            facing = -facing
        w = w * (facing > 0.0).double()
        goal = q - xt
        wl = torch.zeros(n, dtype=torch.float64)
        if lm_idx is not None:
            wl[lm_idx] = 1.0
            goal[lm_idx] = torch.as_tensor(lm_goal) - xt[lm_idx]
        weights = torch.maximum(w, wl)
        a = float(alpha)

        def apply(v: torch.Tensor, weights=weights, a=a) -> torch.Tensor:
            return weights[:, None] * v + a * (lap @ v) + 1e-8 * v

        u = _cg(apply, weights[:, None] * goal, u)

    # 3. Projection of the deformed target onto the source surface.
    _, tri, bary, d = index.query(xt + u)
    tri, bary, d = tri.numpy(), bary.numpy(), d.numpy()
    # the similarity that maps source coordinates into the target frame: inverse of x_s = s R x_t + t
    return Correspondence(triangles=tri, vertices=source.faces.numpy()[tri], weights=bary, distance=d,
                          valid=d <= max_distance, rotation=r.T, scale=1.0 / s, shift=-(r.T @ t) / s)


def _vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for i in range(3):
        np.add.at(vn, f[:, i], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-20)
