"""The native C++ CPU backend (render_core.raster.native) against the pure-torch reference (docs/method.md section 9).

Acceptance bars: PSNR >= 50 dB on RGB and |alpha error| <= 1/255 on >= 99.9% of pixels against the reference, on
random and head-like scenes, for every SIMD path this CPU can execute; fp16 against fp32 blendshape storage of the
same avatar: PSNR >= 45 dB. Also: odd and large image sizes, empty and culled scenes, the near plane, non-finite
inputs, thread-count and batch independence, sparse packing, BLENDSPLAT_SIMD and the render() entry point.
"""

import dataclasses
import math

import numpy as np
import pytest
import torch

from render_core.camera import Cameras, intrinsics, look_at, orbit
from render_core.deform import Frame, deform
from render_core.errors import FrameError, ShapeError
from render_core.evaluation.metrics import psnr
from render_core.media.pixels import to_uint8
from render_core.raster import ShadedSplats, backend_names, default_backend, native, reference, render
from render_core.renderer import AvatarRenderer
from render_core.tools.bench import framed_camera, random_frames
from render_core.tools.synth import synth_avatar

if not native.available():
    pytest.skip(f"native backend not built: {native.IMPORT_ERROR}", allow_module_level=True)

SIMD = native.simd_paths()
MIN_PSNR = 50.0
MIN_PSNR_FP16 = 45.0
ALPHA_TOL = 1.0 / 255.0
GOOD_FRACTION = 0.999
BG3 = torch.tensor([[0.2, 0.3, 0.4], [1.0, 1.0, 1.0], [0.05, 0.6, 0.1]])

_CACHE: dict = {}


def _cached(key, make):
    """Expensive reference renders computed once per module run."""
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


# ------------------------------------------------------------------------------------------------ helpers


def assert_alpha_bar(alpha: torch.Tensor, ref_alpha: torch.Tensor, tol: float = ALPHA_TOL,
                     fraction: float = GOOD_FRACTION, what: str = "alpha") -> None:
    """|alpha - ref| <= tol on at least ``fraction`` of the pixels."""
    assert alpha.shape == ref_alpha.shape, (alpha.shape, ref_alpha.shape)
    err = (alpha.double() - ref_alpha.double()).abs()
    good = float((err <= tol).double().mean())
    assert good >= fraction, f"{what}: only {good:.5f} of pixels within {tol:.2e} (max error {float(err.max()):.3e})"


def assert_parity(rgb, alpha, depth, ref, min_psnr: float = MIN_PSNR) -> float:
    """The acceptance bars against a reference RasterOutput; returns the RGB PSNR. Depth (alpha-composited camera
    z) gets the alpha bar scaled by the largest depth: an alpha error e moves it by about e z."""
    assert rgb.shape == ref.rgb.shape and alpha.shape == ref.alpha.shape and depth.shape == ref.depth.shape
    assert rgb.dtype == alpha.dtype == depth.dtype == torch.float32
    assert torch.isfinite(rgb).all() and torch.isfinite(alpha).all() and torch.isfinite(depth).all()
    p = psnr(rgb, ref.rgb)
    assert p >= min_psnr, f"RGB PSNR {p:.2f} dB < {min_psnr} dB"
    assert_alpha_bar(alpha, ref.alpha)
    assert_alpha_bar(depth, ref.depth, tol=ALPHA_TOL * max(1.0, float(ref.depth.max())), what="depth")
    return p


def _stack(*tensors) -> list[torch.Tensor]:
    return [t.contiguous() for t in tensors]


def random_scene(n: int, batch: int, seed: int) -> list[torch.Tensor]:
    """B different sets of N float32 Gaussians around the origin (head-sized), with a few hard cases per set."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(batch, n, 3, generator=g) * torch.tensor([0.06, 0.05, 0.08])
    quats = torch.randn(batch, n, 4, generator=g)
    scales = torch.exp(torch.randn(batch, n, 3, generator=g) * 0.6) * 0.006
    opac = torch.rand(batch, n, generator=g) * 0.97
    colors = torch.rand(batch, n, 3, generator=g)
    if n >= 6:
        means[:, 0] = torch.tensor([0.5, 0.0, 0.0])  # far outside the image
        scales[:, 1] = 0.05  # large
        opac[:, 2] = 0.002  # below 1/255: culled
        opac[:, 3] = 0.999  # clamped alpha
        scales[:, 4, 2] = 1e-7  # a flat disc
        quats[:, 5] = torch.tensor([3.0, 0.0, 0.0, 0.0])  # unnormalised identity
    return _stack(means, quats, scales, opac, colors)


def native_raster(args, cams, bg=None, mode="classic", **kw):
    """rgb, alpha, depth and timings of the native backend for the five tensors ``args``."""
    out = native.rasterize(ShadedSplats(*args), cams, bg, mode, **kw)
    return out.rgb, out.alpha, out.depth, out.timings


def scene_cameras(width: int = 37, height: int = 29, focal: float = 60.0) -> Cameras:
    """Three views with different intrinsics each (focal length and principal point)."""
    cams = orbit([0.0, 35.0, -20.0], [0.0, 10.0, -15.0], width=width, height=height, focal=focal)
    K = cams.K.clone()
    K[:, 0, 0] *= torch.tensor([1.0, 0.8, 1.25])
    K[:, 1, 1] *= torch.tensor([1.0, 0.9, 1.2])
    K[:, 0, 2] += torch.tensor([0.0, 0.2, -0.15]) * width
    K[:, 1, 2] += torch.tensor([0.0, -0.1, 0.2]) * height
    return Cameras(K, cams.R, cams.t, width, height)


def simple_camera(width: int, height: int, focal: float) -> Cameras:
    """Camera at the origin looking along +z (R = I, t = 0): camera depth equals world z exactly."""
    return Cameras(intrinsics(width, height, focal)[None], torch.eye(3)[None], torch.zeros(1, 3), width, height)


def head_cameras(avatar, size: int, yaws=(0.0, 30.0), pitches=(0.0, -10.0)) -> Cameras:
    focal = float(framed_camera(avatar, size).K[0, 0, 0])
    return orbit(list(yaws), list(pitches), width=size, height=size, focal=focal)


def fused(packed: native.NativeAvatar, frame: Frame, cams: Cameras, bg=None, **kw):
    """(rgb, alpha, depth, timings) of a frame from a packed avatar's fused pipeline."""
    return packed.render(frame.expression, frame.joint_rotations, frame.eyelids, cams, bg, **kw)


def zero_pairs(avatar, gauss_mask: torch.Tensor, shape_mask: torch.Tensor, fields=None):
    """A copy of ``avatar`` whose deltas are exactly zero for the pairs (k, n) with shape_mask[k] & gauss_mask[n]."""
    pair = shape_mask[:, None] & gauss_mask[None, :]  # [K, N]
    names = fields or ["means", "quats", "log_scales", "opacity_logits", "sh"]
    changes = {}
    for name in names:
        t = getattr(avatar.deltas, name).clone()
        t[pair] = 0.0
        changes[name] = t
    return dataclasses.replace(avatar, deltas=dataclasses.replace(avatar.deltas, **changes)), pair


# ------------------------------------------------------------------------------------------------ fixtures


