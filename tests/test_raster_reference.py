"""The reference rasterizer against an independent per-pixel brute-force composite of docs/method.md section 9."""

import math

import numpy as np
import pytest
import torch

from render_core.camera import Cameras, intrinsics, look_at, orbit
from render_core.raster.reference import rasterize
from render_core.raster.splats import ShadedSplats


def _quat_to_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def brute_force(means, quats, scales, opacities, colors, K, R, t, W, H, bg, mode):
    """Section 9, one Gaussian and one pixel at a time, in float64 Python."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    gauss = []
    for i in range(len(means)):
        p = R @ means[i] + t
        x, y, z = p
        if z < 0.01:
            continue
        limx = (W - cx) / fx + 0.3 * W / (2 * fx), cx / fx + 0.3 * W / (2 * fx)
        limy = (H - cy) / fy + 0.3 * H / (2 * fy), cy / fy + 0.3 * H / (2 * fy)
        txc = z * min(limx[0], max(-limx[1], x / z))
        tyc = z * min(limy[0], max(-limy[1], y / z))
        J = np.array([[fx / z, 0, -fx * txc / z**2], [0, fy / z, -fy * tyc / z**2]])
        M = _quat_to_matrix(quats[i]) @ np.diag(scales[i])
        S = J @ R @ M @ M.T @ R.T @ J.T
        det0 = np.linalg.det(S)
        S = S + 0.3 * np.eye(2)
        det = np.linalg.det(S)
        if det <= 0:
            continue
        o = opacities[i] * (math.sqrt(max(det0 / det, 0)) if mode == "antialiased" else 1.0)
        if o < 1 / 255:
            continue
        e = min(3.33, math.sqrt(2 * math.log(255 * o)))
        rx, ry = math.ceil(e * math.sqrt(S[0, 0])), math.ceil(e * math.sqrt(S[1, 1]))
        mx, my = fx * x / z + cx, fy * y / z + cy
        if rx <= 0 or ry <= 0 or mx + rx <= 0 or mx - rx >= W or my + ry <= 0 or my - ry >= H:
            continue
        tw, th = math.ceil(W / 16), math.ceil(H / 16)
        tile_x = (min(max(0, math.floor((mx - rx) / 16)), tw), min(max(0, math.ceil((mx + rx) / 16)), tw))
        tile_y = (min(max(0, math.floor((my - ry) / 16)), th), min(max(0, math.ceil((my + ry) / 16)), th))
        gauss.append((z, i, np.array([mx, my]), np.linalg.inv(S), o, tile_x, tile_y))
    gauss.sort(key=lambda g: (g[0], g[1]))
    rgb, alpha, depth = np.zeros((H, W, 3)), np.zeros((H, W)), np.zeros((H, W))
    for py in range(H):
        for px in range(W):
            T, C, D = 1.0, np.zeros(3), 0.0
            for z, i, m, inv, o, (tx0, tx1), (ty0, ty1) in gauss:
                if not (tx0 <= px // 16 < tx1 and ty0 <= py // 16 < ty1):
                    continue
                d = m - np.array([px + 0.5, py + 0.5])
                sigma = 0.5 * d @ inv @ d
                a = min(0.999, o * math.exp(-sigma))
                if sigma < 0 or a < 1 / 255:
                    continue
                next_t = T * (1 - a)
                if next_t <= 1e-4:
                    break
                C += colors[i] * a * T
                D += z * a * T
                T = next_t
            rgb[py, px] = C + T * bg
            alpha[py, px] = 1 - T
            depth[py, px] = D
    return rgb, alpha, depth


def _scene(n, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([0.06, 0.05, 0.08], dtype=dtype)
    # A few hard cases: behind the camera, straddling the near plane, far off-image, very large.
    means[0] = torch.tensor([0.0, 0.0, 0.7], dtype=dtype)  # behind the camera (camera at z = 0.6)
    means[1] = torch.tensor([0.0, 0.0, 0.595], dtype=dtype)  # z_cam = 0.005 < near plane
    means[2] = torch.tensor([0.5, 0.0, 0.0], dtype=dtype)  # well outside the image
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.6) * 0.006
    scales[3] = 0.05
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.97
    opac[4] = 0.002  # below 1/255: culled
    opac[5] = 0.999
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


def _check(cams, mode, n=60, seed=0, bg=(0.2, 0.3, 0.4)):
    means, quats, scales, opac, colors = _scene(n, seed)
    background = torch.tensor(bg, dtype=torch.float64)
    splats = ShadedSplats(*(t[None].expand(len(cams), *t.shape) for t in (means, quats, scales, opac, colors)))
    out = rasterize(splats, cams.to(torch.float64), background, mode)
    for b in range(len(cams)):
        rgb, alpha, depth = brute_force(
            means.numpy(), quats.numpy(), scales.numpy(), opac.numpy(), colors.numpy(),
            cams.K[b].double().numpy(), cams.R[b].double().numpy(), cams.t[b].double().numpy(),
            cams.width, cams.height, np.array(bg), mode)
        np.testing.assert_allclose(out.rgb[b].numpy(), rgb, atol=1e-5, rtol=0)
        np.testing.assert_allclose(out.alpha[b].numpy(), alpha, atol=1e-5, rtol=0)
        np.testing.assert_allclose(out.depth[b].numpy(), depth, atol=1e-5, rtol=0)
    return out


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_matches_brute_force_on_odd_sizes_and_several_cameras(mode):
    cams = orbit([0.0, 35.0, -20.0], [0.0, 10.0, -15.0], width=37, height=29, focal=60.0)
    out = _check(cams, mode)
    assert float(out.alpha.max()) > 0.5  # the scene is not empty: the comparison means something


def test_matches_brute_force_with_off_centre_principal_point_and_dense_overlap():
    R, t = look_at(torch.tensor([[0.02, -0.01, 0.45]]), torch.zeros(1, 3))
    K = intrinsics(48, 40, 80.0)
    K[0, 2], K[1, 2] = 30.0, 14.0
    cams = Cameras(K[None], R, t, 48, 40)
    out = _check(cams, "classic", n=400, seed=5, bg=(1.0, 1.0, 1.0))
    assert float(out.alpha.max()) > 0.99  # the transmittance stop is exercised


def test_autograd_path_renders_the_same_image():
    cams = orbit([0.0, 25.0], width=33, height=21, focal=50.0)
    args = [t[None].expand(2, *t.shape).clone() for t in _scene(80, 2, torch.float32)]
    plain = rasterize(ShadedSplats(*args), cams, torch.tensor([0.5, 0.5, 0.5]))
    graded = rasterize(ShadedSplats(*[t.requires_grad_() for t in args]), cams, torch.tensor([0.5, 0.5, 0.5]))
    assert graded.rgb.requires_grad
    for a, b in ((plain.rgb, graded.rgb), (plain.alpha, graded.alpha), (plain.depth, graded.depth)):
        torch.testing.assert_close(a, b.detach(), atol=1e-6, rtol=0)


def test_empty_and_fully_culled_scenes_give_background():
    cams = orbit([0.0], width=20, height=12, focal=20.0)
    bg = torch.tensor([0.1, 0.2, 0.3])
    for n in (0, 3):
        means = torch.zeros(1, n, 3)
        means[..., 2] = 5.0  # behind the camera
        splats = ShadedSplats(means, torch.ones(1, n, 4), torch.ones(1, n, 3) * 0.01, torch.ones(1, n) * 0.5,
                              torch.ones(1, n, 3))
        out = rasterize(splats, cams, bg)
        assert torch.equal(out.rgb, bg.expand(1, 12, 20, 3))
        assert torch.equal(out.alpha, torch.zeros(1, 12, 20))


def test_gradcheck_tiny_float64_scene():
    g = torch.Generator().manual_seed(1)
    n = 5
    means = (torch.randn(1, n, 3, generator=g, dtype=torch.float64) * 0.02).requires_grad_()
    quats = torch.randn(1, n, 4, generator=g, dtype=torch.float64).requires_grad_()
    scales = (torch.rand(1, n, 3, generator=g, dtype=torch.float64) * 0.01 + 0.01).requires_grad_()
    opac = (torch.rand(1, n, generator=g, dtype=torch.float64) * 0.6 + 0.2).requires_grad_()
    colors = torch.rand(1, n, 3, generator=g, dtype=torch.float64).requires_grad_()
    cams = orbit([10.0], [5.0], width=14, height=12, focal=30.0).to(torch.float64)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)

    def f(m, q, s, o, c):
        out = rasterize(ShadedSplats(m, q, s, o, c), cams, bg)
        return out.rgb, out.alpha, out.depth

    assert float(f(means, quats, scales, opac, colors)[1].detach().max()) > 0.3
    assert torch.autograd.gradcheck(f, (means, quats, scales, opac, colors), eps=1e-6, atol=1e-6)
