"""The native rasterizer's backward (render_core.raster.native.rasterize_differentiable) against the autograd
gradients of the pure-torch reference (docs/method.md section 9).

The native path computes in float32; the oracle is the reference's autograd on the same inputs in float64 (the
exact gradient of the same function, without float32 rounding), so no finite differences are needed here.
Acceptance bar: for every input tensor, |g_native - g_ref| <= 1e-3 |g_ref| (Frobenius norms) for a random scalar
loss sum(w * rgb) + sum(v * alpha), on random and head-like scenes, both raster modes, every SIMD path. Also: the
forward is native.rasterize's image bit for bit; culled Gaussians (behind the camera, at or straddling the near
plane) get zero gradients, never NaN; the gradients are bitwise the same with 1 and 2 threads; non-finite inputs
raise the forward's error; float64, expanded and partly-differentiable inputs; the background's gradient.
"""

import math

import numpy as np
import pytest
import torch

from render_core.camera import Cameras, intrinsics, orbit
from render_core.deform import deform
from render_core.errors import ShapeError
from render_core.raster import ShadedSplats, native, reference
from render_core.tools.bench import framed_camera, random_frames
from render_core.tools.synth import synth_avatar
from tests.test_native import extreme_scene, simple_camera

if not native.available():
    pytest.skip(f"native backend not built: {native.IMPORT_ERROR}", allow_module_level=True)

SIMD = native.simd_paths()
MODES = ["classic", "antialiased"]
REL_TOL = 1e-3
NAMES = ["means", "quats", "scales", "opacities", "colors", "background"]


@pytest.fixture(autouse=True)
def _no_simd_override(monkeypatch):
    monkeypatch.delenv("BLENDSPLAT_SIMD", raising=False)


# ------------------------------------------------------------------------------------------------ scenes


