"""``blendsplat bench render``: end-to-end frame time of blend + LBS + rasterization, per stage, as JSON;
``blendsplat bench codecs``: encode time and size of rendered frames per streaming codec.

Rules: every timed frame gets fresh random expression coefficients and a fresh random pose (nothing can be cached
between frames), and the head is framed to cover 40-60% of the image (the focal length is calibrated on the
neutral frame before timing). Times are medians over the timed frames; ``total`` is the wall-clock time of the
whole render call. With ``reference_frames`` (opt-in: the torch reference takes tens of seconds a frame at 64k
Gaussians) a non-reference backend's run also times the reference backend on the same avatar and camera
(``vs_reference``), and for the native backend a memory-bandwidth probe reads as many bytes as one blend streams, so
the blend is reported against that bound. Each stage is logged (``render_core.tools.bench``, INFO: the command's
stderr) as it starts, the reference's frames one by one. The cuda backend's stage times come from CUDA events
(``shade``, the SH colour, is its own stage there) and its report names the GPU.
"""

from __future__ import annotations

import logging
import math
import os
import platform
import statistics
import time
from dataclasses import asdict

import numpy as np
import torch

from ..avatar import Avatar
from ..camera import Cameras, orbit
from ..deform import Frame
from ..errors import OptionError
from ..evaluation.metrics import psnr_from_mse
from ..media.pixels import to_rgba8
from ..raster import ShadedSplats, check_backend, gsplat_backend, native
from ..renderer import AvatarRenderer
from .synth import synth_avatar

TARGET_COVERAGE = 0.5
log = logging.getLogger(__name__)


def coverage(alpha: torch.Tensor) -> float:
    """Fraction of pixels with alpha > 0.5."""
    return float((alpha > 0.5).float().mean())


def coverage_rgba8(image: np.ndarray) -> float:
    """Fraction of pixels of 8-bit RGBA [..., 4] with alpha > 0.5 (128 and up, as :func:`coverage` of alpha / 255)."""
    return float((image[..., 3] >= 128).mean())


def framed_camera(avatar: Avatar, size: int, probe: int = 128) -> Cameras:
    """A front camera whose focal length makes the neutral head cover about half of the image."""
    focal = 2.2 * probe
    renderer = AvatarRenderer(avatar)
    neutral = Frame.neutral(avatar)
    for _ in range(5):
        cov = coverage(renderer.render(neutral, orbit(0.0, width=probe, height=probe, focal=focal)).alpha)
        if abs(cov - TARGET_COVERAGE) < 0.03:
            break
        focal *= math.sqrt(TARGET_COVERAGE / max(cov, 1e-3))
    return orbit(0.0, width=size, height=size, focal=focal * size / probe)


def random_frames(avatar: Avatar, batch: int, g: torch.Generator) -> Frame:
    """Fresh random coefficients in [0, 1] and a plausible random pose (head, neck, jaw, eyes)."""
    expression = torch.rand(batch, avatar.num_expressions, generator=g)
    limits = {"root": 0.15, "neck": 0.15, "head": 0.15, "jaw": 0.2, "eye_l": 0.15, "eye_r": 0.15}
    joints = {}
    for name in avatar.joint_names:
        aa = (torch.rand(batch, 3, generator=g) * 2 - 1) * limits.get(name, 0.1)
        if name == "jaw":
            aa = torch.stack([aa[:, 0].abs() + 0.05, aa[:, 1] * 0.1, aa[:, 2] * 0.1], -1)
        joints[name] = aa
    eyelids = torch.rand(batch, 2, generator=g) * 0.5 if avatar.eyelid_offsets is not None else None
    return Frame.from_params(avatar, expression=expression, joints=joints, eyelids=eyelids)


# What a renderer's timings may hold, in order; "bin" (native: depth sort and tile binning) is part of "raster"
STAGES = ("blend", "lbs", "shade", "deform", "raster", "bin")


