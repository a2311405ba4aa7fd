"""Wire messages -> render_core inputs: frame parameters, cameras, background, output size and codec.

Both transports hand the same protobuf messages to the engine, which converts them here; every problem raises
a typed error naming the field (a ``FrameError`` from render_core or :class:`InvalidArgument`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from blendsplat.v1 import render_pb2 as pb
from render_core.avatar import Avatar
from render_core.camera import Cameras
from render_core.deform import Frame
from render_core.drive import parse_frame, parse_line

from .errors import InvalidArgument

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
    unknown = [n for n in names if n not in avatar.expression_names]
    if unknown:
        raise InvalidArgument(f"unknown expression name(s) {', '.join(map(repr, unknown))}; this avatar has: "
                              f"{', '.join(avatar.expression_names)}", field="expression_names")
    if len(set(names)) != len(names):
        raise InvalidArgument("expression names repeat", field="expression_names")
    return list(names)


def _camera_value(cam: pb.Camera) -> object | None:
    kind = cam.WhichOneof("kind")
    if kind == "preset":
        return cam.preset
    if kind == "orbit":
        o = cam.orbit
        value = {"yaw": o.yaw_deg, "pitch": o.pitch_deg}
        return value | ({"distance": o.distance} if o.distance else {})
    if kind == "opencv":
        c = cam.opencv
        for field, values, n in (("k", c.k, 9), ("r", c.r, 9), ("t", c.t, 3)):
            if len(values) != n:
                raise InvalidArgument(f"expected {n} values, got {len(values)}", field=f"camera.opencv.{field}")
        if not c.width or not c.height:
            raise InvalidArgument("the calibrated size is needed to rescale K", field="camera.opencv.width")
        k, r = list(c.k), list(c.r)
        return {"K": [k[0:3], k[3:6], k[6:9]], "R": [r[0:3], r[3:6], r[6:9]], "t": list(c.t),
                "width": c.width, "height": c.height}
    return None


def camera(avatar: Avatar, cam: pb.Camera | None, out: Output, default: Cameras | None = None) -> Cameras:
    """The camera a message asks for, else ``default``, else the avatar's default camera at the output size."""
    value = _camera_value(cam) if cam is not None else None
    if value is None and default is not None:
        return default
    return parse_line(avatar, {} if value is None else {"camera": value}, out.width, out.height).camera


def background(color: pb.Color | None, default: torch.Tensor | None = None, field: str = "background"
               ) -> torch.Tensor:
    """[3] linear RGB in [0, 1]; black when not given."""
    if color is None:
        return default if default is not None else torch.zeros(3)
    values = [color.r, color.g, color.b]
    if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise InvalidArgument(f"colour components must be in [0, 1], got {values}", field=field)
    return torch.tensor(values)


def frame(avatar: Avatar, params: pb.FrameParams, order: list[str]) -> Frame:
    """One frame (batch of 1) from a FrameParams message; ``order`` maps positional coefficients to names."""
    line: dict[str, object] = {}
    if params.coefficients and params.named_coefficients:
        raise InvalidArgument("give coefficients by position or by name, not both", field="coefficients")
    if params.coefficients:
        if len(params.coefficients) != len(order):
            raise InvalidArgument(
                f"expected {len(order)} coefficients in the order {', '.join(order)}; got {len(params.coefficients)}"
                " (or give them by name in named_coefficients)", field="coefficients")
        same = order is avatar.expression_names or order == avatar.expression_names
        line["expression"] = list(params.coefficients) if same else dict(zip(order, params.coefficients, strict=True))
    elif params.named_coefficients:
        line["expression"] = dict(params.named_coefficients)
    if params.eyelids:
        line["eyelids"] = list(params.eyelids)
    if params.joints:
        line["joints"] = {name: list(rot.values) for name, rot in params.joints.items()}
    return parse_frame(avatar, line)
