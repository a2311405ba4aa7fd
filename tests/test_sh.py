import math

import pytest
import torch

from render_core.rotation import axis_angle_to_matrix
from render_core.sh import SH_C0, SH_C1, eval_sh, rotate_sh, sh_basis


def _unit(n: int, dtype=torch.float64) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, dtype=dtype), dim=-1)


def _random_rotations(n: int, dtype=torch.float64) -> torch.Tensor:
    return axis_angle_to_matrix(torch.randn(n, 3, dtype=dtype) * 1.5)


def test_eval_sh_degree1_matches_hand_formula():
    sh = torch.randn(50, 4, 3, dtype=torch.float64)
    d = _unit(50)
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    want = SH_C0 * sh[:, 0] - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    torch.testing.assert_close(eval_sh(sh, d), want, rtol=0, atol=1e-12)
    assert SH_C0 == 0.28209479177387814 and SH_C1 == 0.4886025119029199


def test_basis_matches_gsplat_constants_at_axes():
    # Spot values of the gsplat basis: +z gives C0, C1 on coefficient 2, 2*C2[2] on 6 and 2*C3[3] on 12.
    b = sh_basis(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), 3)
    want = torch.zeros(16, dtype=torch.float64)
    want[0], want[2], want[6], want[12] = SH_C0, SH_C1, 2 * 0.31539156525252005, 2 * 0.3731763325901154
    torch.testing.assert_close(b, want, rtol=0, atol=1e-15)
    # +x: -C1 on coefficient 3, 0.5462... (xx - yy) on 8, -0.59 x(xx - 3yy) on 15, -0.457 x(-1) on 13.
    b = sh_basis(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), 3)
    assert b[3] == -SH_C1 and b[8] == 0.5462742152960396 and b[15] == -0.5900435899266435
    assert math.isclose(float(b[13]), 0.4570457994644658) and math.isclose(float(b[6]), -0.31539156525252005)


def test_basis_is_orthonormal_on_the_sphere():
    # Orthonormal real basis: a Monte-Carlo estimate of the Gram matrix over the sphere is the identity.
    d = _unit(400_000)
    y = sh_basis(d, 3)
    gram = (y.T @ y) * (4 * math.pi / len(d))
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), rtol=0, atol=2e-2)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_rotate_sh_matches_rotated_view_direction(degree):
    c = (degree + 1) ** 2
    sh = torch.randn(64, c, 3, dtype=torch.float64)
    rot = _random_rotations(64)
    d = _unit(64)
    got = eval_sh(rotate_sh(sh, rot), d)
    want = eval_sh(sh, (rot.transpose(-1, -2) @ d[:, :, None]).squeeze(-1))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-10)


def test_rotate_sh_round_trip():
    sh = torch.randn(32, 16, 3, dtype=torch.float64)
    rot = _random_rotations(32)
    back = rotate_sh(rotate_sh(sh, rot), rot.transpose(-1, -2))
    torch.testing.assert_close(back, sh, rtol=0, atol=1e-10)
    # It does rotate: the intermediate differs from the input.
    assert (rotate_sh(sh, rot) - sh).abs().max() > 1e-2


def test_rotate_sh_identity_and_band0():
    sh = torch.randn(10, 16, 3, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64).expand(10, 3, 3)
    torch.testing.assert_close(rotate_sh(sh, eye), sh, rtol=0, atol=1e-12)
    out = rotate_sh(sh, _random_rotations(10))
    assert torch.equal(out[:, 0], sh[:, 0])


def test_rotate_sh_broadcasts_and_float32():
    sh = torch.randn(5, 9, 3)
    rot = _random_rotations(4).float()
    out = rotate_sh(sh[None], rot[:, None])  # [4, 5, 9, 3]
    assert out.shape == (4, 5, 9, 3) and out.dtype == torch.float32
    d = _unit(1).float()
    want = eval_sh(sh[None], (rot.transpose(-1, -2) @ d[0])[:, None, :])
    torch.testing.assert_close(eval_sh(out, d[0]), want, rtol=0, atol=1e-5)


def test_degree_limited_evaluation_ignores_higher_bands():
    sh = torch.randn(20, 16, 3, dtype=torch.float64)
    d = _unit(20)
    changed = sh.clone()
    changed[:, 4:] = torch.randn(20, 12, 3, dtype=torch.float64) * 10
    torch.testing.assert_close(eval_sh(sh, d, degree=1), eval_sh(changed, d, degree=1), rtol=0, atol=0)
    torch.testing.assert_close(eval_sh(sh, d, degree=1), eval_sh(sh[:, :4], d), rtol=0, atol=0)
    assert (eval_sh(sh, d) - eval_sh(changed, d)).abs().max() > 1e-3
    with pytest.raises(ValueError):
        eval_sh(sh[:, :4], d, degree=2)