def _time_frames(renderer: AvatarRenderer, cams: Cameras, frames: int, warmup: int, g: torch.Generator,
                 label: str | None = None, *, output: str) -> dict:
    """Medians of ``frames`` timed renders after ``warmup``; with ``label`` each render is logged as it ends (for
    slow backends: the reference). ``output``: ``"float"`` (:meth:`AvatarRenderer.render`: RGB, alpha and depth)
    or ``"rgba8"`` (:meth:`AvatarRenderer.render_rgba8`: the 8-bit RGBA a stream encodes)."""
    stages: dict[str, list[float]] = {}
    totals: list[float] = []
    covs: list[float] = []
    timings: dict = {}
    for i in range(warmup + frames):
        frame = random_frames(renderer.avatar, len(cams), g)
        t0 = time.perf_counter()
        if output == "rgba8":
            image, timings = renderer.render_rgba8(frame, cams)
            total = (time.perf_counter() - t0) * 1e3
            cov = coverage_rgba8(image)  # after the clock stopped: a stream computes no coverage
        else:
            out = renderer.render(frame, cams)
            total = (time.perf_counter() - t0) * 1e3
            timings, cov = out.timings, coverage(out.alpha)
        if label is not None:
            log.info("%s: %s %d/%d: %.1f s", label, "warm-up frame" if i < warmup else "frame",
                     i + 1 if i < warmup else i + 1 - warmup, warmup if i < warmup else frames, total / 1e3)
        if i < warmup:
            continue
        timings = timings or {}
        for key in STAGES:
            if key in timings:
                stages.setdefault(key, []).append(float(timings[key]))
        totals.append(total)
        covs.append(cov)
    stages["total"] = totals
    return {"ms": {k: round(statistics.median(v), 3) for k, v in stages.items()},
            "coverage": round(statistics.mean(covs), 4), "last_timings": timings}


def profile_frames(renderer: AvatarRenderer, cams: Cameras, g: torch.Generator, path: str, frames: int = 20,
                   top: int = 12) -> dict:
    """Profile ``frames`` renders with torch.profiler (CPU, and CUDA where the renderer runs there); write the
    Chrome trace to ``path`` and return the ``top`` operators by self time on the device (CPU otherwise)."""
    from torch.profiler import ProfilerActivity, profile

    on_gpu = renderer.device_avatar is not None
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if on_gpu else [])
    batches = [random_frames(renderer.avatar, len(cams), g) for _ in range(frames)]
    with profile(activities=activities) as prof:
        t0 = time.perf_counter()
        for frame in batches:
            renderer.render(frame, cams)
        if on_gpu:
            torch.cuda.synchronize()
        wall = (time.perf_counter() - t0) * 1e3 / frames
    prof.export_chrome_trace(path)
    key = "self_device_time_total" if on_gpu else "self_cpu_time_total"
    rows = sorted(prof.key_averages(), key=lambda e: getattr(e, key, 0.0), reverse=True)[:top]
    per_frame = 1e3 * frames
    return {"trace": path, "frames": frames, "ms_per_frame_profiled": round(wall, 3), "sorted_by": key,
            "top": [{"name": e.key, "calls": e.count, "self_ms_per_frame": round(getattr(e, key, 0.0) / per_frame, 4),
                     "cpu_ms_per_frame": round(e.self_cpu_time_total / per_frame, 4)} for e in rows]}


SCHEDULES = ("on", "off", "compare")
OUTPUTS = ("rgba8", "float")


def compare_schedules(renderer: AvatarRenderer, cams: Cameras, frames: int, warmup: int,
                      g: torch.Generator) -> dict:
    """The native renderer's schedule against :meth:`Schedule.baseline` (every switch off), side by side in one
    process: each frame rendered to 8-bit RGBA (what a stream encodes) by both, in alternating order; each one's
    stage medians, the speed-up of the totals, whether every image was identical and, for the precision switch
    (``eight_bit_stop``), the PSNR of the schedule's RGB against the baseline's (255 levels, pooled over the frames)
    and the largest difference in levels (any channel; 0: identical)."""
    runs = {"baseline": native.Schedule.baseline(), "schedule": renderer.schedule}
    stages: dict[str, dict[str, list[float]]] = {name: {} for name in runs}
    sq_error, values, max_levels = 0.0, 0, 0
    for i in range(warmup + frames):
        frame = random_frames(renderer.avatar, len(cams), g)
        images = {}
        for name in (list(runs) if i % 2 == 0 else list(runs)[::-1]):
            t0 = time.perf_counter()
            images[name], timings = renderer.render_rgba8(frame, cams, schedule=runs[name])
            total = (time.perf_counter() - t0) * 1e3
            if i >= warmup:
                for key in ("blend", "lbs", "raster", "bin"):
                    stages[name].setdefault(key, []).append(float(timings[key]))
                stages[name].setdefault("total", []).append(total)
        diff = images["schedule"].astype(np.int32) - images["baseline"]
        rgb = diff[..., :3]
        sq_error, values = sq_error + float(np.square(rgb, dtype=np.float64).sum()), values + rgb.size
        max_levels = max(max_levels, int(np.abs(diff).max()))
    ms = {name: {k: round(statistics.median(v), 3) for k, v in rows.items()} for name, rows in stages.items()}
    return {**{name: {**asdict(s), "ms": ms[name], "fps": round(1000.0 / ms[name]["total"] * len(cams), 2)}
               for name, s in runs.items()},
            "speedup": round(ms["baseline"]["total"] / ms["schedule"]["total"], 3), "identical": max_levels == 0,
            "psnr_db": round(psnr_from_mse(sq_error / values, 255.0), 2), "max_level_difference": max_levels,
            "frames": frames}


