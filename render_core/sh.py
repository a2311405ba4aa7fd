"""Real spherical harmonics (degrees 0-3) as 3DGS and gsplat use them: evaluation and rotation.

Conventions (identical to gsplat's ``spherical_harmonics`` and Inria's 3DGS): coefficients are stored
``[..., C, 3]`` with C = (degree + 1)^2, the DC term first, then band 1 (-y, z, -x), band 2 and band 3 in the
order and with the signs of :func:`sh_basis`. Directions are unit vectors (they are not normalised here).
The renderer adds 0.5 to the evaluated value and clamps at 0 (docs/method.md section 9 step 6); that happens in
:func:`render_core.deform.shade`, not here.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["SH_C0", "SH_C1", "SH_C2", "SH_C3", "eval_sh", "rotate_sh", "sh_basis", "sh_degree_of"]

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)

# Sample directions for rotate_sh: a 20-point Fibonacci sphere. The per-band basis matrices Y_l(P) have
# condition numbers 1.01 (l=1), 1.08 (l=2) and 1.40 (l=3), so the least-squares fit is exact to rounding.
_NUM_SAMPLES = 20
_ROTATION_CACHE: dict[tuple[torch.dtype, torch.device], tuple[Tensor, list[Tensor]]] = {}


def sh_degree_of(num_coeffs: int) -> int:
    """SH degree (0..3) for a per-channel coefficient count C in (1, 4, 9, 16)."""
    degrees = {1: 0, 4: 1, 9: 2, 16: 3}
    if num_coeffs not in degrees:
        raise ValueError(f"SH coefficient count must be 1, 4, 9 or 16, got {num_coeffs}")
    return degrees[num_coeffs]


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis functions evaluated at unit directions.

    Args:
        dirs: [..., 3] unit direction vectors (x, y, z).
        degree: SH degree, 0..3.

    Returns:
        [..., (degree + 1)^2] basis values, DC first, in gsplat's order and sign convention:
        band 1: -C1 y, C1 z, -C1 x; band 2: xy, yz, (2zz - xx - yy), xz, (xx - yy);
        band 3: y(3xx - yy), xyz, y(4zz - xx - yy), z(2zz - 3xx - 3yy), x(4zz - xx - yy), z(xx - yy),
        x(xx - 3yy); each times its constant (SH_C1, SH_C2, SH_C3).
    """
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(sh: Tensor, dirs: Tensor, degree: int | None = None) -> Tensor:
    """Evaluate SH colour functions along unit directions (without the +0.5 offset).

    Args:
        sh: [..., C, 3] coefficients, C in (1, 4, 9, 16), DC first.
        dirs: [..., 3] unit directions; leading dims broadcast against ``sh``'s.
        degree: evaluate only bands 0..degree (progressive SH in training); None uses every stored band.
            Must not exceed the stored degree.

    Returns:
        [..., 3] the value sum_c Y_c(dir) sh[c] per channel.
    """
    stored = sh_degree_of(sh.shape[-2])
    if degree is None:
        degree = stored
    if not 0 <= degree <= stored:
        raise ValueError(f"SH degree {degree} requested but only degree {stored} is stored")
    c = (degree + 1) ** 2
    basis = sh_basis(dirs.to(sh.dtype), degree)  # [..., c]
    return (basis.unsqueeze(-1) * sh[..., :c, :]).sum(-2)


def _fibonacci_sphere(n: int) -> Tensor:
    """n well-spread unit vectors [n, 3] (float64)."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = (1.0 - z * z).clamp_min(0.0).sqrt()
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def _rotation_samples(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, list[Tensor]]:
    """Sample directions P [S, 3] and per-band pseudo-inverses pinv(Y_l(P)) [2l+1, S] for l = 1..3 (index l),
    computed once in float64 and cached per dtype and device."""
    key = (dtype, device)
    if key not in _ROTATION_CACHE:
        p = _fibonacci_sphere(_NUM_SAMPLES)
        y = sh_basis(p, 3)
        pinvs = [torch.empty(0)] + [torch.linalg.pinv(y[:, n * n:(n + 1) ** 2]) for n in (1, 2, 3)]
        _ROTATION_CACHE[key] = (p.to(device, dtype), [m.to(device, dtype) for m in pinvs])
    return _ROTATION_CACHE[key]


def rotate_sh(sh: Tensor, R: Tensor) -> Tensor:
    """SH coefficients of a rotated colour function.

    Returns coefficients of f'(d) = f(R^T d), where f is the function ``sh`` encodes, so that
    ``eval_sh(rotate_sh(sh, R), d) == eval_sh(sh, R^T @ d)``: a Gaussian whose rest-frame colour is ``sh`` and
    which is rotated by R shows ``rotate_sh(sh, R)`` in world space.

    Each band l is rotated by a (2l+1)x(2l+1) matrix D_l = pinv(Y_l(P)) Y_l(P R), with P a fixed set of sample
    directions (rows): rotations map each band onto itself, so the least-squares fit is exact to rounding.
    Band 0 is unchanged.

    Args:
        sh: [..., C, 3] coefficients, C in (1, 4, 9, 16).
        R: [..., 3, 3] rotation matrices; leading dims broadcast against ``sh``'s.

    Returns:
        [broadcast(...), C, 3] rotated coefficients, in ``sh``'s dtype.
    """
    degree = sh_degree_of(sh.shape[-2])
    batch = torch.broadcast_shapes(sh.shape[:-2], R.shape[:-2])
    out = [sh[..., :1, :].expand(*batch, 1, 3)]
    if degree == 0:
        return out[0].clone()
    p, pinvs = _rotation_samples(sh.dtype, sh.device)
    y_rot = sh_basis(p @ R.to(sh.dtype), degree)  # rows p^T R = (R^T p)^T -> [..., S, C]
    for n in range(1, degree + 1):
        band = slice(n * n, (n + 1) ** 2)
        d = pinvs[n] @ y_rot[..., band]  # [..., 2l+1, 2l+1]
        out.append((d @ sh[..., band, :]).expand(*batch, 2 * n + 1, 3))
    return torch.cat(out, dim=-2)
