"""Streaming codecs of the render service: one frame in, one self-contained message out.

Input convention (every encoder): a uint8 array [H, W, 4] whose channels 0-2 are the RGB colour already
composited over the background and whose channel 3 is the accumulated alpha, for clients that composite again
(the colour stays as it is, final). A non-contiguous array is copied to C order; any other dtype, rank or size is a
:class:`~render_core.errors.ShapeError` naming ``image``.

- ``jpeg`` (``image/jpeg``): libjpeg-turbo through simplejpeg, RGB only (alpha dropped), 4:2:0, fast DCT;
  quality 1-100, 0 means 90.
- ``png`` (``image/png``): 8-bit RGBA (alpha kept), written here: the "Up" filter on every row, zlib level 1
  with the run-length strategy (on rendered 512x512 frames faster and smaller than "None" or "Sub", or than the
  default strategy); lossless, quality ignored.
- ``raw_rgba`` (``application/octet-stream``): the array's bytes, row-major RGBA; quality ignored.
- ``raw_i420`` (internal: a frame format for a transport that encodes video itself, not a stream codec of the API):
  the Y, U and V planes of 4:2:0, unpadded and in that order (H x W, then twice ceil(H/2) x ceil(W/2) bytes),
  BT.601 studio range (:func:`~render_core.media.pixels.rgba8_to_i420`); alpha dropped, quality ignored.
- ``h264`` (``video/h264``): libx264 through PyAV, one stateful encoder per stream (not thread-safe), preset
  ultrafast, tune zerolatency, no B-frames, an IDR frame with SPS/PPS first and then every ``2 * fps`` frames;
  each ``encode`` returns exactly one access unit as Annex B bytes. yuv420p, BT.709 limited range (signalled in
  the VUI). Quality 1-100 maps to CRF ``51 - quality // 2`` (higher is better; 56 is CRF 23); 0 means CRF 23.
  4:2:0 needs even sizes: an odd width or height is padded by repeating the last column/row, so the coded
  picture is the next even size and decoders crop back (:class:`H264Decoder` does when given the size).
  ultrafast keeps the stream Constrained Baseline (no CABAC), which every H.264 decoder takes, WebRTC's included;
  on rendered 512x512 frames superfast was about 40% smaller at the same CRF for about 30% more encode time.
"""

from __future__ import annotations

import math
import struct
import zlib
from fractions import Fraction

import numpy as np

from ..errors import CodecError, ShapeError
from .pixels import rgba8_to_i420

CODECS = ("jpeg", "png", "raw_rgba", "h264")
FRAME_FORMATS = ("raw_i420",)  # make_encoder's too; not stream codecs (no decode_image, no media type of the API)
MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png", "raw_rgba": "application/octet-stream",
               "h264": "video/h264"}
JPEG_DEFAULT_QUALITY = 90
H264_DEFAULT_CRF = 23
MAX_SIZE = 16384


def _check_codec(codec: str, also: tuple[str, ...] = ()) -> None:
    if codec not in CODECS + also:
        raise CodecError(f"unknown codec {codec!r}; use one of {', '.join(CODECS)}", field="codec")


def _check_size(width: int, height: int) -> None:
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 1 <= value <= MAX_SIZE:
            raise CodecError(f"must be an integer in [1, {MAX_SIZE}], got {value!r}", field=name)


class Encoder:
    """Encodes frames of one stream at a fixed size; see the module docstring for the conventions."""

    codec: str = ""
    media_type: str = ""

    def __init__(self, width: int, height: int, quality: int = 0):
        self.width, self.height, self.quality = int(width), int(height), int(quality)

    def encode(self, rgba: np.ndarray) -> bytes:
        """One frame [H, W, 4] uint8 (RGB over the background + alpha) -> one message."""
        return self._encode(self._check(rgba))

    def close(self) -> None:
        """Release the codec's resources; the encoder is unusable afterwards."""

    def __enter__(self) -> Encoder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _check(self, rgba: np.ndarray) -> np.ndarray:
        if not isinstance(rgba, np.ndarray) or rgba.dtype != np.uint8:
            kind = rgba.dtype if isinstance(rgba, np.ndarray) else type(rgba).__name__
            raise ShapeError(f"expected a uint8 numpy array, got {kind}", field="image")
        if rgba.shape != (self.height, self.width, 4):
            raise ShapeError(f"expected shape ({self.height}, {self.width}, 4), got {rgba.shape}", field="image")
        return np.ascontiguousarray(rgba)

    def _encode(self, rgba: np.ndarray) -> bytes:
        raise NotImplementedError


