"""A random but well-formed, head-sized avatar with FLAME's joints, so every path runs before training exists.

The head is an ellipsoid (about 15 x 20 x 18 cm) on a neck, in FLAME's world frame (metres, y up, face towards
+z). Gaussians lie on the surface as flat discs; colours are skin with darker eyes and red lips; LBS weights are
soft (every joint has a small weight everywhere) and dominated by the anatomically right joint; each blendshape
is a smooth local bump on the face that changes all five properties, plus a small global term, so no
(Gaussian, blendshape) pair is zero (the dense case). Upper and lower teeth are two arcs of mouth Gaussians.

A library module, not a tool: the native backend's SIMD self-check, the service's warm-up and demo avatar, the
benchmarks and the tests all build avatars here (``render_core.tools.synth`` re-exports it for the commands).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..avatar import FLAME_JOINTS, FLAME_MOUTH_JOINTS, FLAME_PARENTS, Avatar, Gaussians, sh_coeff_count
from ..camera import front_camera
from ..errors import OptionError
from ..rotation import matrix_to_quat

SH_C0 = 0.28209479177387814
HEAD_RADII = (0.075, 0.10, 0.09)
JOINT_POSITIONS = (
    (0.0, -0.09, -0.02),  # root: base of the skull
    (0.0, -0.06, -0.02),  # neck
    (0.0, -0.03, 0.01),  # jaw hinge
    (0.032, 0.025, 0.065),  # eye_l (subject's left, +x)
    (-0.032, 0.025, 0.065),  # eye_r
)
EYE_RADIUS = 0.014
SKIN, LIPS, IRIS = (0.78, 0.58, 0.47), (0.7, 0.3, 0.3), (0.12, 0.08, 0.06)
TEETH, HAIR = (0.92, 0.9, 0.85), (0.2, 0.14, 0.1)


def _frame_from_normal(n: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] whose third column is the unit normal n [N, 3]."""
    helper = torch.where(n[:, 1:2].abs() < 0.9, torch.tensor([0.0, 1.0, 0.0]), torch.tensor([1.0, 0.0, 0.0]))
    a = torch.nn.functional.normalize(torch.linalg.cross(helper, n), dim=-1)
    b = torch.linalg.cross(n, a)
    return torch.stack([a, b, n], dim=-1)


