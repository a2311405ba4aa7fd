"""The cuda backend without a GPU: its argument conversion run through gsplat's own ``rasterization`` on the CPU
(tests/gsplat_cpu.py) against the reference rasterizer, the whole cuda code path (render(), AvatarRenderer, bench,
the trainer's CUDA step) emulated on the CPU, the device-resident avatar in fp32/fp16/bf16, and the errors where
CUDA or gsplat is missing. The same checks on a GPU are in tests/test_cuda.py (marker ``cuda``)."""

import json
import math

import pytest
import torch

from render_core.camera import orbit
from render_core.deform import Frame, deform
from render_core.raster import ShadedSplats, differentiable, gsplat_backend, reference, render
from render_core.renderer import AvatarRenderer
from render_core.tools.bench import bench_render, random_frames

gsplat = pytest.importorskip("gsplat", reason="gsplat is not installed (pip install --no-deps 'gsplat>=1.5,<1.6')")
import gsplat_cpu  # noqa: E402  (tests/: needs gsplat)
from splat_scenes import assert_same_image, head_scene, random_scene  # noqa: E402


def gsplat_on_cpu(monkeypatch, *scene, mode):
    """Our conversion -> gsplat.rasterization (CPU stand-ins for its kernels) -> our RasterOutput."""
    gsplat_cpu.patch_gsplat(monkeypatch)
    colors, alphas, meta = gsplat.rasterization(**gsplat_backend.gsplat_arguments(*scene, mode=mode))
    return gsplat_backend.from_gsplat(colors, alphas, meta)


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gsplat_conventions_match_the_reference_on_a_random_scene(monkeypatch, mode):
    scene = random_scene()
    out = gsplat_on_cpu(monkeypatch, *scene, mode=mode)
    ref = reference.rasterize(*scene, mode)
    got = assert_same_image(out, ref)
    print(f"random scene, {mode}: PSNR rgb {got[0]:.1f} dB, alpha {got[1]:.1f} dB, depth {got[2]:.1f} dB")
    # Projected centres of the Gaussians both keep: the same pixels (viewmats, Ks, +0.5 conventions).
    both = (out.radii > 0).all(-1) & (ref.radii > 0).all(-1)
    assert int(both.sum()) > 100
    assert float((out.means2d[both] - ref.means2d[both]).abs().max()) < 1e-3
    # Both cull what is behind the near plane (camera z < 0.01); the ones just in front are drawn, and large.
    splats, cams, _ = scene
    z = (cams.R[0] @ splats.means[0, :8].T).T[:, 2] + cams.t[0, 2]
    behind = z < 0.01
    assert 0 < int(behind.sum()) < 8
    assert not (out.radii[0, :8][behind] > 0).any() and not (ref.radii[0, :8][behind] > 0).any()


@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gsplat_conventions_match_the_reference_on_a_head(monkeypatch, avatar, mode):
    scene = head_scene(avatar)
    out = gsplat_on_cpu(monkeypatch, *scene, mode=mode)
    ref = reference.rasterize(*scene, mode)
    got = assert_same_image(out, ref)
    print(f"head, {mode}: PSNR rgb {got[0]:.1f} dB, alpha {got[1]:.1f} dB, depth {got[2]:.1f} dB")


def test_gsplat_conversion_is_differentiable(monkeypatch, avatar):
    """Gradients reach every input through the conversion (on the GPU gsplat's backward supplies them)."""
    shaded, cams, _ = head_scene(avatar)
    leaves = [t.detach().clone().requires_grad_(True) for t in shaded.tensors().values()]
    bg = torch.tensor([0.3, 0.2, 0.1], requires_grad=True)
    out = gsplat_on_cpu(monkeypatch, ShadedSplats(*leaves), cams, bg, mode="classic")
    (out.rgb.sum() + out.alpha.sum()).backward()
    for t in (*leaves, bg):
        assert t.grad is not None and torch.isfinite(t.grad).all() and float(t.grad.abs().sum()) > 0