@pytest.fixture(autouse=True)
def _no_simd_override(monkeypatch):
    """Tests that want BLENDSPLAT_SIMD set it themselves; the default path is the fastest."""
    monkeypatch.delenv("BLENDSPLAT_SIMD", raising=False)


@pytest.fixture(scope="module")
def aa_avatar():
    return synth_avatar(gaussians=600, blendshapes=6, seed=4, raster_mode="antialiased")


@pytest.fixture(scope="module", params=["classic", "antialiased", "big_head"])
def head_case(request, avatar, aa_avatar):
    """A posed head (random expression, pose and eyelids) from two views over two backgrounds, and its
    reference render. big_head: 4000 face Gaussians and 20 blendshapes at 96 x 96."""
    av = {"classic": avatar, "antialiased": aa_avatar}.get(request.param)
    if av is None:
        av = synth_avatar(gaussians=4000, blendshapes=20, seed=5)
    assert av.raster_mode == ("antialiased" if request.param == "antialiased" else "classic")
    frame = random_frames(av, 2, torch.Generator().manual_seed(11))
    cams = head_cameras(av, 96 if request.param == "big_head" else 64)
    bg = BG3[:2]
    ref = AvatarRenderer(av, "reference").render(frame, cams, bg)
    assert float((ref.alpha > 0.5).float().mean()) > 0.2  # the head fills the view: the comparison means something
    return av, frame, cams, bg, ref


# ------------------------------------------------------------------------------------------------ 1. random scenes


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("simd", SIMD)
def test_rasterize_random_scenes_match_reference(simd, mode):
    cams = scene_cameras()
    args = random_scene(300, 3, seed=1)
    ref = _cached(("random", mode), lambda: reference.rasterize(ShadedSplats(*args), cams, BG3, mode))
    assert float(ref.alpha.amax(dim=(1, 2)).min()) > 0.9  # every view sees the scene
    rgb, alpha, depth, timings = native_raster(args, cams, BG3, mode, simd=simd)
    assert timings["isa"] == simd
    assert_parity(rgb, alpha, depth, ref)
    assert float((depth - ref.depth).abs().mean()) < 1e-5  # depth close to the reference's


@pytest.mark.parametrize("simd", SIMD)
def test_rasterize_dense_overlap_off_centre_principal_point(simd):
    """Hundreds of overlapping Gaussians: the transmittance stop (T <= 1e-4) is reached; cx, cy off-centre."""
    R, t = look_at(torch.tensor([[0.02, -0.01, 0.45]]), torch.zeros(1, 3))
    K = intrinsics(48, 40, 80.0)
    K[0, 2], K[1, 2] = 30.0, 14.0
    cams = Cameras(K[None], R, t, 48, 40)
    args = random_scene(600, 1, seed=5)
    bg = torch.tensor([1.0, 1.0, 1.0])
    ref = _cached("dense", lambda: reference.rasterize(ShadedSplats(*args), cams, bg))
    assert float(ref.alpha.max()) > 0.999
    rgb, alpha, depth, _ = native_raster(args, cams, bg, simd=simd)
    assert_parity(rgb, alpha, depth, ref)


@pytest.mark.parametrize("simd", SIMD)
def test_rasterize_accepts_views_and_float64(simd):
    """Expanded, sliced and float64 inputs render as their contiguous float32 copies do."""
    cams = scene_cameras(24, 20, 40.0)
    means, quats, scales, opac, colors = random_scene(80, 1, seed=7)
    dense = _stack(means.expand(3, -1, -1), quats.expand(3, -1, -1), scales.expand(3, -1, -1), opac.expand(3, -1),
                   colors.expand(3, -1, -1))
    wide = torch.cat([torch.zeros(1, 80, 2), quats, torch.zeros(1, 80, 1)], -1)
    views = [means.expand(3, -1, -1), wide[..., 2:6].expand(3, -1, -1), scales.double().expand(3, -1, -1),
             opac.expand(3, -1), colors.transpose(1, 2).contiguous().transpose(1, 2).expand(3, -1, -1)]
    a = native_raster(dense, cams, BG3, simd=simd)
    b = native_raster(views, cams, BG3, simd=simd)
    for x, y in zip(a[:3], b[:3], strict=True):
        assert torch.equal(x, y)
    assert float(a[1].max()) > 0.5


def test_rasterize_rejects_unknown_mode():
    args = random_scene(4, 1, seed=0)
    with pytest.raises(ValueError, match="classic"):
        native_raster(args, scene_cameras(), None, "bogus")


@pytest.mark.parametrize("simd", SIMD)
def test_equal_depths_composite_in_index_order(simd):
    """1200 overlapping Gaussians at exactly the same depth (spread over several parallel chunks): ties are broken
    by Gaussian index, as in the reference (compositing order changes the colour)."""
    g = torch.Generator().manual_seed(13)
    n = 1200
    means = torch.cat([torch.rand(1, n, 2, generator=g) * 0.3 - 0.15, torch.full((1, n, 1), 0.5)], -1)
    quats = torch.randn(1, n, 4, generator=g)
    scales = torch.rand(1, n, 3, generator=g) * 0.01 + 0.004
    opac = torch.rand(1, n, generator=g) * 0.5 + 0.2
    colors = torch.rand(1, n, 3, generator=g)
    cams = simple_camera(48, 40, 60.0)
    args = _stack(means, quats, scales, opac, colors)
    ref = reference.rasterize(ShadedSplats(*args), cams)
    rgb, alpha, depth, _ = native_raster(args, cams, simd=simd, threads=2)
    assert float(ref.alpha.mean()) > 0.5
    assert_parity(rgb, alpha, depth, ref)
    flipped = native_raster(_stack(*[t.flip(1) for t in args]), cams, simd=simd)[0]
    assert psnr(flipped, rgb) < 40.0  # the order matters in this scene


@pytest.mark.parametrize("simd", SIMD)
def test_thin_needles_match_reference(simd):
    """Long, very thin Gaussians (aspect 4e4) at many angles: the per-row spans of the eligibility ellipse."""
    g = torch.Generator().manual_seed(0)
    n = 24
    ang = torch.rand(n, generator=g) * math.pi
    means = torch.stack([torch.randn(n, generator=g) * 0.05, torch.randn(n, generator=g) * 0.05,
                         0.6 + torch.rand(n, generator=g) * 0.1], -1)[None]
    quats = torch.stack([torch.cos(ang / 2), torch.zeros(n), torch.zeros(n), torch.sin(ang / 2)], -1)[None]
    scales = torch.tensor([0.4, 1e-5, 1e-5]).expand(1, n, 3)
    args = _stack(means, quats, scales, torch.full((1, n), 0.95), torch.rand(1, n, 3, generator=g))
    cams = simple_camera(256, 256, 300.0)
    ref = _cached("needles", lambda: reference.rasterize(ShadedSplats(*args), cams))
    rgb, alpha, depth, _ = native_raster(args, cams, simd=simd)
    assert 0.05 < float((ref.alpha > 0.5).float().mean()) < 0.9
    assert_parity(rgb, alpha, depth, ref)


