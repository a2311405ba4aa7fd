"""The native CPU backend: a C++ extension (render_core/native/, nanobind + OpenMP) with scalar, AVX2 and AVX-512
kernels chosen at run time. ``BLENDSPLAT_SIMD=scalar|avx2|avx512`` forces one path (an unavailable one is an
error naming the available ones).

Two entry points share the kernels:
  - :func:`rasterize` (and :func:`rasterize_differentiable`, with a C++ backward): shaded splats, as every backend
    takes them (:mod:`render_core.raster.splats`; the ``render()`` backend, tested against the reference
    rasterizer);
  - :class:`NativeAvatar`: an avatar in the packed layout of :mod:`render_core.packed` (Gaussian rows and the
    geometry and colour tables of the (Gaussian, blendshape) pairs that are not zero, fp32, fp16 or int8 with
    their scales, read as they are stored; an avatar read from a schema-2 bundle already is that layout and is used
    as mapped) - rendered by the fused per-frame
    pipeline (blend, pose correctives, eyelids, LBS, SH colour, projection, tile binning, depth sort,
    compositing) for B frames in one call.
Arrays cross into C++ as numpy views of contiguous CPU float32 tensors: no copies.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import host, packed
from ..avatar import PRECISIONS as AVATAR_PRECISIONS
from ..avatar import Avatar, check_raster_mode, sh_coeff_count
from ..camera import Cameras
from ..errors import OptionError, ShapeError
from .splats import RasterOutput, ShadedSplats

try:
    from .. import _native
except ImportError as e:  # a source tree without the compiled extension
    _native = None
    IMPORT_ERROR: str | None = str(e)
else:
    IMPORT_ERROR = None

PRECISIONS = ("fp32", "fp16", "int8")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Schedule:
    """How the native renderer schedules its work: each switch can be turned off to measure what it buys. The first
    three change the cost, never a pixel (the images are bit-identical either way; tests compare them):

    - ``lazy_tiles``: a tile's splats are gathered and their row spans computed a chunk at a time, and the tile
      stops once every pixel has stopped (the splats behind a saturated tile cost nothing);
    - ``square_blocks``: pixels composited in 4 x 4 blocks (one 16-lane vector; 4 x 2 with 8 lanes) instead of
      8 x 2 (8 x 1), which wastes fewer lanes on splats a few pixels wide;
    - ``direct_rgba8``: :meth:`NativeAvatar.render_rgba8` writes 8-bit RGBA from the compositing loop instead of
      float images converted afterwards.

    The fourth is a precision switch, for 8-bit output alone (``direct_rgba8``; float images never change):

    - ``eight_bit_stop``: a pixel also stops once a composited splat takes its transmittance below 1/1020 (the
      exact rule alone goes on to 1e-4): what lies behind could move its colour by at most a quarter of an 8-bit
      level, so the bytes stay within one level of the exact ones (>= 60 dB on the 64k head; tests gate it at 50 dB).
    """

    lazy_tiles: bool = True
    square_blocks: bool = True
    direct_rgba8: bool = True
    eight_bit_stop: bool = True

    @classmethod
    def baseline(cls) -> Schedule:
        """Every switch off: the schedule before them, and the exact image."""
        return cls(lazy_tiles=False, square_blocks=False, direct_rgba8=False, eight_bit_stop=False)

    @property
    def exact(self) -> bool:
        """Whether the images are bit-identical to :meth:`baseline`'s."""
        return not (self.eight_bit_stop and self.direct_rgba8)

    @property
    def flags(self) -> int:
        """The compositing flags of the C++ kernels."""
        _require()
        return ((_native.LAZY_TILES if self.lazy_tiles else 0) | (_native.SQUARE_BLOCKS if self.square_blocks else 0)
                | (_native.EIGHT_BIT_STOP if self.eight_bit_stop else 0))


def available() -> bool:
    return _native is not None


def _require() -> None:
    if _native is None:
        raise RuntimeError(f"the native backend is not built ({IMPORT_ERROR}); reinstall the package")


def simd_paths() -> list[str]:
    """SIMD paths this build can execute on this CPU, slowest first."""
    _require()
    return list(_native.available_isas())