def _check_counts(minimum: int, **counts: int) -> None:
    """OptionError naming the first count below ``minimum``."""
    for name, value in counts.items():
        if value < minimum:
            raise OptionError(f"must be at least {minimum}, got {value}", field=name)


def bench_render(
    backend: str | None = None,
    gaussians: int = 10_000,
    blendshapes: int = 50,
    size: int = 512,
    streams: int = 1,
    frames: int = 10,
    warmup: int = 2,
    sh_degree: int = 3,
    precision: str = "fp16",
    seed: int = 0,
    avatar: Avatar | None = None,
    reference_frames: int = 0,
    threads: int = 0,
    trace: str | None = None,
    layout: str = "dense",
    fuse: str = "graph",
    schedule: str = "on",
    output: str = "rgba8",
) -> dict:
    """Time ``frames`` frames (after ``warmup``) of ``streams`` batched streams; returns the JSON report.

    ``trace``: also profile a few more frames with torch.profiler, write its Chrome trace there and add the
    operators that took the most time (``profile``) to the report.

    ``reference_frames``: also time that many frames of the torch reference backend on the same avatar and camera
    (``vs_reference``: the speed-up); 0 (the default) skips it: at 64k Gaussians and 512 px one reference frame
    takes tens of seconds.

    ``precision`` is the blendshape storage: the synthetic avatar's ("fp32", "fp16" or "int8": quantised pairs,
    which the native blend reads as they are and the cuda backend dequantises to fp32), and for the cuda backend
    the storage on the GPU ("bf16" too, from an fp16 avatar).

    ``schedule`` (native): ``"on"`` (every :class:`~render_core.raster.native.Schedule` switch), ``"off"`` (the
    baseline), or ``"compare"``: the timed frames with the schedule on, then the same frames rendered to RGBA8 by
    both schedules side by side (``vs_baseline``: :func:`compare_schedules`).

    ``output``: what the timed frames render: ``"rgba8"`` (the default: the 8-bit RGBA a stream encodes, which the
    native backend writes from its compositing loop, with the 8-bit stop) or ``"float"`` (RGB, alpha and depth as
    training and ``render`` take them)."""
    if schedule not in SCHEDULES:
        raise OptionError(f"must be one of {', '.join(SCHEDULES)}, got {schedule!r}", field="schedule")
    if output not in OUTPUTS:
        raise OptionError(f"must be one of {', '.join(OUTPUTS)}, got {output!r}", field="output")
    _check_counts(1, size=size, streams=streams, frames=frames)
    _check_counts(0, warmup=warmup, reference_frames=reference_frames, threads=threads)
    backend = check_backend(backend)  # before building the avatar: an unavailable backend fails at once
    if precision == "bf16" and backend != "cuda":
        raise OptionError("bf16 blendshape storage is the cuda backend's only; use fp16 or fp32",
                          field="precision")
    if avatar is None:
        stored = "fp16" if precision == "bf16" else precision
        log.info("building a synthetic avatar: %d Gaussians, %d blendshapes, %s", gaussians, blendshapes, stored)
        avatar = synth_avatar(gaussians, blendshapes, seed=seed, sh_degree=sh_degree).with_precision(stored)
    log.info("preparing the %s renderer and framing the camera", backend)
    # bf16 is a storage on the GPU only (from the fp16 avatar); otherwise every backend stores the avatar's own.
    renderer = AvatarRenderer(avatar, backend, threads=threads, precision="bf16" if precision == "bf16" else None,
                              layout=layout, fuse=fuse,
                              schedule=native.Schedule.baseline() if schedule == "off" else None)
    cams = framed_camera(avatar, size).expand(streams)
    g = torch.Generator().manual_seed(seed + 1)
    log.info("timing %d frame(s) of %d stream(s) at %d px (after %d warm-up)", frames, streams, size, warmup)
    timed = _time_frames(renderer, cams, frames, warmup, g, output=output)
    ms = timed["ms"]
    fps = 1000.0 / ms["total"]
    report = {
        "benchmark": "render",
        "backend": renderer.backend,
        "gaussians": avatar.num_gaussians,
        "mouth_gaussians": avatar.num_mouth,
        "blendshapes": avatar.num_expressions,
        "size": size,
        "streams": streams,
        "sh_degree": avatar.sh_degree,
        "precision": renderer.device_avatar.precision if renderer.device_avatar is not None else avatar.precision,
        "raster_mode": avatar.raster_mode,
        "output": output,
        "coverage": timed["coverage"],
        "fps": round(fps, 3),
        "aggregate_fps": round(fps * streams, 3),
        "ms": ms,
        "frames": frames,
        "warmup": warmup,
        "threads": timed["last_timings"].get("threads", torch.get_num_threads()),
        "machine": {**machine(), "torch": torch.__version__},
    }
    if renderer.native is not None:
        stats = renderer.stats
        log.info("memory-bandwidth probe over %.0f MB (one blend's bytes)", stats.blend_bytes / 1e6)
        # Best of three probes (each the best of five passes): the machine is shared, a single probe can read low.
        probe = max((native.bandwidth_probe(stats.blend_bytes, threads) for _ in range(3)), key=lambda p: p["gbps"])
        bound_ms = stats.blend_bytes / (probe["gbps"] * 1e9) * 1e3
        report["simd"] = timed["last_timings"].get("isa")
        # the CPU cost: frames per second of one core (the render's threads busy for its wall time)
        report["frames_per_core_second"] = round(fps * streams / max(int(report["threads"]), 1), 3)
        report["schedule"] = asdict(renderer.schedule)
        if schedule == "compare":
            log.info("the same frames with the baseline schedule and this one, side by side")
            report["vs_baseline"] = compare_schedules(renderer, cams, frames, warmup, g)
        report["blend"] = {
            "bytes": stats.blend_bytes,
            "stored_pairs": stats.pairs_stored,
            "stored_fraction": round(stats.stored_fraction, 4),
            "bandwidth_gbps": round(probe["gbps"], 2),
            "bound_ms": round(bound_ms, 3),
            "vs_bound": round(ms["blend"] / bound_ms, 3),
        }
    dev = renderer.device_avatar
    if dev is not None:
        report["device"] = gsplat_backend.device_name()
        report["machine"].update(gpu=report["device"], cuda=torch.version.cuda, gsplat=_gsplat_version())
        report["blend"] = {"bytes": dev.nbytes, "layout": dev.layout}  # the blendshapes on the device
        report["fuse"] = renderer.fuse
        if renderer.fuse_error:
            report["fuse_error"] = renderer.fuse_error
    if trace is not None:
        log.info("profiling 20 frames with torch.profiler -> %s", trace)
        report["profile"] = profile_frames(renderer, cams, g, trace)
    if renderer.backend != "reference" and reference_frames > 0:
        log.info("timing %d frame(s) of the torch reference backend for the speed-up (slow: tens of seconds a "
                 "frame at 64k Gaussians; --reference-frames 0 skips it)", reference_frames)
        ref = _time_frames(AvatarRenderer(avatar, "reference"), cams, reference_frames, 1, g, label="reference",
                          output=output)
        ref_fps = 1000.0 / ref["ms"]["total"]
        report["vs_reference"] = {"reference_fps": round(ref_fps, 4), "speedup": round(fps / ref_fps, 1),
                                  "reference_ms": ref["ms"], "frames": reference_frames}
    return report


