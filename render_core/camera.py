"""Pinhole cameras in the OpenCV convention (x right, y down, z forward; world-to-camera R, t; K in pixels).

The world convention follows FLAME: metres, y up, the face looking along +z. :func:`front_camera` looks at the
face from +z; :func:`orbit` circles the head.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from . import host
from .errors import FrameError


@dataclass
class Cameras:
    """A batch of B pinhole cameras sharing one image size.

    K: [B, 3, 3] intrinsics in pixels (fx, fy, cx, cy), R: [B, 3, 3] world-to-camera rotation,
    t: [B, 3] world-to-camera translation (x_cam = R x_world + t).
    """

    K: Tensor  # [B, 3, 3]
    R: Tensor  # [B, 3, 3]
    t: Tensor  # [B, 3]
    width: int
    height: int

    def __post_init__(self):
        b = self.K.shape[0] if self.K.dim() == 3 else -1
        for name, t, shape in (("K", self.K, (b, 3, 3)), ("R", self.R, (b, 3, 3)), ("t", self.t, (b, 3))):
            if tuple(t.shape) != shape:
                raise FrameError(f"expected shape {list(shape)}, got {list(t.shape)}", field=f"camera.{name}")
            if not host.finite(t):
                raise FrameError("must be finite", field=f"camera.{name}")
        if self.width < 1 or self.height < 1:
            raise FrameError(f"image size must be positive, got {self.width}x{self.height}", field="camera")

    def __len__(self) -> int:
        return int(self.K.shape[0])

    @property
    def centres(self) -> Tensor:
        """Camera centres in world space, [B, 3]."""
        return -(self.R.transpose(-1, -2) @ self.t.unsqueeze(-1)).squeeze(-1)

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Cameras:
        return Cameras(self.K.to(device, dtype), self.R.to(device, dtype), self.t.to(device, dtype),
                       self.width, self.height)

    def resized(self, width: int, height: int) -> Cameras:
        """The same cameras rendering a different image size (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        scale = torch.tensor([[sx, sx, sx], [sy, sy, sy], [1.0, 1.0, 1.0]], dtype=self.K.dtype)
        return Cameras(self.K * scale, self.R, self.t, width, height)

    def expand(self, batch: int) -> Cameras:
        """One camera repeated ``batch`` times (views, no copies)."""
        if len(self) != 1:
            raise FrameError(f"only a single camera expands, this batch has {len(self)}", field="camera")
        return Cameras(self.K.expand(batch, 3, 3), self.R.expand(batch, 3, 3), self.t.expand(batch, 3),
                       self.width, self.height)

    def index(self, i: int | slice) -> Cameras:
        s = slice(i, i + 1) if isinstance(i, int) else i
        return Cameras(self.K[s], self.R[s], self.t[s], self.width, self.height)

    @staticmethod
    def cat(cams: list[Cameras]) -> Cameras:
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) != 1:
            raise FrameError(f"cameras of one batch must share an image size, got {sorted(sizes)}", field="camera")
        return Cameras(host.cat([c.K for c in cams]), host.cat([c.R for c in cams]),
                       host.cat([c.t for c in cams]), cams[0].width, cams[0].height)

    def to_dict(self, i: int = 0) -> dict[str, Any]:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K[i].tolist(),
            "R": self.R[i].tolist(),
            "t": self.t[i].tolist(),
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Cameras:
        """One camera from ``{"width", "height", "K" (3x3), "R" (3x3), "t" (3)}``."""
        try:
            w, h = int(d["width"]), int(d["height"])
            K = torch.tensor(d["K"], dtype=torch.float32).reshape(1, 3, 3)
            R = torch.tensor(d["R"], dtype=torch.float32).reshape(1, 3, 3)
            t = torch.tensor(d["t"], dtype=torch.float32).reshape(1, 3)
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise FrameError(
                f"expected {{width, height, K: 3x3, R: 3x3, t: 3}} ({type(e).__name__}: {e})", field="camera"
            ) from None
        if w < 1 or h < 1:
            raise FrameError(f"the image size must be positive, got {w}x{h}", field="camera.width")
        problem = calibration_problem(K[0].double(), R[0].double(), t[0].double())
        if problem is not None:
            raise FrameError(problem[1], field=f"camera.{problem[0]}")
        return Cameras(K, R, t, w, h)


