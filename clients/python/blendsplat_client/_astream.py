"""The asyncio render stream: :class:`AsyncStream`, the same shape as :class:`~blendsplat_client.Stream` with
coroutines (``async with client.stream("demo") as s: await s.send(...); frame = await s.receive()``)."""

from __future__ import annotations

import asyncio
import contextlib

from . import errors
from ._proto import render_pb2 as pb
from ._stream import Frame, StreamCore

_END = object()


class AsyncStream:
    def __init__(self, stub, config: pb.SessionConfig, metadata, timeout: float, decode: bool | None, retry=None):
        self.core = StreamCore(config, decode)
        self.timeout, self._retry = timeout, retry
        self._stub, self._metadata = stub, metadata
        self._in: asyncio.Queue = asyncio.Queue()
        self._ended = self._closed = False
        self._call = self._reader = None

    async def open(self) -> AsyncStream:
        """Open the session (retried on UNAVAILABLE: nothing was sent yet); raises its typed error."""
        attempt = 0
        while True:
            try:
                return await self._open()
            except errors.BlendsplatError as exc:
                delay = self._retry.delay(attempt, exc, idempotent=True) if self._retry else None
                if delay is None:
                    raise
            await asyncio.sleep(delay)
            attempt += 1
            self._in, self._closed, self._call, self._reader = asyncio.Queue(), False, None, None

    async def _open(self) -> AsyncStream:
        self._call = self._stub.RenderStream(metadata=self._metadata)
        self._reader = asyncio.create_task(self._read())
        try:
            await self._write(self.core.open_request())
            self.core.opened(await self._next(self.timeout) or pb.StreamResponse(
                status=pb.Status(code=pb.UNAVAILABLE, message="the stream ended before its header")))
        except BaseException:
            await self.close(cancel=True)
            raise
        return self

    async def _write(self, request: pb.StreamRequest) -> None:
        import grpc

        try:
            await self._call.write(request)
        except (grpc.RpcError, asyncio.InvalidStateError) as exc:
            if isinstance(exc, grpc.RpcError):
                raise errors.from_grpc(exc) from None
            raise errors.FailedPrecondition("the stream has ended") from None

    async def _read(self) -> None:
        import grpc

        try:
            while (reply := await self._call.read()) is not grpc.aio.EOF:
                self._in.put_nowait(reply)
        except grpc.RpcError as exc:
            self._in.put_nowait(exc)
        finally:
            self._in.put_nowait(_END)

    async def _next(self, timeout: float | None):
        wait = self.timeout if timeout is None else timeout
        try:
            item = await asyncio.wait_for(self._in.get(), wait)
        except TimeoutError:
            raise errors.Timeout(f"no reply from the stream within {wait} s") from None
        if item is _END:
            self._in.put_nowait(_END)
            return None
        if isinstance(item, Exception):
            self._in.put_nowait(_END)
            raise errors.from_grpc(item)
        return item

    @property
    def header(self) -> pb.StreamHeader:
        return self.core.header

    @property
    def final(self) -> pb.Status | None:
        return self.core.final

    async def send(self, expression=None, joints=None, eyelids=None, camera=None, background=None, *,
                   index: int | None = None) -> int:
        """Send one pose (driving-file vocabulary); its frame index."""
        if self._ended:
            raise errors.FailedPrecondition("the stream has ended: no more frames")
        await self._write(self.core.frame_request(expression, joints, eyelids, camera, background, index))
        return self.core.index

    async def receive(self, timeout: float | None = None) -> Frame | None:
        """The next frame (acknowledged), or None once the stream has ended; typed errors as the sync stream's."""
        reply = await self._next(timeout)
        if reply is None:
            return None
        frame = self.core.reply(reply)
        if frame is not None and not self._closed:
            with contextlib.suppress(errors.BlendsplatError):  # the server may have ended the stream meanwhile
                await self._write(pb.StreamRequest(ack=pb.Ack(index=frame.index)))
        return frame

    async def render(self, poses, timeout: float | None = None):
        """Frames of ``poses``, one in flight at a time (none dropped): an async generator."""
        for pose in poses:
            index = await self.send(**pose)
            while (frame := await self.receive(timeout)) is not None and frame.index < index:
                pass
            if frame is None:
                return
            yield frame

    async def end(self, timeout: float | None = None) -> list[Frame]:
        """Stop sending; the frames still to come, until the final status."""
        left = []
        if not self._ended:
            self._ended = True
            await self._write(pb.StreamRequest(end=pb.End()))
            with contextlib.suppress(Exception):
                await self._call.done_writing()
        while (frame := await self.receive(timeout)) is not None:
            left.append(frame)
        return left

    async def close(self, cancel: bool = False) -> None:
        if self._closed:
            return
        if not cancel and self.core.header is not None and self.core.final is None:
            with contextlib.suppress(errors.BlendsplatError):
                await self.end()
        self._closed = True
        if self._call is not None:
            self._call.cancel()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader

    async def __aenter__(self) -> AsyncStream:
        return self if self._call is not None else await self.open()

    async def __aexit__(self, exc_type, exc, tb) -> None:
        await self.close(cancel=exc_type is not None)