def _time_raster_step(raster, avatar: Avatar, cams: Cameras, frames: int, warmup: int, g: torch.Generator,
                      device: torch.device | None = None) -> dict:
    """Median forward and backward ms of ``raster(splats, cams, bg, mode)`` -> (rgb, alpha) on fresh shaded splats
    each frame, for the loss sum(w rgb) + sum(v alpha) with random w, v.
    ``device``: where the inputs live (a CUDA device is synchronised before each clock reading)."""
    from ..deform import deform

    device = device or torch.device("cpu")
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    cams_dev = cams.to(device=device)
    fwd, bwd, last = [], [], {}
    for i in range(warmup + frames):
        splats = deform(avatar, random_frames(avatar, len(cams), g))
        shaded = ShadedSplats.from_splats(splats, cams)
        leaves = ShadedSplats(*(t.detach().float().to(device).contiguous().requires_grad_(True)
                                for t in shaded.tensors().values()))
        bg = torch.rand(len(cams), 3, generator=g).to(device).requires_grad_(True)
        w = torch.randn(len(cams), cams.height, cams.width, 3, generator=g).to(device)
        v = torch.randn(len(cams), cams.height, cams.width, generator=g).to(device)
        sync()
        t0 = time.perf_counter()
        rgb, alpha = raster(leaves, cams_dev, bg, avatar.raster_mode)
        sync()
        t1 = time.perf_counter()
        ((rgb * w).sum() + (alpha * v).sum()).backward()
        sync()
        t2 = time.perf_counter()
        if i >= warmup:
            fwd.append((t1 - t0) * 1e3)
            bwd.append((t2 - t1) * 1e3)
            last = {"node": rgb.grad_fn, "alpha": alpha.detach()}
    f, b = statistics.median(fwd), statistics.median(bwd)
    return {"forward_ms": round(f, 3), "backward_ms": round(b, 3), "total_ms": round(f + b, 3), "frames": frames,
            "_last": last}


