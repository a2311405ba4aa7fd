"""Stage 3's fixed correspondence: MediaPipe's face-mesh points (and iris centres) -> points on the open head.

Built once, reproducibly, by :func:`build_correspondence` (``python -m render_core.tracking.correspond`` rewrites
the shipped ``models/open_head_landmarks.npz``): the open head is rendered with our own mesh rasterizer
(:func:`render_core.data.generate.render_frames`: neutral expression, joints at rest, front view, 512x512), the face
mesh is run on that picture, and each landmark takes the point of the triangle under it (the triangle's three
vertices and the landmark's barycentric coordinates in the triangle's projection). Left out, since they do not stay
on one point of the surface: the face outline (:data:`FACE_OVAL`: silhouette points that slide as the head turns),
points that fall on no triangle, and points on the eyeballs, teeth or tongue (the eyelid contour would follow the
gaze). The iris centres (numbered 468: the subject's right eye, 469: the left, MediaPipe's iris order) likewise take the
eyeball's triangle under them (eyeLook* coefficients move it with the eyeball).

``landmarks [L]`` (MediaPipe indices, then 468, 469), ``triangles [L, 3]`` (vertex indices), ``barycentric [L, 3]``,
and ``offsets [L, 3, 4 + K]``: where each landmark really sits relative to its surface point, as a function of the
head's rotation and the K expressions, learnt by :mod:`.calibrate` from renders with a known answer (absent: none).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import TrackingError
from .runner import MODELS_DIR

SHIPPED = MODELS_DIR / "open_head_landmarks.npz"
REFERENCE_SIZE = 512
# MediaPipe's face-oval (silhouette) points: they slide over the surface as the head turns.
FACE_OVAL = (10, 338, 297, 332, 284, 251, 389, 356, 454, 323, 361, 288, 397, 365, 379, 378, 400, 377, 152, 148, 176,
             149, 150, 136, 172, 58, 132, 93, 234, 127, 162, 21, 54, 103, 67, 109)
MOVING_GROUPS = ("eyeball_l", "eyeball_r", "teeth_upper", "teeth_lower", "tongue")


@dataclass(frozen=True)
class Correspondence:
    landmarks: np.ndarray  # [L] int64
    triangles: np.ndarray  # [L, 3] int64
    barycentric: np.ndarray  # [L, 3] float32
    offsets: np.ndarray | None = None  # [L, 3, 4 + K] float32 (module docstring)

    def points(self, vertices: torch.Tensor) -> torch.Tensor:
        """``vertices [..., V, 3]`` -> the L surface points ``[..., L, 3]`` (no offsets)."""
        tri = torch.from_numpy(self.triangles)
        w = torch.from_numpy(self.barycentric).to(vertices.dtype)
        return (vertices[..., tri, :] * w[..., None]).sum(-2)

    @staticmethod
    def offset_features(rotation: torch.Tensor) -> torch.Tensor:
        """The head's rotation (axis-angle relative to the front view) ``[N, 3]`` -> ``[N, 4]``: 1, r."""
        return torch.cat([torch.ones_like(rotation[:, :1]), rotation], 1)

    def anchors(self, points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
        """The surface points ``[L, 3]`` moved by the offsets at each head rotation ``[N, 3]`` -> ``[N, L, 3]``
        (without offsets: the points, broadcast)."""
        if self.offsets is None:
            return points.expand(rotation.shape[0], *points.shape)
        D = torch.from_numpy(self.offsets[..., :4]).to(points.dtype)
        return points + torch.einsum("lcf,nf->nlc", D, self.offset_features(rotation.to(points.dtype)))

    def basis_correction(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """How much more (or less) each landmark moves with each expression than its surface point: ``[K, L, 3]``,
        added to the landmarks' expression basis (zero without offsets)."""
        if self.offsets is None:
            return torch.zeros(0, len(self.landmarks), 3, dtype=dtype)
        return torch.from_numpy(self.offsets[..., 4:]).to(dtype).permute(2, 0, 1)


def load_correspondence(path: Path = SHIPPED) -> Correspondence:
    with np.load(path, allow_pickle=False) as z:
        return Correspondence(z["landmarks"].astype(np.int64), z["triangles"].astype(np.int64),
                              z["barycentric"].astype(np.float32),
                              z["offsets"].astype(np.float32) if "offsets" in z.files else None)


def _reference_view(model, size: int):
    """(RGB of the neutral front view, posed vertices [V, 3], cameras, face_id [H, W])."""
    from ..data.albedo import SkinAlbedo
    from ..data.generate import make_script, render_frames, script_cameras
    from ..data.meshraster import rasterize
    from ..rotation import axis_angle_to_matrix

    script = make_script(model, 2, 0)
    for x in (script.expression, script.joint_rotations, script.eyelids, script.head):
        x.zero_()
    cams = script_cameras(model, script, size)
    rgb, _ = next(render_frames(model, script, cams, SkinAlbedo(model, 0)))
    with torch.no_grad():
        posed, _ = model.evaluate(script.expression[:1], axis_angle_to_matrix(script.joint_rotations[:1]),
                                  script.eyelids[:1], None)
    face_id = rasterize(posed, model.faces, cams.index(slice(0, 1))).face_id[0].numpy()
    return rgb, posed[0].double().numpy(), cams, face_id


VIEWS = ((-20.0, 0.0), (20.0, 0.0), (-10.0, 8.0), (10.0, 8.0), (-10.0, -8.0), (10.0, -8.0), (0.0, 10.0),
         (0.0, -10.0))  # (yaw, pitch) degrees of the refining views
SEARCH_RADIUS = 0.012  # metres around the front view's point
SAMPLES = 6  # barycentric grid steps per triangle side


def _view_landmarks(model, size: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The face mesh's points (and irises) found in each refining view ``[L=470, 2]`` (NaN: not found), and the
    views' projection matrices ``[V, 3, 4]``."""
    from ..data.albedo import SkinAlbedo
    from ..data.generate import make_script, render_frames, script_cameras
    from .landmarks import find_face

    script = make_script(model, len(VIEWS), 0)
    for x in (script.expression, script.joint_rotations, script.eyelids, script.head):
        x.zero_()
    script.head[:, :2] = torch.tensor(VIEWS)
    cams = script_cameras(model, script, size)
    found = []
    for rgb, _ in render_frames(model, script, cams, SkinAlbedo(model, 0)):
        try:
            face = find_face(rgb)
            found.append(np.concatenate([face.landmarks[:, :2], face.iris[:, 0, :2]]))
        except TrackingError:
            found.append(np.full((470, 2), np.nan))
    P = cams.K.double() @ torch.cat([cams.R.double(), cams.t.double()[..., None]], -1)
    return found, P.numpy()


def _refine(verts: np.ndarray, faces: np.ndarray, allowed: np.ndarray, start: np.ndarray, observed: np.ndarray,
            P: np.ndarray) -> tuple[int, np.ndarray, float]:
    """The surface point near ``start`` (triangles of ``allowed`` faces within SEARCH_RADIUS, on a barycentric
    grid) whose projections in the views ``P [V, 3, 4]`` best match ``observed [V, 2]``: (face, weights, rms px)."""
    centres = verts[faces].mean(1)
    near = np.flatnonzero(allowed & (np.linalg.norm(centres - start, axis=1) < SEARCH_RADIUS))
    if not len(near):
        return -1, np.zeros(3), np.inf
    g = np.array([(a, b) for a in range(SAMPLES + 1) for b in range(SAMPLES + 1 - a)], float) / SAMPLES
    w = np.stack([1 - g.sum(1), g[:, 0], g[:, 1]], 1)  # [S, 3]
    pts = np.einsum("sk,tkc->tsc", w, verts[faces[near]])  # [T, S, 3]
    h = np.einsum("vij,tsj->vtsi", P[:, :, :3], pts) + P[:, None, None, :, 3]
    uv = h[..., :2] / h[..., 2:3]
    ok = ~np.isnan(observed).any(1)
    cost = ((uv[ok] - observed[ok][:, None, None]) ** 2).sum(-1).mean(0)  # [T, S]
    t, k = np.unravel_index(cost.argmin(), cost.shape)
    return int(near[t]), w[k], float(np.sqrt(cost[t, k]))


def build_correspondence(model=None, size: int = REFERENCE_SIZE, refine: bool = True) -> tuple[Correspondence, dict]:
    """The correspondence (module docstring) and a report (points kept and why the others were left out)."""
    from ..facemodel.open_head import open_head
    from .landmarks import find_face

    model = model or open_head()
    rgb, verts, cams, face_id = _reference_view(model, size)
    K, R, t = (x[0].double().numpy() for x in (cams.K, cams.R, cams.t))
    cam = verts @ R.T + t
    uv = cam @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    face = find_face(rgb)
    moving = np.zeros(model.num_vertices, bool)
    for g in MOVING_GROUPS:
        moving[model.vertex_groups[g].numpy()] = True
    faces = model.faces.numpy()
    kept, tris, bary = [], [], []
    left_out = {"outline": 0, "no triangle": 0, "moving part": 0}
    points = np.concatenate([face.landmarks[:, :2], face.iris[:, 0, :2]])  # 468, then the irises as 468, 469
    for i, (x, y) in enumerate(points):
        if i in FACE_OVAL:
            left_out["outline"] += 1
            continue
        px, py = int(np.floor(x)), int(np.floor(y))
        f = int(face_id[py, px]) if 0 <= px < size and 0 <= py < size else -1
        if f < 0:
            left_out["no triangle"] += 1
            continue
        if moving[faces[f]].any() != (i >= 468):  # irises on the eyeballs, every other point off them
            if i >= 468 or not refine:  # a face point over an eyeball (an eyelid's margin): snapped below
                left_out["moving part"] += 1
                continue
        a, b, c = uv[faces[f]]
        m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        s, u = np.linalg.solve(m, np.array([x - a[0], y - a[1]]))
        w = np.clip(np.array([1 - s - u, s, u]), 0.0, 1.0)
        kept.append(i)
        tris.append(faces[f])
        bary.append(w / w.sum())
    if refine:
        views, P = _view_landmarks(model, size)
        observed = np.stack([np.concatenate([points[None], np.stack(views)])[:, i] for i in kept], 0)  # [L, V+1, 2]
        cam0 = (cams.K[0].double() @ torch.cat([cams.R[0].double(), cams.t[0].double()[:, None]], -1)).numpy()
        P = np.concatenate([cam0[None], P])
        drop: list[int] = []
        for n, i in enumerate(kept):
            start = (verts[tris[n]] * bary[n][:, None]).sum(0)
            allowed = moving[faces].any(1) if i >= 468 else ~moving[faces].any(1)
            f, w, _ = _refine(verts, faces, allowed, start, observed[n], P)
            if f >= 0:
                tris[n], bary[n] = faces[f], w
            elif moving[tris[n]].any() != (i >= 468):
                drop.append(n)
        for n in reversed(drop):  # an eyelid point with no eyelid near it
            left_out["moving part"] += 1
            del kept[n], tris[n], bary[n]
    corr = Correspondence(np.array(kept, np.int64), np.array(tris, np.int64), np.array(bary, np.float32))
    if list(corr.landmarks[-2:]) != [468, 469]:
        raise TrackingError("the reference view's irises do not fall on the eyeballs", field="model")
    pts = corr.points(torch.from_numpy(verts)).numpy() @ R.T + t
    proj = pts @ K.T
    proj = proj[:, :2] / proj[:, 2:3]
    found = points[corr.landmarks]
    residual = np.linalg.norm(proj - found, axis=1)
    report = {"kept": len(kept), "left_out": left_out, "size": size,
              "residual_px_max": float(residual.max())}
    return corr, report


def write_correspondence(corr: Correspondence, path: Path = SHIPPED) -> Path:
    extra = {} if corr.offsets is None else {"offsets": corr.offsets}
    np.savez_compressed(path, landmarks=corr.landmarks, triangles=corr.triangles, barycentric=corr.barycentric,
                        **extra)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="rebuild the open head's landmark correspondence")
    p.add_argument("--out", type=Path, default=SHIPPED)
    p.add_argument("--no-calibration", action="store_true", help="leave the offsets out (:mod:`.calibrate`)")
    args = p.parse_args(argv)
    corr, report = build_correspondence()
    if not args.no_calibration:
        from dataclasses import replace

        from ..facemodel.open_head import open_head
        from .calibrate import calibrate

        offsets, report["calibration"] = calibrate(open_head(), corr, progress=print)
        corr = replace(corr, offsets=offsets)
    write_correspondence(corr, args.out)
    print(report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
