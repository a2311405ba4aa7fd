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

import numpy as np
import torch
from torch import Tensor

from .avatar import Avatar, Gaussians
from .camera import Cameras
from .deform import Frame, blend, shade, skin
from .errors import OptionError, ShapeError
from .media.pixels import to_rgba8
from .packed import Pairs, SparseDeltas
from .raster import RasterOutput, ShadedSplats, check_backend, gsplat_backend, native, render

# Blendshape storage of a DeviceAvatar; compute is float32 whatever the storage.
STORAGE_DTYPES: dict[str, torch.dtype] = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}


LAYOUTS = ("dense", "sparse")
FUSIONS = ("off", "graph", "compile")


class DeviceAvatar:
    """An avatar resident on one device for the torch pipeline (the cuda backend's; any device works).

    The blendshapes are stored in ``precision`` ("fp32", "fp16" or "bf16"; default the avatar's, and fp32 for an
    int8 avatar: its dequantised values exactly; there is no int8 path on the GPU) in one of two layouts:

    - ``"dense"`` (the default): one ``[K, N x (11 + 3C)]`` matrix, geometry then SH per Gaussian, so Eq. 1 for B
      frames is one matrix product (cuBLAS, float32 accumulation) that streams the matrix once whatever B is: at
      3 TB/s the 64k x 50 fp16 matrix (378 MB) is read in about 0.13 ms. It holds the zeros a sparse avatar does
      not store (``nbytes`` says how much).
    - ``"sparse"``: :class:`~render_core.packed.SparseDeltas` as schema-2 bundles store them, only the stored
      (Gaussian, blendshape) pairs, one gather and one scatter-add per table: less memory, but it materialises
      ``[B, P, D]`` products (B x 0.75 GB at 64k x 50 dense), so it is for memory-bound deployments only.

    Everything else (LBS weights, joints, pose correctives, eyelids, mouth) is float32 on the device;
    :func:`render_core.deform.skin` and :func:`render_core.deform.shade` run on it unchanged.
    """

    def __init__(self, avatar: Avatar, device: torch.device | str, precision: str | None = None,
                 layout: str = "dense"):
        precision = precision or (avatar.precision if avatar.precision in STORAGE_DTYPES else "fp32")
        if precision not in STORAGE_DTYPES:
            raise OptionError(f"must be one of {', '.join(STORAGE_DTYPES)}, got {precision!r}", field="precision")
        if layout not in LAYOUTS:
            raise OptionError(f"must be one of {', '.join(LAYOUTS)}, got {layout!r}", field="layout")
        self.device, self.precision, self.store = torch.device(device), precision, STORAGE_DTYPES[precision]
        self.layout = layout
        sparse = avatar.sparse_deltas()  # a conversion for a dense avatar: done once
        self.deltas = sparse.to(self.device, self.store)
        self.matrix = None
        if layout == "dense":
            self.matrix = _dense_matrix(self.deltas)
            self.deltas = None
        # What skin() reads, float32 on the device (the neutral is added to the blended sums); with the dense
        # layout its deltas are an empty table of the same shape (the matrix holds them).
        held = self.deltas if self.deltas is not None else _no_pairs(sparse, self.device)
        self.avatar = replace(avatar, deltas=held).to(torch.float32, self.device)
        self.avatar.deltas = held
        self.raster_mode = avatar.raster_mode
        self._out_dtype = _mm_out_dtype(self.device, self.store)

    @property
    def nbytes(self) -> int:
        if self.matrix is not None:
            return self.matrix.numel() * self.matrix.element_size()
        return sum(t.numel() * t.element_size() for t in self.deltas.tensors().values())

    def blend(self, expression: Tensor) -> Gaussians:  # [B, K] -> Gaussians with [B, N, ...] tensors
        """Eq. 1, B(psi) = B0 + psi dB, for B frames (values in the storage precision, products and sums in
        float32), returned in float32."""
        expression = expression.to(device=self.device, dtype=torch.float32)
        if self.matrix is None:
            return blend(self.avatar, expression)
        neutral = self.avatar.neutral
        b, n = expression.shape[0], neutral.means.shape[0]
        if self._out_dtype:  # cuBLAS: storage-precision inputs, float32 accumulation and output
            flat = torch.mm(expression.to(self.store), self.matrix, out_dtype=torch.float32)
        else:
            flat = (expression.to(self.store) @ self.matrix).float()
        rows = flat.view(b, n, -1)
        return Gaussians(
            means=neutral.means + rows[..., 0:3], quats=neutral.quats + rows[..., 3:7],
            log_scales=neutral.log_scales + rows[..., 7:10], opacity_logits=neutral.opacity_logits + rows[..., 10],
            sh=neutral.sh + rows[..., 11:].reshape(b, n, *neutral.sh.shape[1:]),
        )


