"""`blendsplat jobs`: a command-line client of the training jobs' REST API (service/jobs/api.py).

Two layers:

- :class:`JobsClient`, an HTTP client with one method per API call (upload, create, list, get, cancel, delete, the
  event stream) and :meth:`JobsClient.follow`, which follows a job until it ends: by its server-sent events
  (``GET /v1/jobs/{id}/events``, resumed with ``Last-Event-ID`` after a dropped connection) or, on a server without
  them (404 for the route, not for the job) or when the stream keeps failing, by polling the job every second.
  Errors are typed: :class:`ApiError` (an HTTP error answer, with the server's code, message and field),
  :class:`ConnectionFailed`, :class:`EventsUnavailable`, :class:`WaitTimeout`.
- the commands (``blendsplat jobs ...``) are :mod:`service.jobs.cli`'s.

Conventions (docs/architecture.md): results go to stdout (the job's JSON with ``--json``, else a short summary);
progress bars (tqdm, only when stderr is a terminal), state changes and errors go to stderr. Exit codes: 0
success (``submit --wait`` / ``wait``: the job succeeded), 1 the job failed or was cancelled, 2 a usage,
connection, HTTP or timeout error, 130 waiting interrupted by Ctrl-C (the job goes on). The API key is sent as
``Authorization: Bearer KEY`` and never printed nor put in a URL.

Uploads are streamed: a dataset folder is packed into a temporary .tar.gz on disk, and the archive is sent as a
multipart/form-data body built as a generator (head, the file in 1 MiB reads, tail) with its Content-Length, so
the file is never held in memory.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import secrets
import tarfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

import httpx

from .sse import Event, parse_events

DEFAULT_SERVER = "http://127.0.0.1:8080"
SERVER_ENV, KEY_ENV = "BLENDSPLAT_SERVER", "BLENDSPLAT_API_KEY"
TERMINAL = frozenset({"succeeded", "failed", "cancelled"})
STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ARCHIVE_SUFFIXES = (".tar.gz", ".tgz", ".tar", ".zip")
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".webm", ".mkv")  # a video the server tracks (it sniffs the content)
CHUNK = 1 << 20  # bytes read from the archive per piece of the upload body
POLL_SECONDS = 1.0
STREAM_FAILURES = 3  # consecutive event-stream failures (no event received) before falling back to polling

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------------ errors
class ClientError(Exception):
    """Anything that stops a command before it has an answer (exit code 2)."""


class ConnectionFailed(ClientError):
    """The server could not be reached, or the connection broke."""


class ApiError(ClientError):
    """An HTTP error answer: the status and the server's ``{"error": {"code", "message", "field"}}``."""

    def __init__(self, status: int, code: str, message: str, field: str = ""):
        self.status, self.code, self.message, self.field = status, code, message, field
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f" (field {self.field})" if self.field else ""
        return f"{self.status} {self.code.lower()}: {self.message}{where}"

    @classmethod
    def of(cls, response: httpx.Response) -> ApiError:
        try:
            body = json.loads(response.read() or b"null")
        except (ValueError, httpx.HTTPError):
            body = None
        error = body.get("error") if isinstance(body, dict) else None
        if isinstance(error, dict):
            return cls(response.status_code, str(error.get("code") or response.reason_phrase),
                       str(error.get("message") or ""), str(error.get("field") or ""))
        if isinstance(body, dict) and "detail" in body:  # a framework's own answer
            return cls(response.status_code, response.reason_phrase, str(body["detail"]))
        text = response.text.strip()[:200] if response.is_stream_consumed else ""
        return cls(response.status_code, response.reason_phrase.replace(" ", "_") or "error",
                   text or "the server gave no reason")


class EventsUnavailable(ClientError):
    """The server has no event stream for jobs (its route answers 404, or not with text/event-stream)."""


class StreamBroken(ClientError):
    """The event stream failed (a dropped connection, a 5xx) or was idle past the read timeout (``idle``): worth
    a reconnect."""

    def __init__(self, message: str, idle: bool = False):
        super().__init__(message)
        self.idle = idle


class WaitTimeout(ClientError):
    """``--timeout`` passed before the job ended."""