def bench_raster_backward(gaussians: int = 10_000, size: int = 256, frames: int = 10, reference_frames: int = 2,
                          warmup: int = 1, batch: int = 1, seed: int = 0, threads: int = 0,
                          simd: str | None = None, device: str = "cpu") -> dict:
    """Forward and backward time of the differentiable rasterizer: the native one
    (:func:`render_core.raster.native.rasterize_differentiable`) against the torch reference's autograd, side by
    side in one run on the same synthetic head (``gaussians`` face Gaussians plus its mouth, SH degree 0, framed to
    cover about half of a ``size`` square image), fresh random expression and pose every frame. Medians (ms) per
    call of ``batch`` frames; the reference runs ``reference_frames`` frames.

    ``device="cuda"``: the timed rasterizer is gsplat's on the GPU (training's CUDA step, inputs already on the
    GPU), reported under ``cuda`` with the GPU's name, and the native one (where built) runs as the comparison
    instead of the reference."""
    from ..raster import reference

    if device not in ("cpu", "cuda"):
        raise OptionError(f"device must be 'cpu' or 'cuda', got {device!r}", field="device")
    _check_counts(1, size=size, frames=frames, batch=batch)
    _check_counts(0, warmup=warmup, reference_frames=reference_frames, threads=threads)
    if device == "cuda":
        check_backend("cuda")
    avatar = synth_avatar(gaussians, 8, seed=seed, sh_degree=0)
    cams = framed_camera(avatar, size).expand(batch)
    g = torch.Generator().manual_seed(seed + 1)

    def native_step(*args):
        return native.rasterize_differentiable(*args, simd=simd, threads=threads)

    def reference_step(*args):
        out = reference.rasterize(*args)
        return out.rgb, out.alpha

    report: dict = {"benchmark": "raster_backward", "device": device, "gaussians": avatar.num_gaussians,
                    "mouth_gaussians": avatar.num_mouth, "size": size, "batch": batch,
                    "raster_mode": avatar.raster_mode}
    if device == "cuda":
        gpu = gsplat_backend.device()
        cuda = _time_raster_step(gsplat_backend.rasterize_differentiable, avatar, cams, frames, warmup, g, gpu)
        report["coverage"] = round(coverage(cuda.pop("_last")["alpha"]), 4)
        report["cuda"] = {**cuda, "gpu": gsplat_backend.device_name(), "gsplat": _gsplat_version()}
        if native.available() and reference_frames > 0:
            nat = _time_raster_step(native_step, avatar, cams, reference_frames, warmup, g)
            nat.pop("_last")
            report["native"] = nat
            report["speedup_vs_native"] = {k: round(nat[f"{k}_ms"] / max(cuda[f"{k}_ms"], 1e-9), 1)
                                           for k in ("forward", "backward", "total")}
    else:
        nat = _time_raster_step(native_step, avatar, cams, frames, warmup, g)
        last = nat.pop("_last")
        node = last["node"]
        report["coverage"] = round(coverage(last["alpha"]), 4)
        report["native"] = {**nat, "simd": node.timings.get("isa"), "threads": node.timings.get("threads"),
                            "forward_stages_ms": {k: round(node.timings[k], 3) for k in ("lbs", "bin", "raster")},
                            "backward_stages_ms": {k: round(node.backward_timings[k], 3)
                                                   for k in ("raster", "project")},
                            "pairs": node.handle.pairs, "saved_bytes": node.handle.nbytes}
        if reference_frames > 0:
            ref = _time_raster_step(reference_step, avatar, cams, reference_frames, warmup, g)
            ref.pop("_last")
            report["reference"] = ref
            report["speedup"] = {k: round(ref[f"{k}_ms"] / max(nat[f"{k}_ms"], 1e-9), 1)
                                 for k in ("forward", "backward", "total")}
    report["machine"] = {**machine(), "torch": torch.__version__, "torch_threads": torch.get_num_threads()}
    return report


