"""The cuda backend (gsplat 1.5.x) on a GPU - parity with the reference rasterizer (forward and gradients), the
GPU-resident avatar (fp32/fp16/bf16 storage, batched streams), the benchmark reports and training steps - marked
``cuda`` and skipped, with the reason, where there is no CUDA device or no gsplat (``pytest -m cuda`` runs them;
docs/cuda-gpu-runbook.md). Also here, and run everywhere: the device-resident avatar on the CPU and the errors that
say why the backend is missing. Without a GPU, tests/test_cuda_conventions.py checks the conventions through
gsplat's own code on the CPU."""

import json
import math
import sys

import numpy as np
import pytest
import torch
from splat_scenes import assert_same_image, head_scene, psnr, random_scene

from render_core.camera import orbit
from render_core.deform import Frame, deform, skin
from render_core.errors import OptionError
from render_core.media.pixels import to_rgba8
from render_core.raster import (
    RasterOutput,
    ShadedSplats,
    backend_names,
    check_backend,
    gsplat_backend,
    reference,
    render,
)
from render_core.renderer import AvatarRenderer, DeviceAvatar
from render_core.tools.bench import bench_raster_backward, bench_render, framed_camera, random_frames
from render_core.tools.synth import synth_avatar

gpu = pytest.mark.skipif(not gsplat_backend.available(), reason=f"cuda backend: {gsplat_backend.unavailable_reason()}")
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")


def _cpu(out: RasterOutput) -> RasterOutput:
    return RasterOutput(out.rgb.cpu(), out.alpha.cpu(), out.depth.cpu())


def _frame(frames: Frame, i: int) -> Frame:
    return Frame(frames.expression[i:i + 1], frames.joint_rotations[i:i + 1],
                 None if frames.eyelids is None else frames.eyelids[i:i + 1])


# ---------------------------------------------------------------------------------------------- on a GPU
@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_rgba8_of_gpu_frames_is_converted_on_the_device_as_on_the_host():
    rgb, alpha = torch.rand(2, 9, 13, 3) * 1.4 - 0.2, torch.rand(2, 9, 13)
    assert np.array_equal(to_rgba8(rgb.cuda(), alpha.cuda()), to_rgba8(rgb, alpha))


@pytest.mark.cuda
@gpu
def test_gsplat_extension_builds_and_is_1_5():
    import gsplat

    gsplat_backend.build_extension()  # the first run compiles gsplat's CUDA sources (minutes)
    assert gsplat.__version__.startswith("1.5.") and "cuda" in backend_names()


@pytest.mark.cuda
@gpu
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
@pytest.mark.parametrize("scene", ["random", "head"])
def test_cuda_matches_the_reference_rasterizer(avatar, scene, mode):
    shaded, cams, bg = random_scene() if scene == "random" else head_scene(avatar)
    ref = reference.rasterize(shaded, cams, bg, mode)
    out = gsplat_backend.rasterize(shaded.to(device="cuda"), cams.to(device="cuda"), bg.cuda(), mode)
    assert out.rgb.is_cuda and out.alpha.is_cuda and out.depth.is_cuda
    got = assert_same_image(_cpu(out), ref)
    print(f"cuda vs reference, {scene}, {mode}: PSNR rgb {got[0]:.1f}, alpha {got[1]:.1f}, depth {got[2]:.1f} dB")
    # CPU inputs through render(): the outputs come back to the CPU.
    if scene == "head":
        splats = deform(avatar, random_frames(avatar, 2, torch.Generator().manual_seed(1)))
        back = render(splats, cams, backend="cuda", background=bg, mode=mode)
        assert back.rgb.device.type == "cpu"
        assert_same_image(back, render(splats, cams, backend="reference", background=bg, mode=mode))


