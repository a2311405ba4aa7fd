"""The sync client: :class:`Client` (REST over httpx, streams and single frames over gRPC)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from . import _pose, errors
from ._config import RetryPolicy, grpc_channel, settings, transport_error
from ._follow import POLL_SECONDS, Follow
from ._rest import Api, Call, part
from ._sse import Event, Parser, not_sse
from ._stream import Stream, StreamCore


class Client(Api):
    """The Blendsplat service, sync. ``url``: the HTTP base URL (default ``$BLENDSPLAT_URL``, else
    http://127.0.0.1:8080); ``grpc_target``: host:port of the gRPC server (default ``$BLENDSPLAT_GRPC_TARGET``, else
    the URL's host on 50051); ``api_key`` (default ``$BLENDSPLAT_API_KEY``); ``timeout``: seconds for every call
    (uploads and artefacts get at least what they need); TLS with an https URL (``ca_file``: a PEM bundle to trust;
    ``grpc_tls`` overrides the gRPC side); ``retry``: :class:`RetryPolicy`; ``decode``: decode frames to numpy (the
    media extra; default when installed); ``transport``: an httpx transport (tests). A context manager."""

    def __init__(self, url: str | None = None, grpc_target: str | None = None, api_key: str | None = None, *,
                 timeout: float = 30.0, ca_file: str | None = None, grpc_tls: bool | None = None,
                 retry: RetryPolicy | None = None, decode: bool | None = None, transport=None):
        import httpx

        self.settings = settings(url, grpc_target, api_key, timeout, grpc_tls, ca_file, retry)
        self.timeout, self.decode = self.settings.timeout, decode
        self.http = httpx.Client(base_url=self.settings.url, headers=self.settings.headers, transport=transport,
                                 verify=self.settings.verify(), timeout=httpx.Timeout(self.timeout))
        self._channel = self._stub = None

    _sleep = staticmethod(time.sleep)  # waits of ``wait`` (tests replace it)

    # ------------------------------------------------------------------------------------------- executors
    def _retrying(self, attempt: Callable[[], Any], idempotent: bool) -> Any:
        tries = 0
        while True:
            try:
                return attempt()
            except errors.BlendsplatError as exc:
                delay = self.settings.retry.delay(tries, exc, idempotent)
                if delay is None:
                    raise
            time.sleep(delay)
            tries += 1

    def _send(self, call: Call) -> Any:
        import httpx

        def attempt():
            try:
                response = self.http.request(call.method, call.path, params=call.params, json=call.json,
                                             headers=call.headers, content=call.body(False) if call.body else None,
                                             timeout=call.timeout or self.timeout)
            except httpx.TransportError as exc:
                raise transport_error(exc, self.settings.url) from None
            if response.status_code >= 400:
                raise errors.from_http(response.status_code, response.content, response.headers)
            return call.result(response.status_code, response.content)

        return self._retrying(attempt, call.idempotent)

    @property
    def stub(self):
        """The gRPC stub (the channel is made at first use)."""
        if self._stub is None:
            from ._proto import render_pb2_grpc

            self._channel = grpc_channel(self.settings, asynchronous=False)
            self._stub = render_pb2_grpc.RenderServiceStub(self._channel)
        return self._stub

    def _rpc(self, name: str, request, idempotent: bool = True):
        import grpc

        def attempt():
            try:
                return getattr(self.stub, name)(request, timeout=self.timeout, metadata=self.settings.metadata)
            except grpc.RpcError as exc:
                raise errors.from_grpc(exc) from None

        reply = self._retrying(attempt, idempotent)
        if name == "Render":
            return StreamCore(None, self.decode).frame(reply.frame)
        return reply

    # ------------------------------------------------------------------------------------------- streams
    def stream(self, avatar: str, size: int | tuple[int, int] = 512, codec: str = "jpeg", **options) -> Stream:
        """Open a render stream on ``avatar`` (gRPC): a :class:`Stream`, to use as a context manager. ``options``:
        quality, fps_hint, camera, background, expression_names, max_in_flight, adapter, source_names, smoothing.
        Opening is retried on UNAVAILABLE; a refused session raises its typed error (unknown avatar: NotFound)."""
        camera, background = options.pop("camera", None), options.pop("background", None)
        config = _pose.session(avatar, size, codec, camera_=camera, background=background, **options)
        return self._retrying(lambda: Stream(self.stub, config, self.settings.metadata, self.timeout, self.decode),
                              idempotent=True)

    # ------------------------------------------------------------------------------------------- jobs
    def jobs(self, state: str | None = None, page_size: int = 50) -> Iterator[dict]:
        """Every job (newest first, optionally of one ``state``), page after page as it is iterated."""
        cursor = None
        while True:
            page = self.jobs_page(state, page_size, cursor)
            yield from page["jobs"]
            if not (cursor := page.get("next_cursor")):
                return

    def download(self, job_id: str, name: str, path: str | os.PathLike) -> Path:
        """Save a job's artefact to ``path``; the path."""
        out = Path(path)
        out.write_bytes(self.artefact(job_id, name))
        return out

    def events(self, job_id: str, last_event_id: str | None = None, *, read_timeout: float = 60.0
               ) -> Iterator[Event]:
        """``GET /v1/jobs/{id}/events``: the job's events (after ``last_event_id``) as they come, until the server
        closes the stream (after ``end`` for a finished job). An answer that is not an event stream raises
        :class:`~blendsplat_client.errors.Unimplemented`."""
        import httpx

        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = last_event_id
        parser = Parser()
        try:
            with self.http.stream("GET", f"/v1/jobs/{part(job_id)}/events", headers=headers,
                                  timeout=httpx.Timeout(self.timeout, read=read_timeout)) as response:
                if response.status_code >= 400:
                    raise errors.from_http(response.status_code, response.read(), response.headers)
                not_sse(response.headers)
                for line in response.iter_lines():
                    if (event := parser.line(line)) is not None:
                        yield event
        except httpx.TransportError as exc:
            raise transport_error(exc, self.settings.url) from None

    def wait(self, job_id: str, *, on_event: Callable[[Event], None] | None = None, timeout: float | None = None,
             check: bool = True, on_job: Callable[[dict], None] | None = None,
             poll_seconds: float = POLL_SECONDS) -> dict:
        """Follow a job to its end by its events (reconnecting after the last one seen); the job as it ended. Where
        the server has no event stream, or it keeps failing, the job is polled every ``poll_seconds``.
        ``on_event`` gets every event (progress: iteration, loss, psnr, eta), ``on_job`` every read of the job (the
        first one, one after each stream, each poll). ``check``: raise :class:`~blendsplat_client.errors.JobFailed`
        unless it succeeded. ``timeout``: seconds (:class:`~blendsplat_client.errors.Timeout`). A job deleted
        meanwhile raises :class:`~blendsplat_client.errors.NotFound`."""
        follow = Follow(job_id, timeout, on_event, on_job, poll_seconds)
        job = self.get_job(job_id)
        while not follow.job(job):
            if pause := follow.pause():
                self._sleep(pause)
            if follow.streaming:
                follow.closed(self._read_events(follow))
            else:
                follow.left()
            job = self.get_job(job_id)
        if check and job.get("state") != "succeeded":
            raise errors.JobFailed(job)
        return job

    def _read_events(self, follow: Follow) -> errors.BlendsplatError | None:
        """One event stream of a followed job, until it closes, fails (the error, returned) or says the job ended."""
        follow.opening()
        stream = self.events(follow.job_id, follow.last_id, read_timeout=follow.read_timeout())
        try:
            while True:
                try:
                    event = next(stream)
                except StopIteration:
                    return None
                except errors.BlendsplatError as exc:
                    return exc
                if follow.event(event):
                    return None
        finally:
            stream.close()

    # ------------------------------------------------------------------------------------------- lifetime
    def close(self) -> None:
        self.http.close()
        if self._channel is not None:
            self._channel.close()
            self._channel = self._stub = None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