def random_scene(n: int, batch: int, seed: int, hard: bool = True) -> list[torch.Tensor]:
    """B different sets of N float32 Gaussians around the origin, with a few hard cases per set."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(batch, n, 3, generator=g) * torch.tensor([0.06, 0.05, 0.08])
    quats = torch.randn(batch, n, 4, generator=g)
    scales = torch.exp(torch.randn(batch, n, 3, generator=g) * 0.6) * 0.008
    opac = torch.rand(batch, n, generator=g) * 0.97
    colors = torch.rand(batch, n, 3, generator=g)
    if hard and n >= 8:
        means[:, 0] = torch.tensor([0.5, 0.0, 0.0])  # far outside the image
        scales[:, 1] = 0.05  # large
        opac[:, 2] = 0.002  # below 1/255: culled
        opac[:, 3] = 0.9995  # alpha clamped at 0.999 near its centre
        scales[:, 4, 2] = 1e-7  # a flat disc
        quats[:, 5] = torch.tensor([3.0, 0.0, 0.0, 0.0])  # unnormalised identity
        means[:, 6, 0] = 0.25  # beyond the Jacobian's clamp, but its tail still in view
        scales[:, 6] = 0.03
    return [t.contiguous() for t in (means, quats, scales, opac, colors)]


def scene_cameras(width: int, height: int, focal: float, batch: int = 2) -> Cameras:
    """Views from different directions with different intrinsics (focal lengths, principal points)."""
    cams = orbit([0.0, 35.0, -20.0][:batch], [0.0, 10.0, -15.0][:batch], width=width, height=height, focal=focal)
    K = cams.K.clone()
    K[:, 0, 0] *= torch.tensor([1.0, 0.8, 1.25])[:batch]
    K[:, 1, 1] *= torch.tensor([1.0, 0.9, 1.2])[:batch]
    K[:, 0, 2] += torch.tensor([0.0, 0.2, -0.15])[:batch] * width
    K[:, 1, 2] += torch.tensor([0.0, -0.1, 0.2])[:batch] * height
    return Cameras(K, cams.R, cams.t, width, height)


def head_scene(gaussians: int, size: int, seed: int, mode: str):
    """A posed synthetic head (random expression, pose and eyelids) seen from two views: splat arguments and
    cameras."""
    av = synth_avatar(gaussians=gaussians, blendshapes=4, seed=seed, raster_mode=mode)
    frame = random_frames(av, 2, torch.Generator().manual_seed(seed))
    focal = float(framed_camera(av, size).K[0, 0, 0])
    cams = orbit([0.0, 30.0], [0.0, -10.0], width=size, height=size, focal=focal)
    shaded = ShadedSplats.from_splats(deform(av, frame), cams)
    return [t.detach().float().contiguous() for t in shaded.tensors().values()], cams


def loss_weights(b: int, h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(b, h, w, 3, generator=g), torch.randn(b, h, w, generator=g)


def native_grads(args, cams, bg, mode, weights, **kw):
    """(rgb, alpha, gradients of every input and of the background) through the native backward."""
    leaves = [t.clone().requires_grad_(True) for t in args]
    bgl = bg.clone().requires_grad_(True)
    rgb, alpha = native.rasterize_differentiable(ShadedSplats(*leaves), cams, bgl, mode, **kw)
    ((rgb * weights[0]).sum() + (alpha * weights[1]).sum()).backward()
    return rgb.detach(), alpha.detach(), [t.grad for t in (*leaves, bgl)]


def reference_grads(args, cams, bg, mode, weights):
    leaves = [t.double().requires_grad_(True) for t in args]
    bgl = bg.double().requires_grad_(True)
    out = reference.rasterize(ShadedSplats(*leaves), cams, bgl, mode)
    ((out.rgb * weights[0].double()).sum() + (out.alpha * weights[1].double()).sum()).backward()
    return out, [t.grad for t in (*leaves, bgl)]


def relative_errors(got, want) -> dict[str, float]:
    return {name: float((a.double() - b).norm() / b.norm().clamp_min(1e-30))
            for name, a, b in zip(NAMES, got, want, strict=True)}


def assert_gradients_match(got, want, tol: float = REL_TOL) -> dict[str, float]:
    for name, a, b in zip(NAMES, got, want, strict=True):
        assert a.shape == b.shape, (name, a.shape, b.shape)
        assert torch.isfinite(a).all(), f"{name}: non-finite gradient"
        assert float(b.norm()) > 0, f"{name}: the reference gradient is zero (the test means nothing)"
    errs = relative_errors(got, want)
    bad = {k: v for k, v in errs.items() if not v <= tol}
    assert not bad, f"gradients differ from the reference (relative to the norm): {bad}"
    return errs


_CACHE: dict = {}


def _cached(key, make):
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


# ------------------------------------------------------------------------------------------------ parity

BG2 = torch.tensor([[0.2, 0.3, 0.4], [1.0, 0.9, 0.8]])
SIZES = [(24, 24), (40, 31)]


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("case", ["random50_24x24", "random300_40x31", "head300_32x32"])
def test_gradients_match_reference(case, mode, simd):
    def make():
        if case.startswith("head"):
            args, cams = head_scene(250, 32, seed=3, mode=mode)
        else:
            n = int(case[len("random"):case.index("_")])
            w, h = (24, 24) if n == 50 else (40, 31)
            args, cams = random_scene(n, 2, seed=n), scene_cameras(w, h, 1.6 * max(w, h))
        weights = loss_weights(2, cams.height, cams.width, seed=7)
        ref, grads = reference_grads(args, cams, BG2, mode, weights)
        return args, cams, weights, ref, grads

    args, cams, weights, ref, want = _cached((case, mode), make)
    assert float(ref.alpha.detach().amax(dim=(1, 2)).min()) > 0.5  # every view sees the scene
    rgb, alpha, got = native_grads(args, cams, BG2, mode, weights, simd=simd)
    assert float((rgb.double() - ref.rgb.detach()).abs().max()) < 1e-3
    assert float((alpha.double() - ref.alpha.detach()).abs().max()) < 1e-3
    assert_gradients_match(got, want)


@pytest.mark.parametrize("mode", MODES)
def test_gradients_match_reference_in_a_dense_scene(mode):
    """600 overlapping Gaussians, many nearly opaque: transmittance stops (T <= 1e-4) and alpha clamps (0.999)
    everywhere in the centre; an off-centre principal point."""
    g = torch.Generator().manual_seed(5)
    args = random_scene(600, 2, seed=5)
    args[3] = torch.where(torch.rand(2, 600, generator=g) < 0.3, torch.tensor(0.9999), args[3]).contiguous()
    cams = scene_cameras(36, 30, 70.0)
    K = cams.K.clone()
    K[:, 0, 2], K[:, 1, 2] = 22.0, 11.0
    cams = Cameras(K, cams.R, cams.t, 36, 30)
    weights = loss_weights(2, 30, 36, seed=3)
    ref, want = reference_grads(args, cams, BG2, mode, weights)
    assert float((ref.alpha.detach() > 0.9998).float().mean()) > 0.1  # stopped pixels exist
    _, _, got = native_grads(args, cams, BG2, mode, weights)
    assert_gradients_match(got, want)


@pytest.mark.parametrize("mode", MODES)
def test_gradients_match_reference_where_alpha_is_clamped(mode):
    """Large fully opaque Gaussians (opacity 1: alpha = 0.999 on dozens of pixels around each centre, where no
    gradient flows through alpha) over a random scene."""
    args = random_scene(150, 2, seed=12, hard=False)
    g = torch.Generator().manual_seed(12)
    k = 5
    args[0][:, :k] = torch.randn(2, k, 3, generator=g) * torch.tensor([0.05, 0.04, 0.02])
    args[2][:, :k] = torch.rand(2, k, 3, generator=g) * 0.3 + 0.6
    args[2][:, :k, 2] = 0.002
    args[3][:, :k] = 1.0
    cams = scene_cameras(40, 31, 60.0)
    weights = loss_weights(2, 31, 40, seed=9)
    ref, want = reference_grads(args, cams, BG2, mode, weights)
    proj = reference.project(*[t.double() for t in args[:4]], cams, mode)
    px = torch.stack(torch.meshgrid(torch.arange(40.0), torch.arange(31.0), indexing="xy"), -1) + 0.5
    d = proj.means2d[:, :k, None, None, :].detach() - px  # [B, k, H, W, 2]
    a, b, c = proj.conics[:, :k, None, None].detach().unbind(-1)
    sigma = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
    clamped = proj.opacities[:, :k, None, None].detach() * torch.exp(-sigma) > 0.999
    assert int(clamped.sum()) > 50
    _, _, got = native_grads(args, cams, BG2, mode, weights)
    assert_gradients_match(got, want)


@pytest.mark.parametrize("size", [(1, 1), (17, 33), (33, 17)], ids=["1x1", "17x33", "33x17"])
def test_gradients_match_reference_at_odd_sizes(size):
    """Images that are not whole tiles (partial tiles on the right and bottom; a single pixel)."""
    w, h = size
    args = random_scene(200, 2, seed=3)
    cams = scene_cameras(w, h, 2.0 * max(w, h))
    weights = loss_weights(2, h, w, seed=1)
    ref, want = reference_grads(args, cams, BG2, "classic", weights)
    assert float(ref.alpha.detach().max()) > 0.5
    _, _, got = native_grads(args, cams, BG2, "classic", weights)
    assert_gradients_match(got, want)


def test_no_gaussians():
    args = [t[:, :0].contiguous() for t in random_scene(10, 2, seed=3)]
    weights = loss_weights(2, 20, 20, seed=0)
    rgb, alpha, got = native_grads(args, scene_cameras(20, 20, 30.0), BG2, "classic", weights)
    assert torch.equal(alpha, torch.zeros_like(alpha))
    assert [tuple(t.shape) for t in got] == [(2, 0, 3), (2, 0, 4), (2, 0, 3), (2, 0), (2, 0, 3), (2, 3)]
    assert torch.allclose(got[5], weights[0].sum((1, 2)), rtol=1e-5, atol=1e-4)


# ------------------------------------------------------------------------------------------------ forward


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("mode", MODES)
def test_forward_is_the_native_image(mode, simd):
    args = random_scene(200, 2, seed=11)
    cams = scene_cameras(33, 17, 50.0)
    rgb, alpha = native.rasterize_differentiable(ShadedSplats(*args), cams, BG2, mode, simd=simd)
    want = native.rasterize(ShadedSplats(*args), cams, BG2, mode, simd=simd)
    assert rgb.dtype == alpha.dtype == torch.float32
    assert torch.equal(rgb, want.rgb) and torch.equal(alpha, want.alpha)
    assert float(alpha.max()) > 0.5


def test_no_grad_and_partly_differentiable_inputs():
    """Only the inputs that require gradients get them; under no_grad nothing is recorded."""
    args = random_scene(80, 2, seed=2)
    cams = scene_cameras(24, 24, 40.0)
    with torch.no_grad():
        rgb, alpha = native.rasterize_differentiable(ShadedSplats(*args), cams)
    assert not rgb.requires_grad and not alpha.requires_grad
    means = args[0].clone().requires_grad_(True)
    colors = args[4].clone().requires_grad_(True)
    rgb, alpha = native.rasterize_differentiable(ShadedSplats(means, args[1], args[2], args[3], colors), cams)
    (rgb.sum() + alpha.sum()).backward()
    assert means.grad is not None and colors.grad is not None
    assert float(means.grad.abs().sum()) > 0 and float(colors.grad.abs().sum()) > 0
    # Only alpha used: the colour gradient is exactly zero, the others are not.
    means.grad = colors.grad = None
    _, alpha = native.rasterize_differentiable(ShadedSplats(means, args[1], args[2], args[3], colors), cams)
    alpha.sum().backward()
    assert torch.equal(colors.grad, torch.zeros_like(colors)) and float(means.grad.abs().sum()) > 0


# ------------------------------------------------------------------------------------------------ inputs


@pytest.mark.parametrize("bg_kind", ["none", "shared", "per_camera"])
def test_float64_expanded_inputs_and_background_shapes(bg_kind):
    """float64 inputs get float64 gradients; one set of splats expanded to two cameras gets the sum of both
    views' gradients; the background's gradient has the background's shape."""
    one = random_scene(120, 1, seed=4)
    cams = scene_cameras(28, 22, 45.0)
    weights = loss_weights(2, 22, 28, seed=1)
    bg = {"none": None, "shared": torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64), "per_camera": BG2}[bg_kind]
    leaves = [t.double().requires_grad_(True) for t in one]
    bgl = None if bg is None else bg.clone().requires_grad_(True)
    rgb, alpha = native.rasterize_differentiable(ShadedSplats(*[t.expand(2, *t.shape[1:]) for t in leaves]), cams, bgl)
    ((rgb * weights[0]).sum() + (alpha * weights[1]).sum()).backward()
    ref_leaves = [t.double().requires_grad_(True) for t in one]
    ref_bg = None if bg is None else bg.double().clone().requires_grad_(True)
    out = reference.rasterize(ShadedSplats(*[t.expand(2, *t.shape[1:]) for t in ref_leaves]), cams, ref_bg)
    ((out.rgb * weights[0].double()).sum() + (out.alpha * weights[1].double()).sum()).backward()
    got = [t.grad for t in leaves]
    want = [t.grad for t in ref_leaves]
    for a in got:
        assert a.dtype == torch.float64 and a.shape[0] == 1
    if bg is not None:
        assert bgl.grad.shape == bg.shape and bgl.grad.dtype == bg.dtype
        got.append(bgl.grad)
        want.append(ref_bg.grad)
    else:
        got.append(torch.ones(1))
        want.append(torch.ones(1, dtype=torch.float64))
    assert_gradients_match(got, want)