@pytest.mark.cuda
@gpu
def test_cuda_gradients_match_the_reference_autograd(avatar):
    shaded, cams, bg = head_scene(avatar)
    g = torch.Generator().manual_seed(2)
    w = torch.randn(2, cams.height, cams.width, 3, generator=g)
    v = torch.randn(2, cams.height, cams.width, generator=g)

    def grads(device, raster):
        leaves = [t.detach().to(device).clone().requires_grad_(True) for t in (*shaded.tensors().values(), bg)]
        rgb, alpha = raster(ShadedSplats(*leaves[:5]), cams.to(device=device), leaves[5], "classic")
        ((rgb * w.to(device)).sum() + (alpha * v.to(device)).sum()).backward()
        return [t.grad.cpu().double().flatten() for t in leaves]

    def ref_raster(*args):
        out = reference.rasterize(*args)
        return out.rgb, out.alpha

    want = grads("cpu", ref_raster)
    got = grads("cuda", gsplat_backend.rasterize_differentiable)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "background"), got, want, strict=True):
        cos = float(torch.nn.functional.cosine_similarity(a, b, dim=0))
        rel = float((a - b).norm() / b.norm())
        print(f"gradient {name}: cosine {cos:.5f}, relative error {rel:.2e}")
        assert cos > 0.99 and rel < 0.1, (name, cos, rel)


@pytest.mark.cuda
@gpu
def test_avatar_renderer_on_the_gpu_matches_the_reference(avatar):
    frames = random_frames(avatar, 3, torch.Generator().manual_seed(5))
    cams = orbit([0.0, 20.0, -35.0], [0.0, 10.0, -5.0], width=128, height=128)
    bg = torch.tensor([0.0, 0.2, 0.4])
    want = AvatarRenderer(avatar, "reference").render(frames, cams, bg)
    for fuse, stages in (("off", {"blend", "lbs", "shade", "raster"}), ("graph", {"deform", "raster"})):
        renderer = AvatarRenderer(avatar, "cuda", precision="fp32", fuse=fuse)
        out = renderer.render(frames, cams, bg)
        assert renderer.fuse == fuse, renderer.fuse_error
        assert out.rgb.is_cuda and set(out.timings) == stages
        assert all(v >= 0 for v in out.timings.values())
        assert_same_image(_cpu(out), want)


@pytest.mark.cuda
@gpu
def test_batched_streams_equal_single_renders():
    avatar = synth_avatar(8000, 50, seed=2).with_precision("fp16")
    frames = random_frames(avatar, 8, torch.Generator().manual_seed(3))
    cams = orbit(torch.linspace(-30, 30, 8).tolist(), width=128, height=128)
    renderer = AvatarRenderer(avatar, "cuda")
    batch = renderer.render(frames, cams)
    for i in range(8):
        single = renderer.render(_frame(frames, i), cams.index(i))
        # The same image up to matmul rounding (a splat at the 1/255 alpha cut-off may flip in a pixel or two).
        assert float((single.rgb[0] - batch.rgb[i]).abs().max()) < 1e-2, i
        assert psnr(single.rgb[0], batch.rgb[i]) >= 60, i


@pytest.mark.cuda
@gpu
@pytest.mark.parametrize("precision,db", [("fp16", 45.0), ("bf16", 40.0)])
def test_low_precision_storage_against_fp32(precision, db):
    """512 x 512, 64k Gaussians, K = 50 (the benchmark's avatar): fp16 storage >= 45 dB against fp32."""
    avatar = synth_avatar(64_000, 50, seed=0)
    frames = random_frames(avatar, 4, torch.Generator().manual_seed(7))
    cams = framed_camera(avatar, 512).expand(4)  # the head covers about half of the image
    want = AvatarRenderer(avatar, "cuda", precision="fp32").render(frames, cams)
    got = AvatarRenderer(avatar, "cuda", precision=precision).render(frames, cams)
    value = psnr(got.rgb, want.rgb)
    print(f"{precision} vs fp32 storage: PSNR {value:.1f} dB (coverage {float((want.alpha > 0.5).float().mean()):.2f})")
    assert value >= db


