"""Python values -> the wire's messages: a session's configuration and a frame's pose, in the driving-file
vocabulary (docs/method.md section 11): ``expression`` (a list of K coefficients, or ``{name: value}``), ``joints``
(``{name: [3 axis-angle or 6 values]}``), ``eyelids`` (``[left, right]``), ``camera`` (a preset name, an orbit
``{"yaw", "pitch", "distance"}`` or an OpenCV camera ``{"K", "R", "t", "width", "height"}``), ``background``
(``(r, g, b)``, linear 0-1). A driving file's line is ``stream.send(**json.loads(line))``."""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

from ._proto import render_pb2 as pb

CODECS = {"jpeg": pb.CODEC_JPEG, "png": pb.CODEC_PNG, "raw": pb.CODEC_RAW_RGBA, "raw_rgba": pb.CODEC_RAW_RGBA,
          "rgba": pb.CODEC_RAW_RGBA, "h264": pb.CODEC_H264}
CODEC_NAMES = {pb.CODEC_UNSPECIFIED: "jpeg", pb.CODEC_JPEG: "jpeg", pb.CODEC_PNG: "png",
               pb.CODEC_RAW_RGBA: "raw", pb.CODEC_H264: "h264"}


def _floats(values: Any, what: str) -> list[float]:
    try:
        return [float(v) for v in (values.tolist() if hasattr(values, "tolist") else values)]
    except (TypeError, ValueError):
        raise TypeError(f"{what} must be a sequence of numbers") from None


def codec(name: str | int) -> int:
    if isinstance(name, int):
        return name
    try:
        return CODECS[name.lower()]
    except KeyError:
        raise ValueError(f"codec must be one of {sorted(CODECS)}, got {name!r}") from None


def camera(value: Any) -> pb.Camera | None:
    """A camera message from a preset name, an orbit, an OpenCV camera (or a ``pb.Camera``)."""
    if value is None or isinstance(value, pb.Camera):
        return value
    if isinstance(value, str):
        return pb.Camera(preset=value)
    if not isinstance(value, Mapping):
        raise TypeError("camera must be a preset name or a mapping (orbit or OpenCV)")
    if "K" in value or "k" in value:
        return pb.Camera(opencv=pb.OpenCVCamera(
            k=_floats(_flat(value.get("K", value.get("k"))), "camera.K"),
            r=_floats(_flat(value.get("R", value.get("r", [1, 0, 0, 0, 1, 0, 0, 0, 1]))), "camera.R"),
            t=_floats(value.get("t", [0, 0, 0]), "camera.t"),
            width=int(value.get("width", 0)), height=int(value.get("height", 0))))
    return pb.Camera(orbit=pb.Orbit(yaw_deg=float(value.get("yaw", value.get("yaw_deg", 0.0))),
                                    pitch_deg=float(value.get("pitch", value.get("pitch_deg", 0.0))),
                                    distance=float(value.get("distance", 0.0))))


def _flat(rows: Any) -> list:
    rows = rows.tolist() if hasattr(rows, "tolist") else rows
    return [v for row in rows for v in row] if rows and isinstance(rows[0], Sequence) else list(rows)


def color(value: Any) -> pb.Color | None:
    if value is None or isinstance(value, pb.Color):
        return value
    r, g, b = _floats(value, "background")
    return pb.Color(r=r, g=g, b=b)


def frame(index: int, expression: Any = None, joints: Mapping[str, Any] | None = None, eyelids: Any = None,
          camera_: Any = None, background: Any = None) -> pb.FrameParams:
    """One frame's parameters, stamped with the client's time (microseconds)."""
    params = pb.FrameParams(index=index, client_time_us=time.time_ns() // 1000)
    if isinstance(expression, Mapping):
        for name, value in expression.items():
            params.named_coefficients[str(name)] = float(value)
    elif expression is not None:
        params.coefficients.extend(_floats(expression, "expression"))
    for name, rotation in (joints or {}).items():
        params.joints[str(name)].values.extend(_floats(rotation, f"joints.{name}"))
    if eyelids is not None:
        params.eyelids.extend(_floats(eyelids, "eyelids"))
    if (cam := camera(camera_)) is not None:
        params.camera.CopyFrom(cam)
    if (bg := color(background)) is not None:
        params.background.CopyFrom(bg)
    return params


def session(avatar: str, size: int | tuple[int, int] = 512, codec_: str | int = "jpeg", *, quality: int = 0,
            fps_hint: float = 0.0, camera_: Any = None, background: Any = None,
            expression_names: Sequence[str] = (), max_in_flight: int = 0, adapter: str = "",
            source_names: Sequence[str] = (), smoothing: Mapping[str, float] | None = None) -> pb.SessionConfig:
    """A session's configuration (``size``: one side of a square, or ``(width, height)``)."""
    width, height = (size, size) if isinstance(size, int) else size
    config = pb.SessionConfig(avatar_id=avatar, width=int(width), height=int(height), codec=codec(codec_),
                              quality=int(quality), fps_hint=float(fps_hint), max_in_flight=int(max_in_flight),
                              expression_names=list(expression_names), adapter=adapter,
                              source_names=list(source_names))
    if (cam := camera(camera_)) is not None:
        config.camera.CopyFrom(cam)
    if (bg := color(background)) is not None:
        config.background.CopyFrom(bg)
    if smoothing:
        config.smoothing.CopyFrom(pb.OneEuro(**{k: float(v) for k, v in smoothing.items()}))
    return config
