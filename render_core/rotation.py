"""Rotation helpers: axis-angle, 6D, quaternions (w first) and rotation matrices, batched over leading dims.

All functions are differentiable and work in float32 or float64.
"""

from __future__ import annotations

import torch
from torch import Tensor


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula: axis-angle [..., 3] -> rotation matrix [..., 3, 3]; exact identity at zero."""
    theta2 = (aa * aa).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    # sin(t)/t and (1 - cos t)/t^2 with Taylor series near zero.
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def rot6d_to_matrix(r6: Tensor) -> Tensor:
    """6D rotation [..., 6] (the first two rows of the matrix, as FLAME trackers store it; identity is
    1,0,0,0,1,0) -> rotation matrix [..., 3, 3], by Gram-Schmidt."""
    a1, a2 = r6[..., :3], r6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2)
    return torch.stack([b1, b2, b3], dim=-2)


def matrix_to_rot6d(m: Tensor) -> Tensor:
    """Rotation matrix [..., 3, 3] -> 6D [..., 6] (first two rows)."""
    return m[..., :2, :].reshape(*m.shape[:-2], 6)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Quaternion [..., 4] (w, x, y, z; normalised here) -> rotation matrix [..., 3, 3]."""
    q = torch.nn.functional.normalize(q, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(m: Tensor) -> Tensor:
    """Rotation matrix [..., 3, 3] -> unit quaternion [..., 4] (w, x, y, z) with w >= 0.

    Shepperd's method: the largest of the four candidate denominators is used, so it is stable everywhere.
    """
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
            torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
        ],
        dim=-2,
    )  # [..., 4 candidates, 4]
    diag = torch.stack([cands[..., i, i] for i in range(4)], -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best[..., None].expand(*best.shape, 4)).squeeze(-2)
    q = q / (2 * torch.gather(diag, -1, best).clamp_min(1e-12).sqrt())
    q = torch.nn.functional.normalize(q, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of w-first quaternions [..., 4] (rotation b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def inverse_transpose3(m: Tensor) -> Tensor:
    """(M^-1)^T of 3x3 matrices [..., 3, 3] by cofactors (cof(M) / det(M))."""
    c0 = torch.linalg.cross(m[..., 1, :], m[..., 2, :])
    c1 = torch.linalg.cross(m[..., 2, :], m[..., 0, :])
    c2 = torch.linalg.cross(m[..., 0, :], m[..., 1, :])
    cof = torch.stack([c0, c1, c2], dim=-2)
    det = (m[..., 0, :] * c0).sum(-1)[..., None, None]
    return cof / det


def orthogonalize(m: Tensor, iterations: int = 3) -> Tensor:
    """Nearest rotation to 3x3 matrices [..., 3, 3] (polar decomposition) by Newton's iteration
    R <- (R + R^-T) / 2, as the paper's reference code does (three iterations); exact for rotations."""
    for _ in range(iterations):
        m = 0.5 * (m + inverse_transpose3(m))
    return m