@pytest.mark.cuda
@gpu
def test_posed_gaussians_training_steps_lower_the_loss():
    scene, cams, _ = random_scene(n=2000, seed=3)
    dev = torch.device("cuda")
    cams = cams.to(device=dev)
    target, _ = gsplat_backend.rasterize_differentiable(scene.to(device=dev), cams)
    g = torch.Generator().manual_seed(9)
    leaves = [(scene.means[:1] + 0.01 * torch.randn(1, 2000, 3, generator=g)).to(dev).requires_grad_(True),
              (scene.colors[:1] * 0.5).to(dev).requires_grad_(True),
              torch.logit(scene.opacities[:1].clamp(0.02, 0.98) * 0.5).to(dev).requires_grad_(True)]
    opt = torch.optim.Adam(leaves, lr=3e-3)
    losses = []
    for _ in range(30):
        m, c, o = (t.expand(2, *t.shape[1:]) for t in leaves)
        splats = ShadedSplats(m, scene.quats.to(dev), scene.scales.to(dev), torch.sigmoid(o), c)
        rgb, _ = gsplat_backend.rasterize_differentiable(splats, cams)
        loss = (rgb - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0], losses


@pytest.mark.cuda
@gpu
def test_training_on_cuda_lowers_the_loss(tmp_path):
    from render_core.data.generate import synth_dataset
    from render_core.facemodel.open_head import open_head
    from render_core.train import get_preset, train

    head = open_head()

    data = tmp_path / "data"
    synth_dataset(data, frames=6, size=64, seed=1, facemodel=head)
    preset = get_preset("tiny").with_(gaussians=400, mouth=40, sh_every=15, checkpoint_every=1000, log_every=1,
                                      final_eval_frames=2, xyz_decay_steps=50)
    summary = train(data, tmp_path / "toy.bsplat", workdir=tmp_path / "work", preset=preset, iterations=50,
                    facemodel=head, device="cuda")
    lines = [json.loads(s) for s in (tmp_path / "work" / "log.jsonl").read_text().splitlines()]
    first, last = np.mean([r["loss"] for r in lines[:5]]), np.mean([r["loss"] for r in lines[-5:]])
    print(f"cuda training: loss {first:.4f} -> {last:.4f}, {summary['ms_per_iteration']} ms per iteration")
    assert summary["device"] == "cuda" and summary["bundle"] and last < 0.7 * first


@pytest.mark.cuda
@gpu
def test_training_on_cuda_keeps_the_whole_step_on_the_gpu(tmp_path):
    """Model, optimizer state, densification statistics and targets live on the GPU through densification; the
    checkpoint resumes on the CPU; the stage split is printed for the report."""
    from render_core.data.generate import synth_dataset
    from render_core.facemodel.open_head import open_head
    from render_core.train import get_preset
    from render_core.train.trainer import Trainer

    head = open_head()
    synth_dataset(tmp_path / "data", frames=6, size=64, seed=1, facemodel=head)
    preset = get_preset("tiny").with_(gaussians=400, mouth=40, sh_every=5, checkpoint_every=1000, log_every=1,
                                      densify_from=1, densify_every=4, densify_until=20, densify_grad=2e-4,
                                      prune_big_after=8, max_screen_radius=8.0)
    trainer = Trainer(tmp_path / "data", tmp_path / "work", preset, device="cuda", facemodel=head, iterations=24)
    trainer.run()
    tensors = dict(trainer.model.named_parameters()) | dict(trainer.model.named_buffers())
    assert all(t.is_cuda for t in tensors.values()), [k for k, t in tensors.items() if not t.is_cuda]
    assert trainer.model.pose_correctives is None or trainer.model.pose_correctives.is_cuda
    moments = [v for st in trainer.optimizer.state.values() for v in st.values() if torch.is_tensor(v)]
    assert moments and all(v.is_cuda for v in moments)
    assert trainer.strategy.grad_accum.is_cuda and trainer.strategy.max_radii.is_cuda
    assert sum(d["cloned"] + d["split"] for d in trainer.summary()["densified"]) > 0
    print("cuda training stage ms:", trainer.summary()["stage_ms"])
    path = trainer.checkpoint()
    on_cpu = Trainer(tmp_path / "data", tmp_path / "work2", preset, device="cpu", facemodel=head, iterations=26)
    on_cpu.resume(path)
    assert on_cpu.iteration == 24 and not on_cpu.model.means.is_cuda
    assert math.isfinite(on_cpu.step().losses["loss"])