def _dense_matrix(deltas: SparseDeltas) -> Tensor:
    """``[K, N x (11 + 3C)]``: each Gaussian's geometry (means, quats, log-scales, opacity) then its SH deltas."""
    k, n = deltas.num_expressions, deltas.num_gaussians
    g, c = deltas.geometry, deltas.color
    out = torch.zeros(k, n, g.length + c.length, dtype=deltas.dtype, device=deltas.device)
    out[g.col.long(), g.rows(), :g.length] = g.matrix()
    out[c.col.long(), c.rows(), g.length:] = c.matrix()
    return out.view(k, -1)


def _no_pairs(deltas: SparseDeltas, device: torch.device) -> SparseDeltas:
    """``deltas``' shape (K, N, C) with no stored pair."""
    def empty(p: Pairs) -> Pairs:
        return Pairs(torch.zeros(deltas.num_gaussians + 1, dtype=torch.int32, device=device),
                     torch.zeros(0, dtype=torch.uint16, device=device),
                     torch.zeros(p.padding, dtype=torch.float32 if p.quantized else p.values.dtype, device=device),
                     p.length)

    return SparseDeltas(empty(deltas.geometry), empty(deltas.color), deltas.num_expressions, deltas.num_gaussians,
                        deltas.sh_coeffs)


def _mm_out_dtype(device: torch.device, store: torch.dtype) -> bool:
    """Whether ``torch.mm(..., out_dtype=torch.float32)`` runs here for ``store`` inputs (CUDA: fp16/bf16)."""
    if store == torch.float32 or device.type != "cuda":
        return False
    try:
        a = torch.ones(2, 2, dtype=store, device=device)
        return torch.mm(a, a, out_dtype=torch.float32).dtype == torch.float32
    except (RuntimeError, TypeError):
        return False