def _rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def _head_points(n: int, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """n points and unit normals: 80% on the head ellipsoid, 20% on the neck cylinder."""
    n_neck = n // 5
    n_head = n - n_neck
    d = torch.nn.functional.normalize(torch.randn(n_head, 3, generator=g), dim=-1)
    radii = torch.tensor(HEAD_RADII)
    head = d * radii
    head_n = torch.nn.functional.normalize(d / radii, dim=-1)
    ang = torch.rand(n_neck, generator=g) * 2 * math.pi
    y = -0.075 - torch.rand(n_neck, generator=g) * 0.08
    neck_n = torch.stack([torch.sin(ang), torch.zeros_like(ang), torch.cos(ang)], dim=-1)
    neck = neck_n * 0.05 + torch.stack([torch.zeros_like(y), y, torch.full_like(y, -0.02)], dim=-1)
    return torch.cat([head, neck]), torch.cat([head_n, neck_n])


def _lbs_weights(x: Tensor) -> Tensor:
    """Soft, dominant-joint weights [N, 5] over FLAME's joints."""
    logits = torch.zeros(len(x), 5)
    jaw_region = (x[:, 1] < -0.025) & (x[:, 2] > 0.0) & (x[:, 1] > -0.11)
    neck_region = x[:, 1] < -0.08
    logits[:, 0] = 2.0
    logits[:, 1] = torch.where(neck_region, 8.0, 0.0)
    logits[:, 2] = torch.where(jaw_region & ~neck_region, 8.0, 0.0)
    for j in (3, 4):
        dist = (x - torch.tensor(JOINT_POSITIONS[j])).norm(dim=-1)
        logits[:, j] = torch.where(dist < 2 * EYE_RADIUS, 9.0, 0.0)
    return torch.softmax(logits, dim=-1)


def _colours(x: Tensor) -> Tensor:
    rgb = torch.tensor(SKIN).expand(len(x), 3).clone()
    mouth_dist = ((x[:, 0] / 0.025) ** 2 + ((x[:, 1] + 0.04) / 0.008) ** 2)
    rgb[(mouth_dist < 1.0) & (x[:, 2] > 0)] = torch.tensor(LIPS)
    for j in (3, 4):
        rgb[(x - torch.tensor(JOINT_POSITIONS[j])).norm(dim=-1) < EYE_RADIUS * 1.6] = torch.tensor(IRIS)
    rgb[(x[:, 1] > 0.05) | ((x[:, 2] < -0.02) & (x[:, 1] > -0.04))] = torch.tensor(HAIR)
    return rgb


def _teeth(m: int, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """m Gaussians on two arcs behind the lips: upper (group 0) and lower (group 1)."""
    group = (torch.arange(m) >= m // 2).long()
    u = torch.rand(m, generator=g) * 2 - 1
    x = 0.022 * u
    z = 0.072 - 0.02 * u**2
    y = torch.where(group == 0, -0.036, -0.046) + (torch.rand(m, generator=g) - 0.5) * 0.006
    return torch.stack([x, y, z], dim=-1), group


def synth_avatar(
    gaussians: int = 10_000,
    blendshapes: int = 50,
    seed: int = 0,
    sh_degree: int = 3,
    mouth: int | None = None,
    raster_mode: str = "classic",
    local: bool = False,
) -> Avatar:
    """A random, head-sized avatar with ``gaussians`` face Gaussians and ``blendshapes`` expressions.

    ``mouth`` mouth-interior Gaussians (default: gaussians // 8, at least 2). Deterministic for a seed.
    Each blendshape is a smooth bump (2-4 cm) on the front of the face. By default every (Gaussian, blendshape)
    pair also gets a small global term, so no pair is zero (the dense worst case of the benchmarks); ``local``
    gives each blendshape compact support instead, as a face model's has: the bump is cut where it falls below
    1e-3 and Gaussians outside it (the back of the head, most of the face) have exactly zero deltas.
    """
    if gaussians < 1:
        raise OptionError(f"need at least one Gaussian, got {gaussians}", field="gaussians")
    if blendshapes < 0:
        raise OptionError(f"must not be negative, got {blendshapes}", field="blendshapes")
    if mouth is not None and mouth < 0:
        raise OptionError(f"must not be negative, got {mouth}", field="mouth")
    g = torch.Generator().manual_seed(seed)
    n, k, c = gaussians, blendshapes, sh_coeff_count(sh_degree)
    m = max(2, gaussians // 8) if mouth is None else mouth

    x, normal = _head_points(n, g)
    area = 4 * math.pi * 0.088**2 + 2 * math.pi * 0.05 * 0.08
    s = math.sqrt(area / n) * 0.9
    log_scales = torch.log(torch.tensor([s, s, 0.25 * s])).expand(n, 3) + 0.1 * torch.randn(n, 3, generator=g)
    quats = matrix_to_quat(_frame_from_normal(normal))
    sh = torch.zeros(n, c, 3)
    sh[:, 0] = _rgb_to_sh_dc((_colours(x) + 0.04 * torch.randn(n, 3, generator=g)).clamp(0, 1))
    if c > 1:
        sh[:, 1:] = 0.04 * torch.randn(n, c - 1, 3, generator=g)
    neutral = Gaussians(x, quats, log_scales, torch.full((n,), 3.0) + torch.randn(n, generator=g), sh)

    # Blendshapes: a smooth local bump on the front of the face per k, plus a small global term.
    centres = torch.nn.functional.normalize(
        torch.randn(k, 3, generator=g) * torch.tensor([0.6, 0.5, 0.3]) + torch.tensor([0.0, -0.1, 1.0]), dim=-1
    ) * torch.tensor(HEAD_RADII)
    radius = 0.02 + 0.02 * torch.rand(k, 1, generator=g)
    falloff = torch.exp(-((x[None] - centres[:, None]) ** 2).sum(-1) / (2 * radius**2))  # [K, N]
    direction = torch.nn.functional.normalize(torch.randn(k, 1, 3, generator=g), dim=-1)
    magnitude = 0.004 + 0.006 * torch.rand(k, 1, 1, generator=g)
    noise, floor = (0.0, 0.0) if local else (1e-5, 0.01)
    if local:
        falloff = torch.where(falloff < 1e-3, 0.0, falloff)
    f = falloff[..., None]
    deltas = Gaussians(
        means=f * direction * magnitude + noise * torch.randn(k, n, 3, generator=g),
        quats=(f + floor) * 0.03 * torch.randn(k, n, 4, generator=g),
        log_scales=(f + floor) * 0.05 * torch.randn(k, n, 3, generator=g),
        opacity_logits=(falloff + floor) * 0.2 * torch.randn(k, n, generator=g),
        sh=(f[..., None] + floor) * 0.1 * torch.randn(k, n, c, 3, generator=g),
    )

    # Eyelids close downwards over each eye; pose correctives are small and smooth.
    eyelids = torch.zeros(2, n, 3)
    for i, j in enumerate((3, 4)):
        near = torch.exp(-((x - torch.tensor(JOINT_POSITIONS[j])) ** 2).sum(-1) / (2 * (1.2 * EYE_RADIUS) ** 2))
        eyelids[i, :, 1] = -0.006 * near * (x[:, 1] > JOINT_POSITIONS[j][1]).float()
    pose_correctives = 1e-3 * torch.randn(9 * 4, 1, 3, generator=g) * torch.cos(40 * x[None, :, 1:2])

    tx, group = _teeth(m, g)
    mq = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(m, 4).clone()
    msh = torch.zeros(m, c, 3)
    msh[:, 0] = _rgb_to_sh_dc(torch.tensor(TEETH))
    mouth_g = Gaussians(tx, mq, torch.log(torch.tensor([0.002, 0.003, 0.001])).expand(m, 3).clone(),
                        torch.full((m,), 3.0), msh)

    avatar = Avatar(
        neutral=neutral,
        deltas=deltas,
        lbs_weights=_lbs_weights(x),
        joint_positions=torch.tensor(JOINT_POSITIONS),
        joint_names=list(FLAME_JOINTS),
        joint_parents=list(FLAME_PARENTS),
        expression_names=[f"exp_{i:02d}" for i in range(k)],
        mouth=mouth_g,
        mouth_group=group,
        mouth_joint_names=FLAME_MOUTH_JOINTS,
        pose_correctives=pose_correctives,
        eyelid_offsets=eyelids,
        sh_degree=sh_degree,
        face_model="synthetic-flame",
        raster_mode=raster_mode,  # type: ignore[arg-type]
        default_camera=front_camera(512, 512).to_dict(),
        provenance={"generator": "blendsplat bundle synth", "seed": seed},
    )
    avatar.validate()
    return avatar