def simd_choice(simd: str | None = None) -> str:
    """The SIMD path to use: ``simd`` if given, else ``BLENDSPLAT_SIMD``, else the fastest verified path."""
    source = "simd" if simd else "BLENDSPLAT_SIMD"
    choice = simd or os.environ.get("BLENDSPLAT_SIMD", "auto") or "auto"
    if choice == "auto":
        return verified_fastest_path()
    if choice not in simd_paths():
        raise OptionError(f"{choice!r} is not a SIMD path this CPU and build run; available: "
                          f"{', '.join(simd_paths())} (or auto)", field=source)
    return choice


@functools.cache
def verified_fastest_path() -> str:
    """The fastest SIMD path that renders a small avatar like the scalar path does (checked once per process).

    A path that disagrees (a miscompiled or untested instruction set on a new CPU) is skipped with a warning, so
    "auto" never trades correctness for speed.
    """
    paths = simd_paths()
    if len(paths) == 1:
        return paths[0]
    from ..camera import orbit
    from ..facemodel.synthetic import synth_avatar
    from ..rotation import axis_angle_to_matrix

    avatar = synth_avatar(400, 4, seed=11)
    packed = NativeAvatar(avatar)
    cams = orbit([0.0, 35.0], [5.0, -10.0], width=40, height=40)
    g = torch.Generator().manual_seed(5)
    expression = torch.rand(2, avatar.num_expressions, generator=g)
    rotations = axis_angle_to_matrix(0.2 * torch.randn(2, avatar.num_joints, 3, generator=g))
    eyelids = torch.rand(2, 2, generator=g)

    def rgb(path: str) -> Tensor:
        return packed.render(expression, rotations, eyelids, cams, simd=path)[0]

    want = rgb("scalar")
    for path in reversed(paths[1:]):
        err = float((rgb(path) - want).abs().max())
        if err <= 1e-3:
            return path
        log.warning("SIMD path %s disagrees with the scalar path (max error %.3g); not using it", path, err)
    return "scalar"


def _np(t: Tensor) -> np.ndarray:
    """A contiguous CPU float32 numpy view (a copy only when the tensor is not already float32, CPU and
    contiguous; without a torch call that gives the GIL up: render_core.host)."""
    return host.array(t, np.float32)


def _check_finite(**tensors: Tensor | None) -> None:
    for name, t in tensors.items():
        if t is not None and not host.finite(t):
            raise ShapeError("must be finite (no NaN or Inf)", field=name)


def _check_cameras(cameras: Cameras) -> None:
    _check_finite(**{"camera.K": cameras.K, "camera.R": cameras.R, "camera.t": cameras.t})


