"""Service errors and the one place that maps every error to a gRPC status code and an HTTP answer.

:func:`to_status` makes any exception a wire status (what gRPC and the WebSocket send); :func:`http_error` makes it
the HTTP transport's answer: the status, the one JSON error body, and the headers some errors add (``Retry-After``,
``WWW-Authenticate``, ``Connection: close``). An INTERNAL error is logged there with an id its answer carries.
"""

from __future__ import annotations

import logging
import os
import uuid
from pathlib import Path
from typing import Any

import grpc

from blendsplat.v1 import render_pb2 as pb
from render_core.errors import BlendsplatError

# Every error text on the wire is bounded: gRPC carries the details of a failed call in its trailing metadata (8 KiB
# by default; more and the client sees RESOURCE_EXHAUSTED instead of the real status), and an HTTP error body should
# not grow with what a client sent either. Lists of names say a few and a count (:func:`some`).
MAX_MESSAGE_CHARS = 1000
MAX_FIELD_CHARS = 120
SOME_NAMES = 5
log = logging.getLogger(__name__)


# Server paths never reach a client: every folder registered here (the data folder: the bundle store, uploads, work
# folders, adapters, face models all lie in it) is cut from client-facing text, leaving relative names
# (``bundles/x.bundle``). :func:`to_status` (so every HTTP, gRPC and WebSocket error), /readyz's reasons, a job's
# recorded error and its JSON artefacts go through :func:`redact`. The service and the worker register their
# settings' data folder at start (:func:`hide_paths`).
_HIDDEN: set[str] = set()


def hide_paths(*roots: str | os.PathLike) -> None:
    """Register folders whose absolute paths :func:`redact` removes (as given, absolute and resolved)."""
    for root in roots:
        for form in (Path(root).absolute(), Path(root).resolve()):
            text = str(form).rstrip(os.sep)
            if len(text) > 1:  # never "/"
                _HIDDEN.add(text)


def redact(text: str) -> str:
    """``text`` with every registered folder cut: ``<root>/a/b`` -> ``a/b``, the folder itself -> ``the data folder``
    (the longest first, so a folder inside another is cut whole)."""
    if not isinstance(text, str) or not _HIDDEN:
        return text
    for root in sorted(_HIDDEN, key=len, reverse=True):
        if root in text:
            text = text.replace(root + os.sep, "").replace(root, "the data folder")
    return text