class JpegEncoder(Encoder):
    codec, media_type = "jpeg", MEDIA_TYPES["jpeg"]

    def _encode(self, rgba: np.ndarray) -> bytes:
        import simplejpeg

        # libjpeg-turbo reads RGBA directly and ignores the fourth byte: no copy to drop alpha.
        return simplejpeg.encode_jpeg(rgba, quality=self.quality or JPEG_DEFAULT_QUALITY, colorspace="RGBA",
                                      colorsubsampling="420", fastdct=True)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


class PngEncoder(Encoder):
    codec, media_type = "png", MEDIA_TYPES["png"]

    def _encode(self, rgba: np.ndarray) -> bytes:
        h, w = rgba.shape[:2]
        rows = rgba.reshape(h, w * 4)
        # Filter type 2 ("Up") on every row: the difference to the row above (modulo 256); the first row's
        # "above" is zeros, so it stays as is.
        filtered = np.empty((h, w * 4 + 1), np.uint8)
        filtered[:, 0] = 2
        filtered[0, 1:] = rows[0]
        np.subtract(rows[1:], rows[:-1], out=filtered[1:, 1:])
        ihdr = struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0)  # 8-bit RGBA, deflate, adaptive filtering, no interlace
        deflate = zlib.compressobj(1, zlib.DEFLATED, 15, 8, zlib.Z_RLE)
        idat = deflate.compress(filtered.data) + deflate.flush()
        return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b"")


class RawRgbaEncoder(Encoder):
    codec, media_type = "raw_rgba", MEDIA_TYPES["raw_rgba"]

    def _encode(self, rgba: np.ndarray) -> bytes:
        return rgba.tobytes()


class RawI420Encoder(Encoder):
    codec, media_type = "raw_i420", "application/octet-stream"

    def _encode(self, rgba: np.ndarray) -> bytes:
        h, w = self.height, self.width
        ch, cw = (h + 1) // 2, (w + 1) // 2
        out = np.empty(h * w + 2 * ch * cw, np.uint8)
        rgba8_to_i420(rgba, out[:h * w].reshape(h, w), out[h * w:h * w + ch * cw].reshape(ch, cw),
                      out[h * w + ch * cw:].reshape(ch, cw))
        return out.tobytes()


def h264_crf(quality: int) -> int:
    """The CRF that ``quality`` (0: default, else 1-100, higher is better) selects for H.264."""
    return H264_DEFAULT_CRF if quality == 0 else 51 - quality // 2


