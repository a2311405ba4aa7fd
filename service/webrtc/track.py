"""The outgoing video track of a WebRTC session: the newest rendered frame wins.

aiortc's sender loop calls :meth:`FrameTrack.recv`, encodes what it returns in the event loop's executor (H.264 with
libx264 or VP8 with libvpx, through PyAV: the encoders of :mod:`.encoder`) and sends the RTP packets, then calls
``recv`` again. The engine hands this sink's frames over as the 4:2:0 planes the encoders take (``raw_i420``,
converted from RGBA on its encode threads, off the loop and the render thread) to :meth:`FrameTrack.put` as they are
delivered (the session's sink); the track holds one of them at a time. A frame that arrives while the previous one
still waits for the encoder replaces it (a slow or congested peer drops frames, nothing queues), and ``recv``
hands the encoder the newest.

Timing: a frame's encode-and-send time is measured from the ``recv`` that handed it out to the next ``recv`` call
(aiortc's loop encodes, packetizes and sends in between); :attr:`FrameTrack.on_sent` gets each frame then (the
encoder's own wall and CPU time for it are :mod:`.encoder`'s ``Cost``).
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
    data: bytes  # YUV 4:2:0: the Y, U and V planes, unpadded (the engine's raw_i420)
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
        self._last: av.VideoFrame | None = None  # the frame sent last (sent again when no new one comes)
        self._video: av.VideoFrame | None = None  # the one YUV 4:2:0 frame handed to the encoder (see _fill)
        self._planes: list[np.ndarray] = []  # its Y, U and V planes as [rows, line size] arrays
        ch, cw = (height + 1) // 2, (width + 1) // 2
        self._shapes = ((height, width), (ch, cw), (ch, cw))  # of the planes in a frame's data
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
        video = self._fill(frame.data)
        frame.handed = time.perf_counter()
        video.pts = frame.pts = self._next_pts(frame.handed)
        video.time_base = TIME_BASE
        self._handed, self._last = frame, video
        self.on_done(frame.index)
        return video

    def _fill(self, data: bytes) -> av.VideoFrame:
        """The track's one YUV 4:2:0 frame, holding ``data`` (the engine's ``raw_i420``: Y, U, V planes, unpadded;
        converted from RGBA on its encode threads, 0.11 ms a 512x512 frame, where the RGBA copied into an RGBA frame
        here cost 0.3 ms and FFmpeg's conversion in the encoder 0.34 more). aiortc's loop has encoded the frame
        handed out before it calls ``recv`` again, and the encoder keeps no reference to it, so one frame serves
        them all (no allocation, no page faults)."""
        video = self._video
        if video is None:
            video = self._video = av.VideoFrame(self.width, self.height, "yuv420p")
            self._planes = [np.frombuffer(p, np.uint8).reshape(-1, p.line_size) for p in video.planes]
        start = 0
        for plane, (h, w) in zip(self._planes, self._shapes, strict=True):
            plane[:h, :w] = np.frombuffer(data, np.uint8, h * w, start).reshape(h, w)
            start += h * w
        video.pict_type = av.video.frame.PictureType.NONE  # what an encoder set for the last one (a keyframe) goes
        return video

    def stop(self) -> None:
        super().stop()
        self._new.set()
        if self._latest is not None:
            self.on_done(self._latest.index)
            self._latest = None
