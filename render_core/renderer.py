"""One avatar, one backend: frames in, images out.

:class:`AvatarRenderer` is what offline rendering, the benchmarks and the service use. It prepares what its backend
needs once per avatar (the native backend packs the blendshapes for streaming reads) and renders batches of
frames, reporting per-stage timings:

- ``native``: the fused C++ pipeline (blend, pose correctives, eyelids, LBS, SH colour, projection, binning,
  compositing) for B frames in one call;
- ``reference``: :func:`render_core.deform.blend`, :func:`render_core.deform.skin` and the torch rasterizer.
"""

from __future__ import annotations

import time

import torch
from torch import Tensor

from .avatar import Avatar
from .camera import Cameras
from .deform import Frame, blend, skin
from .errors import ShapeError
from .raster import RasterOutput, check_backend, native, render


class AvatarRenderer:
    """Renders frames of one avatar with one backend (default: native where built).

    ``precision`` ("fp32" or "fp16") is the native backend's blendshape storage (default: the avatar's own);
    ``simd`` forces a SIMD path (default: ``BLENDSPLAT_SIMD`` or the fastest); ``threads`` 0 uses all.
    """

    def __init__(self, avatar: Avatar, backend: str | None = None, *, precision: str | None = None,
                 simd: str | None = None, threads: int = 0):
        self.avatar = avatar
        self.backend = check_backend(backend)
        self.simd, self.threads = simd, threads
        self.native = native.NativeAvatar(avatar, precision) if self.backend == "native" else None
        # The reference path computes in float32 whatever the storage; cast fp16 avatars once, not per frame.
        needs_cast = self.native is None and avatar.precision != "fp32"
        self._compute_avatar = avatar.with_precision("fp32") if needs_cast else avatar

    @property
    def stats(self) -> native.PackStats | None:
        """What the native packing stored (None for the reference backend)."""
        return self.native.stats if self.native is not None else None

    def render(self, frame: Frame, cameras: Cameras, background: Tensor | None = None) -> RasterOutput:
        """B frames seen by B cameras (or one camera for all); RGB, alpha, depth and ``timings`` in ms."""
        frame.check(self.avatar)
        b = frame.batch_size
        if len(cameras) != b:
            if len(cameras) != 1:
                raise ShapeError(f"{b} frames need {b} cameras or one, got {len(cameras)}", field="cameras")
            cameras = cameras.expand(b)
        if self.native is not None:
            rgb, alpha, depth, timings = self.native.render(frame.expression, frame.joint_rotations, frame.eyelids,
                                                            cameras, background, simd=self.simd,
                                                            threads=self.threads)
            return RasterOutput(rgb, alpha, depth, timings=timings)
        with torch.no_grad():
            t0 = time.perf_counter()
            blended = blend(self._compute_avatar, frame.expression)
            t1 = time.perf_counter()
            splats = skin(self._compute_avatar, blended, frame)
            t2 = time.perf_counter()
            out = render(splats, cameras, backend=self.backend, background=background, mode=self.avatar.raster_mode)
            t3 = time.perf_counter()
        out.timings = {"blend": (t1 - t0) * 1e3, "lbs": (t2 - t1) * 1e3, "raster": (t3 - t2) * 1e3}
        return out

