"""An animatable avatar straight from a face model (docs/method.md section 3, computed per Gaussian, no grid).

- Positions: Poisson-disk samples of the neutral mesh (:func:`poisson_disk`: weighted sample elimination of 5 N
  area-weighted candidates down to exactly N; no two samples closer than about 0.69 of the hexagonal-packing
  spacing for N samples on that area).
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

from ..avatar import Avatar, Gaussians, sh_coeff_count
from ..camera import front_camera
from ..errors import OptionError
from ..facemodel import FaceModel
from ..rotation import matrix_to_quat, quat_multiply
from ..sh import rotate_sh

SKIN = (0.80, 0.62, 0.52)
MOUTH = (0.12, 0.05, 0.05)


def poisson_disk(vertices: Tensor, faces: Tensor, n: int, generator: torch.Generator,
                 candidates: int = 5) -> tuple[Tensor, Tensor]:
    """Exactly ``n`` Poisson-disk samples of a triangle mesh by weighted sample elimination (Yuksel 2015).

    ``candidates`` x n uniform (area-weighted) surface samples are thinned to n: each candidate i carries the weight
    w_i = sum_j (1 - d_ij / 2r)^8 over the candidates j closer than 2r (Euclidean distance, d_ij clamped below at
    2 r_min = 2r (1 - (n / m)^1.5) 0.65: Yuksel's weight limiting), r = sqrt(A / (2 sqrt(3) n)) being the largest
    Poisson-disk radius n samples can have on area A (hexagonal packing at spacing 2r). Yuksel removes the heaviest
    sample and updates its neighbours' weights, one at a time (a heap). Here each round removes, together, the
    samples that are among the (remaining - n) heaviest and heavier than all their remaining neighbours (ties: the
    larger index): no two are neighbours, so their removals do not interact, and they are samples the sequential
    order would take next. On the open head (5 n candidates) the closest pair ends at about 0.69 x 2r and the
    median nearest-neighbour distance at 0.78 x 2r; 64k samples take about 3.5 s of one CPU core (30 to 60 rounds).
    Deterministic for a given ``generator``.

    Returns:
        (triangle index [n] int64, barycentric [n, 3]) in the vertices' dtype.
    """
    v = vertices
    tri = v[faces]  # [F, 3, 3]
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).norm(dim=1)
    m = max(candidates * n, n)
    t = torch.multinomial(area.double(), m, replacement=True, generator=generator)
    u, w = torch.rand(m, generator=generator, dtype=v.dtype), torch.rand(m, generator=generator, dtype=v.dtype)
    su = u.sqrt()
    bary = torch.stack([1 - su, su * (1 - w), su * w], 1)
    if m == n:
        return t, bary
    x = (tri[t] * bary[..., None]).sum(1).double()
    r_max = math.sqrt(float(area.sum()) / (2 * math.sqrt(3) * n))
    r_min = r_max * (1 - (n / m) ** 1.5) * 0.65
    i, j, d = _close_pairs(x, 2 * r_max)
    pw = (1 - d.clamp_min(2 * r_min) / (2 * r_max)) ** 8
    weight = torch.zeros(m, dtype=torch.float64).index_add_(0, i, pw).index_add_(0, j, pw)
    alive = torch.ones(m, dtype=torch.bool)
    count = m
    while count > n:
        wi, wj = weight[i], weight[j]
        j_wins = (wj > wi) | ((wj == wi) & (j > i))  # ties: the larger index is the heavier
        beaten = torch.zeros(m, dtype=torch.bool)
        beaten[i[j_wins]] = True
        beaten[j[~j_wins]] = True
        # Local maxima among the (count - n) heaviest: the ones sequential elimination would take next.
        live = weight[alive]
        need = count - n
        floor = torch.kthvalue(live, len(live) - need + 1).values if need < len(live) else live.min()
        heaviest = (alive & ~beaten & (weight >= floor)).nonzero().flatten()
        if len(heaviest) > count - n:
            order = torch.argsort(weight[heaviest], descending=True, stable=True)
            heaviest = heaviest[order[: count - n]]
        gone = torch.zeros(m, dtype=torch.bool)
        gone[heaviest] = True
        alive[heaviest] = False
        count -= len(heaviest)
        gi, gj = gone[i], gone[j]
        weight.index_add_(0, j[gi], -pw[gi]).index_add_(0, i[gj], -pw[gj])
        keep = ~(gi | gj)
        i, j, pw = i[keep], j[keep], pw[keep]
    kept = alive.nonzero().flatten()
    return t[kept], bary[kept]


def _close_pairs(x: Tensor, radius: float, chunk: int = 1 << 14) -> tuple[Tensor, Tensor, Tensor]:
    """Every pair (i < j) of points [P, 3] closer than ``radius``: (i, j, distance), through a hash grid of cell
    ``radius`` (each point against the later points of its own cell and all points of 13 of the 26 neighbouring
    cells, so each pair comes once). Distances in float32 (relative to the points' bounding box corner)."""
    rel = x - x.min(0).values
    cell = torch.floor(rel / radius).long() + 1  # >= 1: neighbours never wrap
    dims = cell.max(0).values + 2
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = torch.argsort(key, stable=True)
    sorted_key = key[order]
    px, py, pz = rel[order].float().t().contiguous()  # coordinates in the sorted order
    offsets = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]
    shift = torch.tensor([(a * dims[1] + b) * dims[2] + c for a, b, c in [(0, 0, 0)] + offsets])  # [14]
    r2 = radius * radius
    out_i, out_j, out_d = [], [], []
    for rows in torch.arange(len(x)).split(chunk):  # rows: positions in the sorted order
        k = sorted_key[rows][:, None] + shift[None]  # [c, 14]
        lo = torch.searchsorted(sorted_key, k)
        hi = torch.searchsorted(sorted_key, k, right=True)
        lo[:, 0] = rows + 1  # own cell: only the later points
        count = (hi - lo).clamp_min(0).flatten()
        total = int(count.sum())
        a = rows.repeat_interleave(14 * torch.ones(len(rows), dtype=torch.long)).repeat_interleave(count) \
            if total else rows[:0]
        b = lo.flatten().repeat_interleave(count) + torch.arange(total) - \
            (torch.cumsum(count, 0) - count).repeat_interleave(count)
        d2 = (px[a] - px[b]).square() + (py[a] - py[b]).square() + (pz[a] - pz[b]).square()
        near = d2 < r2
        a, b = order[a[near]], order[b[near]]
        out_i.append(torch.minimum(a, b))
        out_j.append(torch.maximum(a, b))
        out_d.append(d2[near].sqrt().double())
    return torch.cat(out_i), torch.cat(out_j), torch.cat(out_d)


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
        raise OptionError(f"need at least one face Gaussian and two mouth Gaussians, got {gaussians} and {mouth}",
                          field="gaussians" if gaussians < 1 else "mouth")
    g = torch.Generator().manual_seed(seed)
    verts, faces = model.template.double(), model.faces
    tri_idx, bary = poisson_disk(verts, faces, gaussians, g)
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
