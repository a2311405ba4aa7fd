"""Following a job to its end (``wait`` of both clients), described once as :class:`Follow`, the state the sync and
asyncio loops drive: the job read first, then its server-sent events (``GET /v1/jobs/{id}/events``, reconnecting
with ``Last-Event-ID`` after a dropped connection, the job read again after each stream), and polling the job every
``poll_seconds`` where the server has no event stream (the route answers 404, 405 or 501, or not with
text/event-stream) or the stream keeps failing (:data:`STREAM_FAILURES` times in a row with no event)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from . import errors
from ._rest import TERMINAL
from ._sse import Event

POLL_SECONDS = 1.0
STREAM_FAILURES = 3  # consecutive failed streams (no event received) before polling instead
MAX_READ = 60.0  # seconds a stream may be silent (the server's keep-alives come well within it)


def no_stream(error: errors.BlendsplatError) -> bool:
    """Whether an error opening the event stream says the server has none (a job that is missing is told apart by
    the job's read that follows)."""
    return isinstance(error, errors.NotFound | errors.Unimplemented) or error.http_status in (405, 501)


def broken(error: errors.BlendsplatError) -> bool:
    """Whether the stream failed in a way worth a reconnect (a dropped connection, 5xx, 429)."""
    status = error.http_status
    return isinstance(error, errors.Unavailable) or (status is not None and (status >= 500 or status == 429)) or (
        status is None and isinstance(error, errors.Internal | errors.ResourceExhausted))


class Follow:
    """One ``wait``: the deadline, the last event id, the failures in a row, the callbacks."""

    def __init__(self, job_id: str, timeout: float | None, on_event: Callable[[Event], None] | None,
                 on_job: Callable[[dict], None] | None, poll_seconds: float = POLL_SECONDS):
        if poll_seconds <= 0:
            raise ValueError("poll_seconds must be positive")
        self.job_id, self.timeout, self.poll_seconds = job_id, timeout, poll_seconds
        self.on_event, self.on_job = on_event, on_job
        self.deadline = None if timeout is None else time.monotonic() + timeout
        self.last_id: str | None = None
        self.failures = 0
        self.streaming = True  # False: polling
        self.received = self.ended = self.deleted = False

    def left(self) -> float:
        """Seconds left before the deadline; :class:`~blendsplat_client.errors.Timeout` once it has passed."""
        if self.deadline is None:
            return math.inf
        remaining = self.deadline - time.monotonic()
        if remaining <= 0:
            raise errors.Timeout(f"timed out after {self.timeout:g} s waiting for job {self.job_id}")
        return remaining

    def read_timeout(self) -> float:
        """How long the next stream may be silent."""
        return min(MAX_READ, self.left() + 0.5)

    def job(self, job: dict[str, Any]) -> bool:
        """A read of the job (to ``on_job``); whether it has ended."""
        if self.on_job is not None:
            self.on_job(job)
        return job.get("state") in TERMINAL

    def opening(self) -> None:
        """A stream is about to be opened."""
        self.received = self.ended = False

    def event(self, event: Event) -> bool:
        """An event of the stream (to ``on_event``); whether to stop reading it (the job has ended or is gone)."""
        self.received = True
        if event.id is not None:
            self.last_id = event.id
        if self.on_event is not None:
            self.on_event(event)
        if event.event == "end" or (event.event == "state" and event.data.get("state") in TERMINAL):
            self.ended = True
            self.deleted = event.event == "end" and event.data.get("state") == "deleted"
            return True
        self.left()
        return False

    def closed(self, error: errors.BlendsplatError | None) -> None:
        """The stream ended (``error``: how it failed, None: the server closed it). Raises what is not the
        stream's own failure (a refused key, a deleted job)."""
        if self.deleted:
            raise errors.NotFound(f"job {self.job_id} was deleted", field="job_id")
        if error is None:
            self.failures = 0 if self.ended or self.received else self.failures + 1
        elif no_stream(error):
            self.streaming = False  # polling; the job's read that follows raises NotFound if it is the job
        elif isinstance(error, errors.Timeout):
            self.failures = 0 if self.received else self.failures  # silent for a while: ask again
        elif broken(error):
            self.failures = 1 if self.received else self.failures + 1
        else:
            raise error

    def pause(self) -> float:
        """Seconds to wait before the next stream, or before the next poll once polling (:attr:`streaming`)."""
        if self.streaming and self.failures >= STREAM_FAILURES:
            self.streaming = False  # the stream keeps failing: polling instead
        if not self.streaming:
            return min(self.left(), self.poll_seconds)
        return min(self.left(), 0.5 * 2 ** (self.failures - 1)) if self.failures else 0.0
