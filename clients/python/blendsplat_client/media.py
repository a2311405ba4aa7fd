"""Decoding frames and writing videos: the ``media`` extra (``pip install 'blendsplat-client[media]'``: PyAV and
numpy). Without it frames stay encoded bytes (``Frame.data``) and :class:`Mp4Writer` is unavailable.

Images are numpy arrays, height x width x channels, uint8: RGB for JPEG and H.264, RGBA for PNG and raw RGBA.
"""

from __future__ import annotations

import os
from fractions import Fraction
from typing import Any


def available() -> bool:
    """Whether the media extra is installed."""
    try:
        import av  # noqa: F401
        import numpy  # noqa: F401
    except ImportError:
        return False
    return True


def _need() -> None:
    if not available():
        raise ImportError("decoding frames and writing videos need the media extra: "
                          "pip install 'blendsplat-client[media]'")


class Decoder:
    """Decodes one stream's frames in order (H.264 frames depend on the ones before)."""

    def __init__(self) -> None:
        _need()
        self._contexts: dict[str, Any] = {}

    def decode(self, codec: str, data: bytes, width: int, height: int):
        import av
        import numpy as np

        if codec == "raw":
            return np.frombuffer(data, np.uint8).reshape(height, width, 4).copy()
        name = {"jpeg": "mjpeg", "png": "png", "h264": "h264"}[codec]
        context = self._contexts.get(name)
        if context is None:
            context = self._contexts[name] = av.CodecContext.create(name, "r")
        frames = context.decode(av.Packet(data))
        if not frames:
            return None  # H.264: the decoder wants more (never with the service's one access unit per frame)
        return frames[-1].to_ndarray(format="rgba" if codec == "png" else "rgb24")


class Mp4Writer:
    """Writes RGB(A) frames (numpy arrays) to an MP4 file (H.264 when PyAV has an encoder for it, else MPEG-4
    Part 2), at ``fps``. Odd sizes are cropped by a pixel (4:2:0 needs even ones). A context manager."""

    def __init__(self, path: str | os.PathLike, fps: float = 30.0, *, crf: int = 20):
        _need()
        import av

        self.path, self.frames = os.fspath(path), 0
        self._container = av.open(self.path, "w")
        self._fps, self._crf, self._stream = Fraction(fps).limit_denominator(1001), crf, None
        self._av = av

    def _open(self, width: int, height: int) -> None:
        codecs = self._av.codecs_available
        name = "libx264" if "libx264" in codecs else "h264" if "h264" in codecs else "mpeg4"
        self._stream = self._container.add_stream(name, rate=self._fps)
        self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, "yuv420p"
        if name == "libx264":
            self._stream.options = {"crf": str(self._crf), "preset": "veryfast"}

    def write(self, image) -> None:
        """Add one frame (height x width x 3 or 4, uint8)."""
        image = image[: image.shape[0] // 2 * 2, : image.shape[1] // 2 * 2, :3]
        if self._stream is None:
            self._open(image.shape[1], image.shape[0])
        frame = self._av.VideoFrame.from_ndarray(image.copy(order="C"), format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        if self._container is None:
            return
        try:
            if self._stream is not None:
                for packet in self._stream.encode():
                    self._container.mux(packet)
        finally:
            self._container.close()
            self._container = None

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