def _outputs(b: int, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return (np.empty((b, h, w, 3), np.float32), np.empty((b, h, w), np.float32), np.empty((b, h, w), np.float32))


def _background(background: Tensor | None, b: int) -> np.ndarray:
    if background is None:
        return np.zeros((b, 3), np.float32)
    return np.ascontiguousarray(np.broadcast_to(_np(background).reshape(-1, 3), (b, 3)))


def _camera_arrays(cameras: Cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return _np(cameras.K), _np(cameras.R), _np(cameras.t)


def _check_posed(splats: ShadedSplats, cameras: Cameras, background: Tensor | None, mode: str) -> None:
    """What both rasterize entry points check before the native code runs (it checks the shapes)."""
    _require()
    check_raster_mode(mode)
    _check_finite(**splats.tensors(), background=background)
    _check_cameras(cameras)


def rasterize(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None, mode: str = "classic", *,
              simd: str | None = None, threads: int = 0, schedule: Schedule | None = None) -> RasterOutput:
    """Splat ``splats`` for ``cameras`` as every backend does (:mod:`render_core.raster.splats`), in float32 with
    the stage timings; no autograd. ``simd``: the SIMD path (:func:`simd_choice`); ``threads`` 0: all;
    ``schedule``: :class:`Schedule` (default: every switch on)."""
    _check_posed(splats, cameras, background, mode)
    b = splats.means.shape[0]
    rgb, alpha, depth = _outputs(b, cameras.height, cameras.width)
    K, R, t = _camera_arrays(cameras)
    timings = _native.rasterize(*map(_np, splats.tensors().values()), K, R, t, cameras.width, cameras.height,
                                mode == "antialiased", _background(background, b), rgb, alpha, depth,
                                simd_choice(simd), threads, (schedule or Schedule()).flags)
    return RasterOutput(torch.from_numpy(rgb), torch.from_numpy(alpha), torch.from_numpy(depth),
                        timings=dict(timings))


class _Rasterize(torch.autograd.Function):
    """The native forward and backward of :func:`rasterize` (float32 in C++; see rasterize_differentiable), taking
    the splats' five tensors one by one (autograd tracks tensor arguments)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, background, cameras, mode, simd, threads):
        b = means.shape[0]
        m32, q32, s32, o32 = (t.detach().to(dtype=torch.float32).contiguous()
                              for t in (means, quats, scales, opacities))
        bg = _background(background, b)
        rgb, alpha, depth = _outputs(b, cameras.height, cameras.width)
        K, R, t = _camera_arrays(cameras)
        timings, handle = _native.rasterize_train(
            m32.numpy(), q32.numpy(), s32.numpy(), o32.numpy(), _np(colors), K, R, t, cameras.width,
            cameras.height, mode == "antialiased", bg, rgb, alpha, depth, simd_choice(simd), threads)
        # The float32 copies (or the inputs themselves where already float32 and contiguous): autograd checks
        # that they are not modified in place before the backward.
        ctx.save_for_backward(m32, q32, s32, o32)
        ctx.handle, ctx.bg, ctx.threads = handle, bg, threads
        ctx.dtypes = [t.dtype for t in (means, quats, scales, opacities, colors)]
        ctx.bg_shape = None if background is None else (background.shape, background.dtype)
        ctx.timings = dict(timings)
        return torch.from_numpy(rgb), torch.from_numpy(alpha)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_rgb, grad_alpha):
        m32, q32, s32, o32 = ctx.saved_tensors
        b, n = o32.shape
        g = [np.empty((b, n, 3), np.float32), np.empty((b, n, 4), np.float32), np.empty((b, n, 3), np.float32),
             np.empty((b, n), np.float32), np.empty((b, n, 3), np.float32)]
        g_bg = np.empty((b, 3), np.float32)
        timings = _native.rasterize_backward(ctx.handle, m32.numpy(), q32.numpy(), s32.numpy(), o32.numpy(),
                                             ctx.bg, _np(grad_rgb), _np(grad_alpha), *g, g_bg, ctx.threads)
        ctx.backward_timings = dict(timings)
        grads = [torch.from_numpy(x).to(dt) for x, dt in zip(g, ctx.dtypes, strict=True)]
        grad_bg = None
        if ctx.bg_shape is not None and ctx.needs_input_grad[5]:
            shape, dtype = ctx.bg_shape
            grad_bg = torch.from_numpy(g_bg).to(dtype).sum_to_size(shape)
        grads = [x if need else None for x, need in zip(grads, ctx.needs_input_grad[:5], strict=True)]
        return (*grads, grad_bg, None, None, None, None)


def rasterize_differentiable(splats: ShadedSplats, cameras: Cameras, background: Tensor | None = None,
                             mode: str = "classic", *, simd: str | None = None,
                             threads: int = 0) -> tuple[Tensor, Tensor]:
    """:func:`rasterize` with a native backward: rgb [B, H, W, 3] and alpha [B, H, W] (float32), differentiable
    w.r.t. the splats' tensors and the background (depth is not returned: not differentiable).

    The same image as :func:`rasterize`, bit for bit. The gradients are those of docs/method.md section 9 exactly as the
    reference rasterizer's autograd gives them (no gradient through skipped, clamped or stopped pairs, nor through
    culling), computed in float32 and returned in each input's dtype; bitwise the same for any thread count.

    Memory kept from the forward to the backward, per frame: 64 bytes per Gaussian (its projected splat), 4 bytes
    per (Gaussian, 16x16 tile) pair, 8 bytes per pixel (final transmittance and last contributor), plus float32
    copies of means, quats, scales and opacities where the inputs are not float32 and contiguous. The backward
    itself needs 36 bytes per pair (per-pair gradient moments), kept by the calling thread for reuse.
    """
    _check_posed(splats, cameras, background, mode)
    return _Rasterize.apply(*splats.tensors().values(), background, cameras, mode, simd, threads)


@dataclass
class PackStats:
    """What packing kept: the stored entries of the geometry and colour pair tables (each (Gaussian, blendshape)
    pair has one of each, stored when non-zero: ``pairs_total`` = 2 N K) and the bytes one frame's blend streams."""

    pairs_stored: int
    pairs_total: int
    blend_bytes: int
    precision: str

    @property
    def stored_fraction(self) -> float:
        return self.pairs_stored / self.pairs_total if self.pairs_total else 0.0


class NativeAvatar:
    """An avatar in the packed layout (:mod:`render_core.packed`) for the native fused pipeline.

    An avatar read from a schema-2 bundle already is that layout: its memory-mapped tensors go to the C++ side as
    they are (no copy; only the small transposed LBS weights are built). Any other avatar is packed once here.
    ``precision`` (:data:`PRECISIONS`; default the avatar's) is the storage the blend reads: another than the
    avatar's is made here (cast, quantised to int8 or dequantised from it).
    """

    def __init__(self, avatar: Avatar, precision: str | None = None):
        _require()
        if precision is None:
            precision = avatar.precision
        if precision not in PRECISIONS:
            raise OptionError(f"must be one of {PRECISIONS}, got {precision!r}", field="precision")
        store = AVATAR_PRECISIONS[precision]
        side = torch.float16 if store == torch.int8 else store  # the pose correctives of int8 avatars are fp16
        n, k, j = avatar.num_gaussians, avatar.num_expressions, avatar.num_joints
        c = sh_coeff_count(avatar.sh_degree)
        deltas = avatar.sparse_deltas(store)
        pc = (packed.pack_correctives(avatar.pose_correctives, side) if avatar.pose_correctives is not None and j > 1
              else torch.zeros(0, dtype=side))
        eyelid = (packed.pack_eyelids(avatar.eyelid_offsets) if avatar.eyelid_offsets is not None
                  else torch.zeros(0))
        mouth_joint = torch.tensor([avatar.joint_index(nm) for nm in avatar.mouth_joint_names])[avatar.mouth_group]
        # [J, N + M]: consecutive Gaussians load as one vector; the mouth follows its joint rigidly.
        lbs = torch.zeros(j, n + avatar.num_mouth)
        lbs[:, :n] = avatar.lbs_weights.T
        lbs[mouth_joint, torch.arange(n, n + avatar.num_mouth)] = 1.0

        def bits(t: Tensor) -> np.ndarray:  # fp16 crosses as its uint16 bits, int8 as it is
            if t.dtype == torch.float16:
                return t.contiguous().view(torch.int16).numpy().view(np.uint16)
            return t.contiguous().numpy() if t.dtype == torch.int8 else _np(t)

        def extra(t: Tensor | None, dtype: type) -> np.ndarray:  # int8 tables' scales and residuals, else empty
            return t.contiguous().numpy() if t is not None else np.zeros(0, dtype)

        g, sh = deltas.geometry, deltas.color
        self._arrays = dict(
            base=_np(packed.pack_rows(avatar.neutral, avatar.mouth)),
            geo_ptr=g.row_ptr.numpy(), geo_col=g.col.numpy(), geo_vals=bits(g.values),
            sh_ptr=sh.row_ptr.numpy(), sh_col=sh.col.numpy(), sh_vals=bits(sh.values),
            pc=bits(pc),
            eyelid=_np(eyelid),
            lbs=lbs.numpy(),
            joints=_np(avatar.joint_positions),
            parents=np.asarray(avatar.joint_parents, dtype=np.int32),
            geo_scale=extra(g.scale, np.float32), geo_residual=extra(g.position_residual, np.int8),
            sh_scale=extra(sh.scale, np.float32),
        )
        self.handle = _native.NativeAvatar(**self._arrays, n_face=n, K=k, C=c)
        self.avatar = avatar
        streamed = ("base", "geo_ptr", "geo_col", "geo_vals", "sh_ptr", "sh_col", "sh_vals", "pc",
                    "geo_residual", "geo_scale", "sh_scale")
        self.stats = PackStats(
            pairs_stored=g.count + sh.count, pairs_total=2 * n * k,
            blend_bytes=int(sum(self._arrays[key].nbytes for key in streamed)),
            precision=precision,
        )

    @property
    def nbytes(self) -> int:
        """Host bytes of the packed arrays this object made: arrays that are the avatar's own memory (an avatar
        read from a schema-2 bundle, whose file already is the packed layout) are not counted again."""
        spans = [(t.untyped_storage().data_ptr(), t.untyped_storage().nbytes()) for t in _avatar_tensors(self.avatar)
                 if t.device.type == "cpu"]

        def owned(a: np.ndarray) -> bool:
            p = a.__array_interface__["data"][0]
            return a.nbytes > 0 and not any(start <= p < start + size for start, size in spans)

        return sum(a.nbytes for a in self._arrays.values() if owned(a))

    def render(
        self,
        expression: Tensor,  # [B, K]
        joint_rotations: Tensor,  # [B, J, 3, 3]
        eyelids: Tensor | None,  # [B, 2]
        cameras: Cameras,  # B cameras
        background: Tensor | None = None,  # [B, 3] or [3]
        *,
        simd: str | None = None,
        threads: int = 0,
        schedule: Schedule | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Fused blend + skinning + splatting of B frames; rgb, alpha, depth and per-stage timings (ms).
        ``schedule``: :class:`Schedule` (default: every switch on)."""
        args = self._inputs(expression, joint_rotations, eyelids, cameras, background)
        rgb, alpha, depth = _outputs(expression.shape[0], cameras.height, cameras.width)
        timings = _native.render(self.handle, *args, rgb, alpha, depth, simd_choice(simd), threads,
                                 (schedule or Schedule()).flags)
        return torch.from_numpy(rgb), torch.from_numpy(alpha), torch.from_numpy(depth), dict(timings)

    def render_rgba8(self, expression: Tensor, joint_rotations: Tensor, eyelids: Tensor | None, cameras: Cameras,
                     background: Tensor | None = None, *, simd: str | None = None, threads: int = 0,
                     schedule: Schedule | None = None) -> tuple[np.ndarray, dict]:
        """As :meth:`render`, as 8-bit RGBA [B, H, W, 4] (colour over the background, then alpha; what
        :func:`to_rgba8` makes of :meth:`render`'s rgb and alpha, bit for bit) and the timings; with
        ``schedule.direct_rgba8`` written by the compositing loop, without float images."""
        schedule = schedule or Schedule()
        if not schedule.direct_rgba8:
            rgb, alpha, _, timings = self.render(expression, joint_rotations, eyelids, cameras, background,
                                                 simd=simd, threads=threads, schedule=schedule)
            return to_rgba8(rgb, alpha, threads), timings
        args = self._inputs(expression, joint_rotations, eyelids, cameras, background)
        out = np.empty((expression.shape[0], cameras.height, cameras.width, 4), np.uint8)
        timings = _native.render_rgba8(self.handle, *args, out, simd_choice(simd), threads, schedule.flags)
        return out, dict(timings)

    def _inputs(self, expression: Tensor, joint_rotations: Tensor, eyelids: Tensor | None, cameras: Cameras,
                background: Tensor | None) -> tuple:
        """The checked arguments of the native entry points, up to the background."""
        b = expression.shape[0]
        if len(cameras) != b:
            raise ShapeError(f"{b} frames need {b} cameras, got {len(cameras)}", field="cameras")
        _check_finite(expression=expression, joint_rotations=joint_rotations, eyelids=eyelids, background=background)
        _check_cameras(cameras)
        K, R, t = _camera_arrays(cameras)
        lids = np.zeros((b, 2), np.float32) if eyelids is None else _np(eyelids)
        return (_np(expression), _np(joint_rotations), lids, K, R, t, cameras.width, cameras.height,
                self.avatar.raster_mode == "antialiased", _background(background, b))


def _avatar_tensors(avatar: Avatar) -> list[Tensor]:
    groups = [avatar.neutral, avatar.mouth, avatar.deltas]
    out = [t for g in groups for t in g.tensors().values()]
    return out + [t for t in (avatar.lbs_weights, avatar.pose_correctives, avatar.eyelid_offsets) if t is not None]


def bandwidth_probe(nbytes: int, threads: int = 0) -> dict:
    """Read ``nbytes`` from memory with all threads (best of several passes): the bound a streaming blend meets."""
    _require()
    return dict(_native.bandwidth_probe(int(nbytes), threads))


def rgba8_to_i420(rgba: np.ndarray, y: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
    """[H, W, 4] uint8 RGBA into the Y, U and V planes of a 4:2:0 frame ([rows, line size] uint8 each, C order):
    :func:`render_core.media.pixels.rgba8_to_i420`'s conversion, on the calling thread."""
    _require()
    _native.rgba8_to_i420(rgba, y, u, v)


def to_rgba8(rgb: Tensor, alpha: Tensor, threads: int = 0) -> np.ndarray:
    """[B, H, W, 3] colour and [B, H, W] alpha in [0, 1] -> [B, H, W, 4] uint8 RGBA, rounded (for encoders)."""
    _require()
    out = np.empty((*alpha.shape, 4), np.uint8)
    _native.to_rgba8(_np(rgb), _np(alpha), out, threads)
    return out
