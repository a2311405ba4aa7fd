"""Wire messages -> render_core inputs: frame parameters, cameras, background, output size and codec.

The one place where what a client sends is checked, for every transport (gRPC streams and Render, the WebSocket,
POST /v1/render all build their jobs here, through :meth:`service.engine.Job.build` and the session): every frame
parameter (coefficients, joint rotations, eyelids, the camera's intrinsics and rotation, the background) is
validated before the frame can join a batch, and every problem raises a typed error naming the field as the client
sent it (``camera.opencv.k``, ``joints.jaw``; a ``FrameError`` from render_core or :class:`InvalidArgument`).

Per-frame work is bounded here too: :func:`frame_cost` estimates a frame's (Gaussian, pixel) pairs from the
avatar's Gaussians at rest, its camera and output size, and :func:`check_cost` refuses a frame over the replica's
budget (``BLENDSPLAT_MAX_FRAME_SPLAT_PIXELS``) with RESOURCE_EXHAUSTED naming the size or the camera.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from blendsplat.v1 import render_pb2 as pb
from render_core.avatar import Avatar
from render_core.camera import Cameras, calibration_problem
from render_core.deform import ROTATION_TOL, Frame
from render_core.drive import calibrated_camera, default_camera, orbit_camera, preset_camera

from .errors import InvalidArgument, ResourceExhausted, some

CODEC_NAMES = {pb.CODEC_UNSPECIFIED: "jpeg", pb.CODEC_JPEG: "jpeg", pb.CODEC_PNG: "png",
               pb.CODEC_RAW_RGBA: "raw_rgba", pb.CODEC_H264: "h264"}
DEFAULT_SIZE = 512


@dataclass(frozen=True)
class Output:
    """What a session or a single render produces: size, codec and its quality."""

    width: int
    height: int
    codec: str
    codec_enum: int
    quality: int


def output(width: int, height: int, codec: int, quality: int, max_size: int) -> Output:
    """Validate the requested output; a missing size is 512 (or the other side, for a square)."""
    width, height = width or height or DEFAULT_SIZE, height or width or DEFAULT_SIZE
    for field, v in (("width", width), ("height", height)):
        if v > max_size:
            raise InvalidArgument(f"{v} pixels is more than this server's maximum {max_size}", field=field)
    if codec not in CODEC_NAMES:
        raise InvalidArgument(f"unknown codec {codec}; codecs: {', '.join(pb.Codec.keys())}", field="codec")
    return Output(width, height, CODEC_NAMES[codec], codec or pb.CODEC_JPEG, quality)


def expression_order(avatar: Avatar, names: list[str]) -> list[str]:
    """The order of positional coefficients: the client's (checked) or the avatar's."""
    if not names:
        return list(avatar.expression_names)
    return checked_order(names, avatar.expression_names, "expression names", "this avatar has", "expression_names")


def checked_order(names: list[str], known: list[str], what: str, whose: str, field: str) -> list[str]:
    """``names``, a client's order of positional values, when each is one of ``known`` and none repeats
    (InvalidArgument naming ``field`` otherwise: the unknown ones and what ``whose`` has, bounded)."""
    known_set = set(known)
    unknown = [n for n in names if n not in known_set]
    if unknown:
        raise InvalidArgument(f"unknown {what} {some(unknown)}; {whose} {len(known)}: {some(known, 10)}",
                              field=field)
    if len(set(names)) != len(names):
        raise InvalidArgument(f"{what} repeat", field=field)
    return list(names)


def _finite(value: float, field: str) -> float:
    if not math.isfinite(value):
        raise InvalidArgument(f"must be finite, got {value}", field=field)
    return value


# The wire's names of a calibration's parts (OpenCVCamera's fields).
_OPENCV_PARTS = {"K": "k", "R": "r", "t": "t", "width": "width"}


def camera(avatar: Avatar, cam: pb.Camera | None, out: Output, default: Cameras | None = None) -> Cameras:
    """The camera a message asks for, else ``default``, else the avatar's default camera at the output size.

    Whatever the message gave (a preset, an orbit, an OpenCV calibration rescaled to the output size), the camera
    that comes out is checked as render_core checks every user camera
    (:func:`render_core.camera.calibration_problem`: finite, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with
    positive focals, R a rotation), errors naming the wire's field (``camera.opencv.k``, ``camera.orbit.yaw_deg``)
    as each part is read."""
    kind = cam.WhichOneof("kind") if cam is not None else None
    if kind is None and default is not None:
        return default
    w, h = out.width, out.height
    if kind == "preset":
        cameras = preset_camera(avatar, cam.preset, w, h, field="camera.preset")
    elif kind == "orbit":
        o = cam.orbit
        yaw = _finite(o.yaw_deg, "camera.orbit.yaw_deg")
        pitch = _finite(o.pitch_deg, "camera.orbit.pitch_deg")
        distance = _finite(o.distance, "camera.orbit.distance")
        if not -90.0 < pitch < 90.0:
            raise InvalidArgument(f"must be between -90 and 90 degrees (exclusive), got {pitch}",
                                  field="camera.orbit.pitch_deg")
        if distance < 0:
            raise InvalidArgument(f"must be positive (0: the avatar's default), got {distance}",
                                  field="camera.orbit.distance")
        cameras = orbit_camera(avatar, w, h, yaw, pitch, distance or None)
    elif kind == "opencv":
        c = cam.opencv
        for field, values, n in (("k", c.k, 9), ("r", c.r, 9), ("t", c.t, 3)):
            if len(values) != n:
                raise InvalidArgument(f"expected {n} values, got {len(values)}", field=f"camera.opencv.{field}")
        if not c.width or not c.height:
            raise InvalidArgument("the calibrated size is needed to rescale K", field="camera.opencv.width")
        k, r = list(c.k), list(c.r)
        cameras = calibrated_camera([k[0:3], k[3:6], k[6:9]], [r[0:3], r[3:6], r[6:9]], list(c.t),
                                    (c.width, c.height), w, h, field="camera.opencv", parts=_OPENCV_PARTS)
    else:
        cameras = default_camera(avatar, w, h)
    problem = calibration_problem(cameras.K[0].double(), cameras.R[0].double(), cameras.t[0].double())
    if problem is not None:  # e.g. a K whose focal vanished in the rescale, a degenerate orbit
        part, message = problem
        if kind == "opencv":
            raise InvalidArgument(f"{message} (at the output size {w}x{h})",
                                  field=f"camera.opencv.{_OPENCV_PARTS[part]}")
        raise InvalidArgument(f"gives no usable camera ({part}: {message})",
                              field=f"camera.{kind}" if kind else "camera")
    return cameras


def background(color: pb.Color | None, default: torch.Tensor | None = None, field: str = "background"
               ) -> torch.Tensor:
    """[3] linear RGB in [0, 1]; black when not given."""
    if color is None:
        return default if default is not None else torch.zeros(3)
    values = [color.r, color.g, color.b]
    if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise InvalidArgument(f"colour components must be in [0, 1], got {values}", field=field)
    return torch.from_numpy(np.array(values, np.float32))


_NOT_A_ROTATION = ("not a rotation: 6D needs two non-zero, non-parallel 3-vectors (the first two rows of the matrix); "
                   "axis-angle an angle in radians of moderate size")
_EYE64, _EYE32 = np.eye(3), np.eye(3, dtype=np.float32)


def _rotations_ok(m: np.ndarray) -> np.ndarray:
    """[n] bool: which of the [n, 3, 3] matrices are rotations, checked in float64 as Frame.check does: finite,
    orthonormal to ROTATION_TOL (max |M M^T - I|), determinant above 1 - ROTATION_TOL."""
    md = m.astype(np.float64)
    ok = np.isfinite(md).all(axis=(1, 2))
    if not ok.all():
        md = np.where(ok[:, None, None], md, 0.0)  # the zero matrix fails below, without NaN warnings
    ok &= np.abs(md @ md.transpose(0, 2, 1) - _EYE64).max(axis=(1, 2)) <= ROTATION_TOL
    ok &= np.linalg.det(md) > 1 - ROTATION_TOL
    return ok


# A pose is built on the event loop with numpy, not torch. Most torch calls release the GIL and must take it back,
# and taking it back waits for the switch interval (5 ms) whenever another Python thread runs (an encoder lane,
# aiortc, the gRPC threads): render_core's torch Rodrigues, 0.25 ms alone, took 8.7 ms a call beside one busy
# thread and 27 ms beside two; numpy on a few values keeps the GIL. The formulas are render_core.rotation's.
def _axis_angle_np(aa: np.ndarray) -> np.ndarray:
    """[n, 3] float32 axis-angle -> [n, 3, 3] float32 rotation matrices (Rodrigues; exact identity at zero)."""
    theta2 = (aa * aa).sum(-1)[:, None, None]
    theta = np.sqrt(np.maximum(theta2, 1e-24))
    small = theta2 < 1e-8
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(theta) / theta)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(theta)) / np.maximum(theta2, 1e-24))
    x, y, z = aa[:, 0], aa[:, 1], aa[:, 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(-1, 3, 3)
    return _EYE32 + a * k + b * (k @ k)


def _rot6d_np(r6: np.ndarray) -> np.ndarray:
    """[n, 6] float32 6D (the matrix's first two rows) -> [n, 3, 3] float32 rotation matrices, by Gram-Schmidt."""
    a1, a2 = r6[:, :3], r6[:, 3:]
    b1 = a1 / np.maximum(np.linalg.norm(a1, axis=-1, keepdims=True), 1e-12)
    a2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 = a2 / np.maximum(np.linalg.norm(a2, axis=-1, keepdims=True), 1e-12)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-2)