def some(names, limit: int = SOME_NAMES) -> str:
    """A bounded listing: ``'a', 'b', 'c' and 9997 more`` (every name quoted and cut to 40 characters)."""
    names = list(names)
    shown = ", ".join(repr(n if len(n) <= 40 else n[:40] + "...") if isinstance(n, str) else repr(n)
                      for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def bounded(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` cut to ``limit`` characters, saying how much was left out."""
    if len(text) <= limit:
        return text
    keep = max(0, limit - 40)  # room for the note
    return f"{text[:keep]}... ({len(text) - keep} more characters)"


class ServiceError(Exception):
    """An error a client caused or must handle; ``code`` is the wire status (a ``blendsplat.v1.Code`` value)."""

    code: int = pb.INTERNAL
    http: int | None = None  # HTTP only: a status of its own, not the code's (a body too large: 413)
    closes: bool = False  # HTTP only: the request body was not read to its end, so the connection is closed

    def __init__(self, message: str, *, field: str | None = None):
        self.field = field
        self.detail = message  # without the field (for replies that carry the field separately)
        super().__init__(f"{field}: {message}" if field else message)

    def http_headers(self) -> dict[str, str]:
        """Headers the HTTP answer adds (``Retry-After``...)."""
        return {}


class InvalidArgument(ServiceError):
    code = pb.INVALID_ARGUMENT


class NotFound(ServiceError):
    code = pb.NOT_FOUND


class ResourceExhausted(ServiceError):
    code = pb.RESOURCE_EXHAUSTED


class FailedPrecondition(ServiceError):
    code = pb.FAILED_PRECONDITION


class Unavailable(ServiceError):
    code = pb.UNAVAILABLE


class PermissionDenied(ServiceError):
    """A valid key without the scope, or another tenant's resource: HTTP 403, gRPC PERMISSION_DENIED."""

    code = pb.PERMISSION_DENIED


class BodyTooLarge(InvalidArgument):
    """HTTP only: a request body over its route's limit (413; the connection is closed, the rest never read)."""

    http, closes = 413, True


class BodyTimeout(InvalidArgument):
    """HTTP only: a request body that stalled (408; the connection is closed)."""

    http, closes = 408, True


class BodyRefused(Unavailable):
    """A request body still arriving when the server drains (503; the connection is closed)."""

    closes = True


_HTTP = {
    pb.OK: 200, pb.CANCELLED: 499, pb.INVALID_ARGUMENT: 422, pb.NOT_FOUND: 404, pb.PERMISSION_DENIED: 403,
    pb.RESOURCE_EXHAUSTED: 429, pb.FAILED_PRECONDITION: 409, pb.INTERNAL: 500, pb.UNAVAILABLE: 503,
    pb.UNAUTHENTICATED: 401,
}


def to_status(exc: BaseException, frame_index: int = 0) -> pb.Status:
    """Any exception as a wire status: typed errors keep their code and field (the message then leaves the field
    out); others are INTERNAL. render_core's typed errors (:class:`~render_core.errors.BlendsplatError`: a frame,
    camera, codec setting, bundle or option the client sent) are INVALID_ARGUMENT (HTTP 422); a MemoryError (an
    allocation refused) is RESOURCE_EXHAUSTED. Message and field are bounded (:func:`bounded`)."""
    if isinstance(exc, ServiceError | BlendsplatError):
        code = exc.code if isinstance(exc, ServiceError) else pb.INVALID_ARGUMENT  # render_core: the client's input
        return pb.Status(code=code, message=bounded(redact(exc.detail)),
                         field=bounded(redact(exc.field or ""), MAX_FIELD_CHARS), frame_index=frame_index)
    if isinstance(exc, MemoryError):
        return pb.Status(code=pb.RESOURCE_EXHAUSTED, message="not enough memory for this request",
                         frame_index=frame_index)
    return pb.Status(code=pb.INTERNAL, message=f"internal error ({type(exc).__name__})", frame_index=frame_index)


def grpc_code(code: int) -> grpc.StatusCode:
    name = pb.Code.Name(code)
    return getattr(grpc.StatusCode, name)


def http_status(code: int) -> int:
    return _HTTP.get(code, 500)


def http_error(exc: BaseException, where: str = "", metrics=None) -> tuple[int, dict[str, Any], dict[str, str]]:
    """Any exception as an HTTP answer: (status, body, headers). The body is ``{"error": {"code", "message",
    "field"}}`` from :func:`to_status`; an INTERNAL error is logged with its traceback under a new error id (``where``
    says what was being served), which the body carries too (``errorId``), never the exception's text. ``metrics``:
    counts the error (``blendsplat_errors_total{transport="http"}``)."""
    status = to_status(exc)
    if metrics is not None:
        metrics.errors.labels(pb.Code.Name(status.code), "http").inc()
    body: dict[str, Any] = {"error": {"code": pb.Code.Name(status.code), "message": status.message,
                                      "field": status.field}}
    if status.code == pb.INTERNAL:
        error_id = uuid.uuid4().hex[:16]
        log.error("internal error %s%s: %s: %s", error_id, f" ({where})" if where else "", type(exc).__name__,
                  exc, exc_info=exc)
        body["error"]["message"] = f"{status.message}; error id {error_id}"
        body["error"]["errorId"] = error_id
    if not isinstance(exc, ServiceError):
        return http_status(status.code), body, {}
    headers = {**exc.http_headers(), **({"Connection": "close"} if exc.closes else {})}
    return exc.http or http_status(status.code), body, headers


def invalid_request(errors: list[dict[str, Any]]) -> InvalidArgument:
    """A request that failed validation (FastAPI's, pydantic's error list) as INVALID_ARGUMENT, naming the first
    field at fault (``iterations``, ``limit``, ``idempotency-key``; the location's kind, body or query, left out)."""
    first = errors[0] if errors else {}
    location = [str(part) for part in first.get("loc", ())]
    field = ".".join(location[1:]) if len(location) > 1 else (location[0] if location else "body")
    message = str(first.get("msg", "invalid request"))
    if len(errors) > 1:
        message += f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})"
    return InvalidArgument(message, field=field)