def test_rasterize_rejects_mismatched_shapes():
    cams = scene_cameras(16, 12, 20.0)
    args = random_scene(10, 3, seed=0)
    for i, bad in enumerate([args[0][..., :2], args[1][..., :3], args[2][:, :5], args[3][:2], args[4][..., None]]):
        wrong = list(args)
        wrong[i] = bad.contiguous()
        with pytest.raises((ShapeError, ValueError), match=SPLAT_FIELDS[i]):
            native_raster(wrong, cams)
    with pytest.raises((ShapeError, ValueError, FrameError)):
        native_raster(args, cams.index(0))  # 3 splat sets, 1 camera
    with pytest.raises((ShapeError, ValueError)):
        native_raster(args, cams, torch.zeros(2, 3))  # 3 cameras, 2 backgrounds


def test_fused_rejects_mismatched_shapes(avatar):
    packed = native.NativeAvatar(avatar)
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(0))
    cams = orbit([0.0, 10.0], width=16, height=16, focal=40.0)
    with pytest.raises(ShapeError, match="cameras"):
        fused(packed, frame, cams.index(0))
    with pytest.raises((ShapeError, ValueError), match="expression"):
        packed.render(frame.expression[:, :-1], frame.joint_rotations, frame.eyelids, cams)
    with pytest.raises((ShapeError, ValueError), match="joint_rotations"):
        packed.render(frame.expression, frame.joint_rotations[:, :-1], frame.eyelids, cams)
    with pytest.raises((ShapeError, ValueError), match="eyelids"):
        packed.render(frame.expression, frame.joint_rotations, frame.eyelids[:, :1], cams)


def test_timings_report_every_stage(avatar):
    frame = random_frames(avatar, 1, torch.Generator().manual_seed(0))
    cams = orbit([0.0], width=16, height=16, focal=40.0)
    for timings in (native_raster(random_scene(20, 1, seed=0), cams)[3],
                    fused(native.NativeAvatar(avatar), frame, cams)[3]):
        assert {"blend", "lbs", "raster", "bin", "isa", "threads"} <= set(timings)
        for key in ("blend", "lbs", "raster", "bin"):
            assert isinstance(timings[key], float) and timings[key] >= 0.0
        assert timings["bin"] <= timings["raster"]
        assert timings["isa"] in SIMD


# ------------------------------------------------------------------------------------------------ 2. head-like scenes


@pytest.mark.parametrize("simd", SIMD)
def test_avatar_renderer_matches_reference_on_posed_head(simd, head_case):
    av, frame, cams, bg, ref = head_case
    r = AvatarRenderer(av, "native", simd=simd)
    assert r.backend == "native" and r.stats is not None
    out = r.render(frame, cams, bg)
    assert out.timings["isa"] == simd
    assert_parity(out.rgb, out.alpha, out.depth, ref)


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("variant", ["sh0", "sh1", "sh2", "no_correctives_no_eyelids", "one_camera_for_all",
                                     "float64_avatar"])
def test_fused_pipeline_variants_match_reference(variant, simd):
    """Every packed row width (SH degree 0..3 -> 16, 32, 48, 64 floats), avatars without pose correctives or
    eyelid offsets, one camera broadcast to all frames, and a float64 avatar and frame (packed as fp32; the
    reference computes in float64)."""
    def make():
        degree = int(variant[2]) if variant.startswith("sh") else 3
        av = synth_avatar(gaussians=300, blendshapes=5, seed=8, sh_degree=degree)
        if variant == "no_correctives_no_eyelids":
            av = dataclasses.replace(av, pose_correctives=None, eyelid_offsets=None)
        cams = head_cameras(av, 32)
        if variant == "one_camera_for_all":
            cams = cams.index(1)
        frame = random_frames(av, 3 if variant == "one_camera_for_all" else 2, torch.Generator().manual_seed(2))
        if variant == "float64_avatar":
            av, frame = av.to(torch.float64), frame.to(torch.float64)
        if variant == "no_correctives_no_eyelids":
            frame.eyelids = torch.full((frame.batch_size, 2), 0.4)  # ignored by both backends
        bg = torch.tensor([0.3, 0.1, 0.7])
        return av, frame, cams, bg, AvatarRenderer(av, "reference").render(frame, cams, bg)

    av, frame, cams, bg, ref = _cached(("variant", variant), make)
    assert float(ref.alpha.mean()) > 0.1
    r = AvatarRenderer(av, "native", simd=simd)
    assert r.stats.precision == "fp32"
    out = r.render(frame, cams, bg)
    assert_parity(out.rgb, out.alpha, out.depth, ref)


# ------------------------------------------------------------------------------------------------ 3. odd sizes


ODD_SIZES = [(1, 1), (17, 33), (33, 17)]


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("size", ODD_SIZES, ids=[f"{w}x{h}" for w, h in ODD_SIZES])
def test_rasterize_odd_sizes(size, simd):
    w, h = size
    cams = scene_cameras(w, h, focal=2.0 * max(w, h))
    args = random_scene(200, 3, seed=3)
    ref = _cached(("odd", size), lambda: reference.rasterize(ShadedSplats(*args), cams, BG3))
    assert float(ref.alpha.max()) > 0.5
    rgb, alpha, depth, _ = native_raster(args, cams, BG3, simd=simd)
    assert rgb.shape == (3, h, w, 3) and alpha.shape == (3, h, w) and depth.shape == (3, h, w)
    assert_parity(rgb, alpha, depth, ref)


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("size", ODD_SIZES, ids=[f"{w}x{h}" for w, h in ODD_SIZES])
def test_fused_odd_sizes(size, simd, avatar):
    w, h = size
    focal = float(framed_camera(avatar, 32).K[0, 0, 0]) * max(w, h) / 32
    cams = orbit([0.0, 20.0], width=w, height=h, focal=focal)
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(4))
    ref = _cached(("fused-odd", size), lambda: AvatarRenderer(avatar, "reference").render(frame, cams, BG3[:2]))
    out = AvatarRenderer(avatar, "native", simd=simd).render(frame, cams, BG3[:2])
    assert out.rgb.shape == (2, h, w, 3) and out.alpha.shape == (2, h, w) and out.depth.shape == (2, h, w)
    assert float(ref.alpha.max()) > 0.5
    assert_parity(out.rgb, out.alpha, out.depth, ref)


@pytest.mark.parametrize("simd", SIMD)
def test_rasterize_2048_square(simd):
    """A 2048 x 2048 image (16384 tiles) of a few Gaussians: shape, parity and the background where alpha is 0."""
    cams = orbit([0.0], width=2048, height=2048, focal=3000.0)
    args = random_scene(30, 1, seed=1)
    bg = torch.tensor([0.25, 0.5, 0.75])
    ref = _cached("2048", lambda: reference.rasterize(ShadedSplats(*args), cams, bg))
    rgb, alpha, depth, _ = native_raster(args, cams, bg, simd=simd)
    assert rgb.shape == (1, 2048, 2048, 3) and alpha.shape == depth.shape == (1, 2048, 2048)
    empty = alpha == 0
    assert 0.2 < float(empty.float().mean()) < 0.99  # both covered and empty pixels exist
    assert torch.equal(rgb[empty], bg.expand(int(empty.sum()), 3))
    assert torch.equal(depth[empty], torch.zeros(int(empty.sum())))
    assert_parity(rgb, alpha, depth, ref)


