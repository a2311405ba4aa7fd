"""Scenes and image comparisons shared by the cuda backend's tests (test_cuda_conventions on the CPU, test_cuda on
a GPU)."""

import torch

from render_core.camera import orbit
from render_core.deform import deform
from render_core.evaluation.metrics import psnr
from render_core.raster import ShadedSplats
from render_core.tools.bench import random_frames


def random_scene(n=400, seed=0):
    """Gaussians around the origin (some behind the cameras' near plane, some nearly transparent), unnormalised
    quaternions, two cameras with a size that is not a multiple of 16 and different backgrounds: (splats, cameras,
    backgrounds)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(1, n, 3, generator=g) * 2 - 1) * torch.tensor([0.15, 0.12, 0.15])
    # On the front camera's axis, at and behind its near plane (camera z = 0.6 - z: 0.05 down to -0.02).
    means[0, :8] = torch.stack([torch.zeros(8), torch.zeros(8), torch.linspace(0.55, 0.62, 8)], -1)
    quats = torch.randn(1, n, 4, generator=g) * 3
    scales = torch.exp(torch.rand(1, n, 3, generator=g) * 5.0 - 8.0)  # 0.3 mm (sub-pixel) to 5 cm
    scales[0, :8] = 1e-3
    opacities = torch.rand(1, n, generator=g)
    opacities[0, :8] = 0.3
    opacities[0, 8:16] = torch.rand(8, generator=g) / 255.0
    colors = torch.rand(1, n, 3, generator=g)
    cams = orbit([0.0, 25.0], [0.0, -10.0], width=50, height=38)
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 0.3, 0.0]])
    splats = ShadedSplats(*(t.expand(2, *t.shape[1:]) for t in (means, quats, scales, opacities, colors)))
    return splats, cams, bg


def head_scene(avatar, seed=1):
    """Two posed frames of ``avatar`` shaded for two views: (splats, cameras, background)."""
    g = torch.Generator().manual_seed(seed)
    splats = deform(avatar, random_frames(avatar, 2, g))
    cams = orbit([-20.0, 30.0], [5.0, -5.0], width=80, height=72)
    return ShadedSplats.from_splats(splats, cams), cams, torch.tensor([0.1, 0.1, 0.1])


def assert_same_image(out, ref, db=45.0):
    assert out.rgb.shape == ref.rgb.shape and out.alpha.shape == ref.alpha.shape and out.depth.shape == ref.depth.shape
    assert float(ref.alpha.mean()) > 0.05  # something is in view
    scale = float(ref.depth.abs().max())
    got = (psnr(out.rgb, ref.rgb), psnr(out.alpha, ref.alpha), psnr(out.depth / scale, ref.depth / scale))
    assert min(got) >= db, got
    return got