def smooth_frames(avatar: Avatar, frames: int, fps: float, g: torch.Generator) -> Frame:
    """A talking-head-like sequence at ``fps``: the expression glides between two random ones, the neck turns
    and nods slowly and the jaw opens and closes at 2 Hz (consecutive frames are as similar as in a live stream)."""
    t = torch.arange(frames, dtype=torch.float32)[:, None] / fps
    a, b = torch.rand(2, avatar.num_expressions, generator=g)
    expression = a + (b - a) * (t / max(t[-1].item(), 1e-6))
    zero = torch.zeros_like(t)
    joints = {"neck": torch.cat([0.1 * torch.sin(1.3 * t), 0.3 * torch.sin(2.1 * t), zero], -1),
              "jaw": torch.cat([0.12 + 0.1 * torch.sin(4 * math.pi * t), zero, zero], -1)}
    joints = {k: v for k, v in joints.items() if k in avatar.joint_names}
    return Frame.from_params(avatar, expression=expression, joints=joints)


def bench_codecs(size: int = 512, frames: int = 30, gaussians: int = 20_000, seed: int = 0,
                 background: tuple[float, float, float] = (0.5, 0.5, 0.5)) -> dict:
    """Encode time (median and 95th percentile, ms) and mean size of ``frames`` rendered frames of a synthetic
    avatar (a smooth 30 fps sequence over ``background``) for every streaming codec at its default quality.

    Each codec first encodes one frame on a throwaway encoder (imports, tables); the timed encoder then starts
    fresh, so H.264 includes its opening IDR frame as a new stream would."""
    from ..media.codecs import CODECS, make_encoder

    _check_counts(1, size=size, frames=frames)
    avatar = synth_avatar(gaussians, 50, seed=seed).with_precision("fp16")
    renderer = AvatarRenderer(avatar)
    cams = framed_camera(avatar, size)
    seq = smooth_frames(avatar, frames, 30.0, torch.Generator().manual_seed(seed + 1))
    bg = torch.tensor(background, dtype=torch.float32)
    images = []
    for i in range(0, frames, 8):
        chunk = Frame(seq.expression[i:i + 8], seq.joint_rotations[i:i + 8])
        out = renderer.render(chunk, cams, background=bg)
        images += list(to_rgba8(out.rgb, out.alpha))  # RGB over the background + alpha
    report: dict = {"benchmark": "codecs", "size": size, "frames": frames, "gaussians": avatar.num_gaussians,
                    "backend": renderer.backend, "coverage": round(float((images[0][..., 3] > 127).mean()), 4),
                    "codecs": {}}
    for codec in CODECS:
        with make_encoder(codec, size, size) as warm:
            warm.encode(images[0])
        times, sizes = [], []
        with make_encoder(codec, size, size) as enc:
            for image in images:
                t0 = time.perf_counter()
                data = enc.encode(image)
                times.append((time.perf_counter() - t0) * 1e3)
                sizes.append(len(data))
        mean_bytes = statistics.mean(sizes)
        report["codecs"][codec] = {
            "media_type": enc.media_type,
            "encode_ms": {"median": round(float(np.median(times)), 4),
                          "p95": round(float(np.percentile(times, 95)), 4)},
            "bytes_per_frame": round(mean_bytes, 1),
            "mbit_s_at_30fps": round(mean_bytes * 8 * 30 / 1e6, 3),
        }
    report["machine"] = machine()
    return report


