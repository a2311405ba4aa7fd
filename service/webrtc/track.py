"""The outgoing video track of a WebRTC session: the newest rendered frame wins.

aiortc's sender loop calls :meth:`FrameTrack.recv`, encodes what it returns in its own thread pool (H.264 with
libx264 or VP8 with libvpx, through PyAV) and sends the RTP packets, then calls ``recv`` again. The engine renders
this sink's frames as raw RGBA (the ``raw_rgba`` codec: a copy, no compression on the render thread); the track
holds one of them at a time. A frame that arrives while the previous one still waits for the encoder replaces it
(a slow or congested peer drops frames, nothing queues), and ``recv`` hands the encoder the newest.

Timing: a frame's encode-and-send time is measured from the ``recv`` that handed it out to the next ``recv`` call
(aiortc's loop encodes, packetizes and sends in between); :attr:`FrameTrack.on_sent` gets each frame then.
Presentation times are the 90 kHz clock since the track's first frame (strictly increasing), so the RTP timestamp
of a frame is a fixed per-stream offset plus its ``pts`` (the data channel's timing message carries the ``pts``:
clients match video frames to frame indices by it). With no new frame for ``REPEAT_SECONDS``, the last one is sent
again (no timing message), so receivers keep a live stream and a keyframe request is answered.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction

import av
import numpy as np
from aiortc.mediastreams import MediaStreamError, MediaStreamTrack

CLOCK_RATE = 90_000  # RTP's video clock
TIME_BASE = Fraction(1, CLOCK_RATE)
REPEAT_SECONDS = 1.0


@dataclass
class Pending:
    """One rendered frame on its way to the encoder."""

    index: int
    client_time_us: int
    data: bytes  # RGBA, height x width x 4
    timings: object  # the engine's StageTimings
    dropped: int = 0
    arrived: float = field(default_factory=time.perf_counter)
    handed: float = 0.0  # when recv gave it to the encoder
    pts: int = 0


class FrameTrack(MediaStreamTrack):
    kind = "video"

    def __init__(self, width: int, height: int, on_sent: Callable[[Pending, float], None],
                 on_done: Callable[[int], None]):
        """``on_sent(frame, now)``: a frame was encoded and sent; ``on_done(index)``: the track is done with a frame
        (handed to the encoder, or replaced by a newer one)."""
        super().__init__()
        self.width, self.height = width, height
        self.on_sent, self.on_done = on_sent, on_done
        self.replaced = self.sent = 0
        self._latest: Pending | None = None
        self._new = asyncio.Event()
        self._handed: Pending | None = None
        self._last: av.VideoFrame | None = None
        self._start: float | None = None
        self._pts = -1

    def put(self, frame: Pending) -> None:
        """The newest rendered frame (the one waiting, if any, is dropped)."""
        if self.readyState != "live":
            return self.on_done(frame.index)
        old, self._latest = self._latest, frame
        if old is not None:
            self.replaced += 1
            self.on_done(old.index)
        self._new.set()

    def _next_pts(self, now: float) -> int:
        if self._start is None:
            self._start = now
        self._pts = max(self._pts + 1, round((now - self._start) * CLOCK_RATE))
        return self._pts

    async def recv(self) -> av.VideoFrame:
        now = time.perf_counter()
        if self._handed is not None:  # aiortc's loop is back: the frame handed out last was encoded and sent
            done, self._handed = self._handed, None
            self.sent += 1
            self.on_sent(done, now)
        while True:
            if self.readyState != "live":
                raise MediaStreamError
            if self._latest is not None:
                break
            self._new.clear()
            try:
                await asyncio.wait_for(self._new.wait(), REPEAT_SECONDS if self._last is not None else None)
            except TimeoutError:
                if self._last is not None and self.readyState == "live":
                    self._last.pts = self._next_pts(time.perf_counter())
                    return self._last
        frame, self._latest = self._latest, None
        pixels = np.frombuffer(frame.data, np.uint8).reshape(self.height, self.width, 4)
        video = av.VideoFrame.from_ndarray(pixels, format="rgba")
        frame.handed = time.perf_counter()
        video.pts = frame.pts = self._next_pts(frame.handed)
        video.time_base = TIME_BASE
        self._handed, self._last = frame, video
        self.on_done(frame.index)
        return video

    def stop(self) -> None:
        super().stop()
        self._new.set()
        if self._latest is not None:
            self.on_done(self._latest.index)
            self._latest = None