# ------------------------------------------------------------------------------------------------ 4. empty scenes


def _assert_background(rgb, alpha, depth, bg, b, h, w):
    assert rgb.shape == (b, h, w, 3)
    assert torch.equal(rgb, bg.reshape(-1, 1, 1, 3).expand(b, h, w, 3).float())
    assert torch.equal(alpha, torch.zeros(b, h, w))
    assert torch.equal(depth, torch.zeros(b, h, w))


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("case", ["empty", "behind", "transparent", "off_image", "near_plane"])
def test_rasterize_empty_and_culled_scenes_give_background(case, simd):
    cams = scene_cameras(20, 12, 20.0)
    n = 0 if case == "empty" else 5
    means = torch.zeros(3, n, 3)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(3, n, 4).contiguous()
    scales = torch.full((3, n, 3), 0.01)
    opac = torch.full((3, n), 0.9)
    colors = torch.ones(3, n, 3)
    centres = cams.centres
    forward = cams.R[:, 2]  # camera z axis in world space
    if case == "behind":
        means[:] = (centres - 0.3 * forward)[:, None]
    elif case == "transparent":
        opac[:] = 0.99 / 255.0
    elif case == "off_image":
        means[:] = (centres + 0.5 * forward + 2.0 * cams.R[:, 0])[:, None]  # far to the right of the view
    elif case == "near_plane":
        means[:] = (centres + 0.005 * forward)[:, None]
    rgb, alpha, depth, _ = native_raster(_stack(means, quats, scales, opac, colors), cams, BG3, simd=simd)
    _assert_background(rgb, alpha, depth, BG3, 3, 12, 20)
    # The reference agrees (the scenes really are culled, not just rendered differently).
    ref = reference.rasterize(ShadedSplats(means, quats, scales, opac, colors), cams, BG3)
    assert torch.equal(ref.alpha, alpha)


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("case", ["facing_away", "off_image"])
def test_fused_culled_head_gives_background(case, simd, avatar):
    eye = torch.tensor([[0.0, 0.0, 0.6]])
    # Facing away: the head is behind the camera. Off image: in front (z_cam = 0.3) but 60 degrees off-axis.
    direction = [0.0, 0.0, 1.0] if case == "facing_away" else [math.sin(math.pi / 3), 0.0, -math.cos(math.pi / 3)]
    target = eye + torch.tensor([direction])
    R, t = look_at(eye, target)
    cams = Cameras(intrinsics(24, 20, 50.0)[None], R, t, 24, 20)
    frame = random_frames(avatar, 1, torch.Generator().manual_seed(0))
    bg = torch.tensor([0.6, 0.2, 0.9])
    out = AvatarRenderer(avatar, "native", simd=simd).render(frame, cams, bg)
    _assert_background(out.rgb, out.alpha, out.depth, bg, 1, 20, 24)
    # Control: the same frame seen from the front is not empty.
    front = AvatarRenderer(avatar, "native", simd=simd).render(frame, orbit(0.0, width=24, height=20, focal=50.0))
    assert float(front.alpha.max()) > 0.5


# ------------------------------------------------------------------------------------------------ 5. near plane


def _near_scene():
    """Gaussians in front of a camera at the origin looking along +z (depth = world z exactly)."""
    z = [-0.3, 0.005, 0.0099, 0.01, 0.0101, 0.02, 0.02, 0.05, 0.05, 0.005]
    x = [0.0, 0.0, 0.0, 0.0, 0.001, 0.0, 0.012, 0.0, 0.01, 0.0]  # 0.012 / 0.02: beyond the Jacobian clamp
    scale = [0.05, 0.01, 0.002, 0.001, 0.002, 0.004, 0.01, 0.3, 2.0, 0.05]
    n = len(z)
    g = torch.Generator().manual_seed(9)
    near_means = torch.stack([torch.tensor(x), torch.zeros(n), torch.tensor(z)], -1)
    near_scales = torch.tensor(scale)[:, None] * torch.tensor([1.0, 0.7, 0.4])
    near_opac = torch.linspace(0.3, 0.6, n)
    # A normal scene behind them, so covered and uncovered pixels exist.
    far_means = torch.randn(60, 3, generator=g) * 0.05 + torch.tensor([0.0, 0.0, 0.5])
    far_scales = torch.exp(torch.randn(60, 3, generator=g) * 0.5) * 0.008
    means = torch.cat([near_means, far_means])[None]
    quats = torch.randn(1, n + 60, 4, generator=g)
    scales = torch.cat([near_scales, far_scales])[None]
    opac = torch.cat([near_opac, torch.rand(60, generator=g) * 0.9 + 0.05])[None]
    colors = torch.rand(1, n + 60, 3, generator=g)
    return _stack(means, quats, scales, opac, colors), n


NEAR_CASES = ["behind", "z0.005", "z0.0099", "z0.01", "z0.0101", "z0.02", "z0.02_off_axis", "close_huge",
              "close_giant", "straddling_behind", "all_together"]


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("case", range(len(NEAR_CASES)), ids=NEAR_CASES)
def test_near_plane_and_close_huge_gaussians_match_reference(case, simd):
    (means, quats, scales, opac, colors), n = _near_scene()
    if case < n:  # one near Gaussian alone (in front of the normal scene)
        keep = torch.cat([torch.tensor([case]), torch.arange(n, means.shape[1])])
        args = [t[:, keep] for t in (means, quats, scales, opac, colors)]
    else:
        args = [means, quats, scales, opac, colors]
    args = _stack(*args)
    cams = simple_camera(40, 30, 50.0)
    bg = torch.tensor([0.9, 0.1, 0.4])
    ref = reference.rasterize(ShadedSplats(*args), cams, bg)
    rgb, alpha, depth, _ = native_raster(args, cams, bg, simd=simd)
    assert_parity(rgb, alpha, depth, ref)
    if case < n:  # the near Gaussian is culled (only the normal scene shows) or changes the image
        far = native_raster(_stack(*[t[:, 1:] for t in args]), cams, bg, simd=simd)[0]
        if NEAR_CASES[case] in ("behind", "z0.005", "z0.0099", "straddling_behind"):
            assert torch.equal(far, rgb)
        else:
            assert psnr(far, rgb) < 40.0
    if NEAR_CASES[case] in ("close_huge", "close_giant"):  # covers the whole view
        assert float(ref.alpha.min()) > 0.3


def extreme_scene() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """8 enormous, tiny and nearly degenerate Gaussians at and near the near plane of ``simple_camera(32, 24, 40)``:
    means, quats, scales, opacities ([1, 8, ...])."""
    z = torch.tensor([0.01, 0.0100001, 0.011, 0.02, 0.5, 1e6, 0.5, 0.03])
    means = torch.stack([torch.tensor([0.0, 0.0, 0.0, 1e3, 0.0, 0.0, 0.0, -0.02]), torch.zeros(8), z], -1)[None]
    scales = torch.tensor([1e6, 1e-12, 1e3, 1e-30, 1e-3, 1e5, 1e15, 50.0])[:, None].expand(8, 3).clone()[None]
    scales[0, 6, 1] = 1e-15
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [1e-30, 0.0, 0.0, 0.0],
                          [0.5, 0.5, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.3, -0.2, 0.9, 0.1],
                          [0.0, 0.0, 0.0, 0.0]])[None]
    opac = torch.tensor([0.5, 1.0, 0.7, 0.9, 0.999, 0.8, 0.6, 0.5])[None]
    return means, quats, scales, opac