# --------------------------------------------------------------------------- the cuda code path, emulated on CPU
def test_render_entry_point_with_the_emulated_cuda_backend(monkeypatch, avatar):
    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    splats = deform(avatar, random_frames(avatar, 2, torch.Generator().manual_seed(4)))
    cams = orbit([0.0, -30.0], width=64, height=48)
    bg = torch.tensor([0.5, 0.5, 0.5])
    assert_same_image(render(splats, cams, backend="cuda", background=bg, mode=avatar.raster_mode),
                      render(splats, cams, backend="reference", background=bg, mode=avatar.raster_mode))
    # One splat set seen by two cameras broadcasts as for every backend.
    one = deform(avatar, Frame.neutral(avatar))
    assert render(one, cams, backend="cuda").rgb.shape == (2, 48, 64, 3)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_avatar_renderer_cuda_path_matches_the_reference(monkeypatch, avatar, precision):
    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    frames = random_frames(avatar, 3, torch.Generator().manual_seed(5))
    cams = orbit([0.0, 20.0, -35.0], [0.0, 10.0, -5.0], width=64, height=64)
    bg = torch.tensor([0.0, 0.2, 0.4])
    gpu = AvatarRenderer(avatar, "cuda", precision=precision)
    out = gpu.render(frames, cams, bg)
    assert set(out.timings) == {"blend", "lbs", "shade", "raster"}
    assert_same_image(out, AvatarRenderer(avatar, "reference").render(frames, cams, bg))
    # Batched streams give each stream's single render.
    for i in range(3):
        single = gpu.render(Frame(frames.expression[i:i + 1], frames.joint_rotations[i:i + 1],
                                  frames.eyelids[i:i + 1] if frames.eyelids is not None else None), cams.index(i), bg)
        assert torch.allclose(single.rgb[0], out.rgb[i], atol=1e-4)


def test_bench_render_cuda_report_emulated(monkeypatch, avatar):
    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    report = bench_render("cuda", size=48, streams=2, frames=1, warmup=0, avatar=avatar, reference_frames=0)
    json.dumps(report)
    assert report["backend"] == "cuda" and report["device"] == "cpu (gsplat emulated)"
    assert report["aggregate_fps"] == pytest.approx(2 * report["fps"], rel=1e-3)
    assert {"blend", "lbs", "shade", "raster", "total"} == set(report["ms"])
    assert report["precision"] == avatar.precision and report["blend"]["bytes"] > 0


def test_training_step_on_the_emulated_cuda_path_lowers_the_loss(monkeypatch):
    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    rasterize = differentiable("cuda")
    scene, cams, _ = random_scene(n=120, seed=3)
    target = reference.rasterize(scene, cams).rgb
    g = torch.Generator().manual_seed(9)
    leaves = [(scene.means[:1] + 0.01 * torch.randn(1, 120, 3, generator=g)).requires_grad_(True),
              (scene.colors[:1] * 0.5).requires_grad_(True)]
    opt = torch.optim.Adam(leaves, lr=3e-3)
    losses = []
    for _ in range(6):
        m, c = (t.expand(2, *t.shape[1:]) for t in leaves)
        rgb, alpha = rasterize(ShadedSplats(m, scene.quats, scene.scales, scene.opacities, c), cams, None, "classic")
        loss = (rgb - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.9 * losses[0], losses


def test_train_with_device_cuda_runs_the_emulated_gsplat_step(monkeypatch, head, tmp_path):
    from render_core.data.generate import synth_dataset
    from render_core.train import get_preset, train

    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    calls = []
    real = gsplat_backend.rasterize_differentiable
    monkeypatch.setattr(gsplat_backend, "rasterize_differentiable", lambda *a: calls.append(1) or real(*a))
    synth_dataset(tmp_path / "data", frames=3, size=48, seed=1, facemodel=head)
    preset = get_preset("tiny").with_(gaussians=200, mouth=20, checkpoint_every=1000, log_every=1)
    summary = train(tmp_path / "data", tmp_path / "a.bsplat", workdir=tmp_path / "work", preset=preset,
                    iterations=5, stop_after=3, facemodel=head, device="cuda")
    assert summary["device"] == "cuda" and summary["stopped"] and len(calls) == 3
    assert all(math.isfinite(r["loss"]) for r in (summary["first"], summary["last"]))