@pytest.mark.cuda
@gpu
def test_bench_reports_on_the_gpu():
    report = bench_render("cuda", gaussians=4000, blendshapes=10, size=128, streams=4, frames=3, warmup=1,
                          reference_frames=0)
    json.dumps(report)
    assert report["backend"] == "cuda" and report["device"] == torch.cuda.get_device_name()
    assert report["fuse"] == "graph" and "fuse_error" not in report, report.get("fuse_error")
    assert report["aggregate_fps"] > 0 and {"deform", "raster", "total"} == set(report["ms"])
    eager = bench_render("cuda", gaussians=4000, blendshapes=10, size=128, streams=4, frames=3, warmup=1,
                         reference_frames=0, fuse="off", layout="sparse")
    assert {"blend", "lbs", "shade", "raster", "total"} == set(eager["ms"]) and eager["blend"]["layout"] == "sparse"
    step = bench_raster_backward(gaussians=4000, size=128, frames=3, reference_frames=1, device="cuda")
    json.dumps(step)
    assert step["cuda"]["forward_ms"] > 0 and step["cuda"]["backward_ms"] > 0


@pytest.mark.cuda
@gpu
@pytest.mark.parametrize("fuse", ["graph", "compile"])
def test_fused_frames_equal_the_eager_pipeline_for_each_batch_size(avatar, fuse):
    """One CUDA graph (over torch.compile's kernels or not) per batch size renders what the eager stage-by-stage
    pipeline renders, frame after frame (the static buffers are refilled, never stale); the sparse layout too."""
    eager = AvatarRenderer(avatar, "cuda", fuse="off", layout="sparse")
    fused = AvatarRenderer(avatar, "cuda", fuse=fuse)
    g = torch.Generator().manual_seed(4)
    for b in (1, 3, 1):
        cams = framed_camera(avatar, 96).expand(b)
        for _ in range(2):
            frame = random_frames(avatar, b, g)
            want, got = eager.render(frame, cams), fused.render(frame, cams)
            assert fused.fuse == fuse, fused.fuse_error
            assert set(got.timings) == {"deform", "raster"}
            assert psnr(got.rgb, want.rgb) >= 60, psnr(got.rgb, want.rgb)
    assert sorted(fused._graphs) == [1, 3]


# ------------------------------------------------------------------------- everywhere: the device-resident avatar
@pytest.mark.parametrize("precision,db", [("fp32", 80.0), ("fp16", 45.0), ("bf16", 40.0)])
def test_device_avatar_storage_against_the_fp32_pipeline(avatar, precision, db):
    """DeviceAvatar on the CPU (the cuda renderer's blend and skin, any device) against deform() in float32."""
    frames = random_frames(avatar, 2, torch.Generator().manual_seed(6))
    cams = orbit([0.0, 25.0], width=64, height=64)
    dev = DeviceAvatar(avatar, "cpu", precision)
    assert dev.matrix.dtype == {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}[precision]
    got = skin(dev.avatar, dev.blend(frames.expression), frames)  # as the cuda renderer runs them
    want = deform(avatar.to(torch.float32), frames)
    if precision == "fp32":
        for key in ("means", "quats", "scales", "opacities", "sh", "sh_rotations"):
            assert torch.allclose(getattr(got, key), getattr(want, key), atol=1e-5), key
    a = reference.rasterize(ShadedSplats.from_splats(got, cams), cams)
    b = reference.rasterize(ShadedSplats.from_splats(want, cams), cams)
    assert psnr(a.rgb, b.rgb) >= db, psnr(a.rgb, b.rgb)


def test_device_avatar_rejects_unknown_precision(avatar):
    with pytest.raises(ValueError, match="bf16"):
        DeviceAvatar(avatar, "cpu", "int8")
    with pytest.raises(ValueError, match="layout"):
        DeviceAvatar(avatar, "cpu", "fp16", "csr")