def test_retained_graph_gives_the_same_gradients_twice():
    args = random_scene(60, 2, seed=8)
    cams = scene_cameras(24, 24, 40.0)
    means = args[0].clone().requires_grad_(True)
    rgb, alpha = native.rasterize_differentiable(ShadedSplats(means, *args[1:]), cams)
    loss = rgb.square().sum() + alpha.sum()
    (first,) = torch.autograd.grad(loss, means, retain_graph=True)
    (second,) = torch.autograd.grad(loss, means)
    assert torch.equal(first, second) and float(first.abs().sum()) > 0


def test_in_place_modification_before_backward_is_detected():
    args = random_scene(30, 2, seed=8)
    means = args[0].clone().requires_grad_(True)
    work = means * 1.0  # a float32 contiguous non-leaf: saved as is
    rgb, _ = native.rasterize_differentiable(ShadedSplats(work, *args[1:]), scene_cameras(16, 16, 30.0))
    with torch.no_grad():
        work.add_(0.01)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        rgb.sum().backward()


BAD_VALUES = [math.nan, math.inf, -math.inf]


@pytest.mark.parametrize("value", BAD_VALUES, ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize("field", range(6), ids=NAMES)
def test_non_finite_inputs_raise_the_forward_error(field, value):
    args = random_scene(20, 2, seed=2) + [BG2.clone()]
    args = [t.clone().requires_grad_(True) for t in args]
    bad = [t.detach().clone() for t in args]
    bad[field].view(-1)[bad[field].numel() // 2] = value
    bad[field].requires_grad_(True)
    cams = scene_cameras(16, 12, 20.0)
    with pytest.raises(ShapeError) as err:
        native.rasterize_differentiable(ShadedSplats(*bad[:5]), cams, bad[5])
    with pytest.raises(ShapeError) as forward_err:
        native.rasterize(ShadedSplats(*[t.detach() for t in bad[:5]]), cams, bad[5].detach())
    assert str(err.value) == str(forward_err.value)
    assert "finite" in str(err.value) and NAMES[field] in str(err.value)


def test_rejects_unknown_mode():
    with pytest.raises(ValueError, match="classic"):
        native.rasterize_differentiable(ShadedSplats(*random_scene(4, 1, seed=0)), scene_cameras(8, 8, 10.0, batch=1),
                                        None, "x")


# ------------------------------------------------------------------------------------------------ culling


def _near_scene():
    """A camera at the origin looking along +z; Gaussians behind it, at and straddling the near plane (z = 0.01),
    in front of a normal scene."""
    # (0.01 itself would be culled in float64 and not in float32, whose 0.01 is a little smaller.)
    z = [-0.3, -0.02, 0.005, 0.0099, 0.01001, 0.0101, 0.02, 0.05, 0.05]
    x = [0.0, 0.0, 0.0, 0.0, 0.0, 0.001, 0.012, 0.0, 0.01]
    scale = [0.05, 0.05, 0.01, 0.002, 0.001, 0.002, 0.01, 0.3, 2.0]  # -0.02 with 0.05: straddling the plane
    n = len(z)
    g = torch.Generator().manual_seed(9)
    near_means = torch.stack([torch.tensor(x), torch.zeros(n), torch.tensor(z)], -1)
    near_scales = torch.tensor(scale)[:, None] * torch.tensor([1.0, 0.7, 0.4])
    far_means = torch.randn(60, 3, generator=g) * 0.05 + torch.tensor([0.0, 0.0, 0.5])
    far_scales = torch.exp(torch.randn(60, 3, generator=g) * 0.5) * 0.008
    means = torch.cat([near_means, far_means])[None]
    quats = torch.randn(1, n + 60, 4, generator=g)
    scales = torch.cat([near_scales, far_scales])[None]
    opac = torch.cat([torch.linspace(0.3, 0.6, n), torch.rand(60, generator=g) * 0.9 + 0.05])[None]
    colors = torch.rand(1, n + 60, 3, generator=g)
    cams = Cameras(intrinsics(40, 30, 50.0)[None], torch.eye(3)[None], torch.zeros(1, 3), 40, 30)
    return [t.contiguous() for t in (means, quats, scales, opac, colors)], cams, n


@pytest.mark.parametrize("mode", MODES)
def test_culled_gaussians_get_zero_not_nan_gradients(mode):
    args, cams, n = _near_scene()
    bg = torch.tensor([[0.9, 0.1, 0.4]])
    weights = loss_weights(1, 30, 40, seed=2)
    _, _, got = native_grads(args, cams, bg, mode, weights)
    for name, grad in zip(NAMES, got, strict=True):
        assert torch.isfinite(grad).all(), name
    culled = [0, 1, 2, 3]  # behind, straddling (centre behind), z < near
    for grad in got[:5]:
        assert torch.equal(grad[0, culled], torch.zeros_like(grad[0, culled]))
    # Everything else, the near and close ones included, matches the reference.
    _, want = reference_grads(args, cams, bg, mode, weights)
    assert_gradients_match(got, want)
    assert float(got[0][0, 4].abs().sum()) > 0  # just beyond the near plane are rendered and differentiated


def test_fully_culled_scene_gives_zero_gradients_and_the_background_gradient():
    args = random_scene(10, 2, seed=1, hard=False)
    cams = scene_cameras(16, 12, 20.0)
    behind = (cams.centres - 0.3 * cams.R[:, 2])[:, None]
    args[0] = (args[0] * 0.1 + behind).contiguous()
    weights = loss_weights(2, 12, 16, seed=0)
    rgb, alpha, got = native_grads(args, cams, BG2, "classic", weights)
    assert torch.equal(alpha, torch.zeros_like(alpha))
    for grad in got[:5]:
        assert torch.equal(grad, torch.zeros_like(grad))
    assert torch.allclose(got[5], weights[0].sum((1, 2)), rtol=1e-5, atol=1e-5)  # T = 1 everywhere


def test_extreme_gaussians_give_finite_gradients():
    """Enormous, tiny and nearly degenerate Gaussians at and near the near plane (as test_native's crash test)."""
    cams = simple_camera(32, 24, 40.0)
    means, quats, scales, opac = extreme_scene()
    colors = torch.rand(1, 8, 3, generator=torch.Generator().manual_seed(0))
    args = [t.contiguous() for t in (means, quats, scales, opac, colors)]
    for mode in MODES:
        _, alpha, got = native_grads(args, cams, BG2[:1], mode, loss_weights(1, 24, 32, seed=5))
        assert float(alpha.max()) > 0.1
        for name, grad in zip(NAMES, got, strict=True):
            assert torch.isfinite(grad).all(), (mode, name)


# ------------------------------------------------------------------------------------------------ threads


@pytest.mark.parametrize("simd", SIMD)
def test_gradients_are_bitwise_the_same_for_any_thread_count(simd):
    args, cams = head_scene(600, 48, seed=6, mode="classic")
    weights = loss_weights(2, 48, 48, seed=4)
    _, _, one = native_grads(args, cams, BG2, "classic", weights, simd=simd, threads=1)
    for threads in (2, 3):
        _, _, other = native_grads(args, cams, BG2, "classic", weights, simd=simd, threads=threads)
        for name, a, b in zip(NAMES, one, other, strict=True):
            assert torch.equal(a, b), (threads, name)


def test_context_memory_is_as_documented():
    """What the forward keeps: 64 B per Gaussian, 4 B per (Gaussian, tile) pair, 8 B per pixel (+ bookkeeping)."""
    args = random_scene(500, 2, seed=3)
    cams = scene_cameras(64, 48, 90.0)
    m = [t.numpy() for t in args]
    K, R, t = (x.contiguous().numpy() for x in (cams.K, cams.R, cams.t))
    rgb, alpha, depth = np.empty((2, 48, 64, 3), np.float32), np.empty((2, 48, 64), np.float32), np.empty(
        (2, 48, 64), np.float32)
    _, ctx = native._native.rasterize_train(*m, K, R, t, 64, 48, False, BG2.numpy(), rgb, alpha, depth)
    tiles = 4 * 3
    want = 2 * (500 * 64 + 64 * 48 * 8 + (tiles + 1) * 4) + ctx.pairs * 4
    assert ctx.pairs > 500
    assert want <= ctx.nbytes <= want + 1024
