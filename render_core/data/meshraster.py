"""A vectorised triangle-mesh rasterizer in torch (z-buffer, perspective-correct interpolation); no autograd.

Used by ``data synth`` to render ground-truth frames and exact masks of a face model. Semantics:

- Projection with the OpenCV pinhole camera of :class:`~render_core.camera.Cameras` (x right, y down, z forward,
  ``x_cam = R x_world + t``, pixel = ``K x_cam / z``). Pixel (i, j) - column i, row j - has its centre at
  (i + 0.5, j + 0.5); a pixel is covered by a triangle when its centre lies inside or on the triangle's edges
  (all three edge functions >= 0 after orienting them by the triangle's winding).
- Back faces are KEPT by default (``cull_backfaces=False``): a face-model mesh is not always closed (mouth
  interior, eyeballs), and its inside must render when seen through an open mouth. With ``cull_backfaces=True``
  the triangles whose vertex order is clockwise in the image (normal by the right-hand rule pointing away from
  the camera) are dropped.
- Triangles with any vertex at camera depth ``z <= near`` are dropped whole (no clipping); degenerate triangles
  (zero screen area) are dropped.
- Z-buffer: the nearest surface (smallest camera z at the pixel centre) wins; exact ties go to the lower face
  index, so the result never depends on evaluation order (deterministic).
- Interpolation is perspective-correct: screen barycentrics b_i become ``(b_i / z_i) / sum_j (b_j / z_j)``, so an
  attribute that is linear in the world position is reproduced exactly across a slanted triangle. The depth map
  is the camera z of the surface point on the pixel's ray, ``1 / sum_j (b_j / z_j)``.

How: per image, every triangle's pixel bounding box is expanded into (triangle, pixel) candidate pairs, in chunks
of at most ``chunk_pairs`` pairs; edge functions in float64 give coverage and barycentrics; a scatter-reduce
``amin`` of depth per pixel picks the nearest pair; a second ``amin`` on the face index breaks exact ties. The
only Python loops are over images and pair chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..camera import Cameras
from ..errors import ShapeError

__all__ = ["Fragments", "icosphere", "interpolate", "rasterize", "rasterize_mesh", "vertex_normals"]

NEAR = 1e-3
CHUNK_PAIRS = 1 << 21
_AREA_EPS = 1e-12  # |twice the screen area| (pixels^2) below this: degenerate


@dataclass
class Fragments:
    """The visible surface at every pixel of B images of H x W.

    face_id: [B, H, W] int64, -1 where no triangle covers the pixel.
    bary: [B, H, W, 3] perspective-correct barycentric weights (float64; zeros where uncovered).
    depth: [B, H, W] camera z of the visible surface (float64; 0 where uncovered).
    """

    face_id: Tensor
    bary: Tensor
    depth: Tensor

    @property
    def mask(self) -> Tensor:
        return self.face_id >= 0


def _check(vertices: Tensor, faces: Tensor, cameras: Cameras) -> None:
    if vertices.dim() != 3 or vertices.shape[-1] != 3:
        raise ShapeError(f"expected [B, V, 3], got {list(vertices.shape)}", field="vertices")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ShapeError(f"expected [F, 3], got {list(faces.shape)}", field="faces")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices.shape[1]):
        raise ShapeError(f"vertex indices must lie in [0, {vertices.shape[1]})", field="faces")
    if len(cameras) != vertices.shape[0]:
        raise ShapeError(f"{len(cameras)} cameras for {vertices.shape[0]} meshes", field="cameras")


@torch.no_grad()
def rasterize(
    vertices: Tensor,  # [B, V, 3] world
    faces: Tensor,  # [F, 3]
    cameras: Cameras,  # B cameras
    *,
    near: float = NEAR,
    cull_backfaces: bool = False,
    chunk_pairs: int = CHUNK_PAIRS,
) -> Fragments:
    """Visible triangle, perspective-correct barycentrics and depth per pixel (see the module docstring)."""
    _check(vertices, faces, cameras)
    b_count, width, height = vertices.shape[0], cameras.width, cameras.height
    device = vertices.device
    faces = faces.to(device=device, dtype=torch.int64)
    n_pix = height * width
    face_id = torch.full((b_count, n_pix), -1, dtype=torch.int64, device=device)
    bary = torch.zeros((b_count, n_pix, 3), dtype=torch.float64, device=device)
    depth = torch.zeros((b_count, n_pix), dtype=torch.float64, device=device)
    K = cameras.K.to(device, torch.float64)
    R = cameras.R.to(device, torch.float64)
    t = cameras.t.to(device, torch.float64)
    for b in range(b_count):
        cam = vertices[b].to(torch.float64) @ R[b].T + t[b]  # [V, 3]
        z = cam[:, 2]
        proj = cam @ K[b].T
        uv = proj[:, :2] / torch.where(z > near, z, torch.ones_like(z))[:, None]  # finite for dropped vertices
        tri_uv, tri_z = uv[faces], z[faces]  # [F, 3, 2], [F, 3]
        u0, v0 = tri_uv[:, 0, 0], tri_uv[:, 0, 1]
        u1, v1 = tri_uv[:, 1, 0], tri_uv[:, 1, 1]
        u2, v2 = tri_uv[:, 2, 0], tri_uv[:, 2, 1]
        area = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)  # > 0: clockwise on screen = back face
        keep = (tri_z > near).all(-1) & (area.abs() > _AREA_EPS) & torch.isfinite(area)
        if cull_backfaces:
            keep &= area < 0
        # Pixel columns i with i + 0.5 in [min u, max u], clamped to the image.
        lo = tri_uv.amin(1).clamp(-2.0, max(width, height) + 2.0)
        hi = tri_uv.amax(1).clamp(-2.0, max(width, height) + 2.0)
        x0 = torch.ceil(lo[:, 0] - 0.5).clamp_min(0).to(torch.int64)
        x1 = torch.floor(hi[:, 0] - 0.5).clamp_max(width - 1).to(torch.int64)
        y0 = torch.ceil(lo[:, 1] - 0.5).clamp_min(0).to(torch.int64)
        y1 = torch.floor(hi[:, 1] - 0.5).clamp_max(height - 1).to(torch.int64)
        bw, bh = (x1 - x0 + 1).clamp_min(0), (y1 - y0 + 1).clamp_min(0)
        keep &= (bw > 0) & (bh > 0)
        tris = torch.nonzero(keep).squeeze(1)
        if tris.numel() == 0:
            continue
        counts = bw[tris] * bh[tris]
        ends = torch.cumsum(counts, 0)
        best_z = torch.full((n_pix,), torch.inf, dtype=torch.float64, device=device)
        best_f = face_id[b]
        best_w = bary[b]
        start = 0
        while start < tris.numel():
            base = int(ends[start - 1]) if start else 0
            stop = int(torch.searchsorted(ends, base + chunk_pairs, right=True))
            stop = max(stop, start + 1)  # a triangle bigger than a chunk goes alone
            sel = tris[start:stop]
            cnt = counts[start:stop]
            local = torch.repeat_interleave(torch.arange(sel.numel(), device=device), cnt)
            offset = torch.arange(local.numel(), device=device) - (torch.cumsum(cnt, 0) - cnt)[local]
            f = sel[local]
            px = x0[f] + offset % bw[f]
            py = y0[f] + offset // bw[f]
            cx, cy = px.to(torch.float64) + 0.5, py.to(torch.float64) + 0.5
            a, bu, bv = area[f], u1[f], v1[f]
            au, av, cu, cv = u0[f], v0[f], u2[f], v2[f]
            w0 = ((cu - bu) * (cy - bv) - (cv - bv) * (cx - bu)) / a
            w1 = ((au - cu) * (cy - cv) - (av - cv) * (cx - cu)) / a
            w2 = ((bu - au) * (cy - av) - (bv - av) * (cx - au)) / a
            inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
            if not bool(inside.any()):
                start = stop
                continue
            f, px, py = f[inside], px[inside], py[inside]
            w = torch.stack([w0[inside], w1[inside], w2[inside]], -1)
            w = w / tri_z[f]  # b_i / z_i
            inv_z = w.sum(-1)
            pz = 1.0 / inv_z
            w = w * pz[:, None]
            pix = py * width + px
            # Nearest pair per pixel within the chunk, then ties to the lowest face index.
            cz = torch.full((n_pix,), torch.inf, dtype=torch.float64, device=device)
            cz.scatter_reduce_(0, pix, pz, "amin")
            win = pz == cz[pix]
            cf = torch.full((n_pix,), torch.iinfo(torch.int64).max, dtype=torch.int64, device=device)
            cf.scatter_reduce_(0, pix[win], f[win], "amin")
            win &= f == cf[pix]
            f, pix, pz, w = f[win], pix[win], pz[win], w[win]  # one pair per pixel now
            # Merge with the winners of the earlier chunks.
            old_z, old_f = best_z[pix], best_f[pix]
            better = (pz < old_z) | ((pz == old_z) & (f < old_f))
            pix = pix[better]
            best_z[pix], best_f[pix], best_w[pix] = pz[better], f[better], w[better]
            start = stop
        covered = best_f >= 0
        depth[b] = torch.where(covered, best_z, torch.zeros_like(best_z))
    return Fragments(face_id.view(b_count, height, width), bary.view(b_count, height, width, 3),
                     depth.view(b_count, height, width))


def interpolate(fragments: Fragments, faces: Tensor, attributes: Tensor) -> Tensor:
    """Vertex attributes [B or 1, V, C] interpolated at every pixel -> [B, H, W, C] (zeros where uncovered)."""
    b_count, height, width = fragments.face_id.shape
    if attributes.dim() != 3 or attributes.shape[0] not in (1, b_count):
        raise ShapeError(f"expected [{b_count} or 1, V, C], got {list(attributes.shape)}", field="attributes")
    faces = faces.to(device=attributes.device, dtype=torch.int64)
    channels = attributes.shape[-1]
    out = torch.zeros((b_count, height * width, channels), dtype=attributes.dtype, device=attributes.device)
    fid = fragments.face_id.reshape(b_count, -1)
    w = fragments.bary.reshape(b_count, -1, 3)
    for b in range(b_count):
        idx = torch.nonzero(fid[b] >= 0).squeeze(1)
        if idx.numel() == 0:
            continue
        attr = attributes[b if attributes.shape[0] > 1 else 0]
        corners = attr[faces[fid[b, idx]]]  # [P, 3, C]
        val = (corners.to(torch.float64) * w[b, idx, :, None]).sum(1)
        out[b, idx] = val.to(attributes.dtype)
    return out.view(b_count, height, width, channels)


def rasterize_mesh(
    vertices: Tensor,  # [B, V, 3] world
    faces: Tensor,  # [F, 3]
    cameras: Cameras,
    attributes: Tensor | None = None,  # [B or 1, V, C]
    *,
    near: float = NEAR,
    cull_backfaces: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Render a triangle mesh: (image [B, H, W, C], mask [B, H, W] bool, depth [B, H, W], face_id [B, H, W]).

    ``image`` holds the perspective-correct interpolation of ``attributes`` (C = 0 when None) and zeros where no
    triangle covers the pixel; ``depth`` is the camera z of the visible surface (0 where uncovered, in the dtype
    of ``vertices``); ``face_id`` the visible triangle's index (-1 where uncovered). Semantics: module docstring.
    """
    frags = rasterize(vertices, faces, cameras, near=near, cull_backfaces=cull_backfaces)
    if attributes is None:
        attributes = vertices.new_zeros((1, vertices.shape[1], 0))
    image = interpolate(frags, faces, attributes)
    return image, frags.mask, frags.depth.to(vertices.dtype), frags.face_id


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Unit vertex normals [B, V, 3]: the area-weighted sum of the normals (right-hand rule) of adjacent faces."""
    faces = faces.to(device=vertices.device, dtype=torch.int64)
    tri = vertices[:, faces]  # [B, F, 3, 3]
    fn = torch.linalg.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])  # |fn| = 2 area
    out = torch.zeros_like(vertices)
    for k in range(3):
        out.index_add_(1, faces[:, k], fn)
    return torch.nn.functional.normalize(out, dim=-1)


def icosphere(subdivisions: int = 2, radius: float = 1.0, dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """A unit icosphere (scaled by ``radius``): vertices [V, 3] and outward (counter-clockwise) faces [F, 3]."""
    p = (1.0 + 5.0**0.5) / 2.0
    verts = [(-1, p, 0), (1, p, 0), (-1, -p, 0), (1, -p, 0), (0, -1, p), (0, 1, p), (0, -1, -p), (0, 1, -p),
             (p, 0, -1), (p, 0, 1), (-p, 0, -1), (-p, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11),
             (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    v = torch.nn.functional.normalize(torch.tensor(verts, dtype=torch.float64), dim=-1)
    f = torch.tensor(faces, dtype=torch.int64)
    for _ in range(subdivisions):
        edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # [3F, 2]
        key = edges.sort(1).values
        uniq, inverse = torch.unique(key, dim=0, return_inverse=True)
        mids = torch.nn.functional.normalize((v[uniq[:, 0]] + v[uniq[:, 1]]) / 2, dim=-1)
        m = inverse.view(3, -1) + v.shape[0]  # midpoint index of edges 01, 12, 20 per face
        v = torch.cat([v, mids])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[0], m[1], m[2]
        f = torch.cat([torch.stack(x, -1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return (v * radius).to(dtype), f
