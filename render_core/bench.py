"""``blendsplat bench render``: end-to-end frame time of blend + LBS + rasterization, per stage.

Rules: every timed frame gets fresh random expression coefficients and a fresh random pose (nothing can be cached
between frames), and the head is framed to cover 40-60% of the image (the focal length is calibrated on the
neutral frame before timing). Times are wall-clock medians over the timed frames.
"""

from __future__ import annotations

import math
import platform
import statistics
import time

import torch

from .avatar import Avatar
from .camera import Cameras, orbit
from .deform import Frame, blend, skin
from .raster import render
from .synth import synth_avatar

TARGET_COVERAGE = 0.5


def coverage(alpha: torch.Tensor) -> float:
    """Fraction of pixels with alpha > 0.5."""
    return float((alpha > 0.5).float().mean())


def framed_camera(avatar: Avatar, size: int, backend: str = "reference", probe: int = 128) -> Cameras:
    """A front camera whose focal length makes the neutral head cover about half of the image."""
    focal = 2.2 * probe
    with torch.no_grad():
        splats = skin(avatar, blend(avatar, torch.zeros(1, avatar.num_expressions)), Frame.neutral(avatar))
        for _ in range(4):
            cam = orbit(0.0, width=probe, height=probe, focal=focal)
            cov = coverage(render(splats, cam, backend=backend, mode=avatar.raster_mode).alpha)
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


def bench_render(
    backend: str = "reference",
    gaussians: int = 10_000,
    blendshapes: int = 50,
    size: int = 512,
    streams: int = 1,
    frames: int = 5,
    warmup: int = 1,
    sh_degree: int = 3,
    precision: str = "fp32",
    seed: int = 0,
    avatar: Avatar | None = None,
) -> dict:
    """Time ``frames`` frames (after ``warmup``) of ``streams`` batched streams; returns the JSON report."""
    if avatar is None:
        avatar = synth_avatar(gaussians, blendshapes, seed=seed, sh_degree=sh_degree)
        if precision == "fp16":
            avatar = avatar.to(torch.float16)
    camera = framed_camera(avatar, size)
    cams = Cameras(camera.K.expand(streams, 3, 3), camera.R.expand(streams, 3, 3), camera.t.expand(streams, 3),
                   size, size)
    g = torch.Generator().manual_seed(seed + 1)
    stages: dict[str, list[float]] = {"blend": [], "lbs": [], "raster": [], "total": []}
    covs = []
    with torch.no_grad():
        for i in range(warmup + frames):
            frame = random_frames(avatar, streams, g)
            t0 = time.perf_counter()
            blended = blend(avatar, frame.expression)
            t1 = time.perf_counter()
            splats = skin(avatar, blended, frame)
            t2 = time.perf_counter()
            out = render(splats, cams, backend=backend, mode=avatar.raster_mode)
            t3 = time.perf_counter()
            if i < warmup:
                continue
            for key, dt in (("blend", t1 - t0), ("lbs", t2 - t1), ("raster", t3 - t2), ("total", t3 - t0)):
                stages[key].append(dt * 1000.0)
            covs.append(coverage(out.alpha))
    ms = {k: round(statistics.median(v), 3) for k, v in stages.items()}
    fps = 1000.0 / ms["total"]
    return {
        "benchmark": "render",
        "backend": backend,
        "gaussians": avatar.num_gaussians,
        "mouth_gaussians": avatar.num_mouth,
        "blendshapes": avatar.num_expressions,
        "size": size,
        "streams": streams,
        "sh_degree": avatar.sh_degree,
        "precision": "fp16" if avatar.dtype == torch.float16 else "fp32",
        "raster_mode": avatar.raster_mode,
        "coverage": round(statistics.mean(covs), 4),
        "fps": round(fps, 3),
        "aggregate_fps": round(fps * streams, 3),
        "ms": ms,
        "frames": frames,
        "warmup": warmup,
        "threads": torch.get_num_threads(),
        "machine": {"cpu": _cpu_name(), "python": platform.python_version(), "torch": torch.__version__},
    }


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