# ------------------------------------------------------------------------------------------------------ client
def server_url(text: str) -> str:
    """The server's base URL, checked: http(s)://host[:port][/prefix], no credentials, no query."""
    parts = urlsplit(text.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ClientError(f"--server must be an http:// or https:// URL, got {text!r}")
    if parts.username or parts.password or parts.query or parts.fragment:
        raise ClientError("--server must not carry credentials, a query or a fragment (the key goes in --api-key)")
    return text.strip().rstrip("/")


class JobsClient:
    """The training jobs' REST API over HTTP: one method per call. Errors: :class:`ApiError` (an error answer),
    :class:`ConnectionFailed` (no answer). ``transport`` replaces the network (tests)."""

    def __init__(self, server: str = DEFAULT_SERVER, api_key: str | None = None, *, timeout: float = 30.0,
                 transport: httpx.BaseTransport | None = None):
        self.server = server_url(server)
        headers = {"User-Agent": "blendsplat-jobs", "Accept": "application/json"}
        if api_key:
            key = api_key.strip()
            if not key or not key.isascii() or not key.isprintable() or " " in key:
                raise ClientError("the API key must be one word of printable ASCII")
            headers["Authorization"] = f"Bearer {key}"
        self.http = httpx.Client(base_url=self.server, headers=headers, transport=transport,
                                 timeout=httpx.Timeout(timeout, connect=min(timeout, 10.0)))

    def __enter__(self) -> JobsClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    # ------------------------------------------------------------------------------------------- plumbing
    def url(self, path: str) -> str:
        """An absolute URL of a path the API returned (links)."""
        return self.server + path if path.startswith("/") else path

    def _failed(self, exc: httpx.TransportError) -> ConnectionFailed:
        reason = str(exc) or type(exc).__name__
        if isinstance(exc, httpx.ConnectError):
            return ConnectionFailed(f"cannot reach the server at {self.server} ({reason}); is it running "
                                    f"(`blendsplat up`)? Point at another with --server or {SERVER_ENV}")
        if isinstance(exc, httpx.TimeoutException):
            return ConnectionFailed(f"the server at {self.server} did not answer in time ({type(exc).__name__})")
        return ConnectionFailed(f"the connection to {self.server} failed ({reason})")

    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise self._failed(exc) from None
        if response.status_code >= 400:
            raise ApiError.of(response)
        return response

    @staticmethod
    def _json(response: httpx.Response) -> dict[str, Any]:
        try:
            body = response.json()
        except ValueError:
            raise ClientError(f"the server answered {response.status_code} with no JSON (is {response.url} a "
                              "Blendsplat service?)") from None
        if not isinstance(body, dict):
            raise ClientError("the server answered with an unexpected JSON value")
        return body

    @staticmethod
    def _job_path(job_id: str) -> str:
        if not job_id or not job_id.isprintable():
            raise ClientError(f"not a job id: {job_id!r}")
        return f"/v1/jobs/{quote(job_id, safe='')}"

    # ------------------------------------------------------------------------------------------- the calls
    def upload(self, archive: str | os.PathLike, *, filename: str | None = None,
               progress: Callable[[int], None] | None = None) -> dict[str, Any]:
        """``POST /v1/uploads``: stream an archive as the multipart field ``file``; the upload (``upload_id``,
        frames, ...). ``progress(n)`` is called with the bytes of each piece sent."""
        path = Path(archive)
        size = path.stat().st_size
        name = (filename or path.name).replace('"', "_").replace("\r", "_").replace("\n", "_")
        boundary = f"blendsplat-{secrets.token_hex(16)}"
        head = (f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{name}"\r\n'
                "Content-Type: application/octet-stream\r\n\r\n").encode()
        tail = f"\r\n--{boundary}--\r\n".encode()

        def body() -> Iterator[bytes]:
            yield head
            left = size
            with open(path, "rb") as f:
                while left > 0:
                    chunk = f.read(min(CHUNK, left))
                    if not chunk:
                        raise ClientError(f"{path} shrank while it was uploaded")
                    left -= len(chunk)
                    if progress is not None:
                        progress(len(chunk))
                    yield chunk
            yield tail

        headers = {"Content-Type": f"multipart/form-data; boundary={boundary}",
                   "Content-Length": str(len(head) + size + len(tail))}
        # the server checks and validates the whole dataset before it answers: allow it time
        timeout = httpx.Timeout(self.http.timeout.connect, read=max(600.0, self.http.timeout.read or 0),
                                write=self.http.timeout.write, connect=self.http.timeout.connect)
        return self._json(self._request("POST", "/v1/uploads", content=body(), headers=headers, timeout=timeout))

    def create_job(self, spec: dict[str, Any], idempotency_key: str | None = None) -> dict[str, Any]:
        """``POST /v1/jobs``: the job (201 created, or 200: the job an earlier request with this key created).
        With a key, a request that got no answer (a connection error) is sent once more: the server returns the
        job the first one created rather than a second job."""
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        try:
            return self._json(self._request("POST", "/v1/jobs", json=spec, headers=headers))
        except ConnectionFailed as exc:
            if not idempotency_key:
                raise
            log.warning("creating the job got no answer (%s); trying once more with the same Idempotency-Key", exc)
            time.sleep(0.5)
            return self._json(self._request("POST", "/v1/jobs", json=spec, headers=headers))

    def check(self) -> None:
        """That the server answers the jobs API and accepts the key (``GET /v1/jobs?limit=1``): what a command
        checks before slow local work (packing a dataset). ConnectionFailed or ApiError (401, 403) otherwise."""
        self.list_jobs(limit=1)

    def list_jobs(self, state: str | None = None, limit: int = 50, cursor: str | None = None) -> dict[str, Any]:
        """``GET /v1/jobs``: one page, newest first: ``{"jobs": [...], "next_cursor"}``."""
        params: dict[str, Any] = {"limit": limit}
        if state:
            params["state"] = state
        if cursor:
            params["cursor"] = cursor
        return self._json(self._request("GET", "/v1/jobs", params=params))

    def get_job(self, job_id: str) -> dict[str, Any]:
        """``GET /v1/jobs/{id}``."""
        return self._json(self._request("GET", self._job_path(job_id)))

    def cancel_job(self, job_id: str) -> dict[str, Any]:
        """``POST /v1/jobs/{id}/cancel``: the job (cancelled at once when queued; a running one stops before its
        next iteration; a finished one is left as it is)."""
        return self._json(self._request("POST", self._job_path(job_id) + "/cancel"))

    def delete_job(self, job_id: str) -> None:
        """``DELETE /v1/jobs/{id}``: the row, its events and its work folder."""
        self._request("DELETE", self._job_path(job_id))

    def events(self, job_id: str, last_event_id: str | None = None, *,
               read_timeout: float = 60.0) -> Iterator[Event]:
        """``GET /v1/jobs/{id}/events``: the job's server-sent events as they come (after ``last_event_id``), until
        the server closes the stream. Raises :class:`EventsUnavailable` when the server has no such route (a job
        that does not exist is :class:`ApiError` 404), :class:`StreamBroken` when the stream fails."""
        path = self._job_path(job_id) + "/events"
        headers = {"Accept": "text/event-stream", "Cache-Control": "no-cache"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = last_event_id
        timeout = httpx.Timeout(self.http.timeout.connect, read=read_timeout)
        try:
            with self.http.stream("GET", path, headers=headers, timeout=timeout) as response:
                if response.status_code == 404:
                    error = ApiError.of(response)
                    self.get_job(job_id)  # ApiError 404 when it is the job that is missing
                    raise EventsUnavailable(f"the server has no job event stream ({error})")
                if response.status_code in (405, 501):
                    raise EventsUnavailable(f"the server has no job event stream ({ApiError.of(response)})")
                if response.status_code >= 500 or response.status_code == 429:
                    raise StreamBroken(str(ApiError.of(response)))
                if response.status_code >= 400:
                    raise ApiError.of(response)
                kind = response.headers.get("content-type", "").split(";")[0].strip().lower()
                if kind != "text/event-stream":
                    raise EventsUnavailable(f"the event route answered {kind or 'no content type'}, not an event "
                                            "stream")
                yield from parse_events(response.iter_lines())
        except httpx.TransportError as exc:
            if isinstance(exc, httpx.ConnectError):
                raise self._failed(exc) from None
            raise StreamBroken(str(exc) or type(exc).__name__, idle=isinstance(exc, httpx.ReadTimeout)) from None

    # ------------------------------------------------------------------------------------------- following
    def follow(self, job_id: str, *, on_event: Callable[[Event], None] | None = None,
               on_job: Callable[[dict[str, Any]], None] | None = None, timeout: float | None = None,
               use_events: bool = True, poll_seconds: float = POLL_SECONDS,
               sleep: Callable[[float], None] = time.sleep) -> dict[str, Any]:
        """Follow a job until it ends; the job as it ended. Events go to ``on_event`` while the stream serves
        them; every job read (the first one, after each stream, each poll) to ``on_job``. Raises
        :class:`WaitTimeout` after ``timeout`` seconds; Ctrl-C (KeyboardInterrupt) passes through."""
        deadline = None if timeout is None else time.monotonic() + timeout

        def left() -> float:
            if deadline is None:
                return math.inf
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise WaitTimeout(f"timed out after {timeout:g} s waiting for job {job_id}")
            return remaining

        job = self.get_job(job_id)
        if on_job is not None:
            on_job(job)
        if job.get("state") in TERMINAL:
            return job
        last_id: str | None = None
        failures = 0
        while use_events:
            received = ended = False
            try:
                with contextlib.closing(self.events(job_id, last_id, read_timeout=min(60.0, left() + 0.5))) as events:
                    for event in events:
                        received = True
                        if event.id is not None:
                            last_id = event.id
                        if on_event is not None:
                            on_event(event)
                        if event.event == "state" and event.data.get("state") in TERMINAL:
                            ended = True
                            break
                        if event.event == "end":  # the server's last word: the job has ended (or is gone)
                            if event.data.get("state") == "deleted":
                                raise ClientError(f"job {job_id} was deleted")
                            ended = True
                            break
                        left()
            except EventsUnavailable as exc:
                log.debug("following job %s by polling: %s", job_id, exc)
                break
            except StreamBroken as exc:
                if exc.idle:  # nothing to say for a while: ask again (not a failure)
                    failures = 0 if received else failures
                else:
                    failures = 1 if received else failures + 1
                    log.debug("job %s: the event stream failed (%s)", job_id, exc)
            except ConnectionFailed as exc:
                failures = failures + 1
                log.debug("job %s: the event stream failed (%s)", job_id, exc)
            else:
                failures = 0 if ended or received else failures + 1
            job = self.get_job(job_id)  # the whole job, and whether it ended while the stream was down
            if on_job is not None:
                on_job(job)
            if job.get("state") in TERMINAL:
                return job
            if failures >= STREAM_FAILURES:
                log.warning("job %s: the event stream failed %d times in a row; polling instead", job_id, failures)
                break
            if failures:
                sleep(min(left(), 0.5 * 2 ** (failures - 1)))
        while True:
            sleep(min(left(), poll_seconds))
            left()
            job = self.get_job(job_id)
            if on_job is not None:
                on_job(job)
            if job.get("state") in TERMINAL:
                return job


# ---------------------------------------------------------------------------------------------- the commands
def check_dataset(folder: Path) -> None:
    """Check a tracked-video dataset folder (docs/tracked-video-format.md) before it is packed: the manifest and
    tracking fully, the frame and mask files for existence (the server decodes every one); ClientError naming the
    problem."""
    from render_core.data.portable import read_dataset
    from render_core.errors import DatasetError

    if not (folder / "dataset.json").is_file():
        raise ClientError(f"{folder} is not a tracked-video dataset: it has no dataset.json "
                          "(docs/tracked-video-format.md; `blendsplat data convert` makes one)")
    try:
        read_dataset(folder)
    except DatasetError as exc:
        raise ClientError(f"{folder} is not a valid tracked-video dataset: {exc}") from None


def pack_dataset(folder: Path, out: Path) -> None:
    """Pack a tracked-video dataset folder into a .tar.gz on disk, the dataset in one top-level folder; checked
    first (:func:`check_dataset`)."""
    check_dataset(folder)
    with tarfile.open(out, "w:gz", compresslevel=3, dereference=True) as tar:  # frames are PNG: little to gain
        tar.add(folder, arcname=folder.resolve().name or "dataset",
                filter=lambda m: m if (m.isfile() or m.isdir()) else None)
