"""A job's live history as server-sent events: ``GET /v1/jobs/{job_id}/events`` (the route is in api.py).

Every row of the job's ``job_events`` table (:meth:`service.jobs.store.JobStore.events`) becomes one event, in id
order::

    id: 42
    event: progress
    data: {"job_id":"job_...","time":"2026-...","iteration":120,"total_iterations":600,"fraction":0.2,...}

- ``progress``: ``stage`` (``train``, or ``track`` while a video upload is tracked: :mod:`service.jobs.track`),
  ``iteration``, ``total_iterations``, ``fraction`` (0 to 1), ``loss``, ``psnr``, ``eta_seconds``, ``gaussians``
  (null when the worker did not report one: all of them while tracking); a ``track`` one adds ``step`` (``start``,
  ``landmarks``, ``fit``, ``write``, ``done``, ``other``) and ``message``;
- ``preview``: ``iteration`` and ``url``, the preview artefact (``/v1/jobs/{id}/artefacts/preview``, replaced as
  training goes);
- ``state``: ``state``, ``previous``, ``attempts``, ``error`` (null unless it failed or was cancelled) and
  ``reason`` when there is one (``released``, ``lease expired``);
- ``log``: the log entry (``message``, ...).

Every ``data`` is one line of JSON and carries ``job_id`` and ``time`` (when it was recorded, UTC). ``id`` is the
row id: a client that reconnects with ``Last-Event-ID`` (or ``?after=``) gets only the later events; the
header wins over the query. Nothing is lost while it is away: the table is the history.

**How a stream ends.** When the job has finished (succeeded, failed, cancelled), every event recorded so far is
sent, then one ``event: end`` (no id; ``data: {"job_id", "state"}``) and the stream closes: a client that connects
after the end gets the whole recorded history, then the end. An ``EventSource`` should close itself on ``end``
(it would reconnect otherwise). A stream also ends, without ``end``, after ``events_max_seconds`` and when the
server shuts down (:func:`close_streams`, called at the start of the drain, so a drain is never held up): the
client reconnects with ``Last-Event-ID``, to this replica or another. A job deleted while streaming ends its
stream the same way (with ``end``, state ``deleted``).

**Bounds.** At most ``events_max_streams`` streams per process (more: 429, RESOURCE_EXHAUSTED); an idle stream
sends a comment line (``: keep-alive``) every ``events_keepalive_seconds`` so proxies keep it open. New events
are found by polling the job store every ``events_poll_seconds`` (in a thread: the store is synchronous), which
works the same on SQLite and PostgreSQL and across processes (the worker writes the events).
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
import weakref
from collections.abc import AsyncIterator, Callable
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI
from starlette.responses import StreamingResponse

from ..errors import NotFound, ResourceExhausted, Unavailable
from .checks import MAX_LIST, event_cursor
from .models import EventKind, JobEvent

if TYPE_CHECKING:
    from .training import Training

log = logging.getLogger(__name__)

MEDIA_TYPE = "text/event-stream"
RETRY_MS = 2000  # the reconnection delay a client is told
KEEPALIVE = b": keep-alive\n\n"
PROGRESS_KEYS = ("iteration", "total_iterations", "fraction", "loss", "psnr", "eta_seconds", "gaussians")
STAGES = ("track", "train")  # a progress event's stage on the stream (recorded only for track: none is train)
DEFAULT_MAX_STREAMS = 100


class EventStreams:
    """This process's event streams: how many are open (at most ``limit``) and the signal that closes them all.
    Thread-safe counting (the route runs in a worker thread, streams end on the event loop)."""

    def __init__(self, limit: int):
        self.limit = limit
        self.open = 0
        self.closing = asyncio.Event()
        self._lock = threading.Lock()

    def reserve(self) -> _Slot:
        """A slot for a new stream: ResourceExhausted (429) when ``limit`` are open, Unavailable (503) once the
        server is shutting down."""
        with self._lock:
            if self.closing.is_set():
                raise Unavailable("the server is shutting down; reconnect (with Last-Event-ID)", field="events")
            if self.open >= self.limit:
                raise ResourceExhausted(f"too many event streams on this server ({self.limit} open); retry later",
                                        field="events")
            self.open += 1
        return _Slot(self)

    def _release(self) -> None:
        with self._lock:
            self.open -= 1


class _Slot:
    def __init__(self, streams: EventStreams):
        self._streams: EventStreams | None = streams

    def release(self) -> None:
        streams, self._streams = self._streams, None
        if streams is not None:
            streams._release()


_REGISTRY_LOCK = threading.Lock()


def streams(app: FastAPI) -> EventStreams:
    """The app's :class:`EventStreams` (made on first use, sized by the training settings)."""
    with _REGISTRY_LOCK:
        registry = getattr(app.state, "event_streams", None)
        if registry is None:
            training = getattr(app.state, "training", None)
            limit = training.settings.events_max_streams if training is not None else DEFAULT_MAX_STREAMS
            registry = app.state.event_streams = EventStreams(limit)
        return registry


def close_streams(app: FastAPI) -> None:
    """Shutdown: every open event stream ends at once (its client reconnects elsewhere) and new ones are refused
    (503). Call it on the app's event loop."""
    streams(app).closing.set()


