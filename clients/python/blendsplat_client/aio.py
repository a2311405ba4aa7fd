"""The asyncio client: :class:`AsyncClient`, the same calls as :class:`~blendsplat_client.Client` as coroutines
(iterators as async iterators, the stream as :class:`~blendsplat_client.AsyncStream`)."""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

from . import _pose, errors
from ._astream import AsyncStream
from ._config import RetryPolicy, grpc_channel, settings, transport_error
from ._follow import POLL_SECONDS, Follow
from ._rest import Api, Call, part
from ._sse import Event, Parser, not_sse
from ._stream import StreamCore


class AsyncClient(Api):
    """The Blendsplat service, asyncio: the arguments of :class:`~blendsplat_client.Client`. An async context
    manager (``async with AsyncClient() as client``)."""

    def __init__(self, url: str | None = None, grpc_target: str | None = None, api_key: str | None = None, *,
                 timeout: float = 30.0, ca_file: str | None = None, grpc_tls: bool | None = None,
                 retry: RetryPolicy | None = None, decode: bool | None = None, transport=None):
        import httpx

        self.settings = settings(url, grpc_target, api_key, timeout, grpc_tls, ca_file, retry)
        self.timeout, self.decode = self.settings.timeout, decode
        self.http = httpx.AsyncClient(base_url=self.settings.url, headers=self.settings.headers,
                                      transport=transport, verify=self.settings.verify(),
                                      timeout=httpx.Timeout(self.timeout))
        self._channel = self._stub = None

    _sleep = staticmethod(asyncio.sleep)  # waits of ``wait`` (tests replace it)

    async def _retrying(self, attempt: Callable[[], Any], idempotent: bool) -> Any:
        tries = 0
        while True:
            try:
                return await attempt()
            except errors.BlendsplatError as exc:
                delay = self.settings.retry.delay(tries, exc, idempotent)
                if delay is None:
                    raise
            await asyncio.sleep(delay)
            tries += 1

    async def _send(self, call: Call) -> Any:
        import httpx

        async def attempt():
            try:
                response = await self.http.request(call.method, call.path, params=call.params, json=call.json,
                                                   headers=call.headers,
                                                   content=call.body(True) if call.body else None,
                                                   timeout=call.timeout or self.timeout)
            except httpx.TransportError as exc:
                raise transport_error(exc, self.settings.url) from None
            if response.status_code >= 400:
                raise errors.from_http(response.status_code, response.content, response.headers)
            return call.result(response.status_code, response.content)

        return await self._retrying(attempt, call.idempotent)

    @property
    def stub(self):
        if self._stub is None:
            from ._proto import render_pb2_grpc

            self._channel = grpc_channel(self.settings, asynchronous=True)
            self._stub = render_pb2_grpc.RenderServiceStub(self._channel)
        return self._stub

    async def _rpc(self, name: str, request, idempotent: bool = True):
        import grpc

        async def attempt():
            try:
                return await getattr(self.stub, name)(request, timeout=self.timeout, metadata=self.settings.metadata)
            except grpc.RpcError as exc:
                raise errors.from_grpc(exc) from None

        reply = await self._retrying(attempt, idempotent)
        if name == "Render":
            return StreamCore(None, self.decode).frame(reply.frame)
        return reply

    def stream(self, avatar: str, size: int | tuple[int, int] = 512, codec: str = "jpeg",
               **options) -> AsyncStream:
        """A render stream on ``avatar``: ``async with client.stream("demo") as s`` opens it (retried on
        UNAVAILABLE) and always closes it; or ``s = await client.stream("demo").open()``."""
        camera, background = options.pop("camera", None), options.pop("background", None)
        config = _pose.session(avatar, size, codec, camera_=camera, background=background, **options)
        return AsyncStream(self.stub, config, self.settings.metadata, self.timeout, self.decode,
                           self.settings.retry)

    async def jobs(self, state: str | None = None, page_size: int = 50) -> AsyncIterator[dict]:
        """Every job (newest first), page after page: an async iterator."""
        cursor = None
        while True:
            page = await self.jobs_page(state, page_size, cursor)
            for job in page["jobs"]:
                yield job
            if not (cursor := page.get("next_cursor")):
                return

    async def download(self, job_id: str, name: str, path: str | os.PathLike) -> Path:
        out = Path(path)
        out.write_bytes(await self.artefact(job_id, name))
        return out

    async def events(self, job_id: str, last_event_id: str | None = None, *, read_timeout: float = 60.0
                     ) -> AsyncIterator[Event]:
        """The job's server-sent events, as :meth:`Client.events`: an async iterator."""
        import httpx

        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = last_event_id
        parser = Parser()
        try:
            async with self.http.stream("GET", f"/v1/jobs/{part(job_id)}/events", headers=headers,
                                        timeout=httpx.Timeout(self.timeout, read=read_timeout)) as response:
                if response.status_code >= 400:
                    raise errors.from_http(response.status_code, await response.aread(), response.headers)
                not_sse(response.headers)
                async for line in response.aiter_lines():
                    if (event := parser.line(line)) is not None:
                        yield event
        except httpx.TransportError as exc:
            raise transport_error(exc, self.settings.url) from None

    async def wait(self, job_id: str, *, on_event: Callable[[Event], None] | None = None,
                   timeout: float | None = None, check: bool = True, on_job: Callable[[dict], None] | None = None,
                   poll_seconds: float = POLL_SECONDS) -> dict:
        """Follow a job to its end, as :meth:`Client.wait` (the callbacks are plain functions)."""
        follow = Follow(job_id, timeout, on_event, on_job, poll_seconds)
        job = await self.get_job(job_id)
        while not follow.job(job):
            if pause := follow.pause():
                await self._sleep(pause)
            if follow.streaming:
                follow.closed(await self._read_events(follow))
            else:
                follow.left()
            job = await self.get_job(job_id)
        if check and job.get("state") != "succeeded":
            raise errors.JobFailed(job)
        return job

    async def _read_events(self, follow: Follow) -> errors.BlendsplatError | None:
        follow.opening()
        stream = self.events(follow.job_id, follow.last_id, read_timeout=follow.read_timeout())
        try:
            while True:
                try:
                    event = await anext(stream)
                except StopAsyncIteration:
                    return None
                except errors.BlendsplatError as exc:
                    return exc
                if follow.event(event):
                    return None
        finally:
            await stream.aclose()

    async def close(self) -> None:
        await self.http.aclose()
        if self._channel is not None:
            await self._channel.close()
            self._channel = self._stub = None

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()