class H264Encoder(Encoder):
    codec, media_type = "h264", MEDIA_TYPES["h264"]

    def __init__(self, width: int, height: int, quality: int = 0, fps: float = 30.0):
        import av

        super().__init__(width, height, quality)
        self._av = av
        self.coded_width, self.coded_height = width + width % 2, height + height % 2
        rate = Fraction(fps).limit_denominator(1001)
        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height, ctx.pix_fmt = self.coded_width, self.coded_height, "yuv420p"
        ctx.framerate, ctx.time_base = rate, 1 / rate
        ctx.gop_size = max(1, round(2 * fps))
        ctx.max_b_frames = 0
        ctx.colorspace = ctx.color_primaries = ctx.color_trc = 1  # BT.709
        ctx.color_range = 1  # limited ("tv") range
        ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "crf": str(h264_crf(self.quality))}
        ctx.open()
        self._ctx, self._pts = ctx, 0

    def _encode(self, rgba: np.ndarray) -> bytes:
        if self._ctx is None:
            raise RuntimeError("the H.264 encoder is closed")
        pad_h, pad_w = self.coded_height - self.height, self.coded_width - self.width
        if pad_h or pad_w:
            rgba = np.pad(rgba, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        frame = self._av.VideoFrame.from_ndarray(rgba, format="rgba").reformat(format="yuv420p",
                                                                              dst_colorspace="itu709")
        frame.pts = self._pts
        self._pts += 1
        packets = self._ctx.encode(frame)
        if len(packets) != 1:  # zerolatency: no lookahead, no frame threads, no reordering
            raise RuntimeError(f"libx264 returned {len(packets)} packets for one frame; expected one")
        return bytes(packets[0])

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.encode(None)  # flush (nothing is pending under zerolatency)
            self._ctx = None


def make_encoder(codec: str, width: int, height: int, quality: int = 0, fps: float = 30.0) -> Encoder:
    """An encoder of ``codec`` for frames of ``width`` x ``height``; ``quality`` 0 is the codec's default, else
    1-100 (ignored by the lossless codecs); ``fps`` sets the H.264 timing and keyframe interval. Bad arguments
    raise :class:`~render_core.errors.CodecError` naming the field."""
    _check_codec(codec, FRAME_FORMATS)
    _check_size(width, height)
    if isinstance(quality, bool) or not isinstance(quality, int | np.integer) or not 0 <= quality <= 100:
        raise CodecError(f"must be an integer in [0, 100] (0: the codec's default), got {quality!r}",
                         field="quality")
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not (math.isfinite(fps) and 0 < fps <= 1000):
        raise CodecError(f"must be a number in (0, 1000], got {fps!r}", field="fps")
    if codec == "h264":
        return H264Encoder(width, height, quality, fps)
    cls = {"jpeg": JpegEncoder, "png": PngEncoder, "raw_rgba": RawRgbaEncoder, "raw_i420": RawI420Encoder}[codec]
    return cls(width, height, quality)


def decode_image(codec: str, data: bytes, width: int, height: int) -> np.ndarray:
    """Decode one ``jpeg`` ([H, W, 3]), ``png`` or ``raw_rgba`` ([H, W, 4]) message to uint8; a message of
    another size is a :class:`~render_core.errors.ShapeError` naming ``data``. H.264 needs :class:`H264Decoder`."""
    _check_codec(codec)
    _check_size(width, height)
    if codec == "jpeg":
        import simplejpeg

        image = simplejpeg.decode_jpeg(data, colorspace="RGB")
    elif codec == "png":
        import av

        frames = av.CodecContext.create("png", "r").decode(av.Packet(data))
        image = frames[0].to_ndarray(format="rgba") if len(frames) == 1 else None
    elif codec == "raw_rgba":
        size = width * height * 4
        image = np.frombuffer(data, np.uint8).reshape(height, width, 4).copy() if len(data) == size else None
        if image is None:
            raise ShapeError(f"expected {size} bytes for {width}x{height} RGBA, got {len(data)}", field="data")
    else:
        raise CodecError("H.264 is a stream: decode it with H264Decoder", field="codec")
    if image is None or image.shape[:2] != (height, width):
        got = "no image" if image is None else f"{image.shape[1]}x{image.shape[0]}"
        raise ShapeError(f"expected a {width}x{height} image, got {got}", field="data")
    return image


class H264Decoder:
    """Decodes one stream of :class:`H264Encoder` access units: one [H, W, 3] uint8 RGB frame per ``decode``.

    ``width`` and ``height`` (optional) crop the decoded picture back to the size before the encoder's padding.
    """

    def __init__(self, width: int | None = None, height: int | None = None):
        import av

        self._av = av
        self._ctx = av.CodecContext.create("h264", "r")
        self.width, self.height = width, height

    def decode(self, data: bytes) -> np.ndarray:
        """One access unit (Annex B bytes) -> its frame."""
        if self._ctx is None:
            raise RuntimeError("the H.264 decoder is closed")
        frames = self._ctx.decode(self._av.Packet(data))
        if len(frames) != 1:
            raise ShapeError(f"expected one frame per access unit, got {len(frames)}", field="data")
        rgb = frames[0].to_ndarray(format="rgb24")  # the VUI's colour matrix and range
        return np.ascontiguousarray(rgb[: self.height, : self.width])

    def close(self) -> None:
        self._ctx = None
