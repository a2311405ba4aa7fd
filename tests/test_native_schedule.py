"""The native renderer's schedule switches (render_core.raster.native.Schedule: lazy tiles, square blocks, direct
RGBA8) change its cost, never a pixel: every combination gives bit-identical images on every SIMD path, the RGBA8
output is to_rgba8 of the float images bit for bit, and the benchmark's side-by-side comparison says so. The
precision switch (the 8-bit stop) leaves the float images alone and keeps the 8-bit ones within one level and
50 dB of the exact ones."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from render_core.camera import orbit
from render_core.evaluation.metrics import psnr
from render_core.raster import ShadedSplats, native
from render_core.renderer import AvatarRenderer
from render_core.tools.bench import bench_render, framed_camera, random_frames
from render_core.tools.synth import synth_avatar

pytestmark = pytest.mark.skipif(not native.available(), reason="the native extension is not built")

SIMD = native.simd_paths() if native.available() else []
# Every schedule, and the exact ones (the 8-bit stop changes 8-bit output only).
SCHEDULES = [native.Schedule(*switches) for switches in itertools.product((False, True), repeat=4)]
EXACT = [s for s in SCHEDULES if s.exact]
SIZES = [(96, 96), (61, 37)]  # whole tiles, and partial tiles in both directions


@pytest.fixture(scope="module")
def dense_head():
    """A head dense enough that its tiles hold several lazy chunks (> 64 splats) and saturate."""
    return synth_avatar(gaussians=6000, blendshapes=8, seed=7)


def _cams(avatar, w: int, h: int):
    focal = float(framed_camera(avatar, 64).K[0, 0, 0]) * max(w, h) / 64
    return orbit([0.0, 25.0, -15.0], width=w, height=h, focal=focal)


def _scene(avatar, simd: str, size: tuple[int, int]):
    """A renderer on one SIMD path, three frames, their cameras and three backgrounds."""
    frame = random_frames(avatar, 3, torch.Generator().manual_seed(3))
    bg = torch.tensor([[0.2, 0.4, 0.6], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    return AvatarRenderer(avatar, "native", simd=simd), frame, _cams(avatar, *size), bg


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_every_schedule_renders_the_same_bits(dense_head, simd, size):
    r, frame, cams, bg = _scene(dense_head, simd, size)
    base = r.render(frame, cams, bg, schedule=native.Schedule.baseline())
    assert float((base.alpha > 0.999).float().mean()) > 0.1  # saturated pixels: lazy tiles stop early somewhere
    want8 = native.to_rgba8(base.rgb, base.alpha)
    for schedule in SCHEDULES:
        out = r.render(frame, cams, bg, schedule=schedule)
        for name in ("rgb", "alpha", "depth"):
            assert torch.equal(getattr(out, name), getattr(base, name)), (schedule, name)
    for schedule in EXACT:
        rgba8, timings = r.render_rgba8(frame, cams, bg, schedule=schedule)
        assert rgba8.dtype == np.uint8 and rgba8.shape == (3, size[1], size[0], 4)
        assert np.array_equal(rgba8, want8), schedule
        assert timings["isa"] == simd and timings["raster"] > 0


@pytest.mark.parametrize("simd", SIMD)
def test_posed_rasterization_is_the_same_under_every_schedule(dense_head, simd):
    from render_core.deform import deform

    cams = _cams(dense_head, 80, 48)
    frame = random_frames(dense_head, 3, torch.Generator().manual_seed(5))
    splats = ShadedSplats.from_splats(deform(dense_head.with_precision("fp32"), frame), cams)
    base = native.rasterize(splats, cams, schedule=native.Schedule.baseline(), simd=simd)
    for schedule in SCHEDULES:
        out = native.rasterize(splats, cams, schedule=schedule, simd=simd)
        assert torch.equal(out.rgb, base.rgb) and torch.equal(out.alpha, base.alpha), schedule
        assert torch.equal(out.depth, base.depth), schedule


@pytest.mark.parametrize("simd", SIMD)
@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_the_eight_bit_stop_keeps_each_byte_within_a_level_of_the_exact_image(dense_head, simd, size):
    r, frame, cams, bg = _scene(dense_head, simd, size)
    exact, _ = r.render_rgba8(frame, cams, bg, schedule=native.Schedule(eight_bit_stop=False))
    for square in (False, True):
        stopped, _ = r.render_rgba8(frame, cams, bg, schedule=native.Schedule(square_blocks=square))
        diff = np.abs(stopped.astype(np.int32) - exact)
        assert diff.max() <= 1, (square, int(diff.max()))
        assert 0 < np.count_nonzero(diff) < diff.size // 4  # it stops early (saturated pixels change a little)
        assert psnr(stopped[..., :3], exact[..., :3]) >= 50.0
        assert np.array_equal(stopped[..., 3], exact[..., 3])  # a stopped pixel is opaque either way


def test_the_renderer_default_schedule_is_every_switch_and_can_be_turned_off(dense_head):
    assert AvatarRenderer(dense_head, "native").schedule == native.Schedule(True, True, True, True)
    off = AvatarRenderer(dense_head, "native", schedule=native.Schedule.baseline()).schedule
    assert off == native.Schedule(False, False, False, False) and off.exact
    assert not native.Schedule().exact and native.Schedule(direct_rgba8=False).exact


def test_rgba8_of_the_reference_backend_is_to_rgba8_of_its_render(dense_head):
    r = AvatarRenderer(dense_head, "reference")
    cams = _cams(dense_head, 24, 24)
    frame = random_frames(dense_head, 3, torch.Generator().manual_seed(1))
    rgba8, _ = r.render_rgba8(frame, cams)
    out = r.render(frame, cams)
    assert np.array_equal(rgba8, native.to_rgba8(out.rgb, out.alpha))


def test_unknown_schedule_bits_are_refused(dense_head):
    from render_core import _native

    packed = native.NativeAvatar(dense_head)
    cams = _cams(dense_head, 16, 16).index(slice(0, 1))
    frame = random_frames(dense_head, 1, torch.Generator().manual_seed(1))
    args = packed._inputs(frame.expression, frame.joint_rotations, frame.eyelids, cams, None)
    rgb, alpha, depth = (np.zeros(s, np.float32) for s in ((1, 16, 16, 3), (1, 16, 16), (1, 16, 16)))
    with pytest.raises(ValueError, match="flags"):
        _native.render(packed.handle, *args, rgb, alpha, depth, "auto", 0, 64)
    with pytest.raises(ValueError, match="flags"):
        _native.render_rgba8(packed.handle, *args, np.zeros((1, 16, 16, 4), np.uint8), "auto", 0, 64)
    assert _native.EIGHT_BIT_STOP == 4  # known: the switch the schedule sets


def test_bench_render_times_the_8_bit_output_a_stream_encodes(dense_head, monkeypatch):
    calls = []
    rgba8 = AvatarRenderer.render_rgba8
    monkeypatch.setattr(AvatarRenderer, "render_rgba8", lambda self, *a, **k: calls.append(1) or rgba8(self, *a, **k))
    report = bench_render("native", avatar=dense_head, size=32, frames=2, warmup=1)
    assert report["output"] == "rgba8" and len(calls) == 3 and 0.0 < report["coverage"] < 1.0
    assert {"blend", "lbs", "raster", "bin", "total"} == set(report["ms"])
    calls.clear()
    floats = bench_render("native", avatar=dense_head, size=32, frames=2, warmup=1, output="float")
    assert floats["output"] == "float" and calls == []
    assert floats["coverage"] == pytest.approx(report["coverage"], abs=0.02)  # the same frames (same seed)


def test_bench_render_compares_the_schedules_side_by_side(dense_head):
    report = bench_render("native", avatar=dense_head, size=64, streams=2, frames=2, warmup=1, schedule="compare")
    cmp = report["vs_baseline"]
    assert cmp["frames"] == 2 and cmp["speedup"] > 0
    assert cmp["identical"] is False and 50.0 <= cmp["psnr_db"] < 100.0 and cmp["max_level_difference"] == 1
    assert cmp["baseline"]["lazy_tiles"] is False and cmp["schedule"]["lazy_tiles"] is True
    assert {"blend", "lbs", "raster", "bin", "total"} == set(cmp["schedule"]["ms"])
    assert report["schedule"] == {"lazy_tiles": True, "square_blocks": True, "direct_rgba8": True,
                                  "eight_bit_stop": True}
    assert report["frames_per_core_second"] == pytest.approx(report["aggregate_fps"] / report["threads"], rel=1e-3)
    off = bench_render("native", avatar=dense_head, size=32, frames=1, warmup=0, schedule="off")
    assert off["schedule"]["square_blocks"] is False and "vs_baseline" not in off
    with pytest.raises(Exception, match="schedule"):
        bench_render("native", avatar=dense_head, size=32, frames=1, schedule="fast")


def test_bench_render_stops_the_clock_before_the_coverage(dense_head, monkeypatch):
    """The coverage (a statistic of the report, nothing a stream computes) is not in a frame's time: with a clock
    that jumps a second while the coverage is taken (and a microsecond a reading), every total stays far below it."""
    from render_core.tools import bench

    clock = [0.0]
    real = bench.coverage_rgba8

    def slow_coverage(image):
        clock[0] += 1.0  # one second a call
        return real(image)

    monkeypatch.setattr(bench, "coverage_rgba8", slow_coverage)
    def tick():
        clock[0] += 1e-6
        return clock[0]

    monkeypatch.setattr(bench, "time", SimpleNamespace(perf_counter=tick))
    report = bench_render("native", avatar=dense_head, size=32, frames=2, warmup=1)
    assert report["ms"]["total"] < 1.0 and clock[0] > 3.0 and 0.0 < report["coverage"] < 1.0