def calibration_problem(K: Tensor, R: Tensor, t: Tensor) -> tuple[str, str] | None:
    """The first problem of one pinhole calibration, as (``K`` | ``R`` | ``t``, message), or None when it is
    usable: every value finite; K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (no skew: the
    rasterizers have none); R a rotation (orthonormal within 1e-3, determinant +1). What every camera a user gives
    must pass (driving files, wire messages, a bundle's default camera)."""
    for key, value in (("K", K), ("R", R), ("t", t)):
        if not bool(torch.isfinite(value).all()):
            return key, "values must be finite (no NaN or Infinity)"
    if float(K[0, 0]) <= 0 or float(K[1, 1]) <= 0:
        return "K", f"focal lengths must be positive, got fx={float(K[0, 0]):g}, fy={float(K[1, 1]):g}"
    if float(K[0, 1]) != 0 or float(K[1, 0]) != 0 or [float(v) for v in K[2]] != [0.0, 0.0, 1.0]:
        return "K", "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
    eye = torch.eye(3, dtype=R.dtype)
    if float((R @ R.T - eye).abs().max()) > 1e-3 or float(torch.linalg.det(R)) <= 0:
        return "R", "must be a rotation matrix (orthonormal, determinant +1)"
    return None


def look_at(eye: Tensor, target: Tensor, up: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """World-to-camera (R [..., 3, 3], t [..., 3]) of OpenCV cameras at ``eye`` [..., 3] looking at ``target``.

    ``up`` is the world up direction (default +y); the camera's y axis points down, away from it.
    """
    eye, target = torch.broadcast_tensors(eye, target)
    if up is None:
        up = torch.tensor([0.0, 1.0, 0.0], dtype=eye.dtype)
    z = torch.nn.functional.normalize(target - eye, dim=-1)
    x = torch.nn.functional.normalize(torch.linalg.cross(-up.expand_as(z), z), dim=-1)
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], dim=-2)
    t = -(R @ eye.unsqueeze(-1)).squeeze(-1)
    return R, t


def intrinsics(width: int, height: int, focal: float) -> Tensor:
    """K [3, 3] with square pixels, focal length in pixels and the principal point at the image centre."""
    return torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def orbit(
    yaw_deg: Tensor | list[float] | float,
    pitch_deg: Tensor | list[float] | float = 0.0,
    *,
    width: int = 512,
    height: int = 512,
    distance: float = 0.6,
    focal: float | None = None,
    target: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Cameras:
    """Cameras on a sphere of ``distance`` around ``target``; yaw 0, pitch 0 is the front view (+z).

    Positive yaw moves the camera towards +x (the subject's left), positive pitch upwards. ``focal`` is in pixels
    (default: 2.2 x the image width, a portrait lens that frames a head at 0.6 m).
    """
    yaw = torch.as_tensor(yaw_deg, dtype=torch.float32).reshape(-1)
    pitch = torch.as_tensor(pitch_deg, dtype=torch.float32).reshape(-1)
    yaw, pitch = torch.broadcast_tensors(yaw, pitch)
    yr, pr = torch.deg2rad(yaw), torch.deg2rad(pitch)
    tgt = torch.tensor(target, dtype=torch.float32)
    eye = tgt + distance * torch.stack(
        [torch.sin(yr) * torch.cos(pr), torch.sin(pr), torch.cos(yr) * torch.cos(pr)], dim=-1
    )
    R, t = look_at(eye, tgt.expand_as(eye))
    f = 2.2 * width if focal is None else focal
    K = intrinsics(width, height, f).expand(len(yaw), 3, 3).clone()
    return Cameras(K, R, t, width, height)


def front_camera(width: int = 512, height: int = 512, distance: float = 0.6, focal: float | None = None) -> Cameras:
    """One camera in front of the face (on +z) looking at the origin."""
    return orbit(0.0, 0.0, width=width, height=height, distance=distance, focal=focal)