def test_the_fused_stage_builds_no_tensor_from_host_data(avatar, monkeypatch):
    """What the CUDA graph captures (blend, skin, shade) never turns host data into a device tensor: a CUDA graph
    cannot capture that copy (the mouth's joint lookup once did, and every capture fell back to eager)."""
    renderer = AvatarRenderer(avatar, "reference")
    renderer.device_avatar = DeviceAvatar(avatar, "cpu", "fp16")
    frames = random_frames(avatar, 2, torch.Generator().manual_seed(3))
    cams = framed_camera(avatar, 64).expand(2)
    inputs = [frames.expression, frames.joint_rotations, torch.zeros(2, 2), cams.R, cams.t]
    want = renderer.deform_shade(*inputs)

    def refuse(*args, **kwargs):
        raise AssertionError("a tensor was built from host data inside the captured stage")

    for name in ("tensor", "as_tensor", "from_numpy"):
        monkeypatch.setattr(torch, name, refuse)
    got = renderer.deform_shade(*inputs)
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("precision", ["fp32", "fp16", "bf16"])
def test_dense_and_sparse_layouts_blend_alike(precision):
    """The dense [K, N x D] matrix (one product for B frames) and the stored pairs give the same Eq. 1, on a
    sparse avatar whose zeros the dense layout stores."""
    avatar = synth_avatar(gaussians=600, blendshapes=9, seed=3, local=True)
    dense, sparse = DeviceAvatar(avatar, "cpu", precision, "dense"), DeviceAvatar(avatar, "cpu", precision, "sparse")
    assert dense.nbytes == 9 * 600 * (11 + 3 * avatar.neutral.sh.shape[1]) * dense.matrix.element_size()
    assert sparse.nbytes < dense.nbytes
    psi = torch.rand(4, 9, generator=torch.Generator().manual_seed(2))
    a, b = dense.blend(psi), sparse.blend(psi)
    tol = {"fp32": 1e-5, "fp16": 2e-3, "bf16": 2e-2}[precision]
    for key, t in a.tensors().items():
        torch.testing.assert_close(t, getattr(b, key), atol=tol, rtol=tol, msg=key)


# ------------------------------------------------------------------------------- without CUDA: clear errors
@no_cuda
def test_cuda_backend_is_not_registered_and_says_why(avatar):
    assert "cuda" not in backend_names()
    with pytest.raises(ValueError, match="cuda.*unavailable.*no CUDA device"):
        check_backend("cuda")
    with pytest.raises(ValueError, match="no CUDA device"):
        AvatarRenderer(avatar, "cuda")
    with pytest.raises(ValueError, match="no CUDA device"):
        render(deform(avatar, Frame.neutral(avatar)), orbit(0.0, width=8, height=8), backend="cuda")
    with pytest.raises(RuntimeError, match="no CUDA device"):
        gsplat_backend.require()


def test_unavailable_reason_names_a_missing_or_wrong_gsplat(monkeypatch):
    reason = gsplat_backend.unavailable_reason.__wrapped__  # uncached
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat -> ImportError
    assert "gsplat is not installed" in reason() and "gsplat>=1.5,<1.6" in reason()
    fake = type(sys)("gsplat")
    fake.__version__ = "1.4.0"
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    assert "gsplat 1.4.0" in reason()
    fake.__version__ = "1.5.3"
    assert reason() is None


@no_cuda
def test_bench_and_cli_refuse_cuda_with_the_reason(capsys):
    from service.cli import main

    with pytest.raises(ValueError, match="no CUDA device"):
        bench_render("cuda", gaussians=100, blendshapes=2, size=16)
    with pytest.raises(ValueError, match="no CUDA device"):
        bench_raster_backward(gaussians=100, size=16, device="cuda")
    assert main(["bench", "render", "--backend", "cuda", "--json"]) == 1
    err = capsys.readouterr()
    assert "backend: 'cuda' is unavailable here: no CUDA device" in err.err and err.out == ""
    assert main(["bench", "raster-backward", "--device", "cuda", "--json"]) == 1
    with pytest.raises(ValueError, match="bf16"):
        bench_render("reference", gaussians=100, blendshapes=2, size=16, precision="bf16")


@no_cuda
def test_training_on_cuda_without_it_says_why():
    from render_core.train.trainer import raster_step

    with pytest.raises(OptionError, match="device='cuda'.*no CUDA device"):
        raster_step("cuda")
    with pytest.raises(ValueError, match="'cpu' or 'cuda'"):
        raster_step("tpu")
