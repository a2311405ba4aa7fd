"""The video track's encoders: aiortc's, measured per frame; H.264 with libx264 set for several streams on few cores.

aiortc 1.16's sender makes its encoder (``aiortc.codecs.get_encoder``) when the first frame comes and runs its
``encode`` in the event loop's default executor: off the loop and off the render thread. Its H.264 encoder opens
libx264 at the default preset (medium: trellis quantisation, sub-pixel refinement 7, three reference frames) with
tune zerolatency and as many sliced threads as x264 picks (1.5 a core): 8 to 9 ms of CPU a 512x512 frame on the
2-core development VM. Four streams then took a sixth of the server's CPU, out of the render thread's share.

:class:`H264Encoder` is aiortc's class (its RTP packetisation, its bitrate: the receiver's REMB estimate between
the module's bounds, a new encoder when the target moves by more than 10 %, the I frame a PLI or FIR asks for) with
libx264 at :data:`X264_PRESET` (ultrafast, the engine's own H.264 preset) with the loop filter kept on
(:data:`X264_PARAMS`), one thread per stream (:data:`X264_THREADS`): 1.7 ms of CPU a 512x512 frame on a quiet core
(2.2 ms in the server under four streams) when it also converted RGBA to YUV 4:2:0; frames now arrive in 4:2:0
(the engine converts them: :mod:`.track`), 0.85 ms of CPU a frame in the server, for 1 to 1.5 dB less PSNR at the same
bitrate than medium (43 to 44 dB at 0.8 Mbit/s on the 64k open-head avatar; superfast: 2.2 ms on a quiet core,
0.5 dB more). One thread: streams encode in parallel on the executor's threads; x264's slices on 2 cores only add
hand-offs. VP8 stays aiortc's (libvpx realtime, cpu-used -6, one thread at this size).

Both encoders record each frame's :class:`Cost` (wall and CPU milliseconds of the ``encode`` call), which the
session reports per frame (``encode_ms``, ``video.encodeCpuMs``). :func:`install` gives a sender its encoder before
its RTP loop starts (the sender makes one only when it has none).
"""

from __future__ import annotations

import fractions
import time
from collections.abc import Iterator
from dataclasses import dataclass

import av
from aiortc.codecs import h264, vpx
from aiortc.mediastreams import VIDEO_TIME_BASE, convert_timebase

X264_PRESET = "ultrafast"
X264_PARAMS = "deblock=0,0"  # ultrafast turns the loop filter off; on (at strength 0) it costs ~0.1 ms for ~0.7 dB
X264_THREADS = 1
X264_OPTIONS = {"level": "31", "tune": "zerolatency",  # aiortc's
                "preset": X264_PRESET, "x264-params": X264_PARAMS}


@dataclass(frozen=True)
class Cost:
    """One ``encode`` call: the frame's pts, wall and CPU milliseconds (the codec, RTP packetisation;
    the CPU time is the calling thread's, which is all of it with one codec thread)."""

    pts: int
    wall_ms: float
    cpu_ms: float


class _Measured:
    """Records :class:`Cost` of each ``encode`` call in ``last`` (read by the session once the frame is sent), and
    keeps the frame's timestamp: a YUV 4:2:0 frame goes to the codec as it is (no converted copy), and PyAV rebases
    the pts of the frame it encodes to the codec's time base (1/30 s) in place, which aiortc reads back for the RTP
    timestamp after encoding. The frame leaves with the pts it came with, and the timestamp is the frame's."""

    last: Cost | None = None

    def encode(self, frame: av.VideoFrame, force_keyframe: bool = False) -> tuple[list[bytes], int]:
        pts, time_base = frame.pts, frame.time_base
        wall, cpu = time.perf_counter(), time.thread_time()
        try:
            payloads, _ = super().encode(frame, force_keyframe)
        finally:
            frame.pts, frame.time_base = pts, time_base
        self.last = Cost(pts, (time.perf_counter() - wall) * 1e3, (time.thread_time() - cpu) * 1e3)
        return payloads, convert_timebase(pts, time_base, VIDEO_TIME_BASE)


class Vp8Encoder(_Measured, vpx.Vp8Encoder):
    """aiortc's VP8 encoder as it is, measured."""


class H264Encoder(_Measured, h264.H264Encoder):
    """aiortc's H.264 encoder with :data:`X264_OPTIONS` and :data:`X264_THREADS`, measured; counts the encoders
    opened."""

    def __init__(self) -> None:
        super().__init__()
        self.opened = 0  # libx264 contexts made (the first, then one per size or bitrate change)

    def _encode_frame(self, frame: av.VideoFrame, force_keyframe: bool) -> Iterator[bytes]:
        codec = self.codec
        if codec is not None and (frame.width != codec.width or frame.height != codec.height
                                  or abs(self.target_bitrate - codec.bit_rate) / codec.bit_rate > 0.1):
            codec = self.codec = None  # aiortc's rule: a new encoder (an IDR frame) for a new size or bitrate
        frame.pict_type = av.video.frame.PictureType.I if force_keyframe else av.video.frame.PictureType.NONE
        if codec is None:
            codec = self.codec = av.CodecContext.create("libx264", "w")
            codec.width, codec.height, codec.pix_fmt = frame.width, frame.height, "yuv420p"
            codec.bit_rate = self.target_bitrate
            codec.framerate = fractions.Fraction(h264.MAX_FRAME_RATE, 1)
            codec.time_base = fractions.Fraction(1, h264.MAX_FRAME_RATE)
            codec.thread_count = X264_THREADS
            codec.options = dict(X264_OPTIONS)
            codec.profile = "Baseline"
            self.opened += 1
        data = b"".join(bytes(packet) for packet in codec.encode(frame))
        if data:
            yield from self._split_bitstream(data)


ENCODERS = {"H264": H264Encoder, "VP8": Vp8Encoder}


def install(sender, codec: str) -> None:
    """Give an RTCRtpSender whose negotiated codec is ``codec`` (``H264``, ``VP8``) this module's encoder for it,
    before its RTP loop starts. (aiortc 1.16, pinned: the sender's private ``__encoder``, which it fills with
    ``get_encoder(codec)`` only when it is empty.)"""
    make = ENCODERS.get(codec.upper())
    if make is not None and getattr(sender, "_RTCRtpSender__encoder", None) is None:
        sender._RTCRtpSender__encoder = make()


def encoder_of(sender) -> object | None:
    """The encoder a sender uses (None once its RTP loop has ended)."""
    return getattr(sender, "_RTCRtpSender__encoder", None)


def cost_of(sender, pts: int) -> Cost | None:
    """The :class:`Cost` of the frame with this ``pts`` if it was the sender's last one encoded."""
    last = getattr(encoder_of(sender), "last", None)
    return last if last is not None and last.pts == pts else None
