"""One avatar, one backend: frames in, images out.

:class:`AvatarRenderer` is what offline rendering, the benchmarks and the service use. It prepares what its backend
needs once per avatar (the native backend packs the blendshapes for streaming reads, the cuda backend moves the
avatar to the GPU) and renders batches of frames, reporting per-stage timings:

- ``native``: the fused C++ pipeline (blend, pose correctives, eyelids, LBS, SH colour, projection, binning,
  compositing) for B frames in one call;
- ``cuda``: :class:`DeviceAvatar` on the GPU (blend over the stored pairs of the sparse fp16/bf16/fp32
  blendshapes, :func:`render_core.deform.skin`, :func:`render_core.deform.shade`) and gsplat's rasterizer;
  outputs stay on the GPU;
- ``reference``: :func:`render_core.deform.blend`, :func:`render_core.deform.skin` and the torch rasterizer.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import fields, replace

import torch
from torch import Tensor

from .avatar import Avatar, Gaussians
from .camera import Cameras
from .deform import Frame, blend, skin
from .errors import OptionError, ShapeError
from .packed import SparseDeltas
from .raster import RasterOutput, ShadedSplats, check_backend, gsplat_backend, native, render

# Blendshape storage of a DeviceAvatar; compute is float32 whatever the storage.
STORAGE_DTYPES: dict[str, torch.dtype] = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}


class DeviceAvatar:
    """An avatar resident on one device for the torch pipeline (the cuda backend's; any device works).

    The blendshapes stay sparse (:class:`~render_core.packed.SparseDeltas`, the layout schema-2 bundles store) in
    ``precision`` ("fp32", "fp16" or "bf16"; default the avatar's): Eq. 1 for B frames multiplies only the stored
    (Gaussian, blendshape) pairs, one gather and one scatter-add per table, added to the float32 neutral.
    Everything else (LBS weights, joints, pose correctives, eyelids, mouth) is float32 on the device;
    :func:`render_core.deform.skin` and :func:`render_core.deform.shade` run on it unchanged.
    """

    def __init__(self, avatar: Avatar, device: torch.device | str, precision: str | None = None):
        precision = precision or avatar.precision
        if precision not in STORAGE_DTYPES:
            raise OptionError(f"must be one of {', '.join(STORAGE_DTYPES)}, got {precision!r}", field="precision")
        self.device, self.precision, self.store = torch.device(device), precision, STORAGE_DTYPES[precision]
        self.deltas = avatar.sparse_deltas().to(self.device, self.store)
        # What skin() reads, float32 on the device (the neutral is added to the blended sums).
        self.avatar = replace(avatar, deltas=self.deltas).to(torch.float32, self.device)
        self.avatar.deltas = self.deltas
        self.raster_mode = avatar.raster_mode

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.deltas.tensors().values())

    def blend(self, expression: Tensor) -> Gaussians:  # [B, K] -> Gaussians with [B, N, ...] tensors
        """Eq. 1, B(psi) = B0 + psi dB, for B frames over the stored pairs (values in the storage precision,
        products and sums in float32), returned in float32."""
        return blend(self.avatar, expression.to(device=self.device, dtype=torch.float32))


def _tensors(avatar: Avatar) -> Iterator[Tensor]:
    """Every tensor an avatar holds (its Gaussians' and the rest)."""
    for f in fields(avatar):
        value = getattr(avatar, f.name)
        if isinstance(value, Tensor):
            yield value
        elif isinstance(value, Gaussians | SparseDeltas):
            yield from value.tensors().values()


def _storages(tensors: Iterable[Tensor]) -> dict[tuple[str, int], int]:
    """The distinct memory behind ``tensors`` (views and shared tensors once): (device, address) -> bytes."""
    return {(str(t.device), t.untyped_storage().data_ptr()): t.untyped_storage().nbytes() for t in tensors}


class _Clock:
    """Stage marks: CUDA events on a GPU (one synchronize when read), wall-clock time elsewhere."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.marks: list = []

    def mark(self) -> None:
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            self.marks.append(event)
        else:
            self.marks.append(time.perf_counter())

    def stages(self, names: tuple[str, ...]) -> dict[str, float]:
        """Milliseconds between consecutive marks, one per name (waits for the GPU)."""
        if self.cuda:
            self.marks[-1].synchronize()
            return {k: a.elapsed_time(b) for k, a, b in zip(names, self.marks[:-1], self.marks[1:], strict=True)}
        return {k: (b - a) * 1e3 for k, a, b in zip(names, self.marks[:-1], self.marks[1:], strict=True)}


class AvatarRenderer:
    """Renders frames of one avatar with one backend (default: native where built).

    ``precision`` is the blendshape storage: the native backend's ("fp32" or "fp16") or the cuda backend's ("fp32",
    "fp16" or "bf16"); default the avatar's own. ``simd`` forces a native SIMD path (default: ``BLENDSPLAT_SIMD``
    or the fastest); ``threads`` 0 uses all. The cuda backend's outputs stay on the GPU.
    """

    def __init__(self, avatar: Avatar, backend: str | None = None, *, precision: str | None = None,
                 simd: str | None = None, threads: int = 0):
        self.avatar = avatar
        self.backend = check_backend(backend)
        self.simd, self.threads = simd, threads
        self.native = native.NativeAvatar(avatar, precision) if self.backend == "native" else None
        self.device_avatar = None
        if self.backend == "cuda":
            gsplat_backend.build_extension()  # gsplat compiles its CUDA code on first use: now, not at a frame
            self.device_avatar = DeviceAvatar(avatar, gsplat_backend.device(), precision)
        # The reference path computes in float32 whatever the storage; cast fp16 avatars once, not per frame.
        needs_cast = self.backend == "reference" and avatar.precision != "fp32"
        self._compute_avatar = avatar.with_precision("fp32") if needs_cast else avatar

    @property
    def stats(self) -> native.PackStats | None:
        """What the native packing stored (None for the reference backend)."""
        return self.native.stats if self.native is not None else None

    @property
    def nbytes(self) -> int:
        """Bytes this renderer holds for its avatar, on the host or the device: the native backend's packed arrays,
        the cuda backend's device-resident avatar (the packed blendshape matrix and the float32 tensors skinning
        reads, in GPU memory), the reference backend's float32 copy of an fp16 avatar. Memory shared with the
        avatar it was given is not counted: that avatar is the caller's (0 for the reference backend on an fp32
        avatar, which renders the avatar itself)."""
        held = self.native.nbytes if self.native is not None else 0
        own = _storages(_tensors(self._compute_avatar))
        if self.device_avatar is not None:
            dev = self.device_avatar
            own |= _storages(_tensors(dev.avatar))
        given = _storages(_tensors(self.avatar))
        return held + sum(n for key, n in own.items() if key not in given)

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
        if self.device_avatar is not None:
            return self._render_device(frame, cameras, background)
        clock = _Clock(torch.device("cpu"))
        with torch.no_grad():
            clock.mark()
            blended = blend(self._compute_avatar, frame.expression)
            clock.mark()
            splats = skin(self._compute_avatar, blended, frame)
            clock.mark()
            out = render(splats, cameras, backend=self.backend, background=background, mode=self.avatar.raster_mode)
            clock.mark()
        out.timings = clock.stages(("blend", "lbs", "raster"))
        return out

    def _render_device(self, frame: Frame, cameras: Cameras, background: Tensor | None) -> RasterOutput:
        """The cuda pipeline: blend, skin and shade on the device, then gsplat; stage times from CUDA events.

        Per frame the host only queues kernels (no synchronisation before the timings are read at the end).
        """
        dev = self.device_avatar
        clock = _Clock(dev.device)
        with torch.no_grad():
            cams = cameras.to(torch.float32, dev.device)
            bg = None if background is None else background.to(dev.device, torch.float32)
            clock.mark()
            frame = frame.to(torch.float32, dev.device)
            blended = dev.blend(frame.expression)
            clock.mark()
            splats = skin(dev.avatar, blended, frame)
            clock.mark()
            shaded = ShadedSplats.from_splats(splats, cams)
            clock.mark()
            out = gsplat_backend.rasterize(shaded, cams, bg, dev.raster_mode)
            clock.mark()
        out.timings = clock.stages(("blend", "lbs", "shade", "raster"))
        return out
