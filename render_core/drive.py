"""Driving files: one JSON object per line, each a frame to render (docs/method.md section 11).

A line may hold:
  "expression": a list of exactly K numbers, or an object {name: value} (any subset; others are zero)
  "joints":     an object {joint name: axis-angle [3] or 6D rotation [6]} (unnamed joints stay at rest)
  "eyelids":    [left, right]
  "camera":     a preset name ("front", "left", "right", "up", "down"), an orbit
                {"yaw": deg, "pitch": deg, "distance": m}, or an explicit OpenCV camera
                {"K": 3x3, "R": 3x3, "t": 3, "width": W, "height": H} (K is rescaled to the output size)
``{}`` is the neutral frame seen from the avatar's default camera. Errors name the line and list what is valid.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import torch

from .avatar import Avatar
from .camera import Cameras, orbit
from .deform import Frame
from .errors import FrameError

KEYS = ("expression", "joints", "eyelids", "camera")
T = TypeVar("T")
PRESETS: dict[str, tuple[float, float]] = {
    "front": (0.0, 0.0),
    "left": (40.0, 0.0),
    "right": (-40.0, 0.0),
    "up": (0.0, 25.0),
    "down": (0.0, -25.0),
}
MAX_LINE_BYTES = 1 << 20


@dataclass
class DriveFrame:
    frame: Frame  # batch of 1
    camera: Cameras  # 1 camera at the output size


def default_camera(avatar: Avatar, width: int, height: int) -> Cameras:
    """The avatar's default camera at the requested output size (front view if the bundle has none)."""
    if avatar.default_camera:
        return Cameras.from_dict(avatar.default_camera).resized(width, height)
    return orbit(0.0, width=width, height=height)


def _numbers(value: Any, field: str, length: int | None = None) -> list[float]:
    if not isinstance(value, list) or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                               for v in value):
        raise FrameError("expected a list of numbers", field=field)
    if length is not None and len(value) != length:
        raise FrameError(f"expected {length} values, got {len(value)}", field=field)
    if not all(math.isfinite(v) for v in value):
        raise FrameError("values must be finite (no NaN or Infinity)", field=field)
    return [float(v) for v in value]


def _expression(avatar: Avatar, value: Any) -> torch.Tensor:
    k = avatar.num_expressions
    if isinstance(value, dict):
        out = torch.zeros(1, k)
        unknown = [n for n in value if n not in avatar.expression_names]
        if unknown:
            raise FrameError(
                f"unknown expression name(s) {unknown}; valid names: {', '.join(avatar.expression_names)}",
                field="expression",
            )
        for name, v in value.items():
            out[0, avatar.expression_names.index(name)] = _numbers([v], f"expression.{name}")[0]
        return out
    if isinstance(value, list) and len(value) != k:
        raise FrameError(
            f"expected exactly {k} coefficients (this avatar's K), got {len(value)}; or give an object by name "
            f"with any of: {', '.join(avatar.expression_names)}",
            field="expression",
        )
    return torch.tensor([_numbers(value, "expression", k)])


def _joints(avatar: Avatar, value: Any) -> dict[str, torch.Tensor]:
    if not isinstance(value, dict):
        raise FrameError(f"expected an object {{joint: rotation}}; joints: {', '.join(avatar.joint_names)}",
                         field="joints")
    out = {}
    for name, rot in value.items():
        if name not in avatar.joint_names:
            raise FrameError(f"unknown joint {name!r}; valid joints: {', '.join(avatar.joint_names)}",
                             field="joints")
        nums = _numbers(rot, f"joints.{name}")
        if len(nums) not in (3, 6):
            raise FrameError(f"expected axis-angle (3 values) or 6D (6 values), got {len(nums)}",
                             field=f"joints.{name}")
        out[name] = torch.tensor([nums])
    return out


def preset_camera(avatar: Avatar, name: str, width: int, height: int, field: str = "camera") -> Cameras:
    """A named view (:data:`PRESETS`) at the avatar's default distance and focal length; FrameError naming
    ``field`` for an unknown name."""
    if name not in PRESETS:
        raise FrameError(f"unknown preset {name[:64]!r}; presets: {', '.join(PRESETS)}", field=field)
    yaw, pitch = PRESETS[name]
    return orbit_camera(avatar, width, height, yaw, pitch)


def orbit_camera(avatar: Avatar, width: int, height: int, yaw: float = 0.0, pitch: float = 0.0,
                 distance: float | None = None) -> Cameras:
    """An orbit around the avatar: yaw and pitch in degrees, ``distance`` in metres (default: the default
    camera's), the default camera's focal length."""
    base = default_camera(avatar, width, height)
    distance = float(base.centres[0].norm()) if distance is None else distance
    return orbit(yaw, pitch, width=width, height=height, distance=distance, focal=float(base.K[0, 0, 0]))