def _joint_rotations(avatar: Avatar, joints: Mapping[str, pb.Rotation]) -> tuple[list[int], np.ndarray | None]:
    """The joints of a FrameParams message (``joints``: its map of name -> Rotation) as (joint indices, [n, 3, 3]
    float32 rotation matrices), each from 3 (axis-angle) or 6 (6D) finite values and checked as the frame checks
    every joint (orthonormal to 1e-3, determinant +1); errors name ``joints.<name>`` (``joints`` for an unknown
    name). Built and checked in one batched call per kind (the conversions are elementwise, so each matrix is the
    one a call for that joint alone gives); a problem is reported for the first joint, in the message's order,
    that has one, as a joint-by-joint check would."""
    names, rows, problem = [], ([], []), None  # rows: (position in names, values) of axis-angle, of 6D
    for name, rot in joints.items():
        if name not in avatar.joint_names:
            problem = InvalidArgument(f"unknown joint {some([name])}; this avatar's joints: "
                                      f"{some(avatar.joint_names, 10)}", field="joints")
            break
        values = list(rot.values)
        if len(values) not in (3, 6):
            problem = InvalidArgument(f"expected axis-angle (3 values) or 6D (6 values), got {len(values)}",
                                      field=f"joints.{name}")
            break
        if not all(map(math.isfinite, values)):
            problem = InvalidArgument("values must be finite (no NaN or Infinity)", field=f"joints.{name}")
            break
        rows[len(values) == 6].append((len(names), values))
        names.append(name)
    matrices, at = [], []
    for group, convert in zip(rows, (_axis_angle_np, _rot6d_np), strict=True):
        if group:
            at += [i for i, _ in group]
            with np.errstate(all="ignore"):  # huge values give inf/NaN matrices, refused just below
                matrices.append(convert(np.array([v for _, v in group], np.float32)))
    m = np.concatenate(matrices) if matrices else None
    if m is not None:
        ok = _rotations_ok(m)
        if not ok.all():
            first = min(at[i] for i in np.flatnonzero(~ok))
            raise InvalidArgument(_NOT_A_ROTATION, field=f"joints.{names[first]}")
    if problem is not None:
        raise problem
    return [avatar.joint_names.index(names[i]) for i in at], m