def last_event_id(header: str | None, after: int | None) -> int:
    """Where a stream starts: after the ``Last-Event-ID`` header's id, else after ``?after=``, else at the start."""
    if header is not None and header.strip():
        return event_cursor(header, "Last-Event-ID")
    return event_cursor(after, "after") if after is not None else 0


def event_data(event: JobEvent) -> dict[str, Any]:
    """What a recorded event says on the stream (see the module docstring)."""
    data = dict(event.data)
    out: dict[str, Any] = {"job_id": event.job_id, "time": event.created_at.isoformat()}
    if event.kind is EventKind.PROGRESS:
        out["stage"] = data.get("stage") if data.get("stage") in STAGES else "train"
        out.update({key: data.get(key) for key in PROGRESS_KEYS})
        out.update({k: v for k, v in data.items() if k not in out})
    elif event.kind is EventKind.PREVIEW:
        out.update({"iteration": data.get("iteration"), "url": f"/v1/jobs/{event.job_id}/artefacts/preview"})
    elif event.kind is EventKind.STATE:
        out.update({"state": data.get("state"), "previous": data.get("previous"), "attempts": data.get("attempts"),
                    "error": data.get("error")})
        if data.get("reason"):
            out["reason"] = data["reason"]
    else:
        out.update({k: v for k, v in data.items() if k not in out})
    return out


def format_event(event: JobEvent) -> bytes:
    body = json.dumps(event_data(event), separators=(",", ":"), allow_nan=False, default=str)
    return f"id: {event.id}\nevent: {event.kind.value}\ndata: {body}\n\n".encode()


def _end(job_id: str, state: str) -> bytes:
    return f"event: end\ndata: {json.dumps({'job_id': job_id, 'state': state}, separators=(',', ':'))}\n\n".encode()


async def _follow(training: Training, job_id: str, after: int, registry: EventStreams,
                  drain: asyncio.Event | None, key_id: str | None = None) -> AsyncIterator[bytes]:
    settings = training.settings
    store = training.jobs
    now = time.monotonic()
    deadline = now + settings.events_max_seconds
    quiet_since = key_checked = now
    signals = [registry.closing] + ([drain] if drain is not None else [])
    yield f"retry: {RETRY_MS}\n\n".encode()
    while not any(s.is_set() for s in signals):
        if key_id and time.monotonic() - key_checked >= settings.stream_key_check_seconds:
            key_checked = time.monotonic()  # the key database, not the cache: a revoked key's stream ends
            if await asyncio.to_thread(training.access.revoked, {key_id}):
                yield _revoked(job_id)
                return
        try:
            job = await asyncio.to_thread(store.get, job_id)  # first: a finished job's last events are in the read
            while True:
                batch = await asyncio.to_thread(store.events, job_id, after, MAX_LIST)
                for event in batch:
                    yield format_event(event)
                    after = event.id
                if batch:
                    quiet_since = time.monotonic()
                if len(batch) < MAX_LIST:
                    break
        except NotFound:
            yield _end(job_id, "deleted")
            return
        if job.finished:
            yield _end(job_id, job.state.value)
            return
        now = time.monotonic()
        if now >= deadline:
            return
        if now - quiet_since >= settings.events_keepalive_seconds:
            yield KEEPALIVE
            quiet_since = now
        wait = min(settings.events_poll_seconds, deadline - now,
                   max(0.0, quiet_since + settings.events_keepalive_seconds - now))
        waiters = [asyncio.ensure_future(s.wait()) for s in signals]
        try:
            await asyncio.wait(waiters, timeout=wait, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()


def _revoked(job_id: str) -> bytes:
    body = {"job_id": job_id, "code": "UNAUTHENTICATED", "message": "the API key of this stream was revoked"}
    return f"event: error\ndata: {json.dumps(body, separators=(',', ':'))}\n\n".encode()


def event_stream(app: FastAPI, training: Training, job_id: str, after: int,
                 on_close: Callable[[], None] | None = None, key_id: str | None = None) -> StreamingResponse:
    """The response that streams a job's events after id ``after`` (the caller has checked the job exists and may
    be read). ResourceExhausted (429) when this process has ``events_max_streams`` open. ``on_close`` (called once,
    whenever the stream ends or never starts) frees what the caller holds for it (the key's stream slot). ``key_id``:
    the caller's key, checked again every ``stream_key_check_seconds``; once revoked, an ``error`` event
    (UNAUTHENTICATED) ends the stream."""
    registry = streams(app)
    slot = registry.reserve()
    drain = getattr(app.state, "closing", None)  # set when the server drains (service.http.app)

    def release() -> None:  # each part is idempotent
        slot.release()
        if on_close is not None:
            on_close()

    async def body() -> AsyncIterator[bytes]:
        try:
            async for chunk in _follow(training, job_id, after, registry, drain, key_id):
                yield chunk
        finally:
            release()

    iterator = body()
    weakref.finalize(iterator, release)  # a response that never started streaming frees its slot too
    return StreamingResponse(iterator, media_type=MEDIA_TYPE,
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
