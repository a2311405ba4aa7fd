"""An animatable avatar straight from a face model (METHOD.md section 3, computed per Gaussian, no grid).

- Positions: blue-noise samples of the neutral mesh (area-weighted candidates thinned on a grid whose cell is
  sized for the requested count, so no two samples share a cell; then trimmed to exactly N). This approximates
  Poisson-disk sampling (close pairs are rarer than with uniform samples) without its minimum-distance guarantee.
- Each Gaussian knows its triangle and barycentric coordinates: LBS weights, pose correctives and eyelid offsets
  are the barycentric blend of the triangle's vertex values.
- Expression deltas: for each blendshape k, the triangle's deformation gradient from M0 to M_k (a fourth vertex
  along the scaled normal, as in deformation transfer) and its rotation (polar decomposition). The position
  delta is the surface point's own displacement; the rotation delta rotates the Gaussian (dq = q(R) q0 - q0);
  the SH delta rotates its colour (dSH = rot(SH) - SH). Scale and opacity start without deltas. Triangles a
  blendshape does not move give exactly zero deltas, so those pairs are never stored by the native backend.
- Rest properties as in 3DGS, but flattened on the surface: tangent-aligned discs sized to the sample spacing,
  thin along the normal; opacity 0.1 for training (``opacity``), colour from ``albedo`` (or a skin tone).
- Mouth interior: two dark billboards behind the lips, the upper one on the skull joint, the lower on the jaw.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from .avatar import Avatar, Gaussians, sh_coeff_count
from .camera import front_camera
from .facemodel import FaceModel
from .rotation import matrix_to_quat, quat_multiply
from .sh import rotate_sh

SKIN = (0.80, 0.62, 0.52)
MOUTH = (0.12, 0.05, 0.05)


def _sample_surface(vertices: Tensor, faces: Tensor, n: int, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """Exactly ``n`` well-spaced points on the mesh: (triangle index [n], barycentric [n, 3])."""
    tri = vertices[faces]  # [F, 3, 3]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1)
    total = float(area.sum())
    m = 6 * n
    t = torch.multinomial(area, m, replacement=True, generator=g)
    u, v = torch.rand(m, generator=g), torch.rand(m, generator=g)
    su = u.sqrt()
    bary = torch.stack([1 - su, su * (1 - v), su * v], 1)
    x = (tri[t] * bary[..., None]).sum(1)
    # Thin: one candidate per grid cell, the cell sized so that about n cells are occupied.
    cell = math.sqrt(total / n) * 0.75
    for _ in range(30):
        keys = torch.floor(x / cell).long()
        keys = (keys[:, 0] * 73856093) ^ (keys[:, 1] * 19349663) ^ (keys[:, 2] * 83492791)
        _, first = torch.unique(keys, return_inverse=True)
        winner = torch.full((int(first.max()) + 1,), m, dtype=torch.long).scatter_reduce(
            0, first, torch.arange(m), reduce="amin")
        if len(winner) >= n:
            break
        cell *= 0.9
    chosen = winner[torch.randperm(len(winner), generator=g)[:n]]
    return t[chosen], bary[chosen]


def _tangent_frames(tri: Tensor) -> tuple[Tensor, Tensor]:
    """Per triangle: rotation [F, 3, 3] with columns (edge, bitangent, normal) and the unit normal."""
    e1 = tri[:, 1] - tri[:, 0]
    n = torch.nn.functional.normalize(torch.linalg.cross(e1, tri[:, 2] - tri[:, 0]), dim=1)
    t = torch.nn.functional.normalize(e1, dim=1)
    b = torch.linalg.cross(n, t)
    return torch.stack([t, b, n], dim=2), n


def _edge_frames(tri: Tensor) -> Tensor:
    """[F, 3, 3] with columns (e1, e2, n / sqrt|n|): the triangle frames of deformation transfer (the fourth
    vertex along the normal scaled so that the frame changes as the triangle's size does)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nrm = torch.linalg.cross(e1, e2)
    e3 = nrm / nrm.norm(dim=1, keepdim=True).clamp_min(1e-20).sqrt()
    return torch.stack([e1, e2, e3], dim=2)


def _polar_rotation(f: Tensor) -> Tensor:
    """The rotation of the polar decomposition of each [.., 3, 3] deformation gradient (via SVD, det +1)."""
    u, _, vh = torch.linalg.svd(f)
    d = torch.sign(torch.linalg.det(u @ vh))
    u = torch.cat([u[..., :2], u[..., 2:] * d[:, None, None]], dim=2)
    return u @ vh


def init_avatar(
    model: FaceModel,
    gaussians: int = 50_000,
    mouth: int = 4_000,
    sh_degree: int = 3,
    opacity: float = 0.1,
    albedo: Callable[[Tensor], Tensor] | None = None,
    seed: int = 0,
) -> Avatar:
    """A Gaussian blendshape avatar initialised from ``model`` (every blendshape and joint of the model).

    ``albedo`` maps rest positions [N, 3] to linear RGB [N, 3] (default: a uniform skin tone).
    """
    if gaussians < 1 or mouth < 2:
        raise ValueError("need at least one face Gaussian and two mouth Gaussians")
    g = torch.Generator().manual_seed(seed)
    verts, faces = model.template.double(), model.faces
    tri_idx, bary = _sample_surface(verts, faces, gaussians, g)
    corners = faces[tri_idx]  # [N, 3]

    def interp(values: Tensor) -> Tensor:  # [..., V, C] -> [..., N, C]
        return (values[..., corners, :] * bary[..., None].to(values.dtype)).sum(-2)

    x = interp(verts)
    frames, _ = _tangent_frames(verts[faces])
    q0 = matrix_to_quat(frames[tri_idx].float())
    area = 0.5 * torch.linalg.cross(verts[faces][:, 1] - verts[faces][:, 0],
                                    verts[faces][:, 2] - verts[faces][:, 0]).norm(dim=1)
    spacing = math.sqrt(float(area.sum()) / gaussians)
    c = sh_coeff_count(sh_degree)
    sh = torch.zeros(gaussians, c, 3)
    rgb = albedo(x.float()) if albedo is not None else torch.tensor(SKIN).expand(gaussians, 3)
    sh[:, 0] = (rgb.clamp(0, 1) - 0.5) / 0.28209479177387814
    log_scales = torch.log(torch.tensor([spacing, spacing, 0.2 * spacing])).expand(gaussians, 3).clone()
    logit = math.log(opacity / (1 - opacity))
    neutral = Gaussians(x.float(), q0, log_scales, torch.full((gaussians,), logit), sh)

    # Expression deltas through each triangle's deformation (rotation part) and the surface point's motion.
    k = model.num_expressions
    d_means = torch.zeros(k, gaussians, 3)
    d_quats = torch.zeros(k, gaussians, 4)
    d_sh = torch.zeros(k, gaussians, c, 3)
    used, slot = torch.unique(tri_idx, return_inverse=True)  # the triangles Gaussians sit on
    rest_frames_inv = torch.linalg.inv(_edge_frames(verts[faces[used]]))
    for i in range(k):
        disp = model.expression_basis[i].double()
        moved = disp[faces[used]].abs().amax(dim=(1, 2)) > 0  # used triangles this target moves
        moved_tri = moved[slot]  # per Gaussian
        if not bool(moved_tri.any()):
            continue
        rot_used = torch.eye(3, dtype=torch.float64).expand(len(used), 3, 3).clone()
        rot_used[moved] = _polar_rotation(_edge_frames((verts + disp)[faces[used[moved]]]) @ rest_frames_inv[moved])
        rot = rot_used[slot].float()  # [N, 3, 3]
        d_means[i] = interp(disp).float() * moved_tri[:, None]
        qk = quat_multiply(matrix_to_quat(rot), q0)
        qk = torch.where((qk * q0).sum(-1, keepdim=True) < 0, -qk, qk)  # the same hemisphere as q0
        d_quats[i] = (qk - q0) * moved_tri[:, None]
        if c > 1 and bool(sh[:, 1:].any()):  # a rotation maps each band onto itself: zero bands stay zero
            d_sh[i] = (rotate_sh(sh, rot) - sh) * moved_tri[:, None, None]
    deltas = Gaussians(d_means, d_quats, torch.zeros(k, gaussians, 3), torch.zeros(k, gaussians), d_sh)

    pose_correctives = interp(model.pose_correctives.double()).float() if model.pose_correctives is not None \
        else None
    eyelids = interp(model.eyelid_basis.double()).float() if model.eyelid_basis is not None else None
    lbs = interp(model.lbs_weights.double()).float()
    lbs = lbs / lbs.sum(1, keepdim=True)

    mouth_g, group = _mouth_billboards(model, mouth, sh_degree, g)
    avatar = Avatar(
        neutral=neutral, deltas=deltas, lbs_weights=lbs, joint_positions=model.joint_positions.float(),
        joint_names=list(model.joint_names), joint_parents=list(model.joint_parents),
        expression_names=list(model.expression_names), mouth=mouth_g, mouth_group=group,
        mouth_joint_names=(model.skull_joint, "jaw"), pose_correctives=pose_correctives, eyelid_offsets=eyelids,
        sh_degree=sh_degree, face_model=model.name, default_camera=_framing(x.float()).to_dict(),
        provenance={"generator": "blendsplat bundle init", "face_model": model.name, "seed": seed,
                    "face_model_licence": model.licence},
    )
    avatar.validate()
    return avatar


def _mouth_billboards(model: FaceModel, m: int, sh_degree: int, g: torch.Generator) -> tuple[Gaussians, Tensor]:
    """Two dark 4 x 1.5 cm billboards facing forward behind the lips: upper (skull joint) and lower (jaw)."""
    t = model.template
    front = t[:, 2] > t[:, 2].max() - 0.03
    jaw = model.joint_positions[model.joint_names.index("jaw")]
    lips = front & ((t[:, 1] - jaw[1]).abs() < 0.03) & (t[:, 0].abs() < 0.02)
    centre = t[lips].mean(0) if bool(lips.any()) else t.mean(0)
    centre = centre - torch.tensor([0.0, 0.0, 0.012])
    half = m // 2
    out_x, groups = [], []
    for grp, dy in ((0, 0.0075), (1, -0.0075)):
        count = half if grp == 0 else m - half
        uv = torch.rand(count, 2, generator=g) * torch.tensor([0.04, 0.015]) - torch.tensor([0.02, 0.0075])
        out_x.append(centre + torch.stack([uv[:, 0], uv[:, 1] + dy, torch.zeros(count)], 1))
        groups.append(torch.full((count,), grp, dtype=torch.long))
    x = torch.cat(out_x)
    c = sh_coeff_count(sh_degree)
    sh = torch.zeros(m, c, 3)
    sh[:, 0] = (torch.tensor(MOUTH) - 0.5) / 0.28209479177387814
    s = math.sqrt(0.04 * 0.015 * 2 / m)
    mouth = Gaussians(x, torch.tensor([1.0, 0, 0, 0]).expand(m, 4).clone(),
                      torch.log(torch.tensor([s, s, 0.3 * s])).expand(m, 3).clone(), torch.full((m,), 2.0), sh)
    return mouth, torch.cat(groups)


def _framing(x: Tensor):
    """A front camera at 512 x 512 looking at the origin (the head's centre), the head filling most of the view
    (the neck below the chin may leave it)."""
    extent = float(x[:, 0].abs().max()) * 1.25  # the head's half width, plus room for the head's height
    focal = float(front_camera(512, 512).K[0, 0, 0])
    return front_camera(512, 512, distance=focal * extent / (0.85 * 256) + float(x[:, 2].max()))



def demo_albedo(model: FaceModel) -> Callable[[Tensor], Tensor]:
    """Colours for an untrained demo avatar: skin with redder lips, dark brows, eyes with irises, white teeth and
    a pink tongue, lit once from the upper left (baked), so that expressions read without training."""
    t = model.template
    tri = t[model.faces]
    fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = torch.zeros_like(t).index_add_(0, model.faces.flatten(), fn.repeat_interleave(3, 0))
    vn = torch.nn.functional.normalize(vn, dim=1)
    colour = torch.tensor(SKIN).expand(len(t), 3).clone()
    names = model.expression_names
    motion = {n: model.expression_basis[names.index(n)].norm(dim=1) for n in names}

    def strongest(*targets: str) -> Tensor:
        m = torch.stack([motion[n] for n in targets if n in motion]).amax(0) if any(n in motion for n in targets) \
            else torch.zeros(len(t))
        return m > 0.6 * float(m.max()) if float(m.max()) > 0 else m > 0

    front = t[:, 2] > 0
    lips = strongest("mouthRollLower", "mouthRollUpper") & front & (t[:, 0].abs() < 0.028)
    colour[lips] = torch.tensor([0.72, 0.38, 0.38])
    brows = strongest("browInnerUp", "browOuterUpLeft", "browOuterUpRight") & front
    colour[brows & (t[:, 1] > float(model.joint_positions[4:, 1].max()) + 0.012)] = torch.tensor([0.25, 0.18, 0.14])
    groups = model.vertex_groups
    for side, j in (("eyeball_l", "eye_l"), ("eyeball_r", "eye_r")):
        if side in groups and j in model.joint_names:
            idx = groups[side]
            d = torch.nn.functional.normalize(t[idx] - model.joint_positions[model.joint_names.index(j)], dim=1)
            colour[idx] = torch.where((d[:, 2] > 0.9)[:, None], torch.tensor([0.08, 0.06, 0.05]),
                                      torch.where((d[:, 2] > 0.75)[:, None], torch.tensor([0.25, 0.35, 0.45]),
                                                  torch.tensor([0.92, 0.9, 0.88])))
    for name, rgb in (("teeth_upper", (0.93, 0.92, 0.86)), ("teeth_lower", (0.93, 0.92, 0.86)),
                      ("tongue", (0.75, 0.35, 0.38))):
        if name in groups:
            colour[groups[name]] = torch.tensor(rgb)
    light = torch.nn.functional.normalize(torch.tensor([0.4, 0.5, 0.75]), dim=0)
    lit = colour * (0.45 + 0.65 * (vn @ light).clamp_min(0))[:, None]

    def albedo(x: Tensor) -> Tensor:
        return lit[torch.cdist(x, t).argmin(1)] if len(x) <= 8192 else torch.cat(
            [albedo(chunk) for chunk in x.split(8192)])

    return albedo