def _coefficients(avatar: Avatar, params: pb.FrameParams, order: list[str]) -> np.ndarray:
    """[1, K] float32 coefficients by position (in ``order``) or by name; the wire field named on every problem."""
    out = np.zeros((1, avatar.num_expressions), np.float32)
    if params.coefficients and params.named_coefficients:
        raise InvalidArgument("give coefficients by position or by name, not both", field="coefficients")
    if params.coefficients:
        if len(params.coefficients) != len(order):
            raise InvalidArgument(
                f"expected {len(order)} coefficients in the order {some(order, 10)}; got {len(params.coefficients)}"
                " (or give them by name in named_coefficients)", field="coefficients")
        values = list(params.coefficients)
        if not all(map(math.isfinite, values)):
            raise InvalidArgument("values must be finite (no NaN or Infinity)", field="coefficients")
        if order is avatar.expression_names or order == avatar.expression_names:
            out[0] = values
        else:
            out[0, [avatar.expression_names.index(n) for n in order]] = values
    elif params.named_coefficients:
        index = {n: i for i, n in enumerate(avatar.expression_names)}
        unknown = [n for n in params.named_coefficients if n not in index]
        if unknown:
            raise InvalidArgument(f"unknown expression names {some(unknown)}; this avatar has {len(index)}: "
                                  f"{some(avatar.expression_names, 10)}", field="named_coefficients")
        for name, v in params.named_coefficients.items():
            out[0, index[name]] = _finite(v, f"named_coefficients.{name}")
    return out


def frame(avatar: Avatar, params: pb.FrameParams, order: list[str]) -> Frame:
    """One frame (batch of 1) from a FrameParams message; ``order`` maps positional coefficients to names. Built
    directly from the message, each part checked as it is read (errors name the wire's field), in numpy (see
    :func:`_axis_angle_np`: no torch call that gives the GIL up)."""
    expression = _coefficients(avatar, params, order)
    rotations = np.tile(np.eye(3, dtype=np.float32), (1, avatar.num_joints, 1, 1))
    joints, matrices = _joint_rotations(avatar, params.joints)
    if joints:
        rotations[0, joints] = matrices
    eyelids = None
    if params.eyelids:
        values = list(params.eyelids)
        if len(values) != 2:
            raise InvalidArgument(f"expected 2 values (left, right), got {len(values)}", field="eyelids")
        if not all(map(math.isfinite, values)):
            raise InvalidArgument("values must be finite (no NaN or Infinity)", field="eyelids")
        eyelids = torch.from_numpy(np.array([values], np.float32))
    return Frame(torch.from_numpy(expression), torch.from_numpy(rotations), eyelids)