@pytest.mark.parametrize("simd", SIMD)
def test_extreme_gaussians_do_not_crash(simd):
    """Enormous, tiny and nearly degenerate Gaussians at and near the near plane: finite outputs in range."""
    cams = simple_camera(32, 24, 40.0)
    means, quats, scales, opac = extreme_scene()
    colors = torch.rand(1, 8, 3)
    rgb, alpha, depth, _ = native_raster(_stack(means, quats, scales, opac, colors), cams, BG3[:1], simd=simd)
    for t in (rgb, alpha, depth):
        assert torch.isfinite(t).all()
    assert float(alpha.min()) >= 0.0 and float(alpha.max()) <= 1.0
    assert float(rgb.min()) >= 0.0 and float(rgb.max()) <= 1.0 + 1e-5


# ------------------------------------------------------------------------------------------------ 6. non-finite input


def _poison(t: torch.Tensor, value: float) -> torch.Tensor:
    t = t.clone()
    t.view(-1)[t.numel() // 2] = value
    return t


BAD_VALUES = [math.nan, math.inf, -math.inf]
BAD_IDS = ["nan", "inf", "-inf"]
SPLAT_FIELDS = ["means", "quats", "scales", "opacities", "colors"]


@pytest.mark.parametrize("value", BAD_VALUES, ids=BAD_IDS)
@pytest.mark.parametrize("field", range(5), ids=SPLAT_FIELDS)
def test_rasterize_rejects_non_finite_splats(field, value):
    cams = scene_cameras(16, 12, 20.0)
    args = random_scene(20, 3, seed=2)
    before = native_raster(args, cams, BG3)
    bad = list(args)
    bad[field] = _poison(args[field], value)
    kept = [t.clone() for t in bad]
    with pytest.raises((ShapeError, ValueError)) as err:
        native_raster(bad, cams, BG3)
    msg = str(err.value)
    assert "finite" in msg and (SPLAT_FIELDS[field] in msg or "splats" in msg), msg
    for a, b in zip(bad, kept, strict=True):  # inputs untouched
        assert torch.equal(torch.nan_to_num(a), torch.nan_to_num(b))
    after = native_raster(args, cams, BG3)  # nothing left behind: the next call renders as before
    for a, b in zip(before[:3], after[:3], strict=True):
        assert torch.equal(a, b)


FRAME_FIELDS = ["expression", "joint_rotations", "eyelids"]


@pytest.mark.parametrize("value", BAD_VALUES, ids=BAD_IDS)
@pytest.mark.parametrize("field", FRAME_FIELDS)
def test_fused_rejects_non_finite_frames(field, value, avatar):
    cams = orbit([0.0, 10.0], width=16, height=16, focal=40.0)
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(1))
    packed = native.NativeAvatar(avatar)
    before = fused(packed, frame, cams)
    bad = dataclasses.replace(frame, **{field: _poison(getattr(frame, field), value)})
    # The packed avatar's own entry point.
    with pytest.raises((ShapeError, FrameError, ValueError)) as err:
        fused(packed, bad, cams)
    msg = str(err.value)
    assert "finite" in msg and (field in msg or "frame" in msg), msg
    # The renderer names the offending tensor.
    with pytest.raises(FrameError, match=f"{field}.*non-finite"):
        AvatarRenderer(avatar, "native").render(bad, cams)
    after = fused(packed, frame, cams)
    for a, b in zip(before[:3], after[:3], strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("value", BAD_VALUES, ids=BAD_IDS)
@pytest.mark.parametrize("field", ["K", "R", "t"])
def test_non_finite_camera_is_rejected(field, value):
    cam = orbit([0.0], width=16, height=16, focal=40.0)
    parts = {"K": cam.K, "R": cam.R, "t": cam.t}
    parts[field] = _poison(parts[field], value)
    with pytest.raises(FrameError, match=f"camera.{field}.*finite"):
        Cameras(parts["K"], parts["R"], parts["t"], 16, 16)


@pytest.mark.parametrize("entry", ["rasterize", "native_avatar", "avatar_renderer"])
def test_non_finite_background_is_rejected(entry, avatar):
    """The reference path (render()) rejects a NaN background with ShapeError; the native entry points must too
    rather than return a NaN image."""
    cams = orbit([0.0], width=16, height=16, focal=40.0)
    bg = torch.tensor([math.nan, 0.0, 0.0])
    frame = random_frames(avatar, 1, torch.Generator().manual_seed(1))
    with pytest.raises(ShapeError, match="background"):  # what the reference backend does
        AvatarRenderer(avatar, "reference").render(frame, cams, bg)
    with pytest.raises((ShapeError, ValueError), match="background"):
        if entry == "rasterize":
            native_raster(random_scene(20, 1, seed=2), cams, bg)
        elif entry == "native_avatar":
            fused(native.NativeAvatar(avatar), frame, cams, bg)
        else:
            AvatarRenderer(avatar, "native").render(frame, cams, bg)


# ------------------------------------------------------------------------------------------------ 7. threads


@pytest.mark.parametrize("simd", SIMD)
def test_thread_count_does_not_change_the_image(simd, avatar):
    cams = scene_cameras(64, 48, 90.0)
    args = random_scene(1500, 3, seed=6)  # several 512-Gaussian chunks and many tiles per frame
    one = native_raster(args, cams, BG3, simd=simd, threads=1)
    assert one[3]["threads"] == 1
    for threads in (2, 3, 0):  # 0: all cores
        other = native_raster(args, cams, BG3, simd=simd, threads=threads)
        assert other[3]["threads"] == threads if threads else other[3]["threads"] >= 1
        for a, b in zip(one[:3], other[:3], strict=True):
            assert torch.equal(a, b)

    frame = random_frames(avatar, 3, torch.Generator().manual_seed(3))
    hcams = head_cameras(avatar, 48, yaws=(0.0, 25.0, -40.0), pitches=(0.0, 5.0, -5.0))
    ref = AvatarRenderer(avatar, "native", simd=simd, threads=1).render(frame, hcams, BG3)
    assert ref.timings["threads"] == 1
    for threads in (2, 3, 0):
        out = AvatarRenderer(avatar, "native", simd=simd, threads=threads).render(frame, hcams, BG3)
        assert out.timings["threads"] == threads if threads else out.timings["threads"] >= 1
        for a, b in ((ref.rgb, out.rgb), (ref.alpha, out.alpha), (ref.depth, out.depth)):
            assert torch.equal(a, b)
    assert float(ref.alpha.mean()) > 0.1


@pytest.mark.parametrize("simd", SIMD)
def test_one_frame_sorted_by_halves_is_the_one_thread_order(simd):
    """One frame of enough splats is depth-sorted in two halves by two threads and merged: ties in depth (here
    groups of splats at exactly the same depth, overlapping in different colours) keep index order across the
    halves, so the image is the one thread's bit for bit."""
    cams = simple_camera(96, 80, 90.0)
    means, quats, scales, opac, colors = random_scene(12000, 1, seed=9)  # 6000 a half: above the two-thread floor
    means[..., 2] = 0.6 + (torch.arange(12000) % 4).float() * 0.05  # 4 depths, each in both halves
    means[..., :2] = torch.rand(1, 12000, 2, generator=torch.Generator().manual_seed(10)) * 0.6 - 0.3
    scales, opac = scales * 3.0, opac.clamp(min=0.3)
    args = [means, quats, scales, opac, colors]
    one = native_raster(args, cams, BG3[:1], simd=simd, threads=1)
    assert float(one[1].mean()) > 0.5  # the splats cover the image, so any reordering of a tie would show
    for threads in (2, 3):
        other = native_raster(args, cams, BG3[:1], simd=simd, threads=threads)
        assert other[3]["threads"] == threads
        for a, b in zip(one[:3], other[:3], strict=True):
            assert torch.equal(a, b)
    # the order matters: the same splats with the index order reversed within the ties give another image
    flipped = [t.flip(1) for t in args]
    assert not torch.equal(native_raster(flipped, cams, BG3[:1], simd=simd, threads=2)[0], one[0])


# ------------------------------------------------------------------------------------------------ 8. batches


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("batch", [5, 70], ids=["B5", "B70_over_blend_pass"])
def test_batched_frames_equal_frames_rendered_alone(batch, simd, avatar):
    size = 32 if batch <= 8 else 12
    g = torch.Generator().manual_seed(batch)
    frame = random_frames(avatar, batch, g)
    focal = float(framed_camera(avatar, size).K[0, 0, 0])
    yaws, pitches = torch.rand(batch, generator=g) * 60 - 30, torch.rand(batch, generator=g) * 20 - 10
    cams = orbit(yaws, pitches, width=size, height=size, focal=focal)
    bg = torch.rand(batch, 3, generator=g)
    packed = native.NativeAvatar(avatar)
    rgb, alpha, depth, _ = fused(packed, frame, cams, bg, simd=simd)
    for i in range(batch):
        one = Frame(frame.expression[i:i + 1], frame.joint_rotations[i:i + 1], frame.eyelids[i:i + 1])
        r1, a1, d1, _ = fused(packed, one, cams.index(i), bg[i], simd=simd)
        torch.testing.assert_close(rgb[i:i + 1], r1, atol=1e-6, rtol=0)
        torch.testing.assert_close(alpha[i:i + 1], a1, atol=1e-6, rtol=0)
        torch.testing.assert_close(depth[i:i + 1], d1, atol=1e-6, rtol=0)
    assert float(alpha.mean()) > 0.1
    # The frames do differ (the batch is not one frame repeated).
    assert psnr(rgb[0], rgb[1]) < 40.0


# ------------------------------------------------------------------------------------------------ 9. fp16 storage


@pytest.mark.parametrize("simd", SIMD)
def test_fp16_storage_close_to_fp32(simd, avatar):
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(5))
    cams = head_cameras(avatar, 64)
    r32 = AvatarRenderer(avatar, "native", precision="fp32", simd=simd)
    r16 = AvatarRenderer(avatar, "native", precision="fp16", simd=simd)
    assert r32.stats.precision == "fp32" and r16.stats.precision == "fp16"
    assert r16.stats.blend_bytes < r32.stats.blend_bytes
    assert r16.stats.pairs_stored == r32.stats.pairs_stored
    a = r32.render(frame, cams, BG3[:2])
    b = r16.render(frame, cams, BG3[:2])
    assert float(a.alpha.mean()) > 0.1
    assert psnr(b.rgb, a.rgb) >= MIN_PSNR_FP16
    assert_alpha_bar(b.alpha, a.alpha)