class _Graphed:
    """``fn`` over static device buffers captured as one CUDA graph: a call copies its inputs into the buffers
    and replays every kernel with one launch. The outputs are the graph's own buffers, overwritten by the next
    call (the renderer consumes them before that, on the same stream)."""

    def __init__(self, fn, inputs: list[Tensor]):
        self.inputs = [t.clone() for t in inputs]
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):  # warm-up outside the graph (allocator pools, lazy inits, autotuning)
                fn(*self.inputs)
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.outputs = fn(*self.inputs)

    def __call__(self, *inputs: Tensor):
        for buf, t in zip(self.inputs, inputs, strict=True):
            buf.copy_(t, non_blocking=True)
        self.graph.replay()
        return self.outputs


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

    ``precision`` is the blendshape storage: the native backend's ("fp32", "fp16" or "int8") or the cuda backend's
    ("fp32", "fp16" or "bf16"); default the avatar's own (the cuda and reference backends render an int8 avatar's
    dequantised values). ``simd`` forces a native SIMD path (default: ``BLENDSPLAT_SIMD``
    or the fastest); ``threads`` 0 uses all. The cuda backend's outputs stay on the GPU.

    The cuda backend's ``layout`` is :class:`DeviceAvatar`'s and ``fuse`` how blend + skinning + shading run
    before gsplat: ``"graph"`` (default) as one CUDA graph per batch size (one launch instead of a few hundred;
    their timings are one ``deform`` stage), ``"compile"`` the same over torch.compile's fused kernels, ``"off"``
    eagerly, stage by stage. A graph that cannot be captured falls back to ``"off"`` (``fuse_error`` says why).

    The native backend's ``schedule`` (:class:`~render_core.raster.native.Schedule`: lazy tiles, square blocks,
    RGBA8 straight from the compositing loop; default all on) changes its cost, never its pixels; a call may
    override it (``schedule=Schedule.baseline()`` renders the way it was before them).
    """

    def __init__(self, avatar: Avatar, backend: str | None = None, *, precision: str | None = None,
                 simd: str | None = None, threads: int = 0, layout: str = "dense", fuse: str = "graph",
                 schedule: native.Schedule | None = None):
        self.avatar = avatar
        self.backend = check_backend(backend)
        self.simd, self.threads = simd, threads
        self.schedule = schedule or native.Schedule()
        if fuse not in FUSIONS:
            raise OptionError(f"must be one of {', '.join(FUSIONS)}, got {fuse!r}", field="fuse")
        self.fuse, self.fuse_error = fuse, None
        self._graphs: dict[int, _Graphed] = {}
        self._cams: tuple[Cameras, Cameras] | None = None  # (as given, on the device): reused while unchanged
        self.native = native.NativeAvatar(avatar, precision) if self.backend == "native" else None
        self.device_avatar = None
        if self.backend == "cuda":
            gsplat_backend.build_extension()  # gsplat compiles its CUDA code on first use: now, not at a frame
            self.device_avatar = DeviceAvatar(avatar, gsplat_backend.device(), precision, layout)
            if self.device_avatar.device.type != "cuda":
                self.fuse = "off"  # graphs are CUDA's (the CPU emulation of the cuda path runs eagerly)
        # The reference path computes in float32 whatever the storage; cast fp16 (dequantise int8) avatars once,
        # not per frame.
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
            if dev.matrix is not None:
                own |= _storages([dev.matrix])
        given = _storages(_tensors(self.avatar))
        return held + sum(n for key, n in own.items() if key not in given)

    def _cameras(self, frame: Frame, cameras: Cameras) -> Cameras:
        frame.check(self.avatar)
        b = frame.batch_size
        if len(cameras) != b:
            if len(cameras) != 1:
                raise ShapeError(f"{b} frames need {b} cameras or one, got {len(cameras)}", field="cameras")
            cameras = cameras.expand(b)
        return cameras

    def render_rgba8(self, frame: Frame, cameras: Cameras, background: Tensor | None = None, *,
                     schedule: native.Schedule | None = None) -> tuple[np.ndarray, dict]:
        """B frames as 8-bit RGBA [B, H, W, 4] on the host (RGB over the background, then alpha: what encoders
        take; bit for bit :func:`~render_core.media.pixels.to_rgba8` of :meth:`render`'s images) and the
        timings. The native backend writes it from its compositing loop (``schedule.direct_rgba8``)."""
        if self.native is not None:
            cameras = self._cameras(frame, cameras)
            return self.native.render_rgba8(frame.expression, frame.joint_rotations, frame.eyelids, cameras,
                                            background, simd=self.simd, threads=self.threads,
                                            schedule=schedule or self.schedule)
        out = self.render(frame, cameras, background)
        return to_rgba8(out.rgb, out.alpha), out.timings

    def render(self, frame: Frame, cameras: Cameras, background: Tensor | None = None, *,
               schedule: native.Schedule | None = None) -> RasterOutput:
        """B frames seen by B cameras (or one camera for all); RGB, alpha, depth and ``timings`` in ms."""
        cameras = self._cameras(frame, cameras)
        if self.native is not None:
            rgb, alpha, depth, timings = self.native.render(frame.expression, frame.joint_rotations, frame.eyelids,
                                                            cameras, background, simd=self.simd,
                                                            threads=self.threads, schedule=schedule or self.schedule)
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
        """The cuda pipeline: blend, skin and shade on the device (eagerly or as one graph replay), then gsplat;
        stage times from CUDA events. Per frame the host only queues work (no synchronisation before the timings
        are read at the end)."""
        dev = self.device_avatar
        clock = _Clock(dev.device)
        with torch.no_grad():
            cams = self._device_cameras(cameras)
            bg = None if background is None else background.to(dev.device, torch.float32)
            clock.mark()
            if self.fuse != "off":
                shaded = self._fused(frame, cams)
                names = ("deform", "raster")
            else:
                frame = frame.to(torch.float32, dev.device)
                blended = dev.blend(frame.expression)
                clock.mark()
                splats = skin(dev.avatar, blended, frame)
                clock.mark()
                shaded = ShadedSplats.from_splats(splats, cams)
                names = ("blend", "lbs", "shade", "raster")
            clock.mark()
            out = gsplat_backend.rasterize(shaded, cams, bg, dev.raster_mode)
            clock.mark()
        out.timings = clock.stages(names)
        return out

    def _device_cameras(self, cameras: Cameras) -> Cameras:
        """``cameras`` on the device, float32; the last copy is reused while the cameras are unchanged (a stream's
        camera rarely moves, and each copy is a host-to-device transfer)."""
        last = self._cams
        if last is not None and len(last[0]) == len(cameras) and (last[0].width, last[0].height) == (
                cameras.width, cameras.height) and all(torch.equal(getattr(last[0], k), getattr(cameras, k))
                                                       for k in ("K", "R", "t")):
            return last[1]
        moved = cameras.to(torch.float32, self.device_avatar.device)
        self._cams = (Cameras(cameras.K.clone(), cameras.R.clone(), cameras.t.clone(), cameras.width,
                              cameras.height), moved)
        return moved

    def deform_shade(self, expression: Tensor, joint_rotations: Tensor, eyelids: Tensor, R: Tensor,
                     t: Tensor) -> tuple[Tensor, ...]:
        """Blend, skin and shade B frames for B cameras (device tensors, float32; eyelids zero where there is no
        eyelid motion): the five tensors of :class:`ShadedSplats`. Static shapes and no host synchronisation, so
        it can be captured as a CUDA graph."""
        dev = self.device_avatar
        frame = Frame(expression, joint_rotations, eyelids)
        splats = skin(dev.avatar, dev.blend(expression), frame)
        centres = -(R.transpose(-1, -2) @ t.unsqueeze(-1)).squeeze(-1)
        return splats.means, splats.quats, splats.scales, splats.opacities, shade(splats, centres)

    def _fused(self, frame: Frame, cams: Cameras) -> ShadedSplats:
        b = frame.batch_size
        eyelids = frame.eyelids if frame.eyelids is not None else torch.zeros(b, 2)
        inputs = [frame.expression, frame.joint_rotations, eyelids]
        graph = self._graphs.get(b)
        if graph is None:
            device_inputs = [x.to(self.device_avatar.device, torch.float32) for x in inputs] + [cams.R, cams.t]
            fn = self.deform_shade
            if self.fuse == "compile":
                fn = torch.compile(fn, dynamic=False)
            try:
                graph = _Graphed(fn, device_inputs)
            except Exception as e:  # noqa: BLE001 - a capture failure costs speed, never a frame
                self.fuse, self.fuse_error = "off", f"{type(e).__name__}: {e}"
                return ShadedSplats(*self.deform_shade(*device_inputs))
            if len(self._graphs) >= 16:  # one graph per batch size seen; the oldest goes
                self._graphs.pop(next(iter(self._graphs)))
            self._graphs[b] = graph
        return ShadedSplats(*graph(*inputs, cams.R, cams.t))
