"""Writing rendered frames: images through OpenImageIO (PNG 8-bit RGB, EXR float RGBA) and H.264 video through
PyAV."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import torch
from torch import Tensor

FORMATS = ("png", "exr", "mp4")


def to_uint8(rgb: Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 (rounded, clamped)."""
    return (rgb.detach().clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def write_image(path: str | Path, rgb: Tensor, alpha: Tensor | None = None) -> None:
    """Write one frame. ``.png``: 8-bit RGB (the colour over the background); ``.exr``: float32 RGBA with the
    accumulated alpha (premultiplied colour, the EXR convention, when rendered over black)."""
    path = Path(path)
    if path.suffix == ".exr":
        pixels = rgb.detach().float().cpu().numpy()
        if alpha is not None:
            pixels = np.concatenate([pixels, alpha.detach().float().cpu().numpy()[..., None]], axis=-1)
        spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.FLOAT)
        spec.attribute("compression", "zip")
        data = np.ascontiguousarray(pixels)
    elif path.suffix == ".png":
        data = np.ascontiguousarray(to_uint8(rgb))
        spec = oiio.ImageSpec(data.shape[1], data.shape[0], 3, oiio.UINT8)
    else:
        raise ValueError(f"unsupported image format {path.suffix!r}; use .png or .exr")
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot create {path}: {oiio.geterror()}")
    try:
        if not out.open(str(path), spec) or not out.write_image(data):
            raise OSError(f"cannot write {path}: {out.geterror()}")
    finally:
        out.close()


class VideoWriter:
    """H.264 (yuv420p, constant quality) MP4 writer; width and height must be even."""

    def __init__(self, path: str | Path, width: int, height: int, fps: int = 30, crf: int = 18):
        import av

        if width % 2 or height % 2:
            raise ValueError(f"H.264 video needs an even width and height, got {width}x{height}")
        self._container = av.open(str(path), mode="w")
        self._stream = self._container.add_stream("libx264", rate=fps)
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": str(crf), "preset": "medium"}
        self._av = av

    def write(self, rgb: Tensor) -> None:
        frame = self._av.VideoFrame.from_ndarray(to_uint8(rgb), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