@pytest.mark.parametrize("simd", SIMD)
def test_fp16_avatar_defaults_to_fp16_storage_and_matches_reference(simd, avatar):
    """An avatar stored in fp16 packs as fp16 by default; its values are exact in fp16 storage, so the native
    render meets the reference bars (the reference computes the same fp16 values in fp32)."""
    av16 = avatar.with_precision("fp16")
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(6))
    cams = head_cameras(avatar, 48)
    r = AvatarRenderer(av16, "native", simd=simd)
    assert r.stats.precision == "fp16"
    assert AvatarRenderer(av16, "native", precision="fp32").stats.precision == "fp32"
    ref = _cached("fp16-ref", lambda: AvatarRenderer(av16, "reference").render(frame, cams, BG3[:2]))
    out = r.render(frame, cams, BG3[:2])
    assert_parity(out.rgb, out.alpha, out.depth, ref)


def test_fp16_storage_meets_the_bar_at_full_size():
    """fp16 blendshape storage against fp32 at the benchmark's scale (64k Gaussians, 512 px): PSNR >= 45 dB. (With
    the neutral positions in fp16 too it read 44.5 dB here: positions stay fp32.)"""
    big = synth_avatar(64000, 8, seed=0)
    cam = framed_camera(big, 512)
    frame = random_frames(big, 1, torch.Generator().manual_seed(3))
    full = AvatarRenderer(big, "native", precision="fp32").render(frame, cam)
    half = AvatarRenderer(big.with_precision("fp16"), "native").render(frame, cam)
    assert psnr(half.rgb, full.rgb) >= MIN_PSNR_FP16


def test_unknown_precision_is_rejected(avatar):
    with pytest.raises(ValueError, match="fp16"):
        native.NativeAvatar(avatar, precision="bf16")


