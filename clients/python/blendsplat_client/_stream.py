"""Render streams (gRPC ``RenderStream``): what the sync and asyncio streams share (:class:`StreamCore`: messages
out, replies in, decoding, latency) and the sync :class:`Stream`.

Flow control: the server renders at most ``max_in_flight`` frames ahead of the client's acks, and the newest pose
wins (a pose waiting behind a full window is replaced by a newer one, counted as dropped). The stream acks a frame
when the application takes it (:meth:`Stream.receive`), so a slow reader slows the server down instead of piling
frames up. :meth:`Stream.render` sends one pose and waits for its frame (nothing is dropped): offline rendering.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from . import _pose, errors
from ._proto import render_pb2 as pb

_END = object()  # the reply stream ended


@dataclass
class Frame:
    """A rendered frame: ``index`` (the one its pose was sent with), encoded ``data`` in ``codec``, the decoded
    ``image`` (numpy, with the media extra and ``decode``; else None), ``latency_ms`` (pose sent to frame received,
    measured here), the server's per-stage ``timings`` (ms) and the poses ``dropped`` so far."""

    index: int
    codec: str
    width: int
    height: int
    data: bytes
    image: Any = None
    latency_ms: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    dropped: int = 0


class StreamCore:
    """The protocol state of one stream, independent of the transport."""

    def __init__(self, config: pb.SessionConfig, decode: bool | None):
        from . import media

        self.config = config
        self.decode = media.available() if decode is None else decode
        self.decoder = media.Decoder() if self.decode else None
        self.header: pb.StreamHeader | None = None
        self.index = 0
        self.sent_at: dict[int, float] = {}
        self.final: pb.Status | None = None
        self.latencies: list[float] = []

    def open_request(self) -> pb.StreamRequest:
        return pb.StreamRequest(open=self.config)

    def frame_request(self, expression=None, joints=None, eyelids=None, camera=None, background=None,
                      index: int | None = None) -> pb.StreamRequest:
        self.index = self.index + 1 if index is None else int(index)
        self.sent_at[self.index] = time.perf_counter()
        return pb.StreamRequest(frame=_pose.frame(self.index, expression, joints, eyelids, camera, background))

    def opened(self, reply: pb.StreamResponse) -> None:
        """The first reply: the header, else the status that refused the session (raised)."""
        kind = reply.WhichOneof("msg")
        if kind == "header":
            self.header = reply.header
            return
        status = reply.status if kind == "status" else reply.error
        raise errors.from_status(status)

    def frame(self, reply: pb.RenderedFrame) -> Frame:
        now = time.perf_counter()
        sent = self.sent_at.pop(reply.index, None)
        for old in [i for i in self.sent_at if i < reply.index]:  # replaced by this newer pose (dropped)
            del self.sent_at[old]
        latency = (now - sent) * 1e3 if sent is not None else 0.0
        self.latencies.append(latency)
        name = _pose.CODEC_NAMES.get(reply.codec, "jpeg")
        t = reply.timings
        image = self.decoder.decode(name, reply.data, reply.width, reply.height) if self.decoder else None
        return Frame(reply.index, name, reply.width, reply.height, reply.data, image, latency,
                     {"queue": t.queue_ms, "blend": t.blend_ms, "lbs": t.lbs_ms, "raster": t.raster_ms,
                      "encode": t.encode_ms, "total": t.total_ms, "batch": t.batch}, reply.dropped)

    def reply(self, reply: pb.StreamResponse) -> Frame | None:
        """A reply after the header: a Frame; None for the final OK status; raises the error of a refused message
        (the stream goes on) or of a failed final status."""
        kind = reply.WhichOneof("msg")
        if kind == "frame":
            return self.frame(reply.frame)
        if kind == "error":
            self.sent_at.pop(reply.error.frame_index, None)
            raise errors.from_status(reply.error)
        if kind == "status":
            self.final = reply.status
            if reply.status.code != pb.OK:
                raise errors.from_status(reply.status)
            return None
        raise errors.Internal(f"unexpected stream reply {kind!r}")

    @property
    def names(self) -> list[str]:
        return list(self.header.expression_names) if self.header else []

    @property
    def joint_names(self) -> list[str]:
        return list(self.header.joint_names) if self.header else []