def calibrated_camera(K: Any, R: Any, t: Any, calibrated: tuple[int, int], width: int, height: int,
                      field: str = "camera", parts: dict[str, str] | None = None) -> Cameras:
    """An OpenCV calibration (K 3x3 in pixels of the ``calibrated`` (width, height), R 3x3, t 3) checked as every
    user camera is (:func:`render_core.camera.calibration_problem`) and rescaled to ``width`` x ``height``.
    Errors name ``field``.<part>, the part renamed by ``parts`` (e.g. the wire's lower-case ``k``)."""
    parts = parts or {}
    cw, ch = calibrated
    try:
        return Cameras.from_dict({"width": cw, "height": ch, "K": K, "R": R, "t": t}).resized(width, height)
    except FrameError as e:
        part = (e.field or "").removeprefix("camera").removeprefix(".")
        raise FrameError(e.detail, field=f"{field}.{parts.get(part, part)}" if part else field) from None


def parse_camera(avatar: Avatar, value: Any, width: int, height: int) -> Cameras:
    """A driving file's ``camera`` value (a preset name, an orbit object or an OpenCV calibration) at the output
    size. Raises FrameError naming ``camera`` or its part."""
    if isinstance(value, str):
        return preset_camera(avatar, value, width, height)
    if isinstance(value, dict) and set(value) <= {"yaw", "pitch", "distance"}:
        nums = {k: _numbers([v], f"camera.{k}")[0] for k, v in value.items()}
        return orbit_camera(avatar, width, height, nums.get("yaw", 0.0), nums.get("pitch", 0.0),
                            nums.get("distance"))
    if isinstance(value, dict):
        extra = set(value) - {"K", "R", "t", "width", "height"}
        if extra:
            raise FrameError(f"unknown key(s) {sorted(extra)}; expected {{K, R, t, width, height}}", field="camera")
        return calibrated_camera(value.get("K"), value.get("R"), value.get("t"),
                                 (value.get("width", width), value.get("height", height)), width, height)
    raise FrameError(f"expected a preset ({', '.join(PRESETS)}), an orbit {{yaw, pitch, distance}} or "
                     "{K, R, t, width, height}", field="camera")


def check_keys(obj: Any) -> dict:
    """``obj`` when it is a driving-file object: a JSON object of :data:`KEYS` only. Raises FrameError."""
    if not isinstance(obj, dict):
        raise FrameError(f"expected a JSON object with any of: {', '.join(KEYS)}")
    unknown = [k for k in obj if k not in KEYS]
    if unknown:
        raise FrameError(f"unknown key(s) {unknown}; valid keys: {', '.join(KEYS)}")
    return obj


def parse_frame(avatar: Avatar, obj: Any) -> Frame:
    """The animation parameters of one driving-file object (its camera aside). Raises FrameError."""
    check_keys(obj)
    expression = _expression(avatar, obj["expression"]) if "expression" in obj else None
    joints = _joints(avatar, obj["joints"]) if "joints" in obj else None
    eyelids = torch.tensor([_numbers(obj["eyelids"], "eyelids", 2)]) if "eyelids" in obj else None
    return Frame.from_params(avatar, expression=expression, joints=joints, eyelids=eyelids)  # checked there


def parse_line(avatar: Avatar, obj: Any, width: int, height: int) -> DriveFrame:
    """One driving-file object -> a frame of the avatar and its camera. Raises FrameError."""
    frame = parse_frame(avatar, obj)
    camera = parse_camera(avatar, obj["camera"], width, height) if "camera" in obj else default_camera(
        avatar, width, height)
    return DriveFrame(frame, camera)


def read_drive_file(path: str | Path, avatar: Avatar, width: int, height: int) -> list[DriveFrame]:
    """Parse and validate every line of a driving file before anything renders (blank lines are skipped)."""
    with open(path, "rb") as f:
        frames = parse_lines(enumerate(f, start=1), avatar, width, height, source=str(path))
    if not frames:
        raise FrameError(f"{path}: the driving file has no frames")
    return frames


def parse_lines(lines: Iterable[tuple[int, bytes | str]], avatar: Avatar, width: int, height: int,
                source: str = "<drive>") -> list[DriveFrame]:
    return parse_json_lines(lines, lambda obj: parse_line(avatar, obj, width, height), source)


def parse_json_lines(lines: Iterable[tuple[int, bytes | str]], parse: Callable[[Any], T],
                     source: str = "<drive>") -> list[T]:
    """Numbered JSON lines -> ``parse`` of each (blank lines skipped): the one reading of a driving file's lines
    (a line's size bound, its JSON), every FrameError prefixed with ``source:line``."""
    out = []
    for no, raw in lines:
        if len(raw) > MAX_LINE_BYTES:
            raise FrameError(f"{source}:{no}: line longer than {MAX_LINE_BYTES} bytes")
        text = raw.decode("utf-8", errors="replace") if isinstance(raw, bytes) else raw
        if not text.strip():
            continue
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as e:
            raise FrameError(f"{source}:{no}: not valid JSON ({e.msg} at column {e.colno})") from None
        try:
            out.append(parse(obj))
        except FrameError as e:
            raise FrameError(f"{source}:{no}: {e}") from None
    return out