def _gsplat_version() -> str | None:
    try:
        import gsplat
    except ImportError:
        return None
    return getattr(gsplat, "__version__", None)


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def machine() -> dict:
    """Where a benchmark ran: the CPU's name, the cores this process may use, the Python version."""
    return {"cpu": _cpu_name(), "cores": _cores(), "python": platform.python_version()}


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def generated_adapter(seed: int = 0, expressions: int = 50, joints: tuple[str, ...] = ("jaw",)):
    """The default adapter of ``bench adapter``: ARKit-52 -> a FLAME-sized target (50 expressions + jaw), linear,
    with random weights and clamping. Returns (model bytes, manifest)."""
    from ..adapters.manifest import AdapterManifest
    from ..adapters.onnx_model import model_bytes
    from ..facemodel.open_head import ARKIT_52

    rng = np.random.default_rng(seed)
    manifest = AdapterManifest(
        id="bench-arkit-to-flame", source_names=list(ARKIT_52), source_convention="arkit-52",
        target_face_model="flame-sized", target_expression_names=[f"exp_{i:02d}" for i in range(expressions)],
        target_joint_names=list(joints), expression_min=[-3.0] * expressions, expression_max=[3.0] * expressions,
        provenance={"tool": "blendsplat bench adapter", "method": "random weights"})
    weights = rng.normal(0, 0.3, (expressions + 3 * len(joints), len(ARKIT_52)))
    return model_bytes(manifest, weights), manifest


def bench_adapter(model: bytes | None = None, manifest=None, frames: int = 2000, warmup: int = 100,
                  render_frames: int = 3, size: int = 512, gaussians: int = 10_000, seed: int = 0) -> dict:
    """Per-frame cost of an adapter in the engine's call (onnxruntime run + the finite check), at batch 1 and at
    batch 8 (the batch's time / 8), medians over ``frames`` calls; beside it the render time of one frame of a
    synthetic avatar with the adapter's target expression count (0 render frames: skipped)."""
    from ..adapters.runtime import AdapterRuntime

    _check_counts(1, frames=frames, size=size, gaussians=gaussians)
    _check_counts(0, warmup=warmup, render_frames=render_frames)
    if model is None:
        model, manifest = generated_adapter(seed)
    runtime = AdapterRuntime(model, manifest)
    rng = np.random.default_rng(seed)
    per_frame = {}
    for batch in (1, 8):
        inputs = rng.uniform(0, 1, (warmup + frames, batch, manifest.num_source)).astype(np.float32)
        times = []
        for i, x in enumerate(inputs):
            t0 = time.perf_counter_ns()
            runtime.run(x)
            if i >= warmup:
                times.append((time.perf_counter_ns() - t0) / 1e6)
        per_frame[f"batch{batch}"] = round(statistics.median(times) / batch, 5)
        per_frame[f"batch{batch}_p95"] = round(float(np.percentile(times, 95)) / batch, 5)
    report = {
        "benchmark": "adapter",
        "adapter": manifest.id,
        "source": manifest.source_convention,
        "inputs": manifest.num_source,
        "outputs": {"expression": manifest.num_expressions, "joints": manifest.num_joints,
                    "values": manifest.num_expressions + 3 * manifest.num_joints},
        "model_bytes": len(model),
        "ms_per_frame": {"batch1": per_frame["batch1"], "batch8": per_frame["batch8"]},
        "p95_ms_per_frame": {"batch1": per_frame["batch1_p95"], "batch8": per_frame["batch8_p95"]},
        "frames": frames,
        "threads": {"intra_op": 1},
        "machine": machine(),
    }
    try:
        import onnxruntime

        report["machine"]["onnxruntime"] = onnxruntime.__version__
    except ImportError:  # pragma: no cover - the runtime above imported it
        pass
    if render_frames:
        render = bench_render(gaussians=gaussians, blendshapes=max(manifest.num_expressions, 1), size=size,
                              frames=render_frames, warmup=1, reference_frames=0, seed=seed)
        report["render_ms_per_frame"] = render["ms"]["total"]
        report["render"] = {"backend": render["backend"], "gaussians": render["gaussians"], "size": size,
                            "blendshapes": render["blendshapes"]}
        report["adapter_vs_render"] = round(per_frame["batch8"] / render["ms"]["total"], 6)
    return report