class Stream:
    """A sync render stream; use it as a context manager (``with client.stream("demo") as s``), which always
    closes it. ``header`` is the server's (expression and joint names, size, codec, ``max_in_flight``)."""

    def __init__(self, stub, config: pb.SessionConfig, metadata, timeout: float, decode: bool | None):
        self.core = StreamCore(config, decode)
        self.timeout = timeout
        self._out: queue.Queue = queue.Queue()
        self._in: queue.Queue = queue.Queue()
        self._ended = self._closed = False
        self._out.put(self.core.open_request())
        self._call = stub.RenderStream(self._requests(), metadata=metadata)
        self._reader = threading.Thread(target=self._read, name="blendsplat-stream", daemon=True)
        self._reader.start()
        try:
            self.core.opened(self._next(timeout))
        except BaseException:
            self.close(cancel=True)
            raise

    def _requests(self):
        while (request := self._out.get()) is not None:
            yield request

    def _read(self) -> None:
        import grpc

        try:
            for reply in self._call:
                self._in.put(reply)
        except grpc.RpcError as exc:
            self._in.put(exc)
        finally:
            self._in.put(_END)

    def _next(self, timeout: float | None):
        try:
            item = self._in.get(timeout=self.timeout if timeout is None else timeout)
        except queue.Empty:
            raise errors.Timeout(f"no reply from the stream within {self.timeout if timeout is None else timeout} s")\
                from None
        if item is _END:
            self._in.put(_END)  # every later read sees the end too
            return None
        if isinstance(item, Exception):
            self._in.put(_END)
            raise errors.from_grpc(item)
        return item

    @property
    def header(self) -> pb.StreamHeader:
        return self.core.header

    def send(self, expression=None, joints=None, eyelids=None, camera=None, background=None, *,
             index: int | None = None) -> int:
        """Send one pose (driving-file vocabulary); its frame index (1, 2, ...)."""
        if self._ended:
            raise errors.FailedPrecondition("the stream has ended: no more frames")
        request = self.core.frame_request(expression, joints, eyelids, camera, background, index)
        self._out.put(request)
        return self.core.index

    def receive(self, timeout: float | None = None) -> Frame | None:
        """The next frame (acknowledged), or None once the stream has ended. A refused pose raises its typed error
        (``frame_index`` in its status; the stream goes on); a failed stream raises its status."""
        reply = self._next(timeout)
        if reply is None:
            return None
        frame = self.core.reply(reply)
        if frame is not None and not self._closed:
            self._out.put(pb.StreamRequest(ack=pb.Ack(index=frame.index)))
        return frame

    def render(self, poses, timeout: float | None = None):
        """Frames of ``poses`` (mappings in the driving-file vocabulary), one pose in flight at a time, so none is
        dropped: a generator."""
        for pose in poses:
            index = self.send(**pose)
            while (frame := self.receive(timeout)) is not None and frame.index < index:
                pass
            if frame is None:
                return
            yield frame

    def end(self, timeout: float | None = None) -> list[Frame]:
        """Stop sending: the server renders what it holds and sends its final status; the frames still to come."""
        left = []
        if not self._ended:
            self._ended = True
            self._out.put(pb.StreamRequest(end=pb.End()))
        while (frame := self.receive(timeout)) is not None:
            left.append(frame)
        return left

    @property
    def final(self) -> pb.Status | None:
        """The final status (frames_sent, dropped) once the stream has ended."""
        return self.core.final

    def close(self, cancel: bool = False) -> None:
        """End the stream (cancelled at once with ``cancel``, else half-closed and drained for up to the timeout)."""
        if self._closed:
            return
        if not cancel and self.core.header is not None and self.core.final is None:
            try:
                self.end()
            except errors.BlendsplatError:
                pass
        self._closed = True
        self._out.put(None)
        self._call.cancel()
        self._reader.join(5)

    def __enter__(self) -> Stream:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(cancel=exc_type is not None)