# ------------------------------------------------------------------------------------------- per-frame budget
SAMPLE = 4096  # Gaussians the cost estimate looks at (evenly spread over the avatar; the sum is scaled up)
_NEAR, _BLUR, _ALPHA_MIN, _EXTENT_MAX = 0.01, 0.3, 1.0 / 255.0, 3.33  # the rasterizers' (docs/method.md section 9)


@dataclass(frozen=True)
class _Footprints:
    """What the cost estimate needs of an avatar at rest, for a sample of its Gaussians (face and mouth)."""

    means: np.ndarray  # [S, 3] world space, metres
    sigma: np.ndarray  # [S] largest standard deviation, metres
    extent: np.ndarray  # [S] opacity-aware extent in standard deviations (0: never visible)
    weight: float  # Gaussians per sampled one


_footprints: dict[int, _Footprints] = {}


def _footprints_of(avatar: Avatar) -> _Footprints:
    key = id(avatar)
    if key not in _footprints:
        groups = [g for g in (avatar.neutral, avatar.mouth) if g.count]
        n = sum(g.count for g in groups)
        if n == 0:
            fp = _Footprints(np.zeros((0, 3)), np.zeros(0), np.zeros(0), 0.0)
        else:
            idx = torch.from_numpy(np.unique(np.linspace(0, n - 1, min(n, SAMPLE)).round().astype(np.int64)))

            def cat(name: str) -> torch.Tensor:
                return torch.cat([getattr(g, name).detach().to(torch.float64) for g in groups])[idx]

            opacity = torch.sigmoid(cat("opacity_logits"))
            extent = torch.sqrt(2.0 * torch.log((opacity / _ALPHA_MIN).clamp_min(1.0))).clamp(max=_EXTENT_MAX)
            fp = _Footprints(cat("means").numpy(), cat("log_scales").amax(-1).exp().numpy(), extent.numpy(),
                             n / len(idx))
        _footprints[key] = fp
        weakref.finalize(avatar, _footprints.pop, key, None)
    return _footprints[key]


def frame_cost(avatar: Avatar, cameras: Cameras) -> float:
    """About how many (Gaussian, pixel) pairs one frame of ``avatar`` seen by ``cameras`` (one camera) splats: the
    sum over the Gaussians at rest of their screen boxes (mean +- the opacity-aware extent times the largest
    projected standard deviation), clipped to the image; estimated from an even sample of at most ``SAMPLE``
    Gaussians, so it costs the same for every avatar. Deformation (expressions, joints) is not in the estimate."""
    fp = _footprints_of(avatar)
    if not len(fp.sigma):
        return 0.0
    K, R, t = (x[0].detach().to(torch.float64).numpy() for x in (cameras.K, cameras.R, cameras.t))
    w, h = cameras.width, cameras.height
    with np.errstate(all="ignore"):
        p = fp.means @ R.T + t
        z = np.maximum(p[:, 2], _NEAR)
        rx = fp.extent * np.sqrt((fp.sigma * K[0, 0] / z) ** 2 + _BLUR)
        ry = fp.extent * np.sqrt((fp.sigma * K[1, 1] / z) ** 2 + _BLUR)
        mx, my = p[:, 0] / z * K[0, 0] + K[0, 2], p[:, 1] / z * K[1, 1] + K[1, 2]
        bw = np.clip(mx + rx, 0, w) - np.clip(mx - rx, 0, w)
        bh = np.clip(my + ry, 0, h) - np.clip(my - ry, 0, h)
        area = np.nan_to_num(bw * bh, nan=float(w * h), posinf=float(w * h))
    return float(np.where(p[:, 2] >= _NEAR, np.clip(area, 0, w * h), 0.0).sum() * fp.weight)


def check_cost(cost: float, budget: float, out: Output, field: str) -> float:
    """``cost`` (from :func:`frame_cost`) unless it is over the replica's per-frame ``budget``: then
    RESOURCE_EXHAUSTED naming ``field`` (``width`` for the output size, ``camera`` for a frame's own camera)."""
    if cost > budget:
        raise ResourceExhausted(
            f"this frame would splat about {cost:.3g} (Gaussian, pixel) pairs at {out.width}x{out.height}, over this "
            f"server's per-frame budget of {budget:.3g} (BLENDSPLAT_MAX_FRAME_SPLAT_PIXELS): ask for a smaller size "
            "or a camera further away", field=field)
    return cost