# ------------------------------------------------------------------------------------------------ 10. sparsity


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
@pytest.mark.parametrize("simd", SIMD)
def test_sparse_deltas_are_skipped_and_render_the_same(simd, precision, avatar):
    n, k = avatar.num_gaussians, avatar.num_expressions
    x, y = avatar.neutral.means[:, 0], avatar.neutral.means[:, 1]
    # Half the blendshapes vanish on the right half of the face; all of them above y = 0.05 (empty CSR rows).
    sparse, pair = zero_pairs(avatar, x < 0, torch.arange(k) < k // 2)
    sparse, pair_top = zero_pairs(sparse, y > 0.05, torch.ones(k, dtype=torch.bool))
    zero = pair | pair_top
    assert 0 < int(zero.sum()) < n * k and int(pair_top.sum()) > 0
    stats = native.NativeAvatar(sparse, precision).stats
    assert stats.pairs_total == 2 * n * k  # a geometry and a colour entry per pair
    assert stats.pairs_stored == 2 * (n * k - int(zero.sum()))
    assert stats.stored_fraction == (n * k - int(zero.sum())) / (n * k)
    dense_stats = native.NativeAvatar(avatar, precision).stats
    assert dense_stats.pairs_stored == 2 * n * k and dense_stats.stored_fraction == 1.0
    assert stats.blend_bytes < dense_stats.blend_bytes

    frame = random_frames(avatar, 2, torch.Generator().manual_seed(8))
    cams = head_cameras(avatar, 48)
    ref = _cached("sparse-ref", lambda: AvatarRenderer(sparse, "reference").render(frame, cams, BG3[:2]))
    out = AvatarRenderer(sparse, "native", precision=precision, simd=simd).render(frame, cams, BG3[:2])
    assert_parity(out.rgb, out.alpha, out.depth, ref, min_psnr=MIN_PSNR if precision == "fp32" else MIN_PSNR_FP16)
    # The zeroed pairs matter: the sparse avatar does not look like the dense one.
    dense = AvatarRenderer(avatar, "native", precision=precision, simd=simd).render(frame, cams, BG3[:2])
    assert psnr(out.rgb, dense.rgb) < 45.0


def test_pair_changing_any_property_is_stored(avatar):
    """A pair is stored in the geometry table when any of its position, rotation, scale or opacity deltas is
    non-zero (here: position and rotation zero, the rest not), in the colour table when any SH delta is, and
    dropped from a table only when all of that table's values are zero."""
    k, n = avatar.num_expressions, avatar.num_gaussians
    everywhere = torch.ones(n, dtype=torch.bool)
    unmoved, pair = zero_pairs(avatar, everywhere, torch.ones(k, dtype=torch.bool), fields=["means", "quats"])
    stats = native.NativeAvatar(unmoved).stats
    assert stats.pairs_stored == stats.pairs_total == 2 * int(pair.sum())
    sh_only, _ = zero_pairs(avatar, everywhere, torch.ones(k, dtype=torch.bool),
                            fields=["means", "quats", "log_scales", "opacity_logits"])
    deltas = sh_only.sparse_deltas()
    assert (deltas.geometry.count, deltas.color.count) == (0, n * k)
    assert native.NativeAvatar(sh_only).stats.stored_fraction == 0.5
    none, _ = zero_pairs(avatar, everywhere, torch.ones(k, dtype=torch.bool))
    packed_none = native.NativeAvatar(none)
    assert packed_none.stats.pairs_stored == 0 and packed_none.stats.stored_fraction == 0.0
    # Nothing stored renders as the full avatar with zero expression (same pose and eyelids).
    frame = random_frames(avatar, 2, torch.Generator().manual_seed(3))
    cams = orbit([0.0, 20.0], width=24, height=24, focal=60.0)
    neutral = dataclasses.replace(frame, expression=torch.zeros_like(frame.expression))
    got = fused(packed_none, frame, cams)
    want = fused(native.NativeAvatar(avatar), neutral, cams)
    assert float(want[1].mean()) > 0.1
    for a, b in zip(got[:3], want[:3], strict=True):
        assert torch.equal(a, b)


def _wide_avatar(k: int):
    """8 face Gaussians and ``k`` blendshapes, all zero except the first and the last (which moves the face 2 cm
    to the right and turns it green)."""
    av = synth_avatar(gaussians=8, blendshapes=k, seed=1, sh_degree=0)
    deltas = av.deltas.map(torch.zeros_like)
    deltas.means[0, :, 1] = 0.01
    deltas.means[-1, :, 0] = 0.02
    deltas.sh[-1, :, 0, 1] = 1.0
    return dataclasses.replace(av, deltas=deltas)


@pytest.mark.parametrize("k", [65536, 65537])
def test_last_of_many_blendshapes_is_applied(k):
    """Blendshape indices near and past 2^16 (the packed index type): the last blendshape must act as itself, or
    the avatar must be refused with an error naming the limit."""
    av = _wide_avatar(k)
    try:
        packed = native.NativeAvatar(av)
    except ShapeError as err:
        assert k > 65536 and "65536" in str(err)
        return
    # Geometry: blendshapes 0 and k-1 on all 8 Gaussians; colour: blendshape k-1.
    assert packed.stats.pairs_stored == 24 and packed.stats.stored_fraction == 24 / (2 * 8 * k)
    frame = Frame.neutral(av, 2)
    frame.expression[0, -1] = 1.0
    frame.expression[1, 0] = 0.5
    frame.expression[1, -1] = 0.7
    cams = orbit([0.0, 15.0], width=24, height=24, focal=60.0)
    ref = AvatarRenderer(av, "reference").render(frame, cams)
    out = fused(packed, frame, cams)
    assert_parity(*out[:3], ref)
    rest = fused(packed, Frame.neutral(av, 2), cams)
    assert psnr(rest[0], out[0]) < 30.0  # the last blendshape visibly acts


# ------------------------------------------------------------------------------------------------ 11. BLENDSPLAT_SIMD


@pytest.mark.parametrize("simd", SIMD)
def test_env_var_selects_the_simd_path(simd, monkeypatch, avatar):
    cams = orbit([0.0], width=16, height=16, focal=40.0)
    args = random_scene(20, 1, seed=0)
    frame = random_frames(avatar, 1, torch.Generator().manual_seed(0))
    renderer = AvatarRenderer(avatar, "native")  # built before the variable is set: it is read at each call
    packed = native.NativeAvatar(avatar)
    monkeypatch.setenv("BLENDSPLAT_SIMD", simd)
    assert native.simd_choice() == simd
    assert native_raster(args, cams)[3]["isa"] == simd
    assert fused(packed, frame, cams)[3]["isa"] == simd
    assert renderer.render(frame, cams).timings["isa"] == simd
    assert render(deform(avatar, frame), cams, backend="native").timings["isa"] == simd
    # An explicit simd= argument wins over the variable.
    for other in SIMD:
        assert native_raster(args, cams, simd=other)[3]["isa"] == other


def test_env_var_unset_or_auto_picks_the_fastest(monkeypatch):
    cams = orbit([0.0], width=16, height=16, focal=40.0)
    args = random_scene(20, 1, seed=0)
    monkeypatch.delenv("BLENDSPLAT_SIMD", raising=False)
    assert native_raster(args, cams)[3]["isa"] == SIMD[-1]
    for value in ("auto", ""):
        monkeypatch.setenv("BLENDSPLAT_SIMD", value)
        assert native_raster(args, cams)[3]["isa"] == SIMD[-1]
    assert SIMD[0] == "scalar" and len(set(SIMD)) == len(SIMD)
    assert set(SIMD) <= {"scalar", "avx2", "avx512"}


BAD_SIMD = ["sse9"] + ([] if "avx512" in SIMD else ["avx512"]) + ([] if "avx2" in SIMD else ["avx2"])


@pytest.mark.parametrize("value", BAD_SIMD)
def test_env_var_unavailable_or_unknown_path_raises(value, monkeypatch, avatar):
    cams = orbit([0.0], width=16, height=16, focal=40.0)
    args = random_scene(20, 1, seed=0)
    frame = random_frames(avatar, 1, torch.Generator().manual_seed(0))
    renderer = AvatarRenderer(avatar, "native")
    monkeypatch.setenv("BLENDSPLAT_SIMD", value)

    def check(call):
        with pytest.raises(ValueError) as err:
            call()
        msg = str(err.value)
        assert all(path in msg for path in SIMD), f"{msg!r} does not name the available paths {SIMD}"

    check(lambda: native_raster(args, cams))
    check(lambda: fused(renderer.native, frame, cams))
    check(lambda: renderer.render(frame, cams))
    monkeypatch.delenv("BLENDSPLAT_SIMD")
    check(lambda: native_raster(args, cams, simd=value))  # the same for the argument
    assert native_raster(args, cams)[3]["isa"] == SIMD[-1]  # and nothing sticks


# ------------------------------------------------------------------------------------------------ 12. render()


def test_default_backend_is_native():
    assert default_backend() == "native"
    assert "native" in backend_names() and "reference" in backend_names()


def test_avatar_renderer_defaults_to_native(avatar):
    r = AvatarRenderer(avatar)
    assert r.backend == "native" and isinstance(r.native, native.NativeAvatar)
    assert r.render(Frame.neutral(avatar), orbit(0.0, width=16, height=16)).timings["isa"] == SIMD[-1]


@pytest.mark.parametrize("broadcast", ["pairwise", "one_splat_set", "one_camera"])
def test_render_entry_point_native_matches_reference(broadcast, avatar, aa_avatar):
    g = torch.Generator().manual_seed(12)
    for av in (avatar, aa_avatar):
        frames = random_frames(av, 1 if broadcast == "one_splat_set" else 2, g)
        cams = head_cameras(av, 40, yaws=(0.0,) if broadcast == "one_camera" else (0.0, -30.0),
                            pitches=(0.0,) if broadcast == "one_camera" else (0.0, 10.0))
        splats = deform(av, frames)
        bg = torch.tensor([0.4, 0.4, 0.1])
        ref = render(splats, cams, backend="reference", background=bg, mode=av.raster_mode)
        out = render(splats, cams, backend="native", background=bg, mode=av.raster_mode)
        default = render(splats, cams, background=bg, mode=av.raster_mode)
        assert out.rgb.shape[0] == 2 and out.timings["isa"] == SIMD[-1]
        assert float(ref.alpha.mean()) > 0.1
        assert_parity(out.rgb, out.alpha, out.depth, ref)
        assert torch.equal(default.rgb, out.rgb)


def test_auto_picks_the_fastest_path_that_agrees_with_scalar(monkeypatch, caplog):
    native.verified_fastest_path.cache_clear()
    assert native.verified_fastest_path() == native.simd_paths()[-1]
    if len(native.simd_paths()) == 1:
        return
    fastest = native.simd_paths()[-1]
    real = native.NativeAvatar.render

    def broken(self, *args, simd=None, **kwargs):  # the fastest path renders wrong colours
        rgb, alpha, depth, timings = real(self, *args, simd=simd, **kwargs)
        return (rgb + 0.1 if simd == fastest else rgb), alpha, depth, timings

    monkeypatch.setattr(native.NativeAvatar, "render", broken)
    native.verified_fastest_path.cache_clear()
    try:
        with caplog.at_level("WARNING"):
            picked = native.verified_fastest_path()
        assert picked != fastest and picked in native.simd_paths()
        assert fastest in caplog.text and "disagrees" in caplog.text
    finally:
        native.verified_fastest_path.cache_clear()


def test_native_rgba8_rounds_and_clamps_as_to_uint8():
    rgb = torch.rand(2, 5, 7, 3) * 1.4 - 0.2
    alpha = torch.rand(2, 5, 7)
    assert np.array_equal(native.to_rgba8(rgb, alpha), to_uint8(torch.cat([rgb, alpha[..., None]], -1)))


@pytest.mark.parametrize("height, width, pad", [(48, 64, 0), (7, 9, 5), (1, 1, 3), (6, 3, 0), (70, 130, 30)])
def test_native_rgba8_to_i420_is_the_numpy_conversion_bit_for_bit_and_leaves_row_padding(monkeypatch, height, width,
                                                                                          pad):
    from render_core.media import pixels

    rgba = np.random.default_rng(height * width).integers(0, 256, (height, width, 4), dtype=np.uint8)
    rgba[0, 0, :3] = 255  # the extremes: white and black stay inside studio range
    rgba[-1, -1, :3] = 0
    out = []
    for built in (True, False):
        monkeypatch.setattr(native, "available", lambda built=built: built)
        ch, cw = (height + 1) // 2, (width + 1) // 2
        planes = [np.full((height, width + pad), 7, np.uint8), np.full((ch, cw + pad), 7, np.uint8),
                  np.full((ch, cw + pad), 7, np.uint8)]
        pixels.rgba8_to_i420(rgba, *planes)
        out.append(planes)
    for a, b in zip(*out, strict=True):
        assert np.array_equal(a, b)
        assert (a[:, a.shape[1] - pad:] == 7).all()  # the padding is left alone
    y, u, v = out[0]
    assert y[-1, width - 1] == 16 and (y[0, 0] == 235 or height * width == 1)  # one pixel: black wins
    assert 16 <= u[:, :cw].min() and u[:, :cw].max() <= 240 and 16 <= v[:, :cw].min() and v[:, :cw].max() <= 240
    with pytest.raises(ValueError, match="do not fit"):
        pixels.rgba8_to_i420(rgba, y[:-1], u, v)


def test_rgba8_to_i420_is_ffmpegs_bt601_conversion_within_a_level():
    """The encoders' input as FFmpeg made it before (swscale's RGBA to 4:2:0 default): luma within one level;
    chroma differs only by the filter (a 2x2 mean here), and decodes back to the image as closely."""
    import av

    from render_core.media import pixels

    yy, xx = np.mgrid[0:64, 0:96]
    rgba = np.stack([(xx * 3 + yy) % 256, yy * 4, (xx + yy) // 2, np.full_like(xx, 255)], -1).astype(np.uint8)
    ours = av.VideoFrame(96, 64, "yuv420p")
    pixels.rgba8_to_i420(rgba, *[np.frombuffer(p, np.uint8).reshape(-1, p.line_size) for p in ours.planes])
    ffmpeg = av.VideoFrame.from_ndarray(rgba, format="rgba").reformat(format="yuv420p")
    luma = [np.frombuffer(f.planes[0], np.uint8).reshape(-1, f.planes[0].line_size)[:, :96].astype(int)
            for f in (ours, ffmpeg)]
    assert np.abs(luma[0] - luma[1]).max() <= 1
    back = [psnr(torch.from_numpy(f.to_ndarray(format="rgb24") / 255.0), torch.from_numpy(rgba[..., :3] / 255.0))
            for f in (ours, ffmpeg)]
    assert back[0] >= back[1] - 0.5 and back[0] > 25


def test_local_synth_avatar_leaves_pairs_unstored():
    dense = native.NativeAvatar(synth_avatar(gaussians=2000, blendshapes=6, seed=4))
    local_avatar = synth_avatar(gaussians=2000, blendshapes=6, seed=4, local=True)
    local = native.NativeAvatar(local_avatar)
    assert dense.stats.stored_fraction == 1.0
    assert 0.0 < local.stats.stored_fraction < 0.7
    back = local_avatar.neutral.means[:, 2] < -0.05
    still = (local_avatar.deltas.means.abs().sum(-1) == 0).all(0)  # no blendshape moves them
    assert float(still[back].float().mean()) > 0.5  # most of the back of the head


def test_default_threads_ignore_torch_thread_setting(monkeypatch):
    """torch.set_num_threads changes OpenMP's process-wide default; the renderer's default stays every CPU."""
    import os

    from render_core import _native

    if "OMP_NUM_THREADS" in os.environ:
        pytest.skip("OMP_NUM_THREADS is set: it chooses the default")
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert _native.max_threads() == len(os.sched_getaffinity(0))
    finally:
        torch.set_num_threads(before)
