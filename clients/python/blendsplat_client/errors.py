"""Typed errors. Every error the service answers carries its ``Status`` (code, message, field): from the REST error
body ``{"error": {"code", "message", "field"}}``, from gRPC's trailing metadata ``blendsplat-status-bin`` (a
serialized ``blendsplat.v1.Status``), or from a stream's ``error`` / final ``status`` message. The class is the code's:
``NotFound``, ``InvalidArgument`` (``field`` names what was wrong), ``PermissionDenied``, ``Unauthenticated``,
``ResourceExhausted`` (``retry_after`` when the server said), ``FailedPrecondition``, ``Unavailable``, ``Internal``,
``Unimplemented`` (the server has no such call, e.g. an older one);
``Timeout`` when a call ran past its timeout, ``ConnectionFailed`` (an ``Unavailable``) when no answer came.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

STATUS_TRAILER = "blendsplat-status-bin"


@dataclass(frozen=True)
class Status:
    """The service's status of a failed call or message: the code's name (``NOT_FOUND``), message and field."""

    code: str
    message: str
    field: str = ""
    frame_index: int = 0


class BlendsplatError(Exception):
    """An error answer of the service (or no answer): ``status`` (code, message, field), ``http_status`` for REST,
    ``retry_after`` (seconds) when the server asked the client to wait."""

    code = "UNKNOWN"

    def __init__(self, message: str, *, field: str = "", code: str | None = None, http_status: int | None = None,
                 frame_index: int = 0, retry_after: float | None = None, error_id: str | None = None):
        self.status = Status(code or self.code, message, field or "", frame_index)
        self.http_status, self.retry_after, self.error_id = http_status, retry_after, error_id
        super().__init__(f"{self.status.code}: {message}" + (f" (field {field})" if field else ""))

    @property
    def message(self) -> str:
        return self.status.message

    @property
    def field(self) -> str:
        return self.status.field


class Cancelled(BlendsplatError):
    code = "CANCELLED"


class InvalidArgument(BlendsplatError):
    code = "INVALID_ARGUMENT"


class NotFound(BlendsplatError):
    code = "NOT_FOUND"


class PermissionDenied(BlendsplatError):
    code = "PERMISSION_DENIED"


class ResourceExhausted(BlendsplatError):
    code = "RESOURCE_EXHAUSTED"


class FailedPrecondition(BlendsplatError):
    code = "FAILED_PRECONDITION"


class Internal(BlendsplatError):
    code = "INTERNAL"


class Unimplemented(BlendsplatError):
    """The server has no such call (an older server, or a route answered with something else than expected)."""

    code = "UNIMPLEMENTED"


class Unavailable(BlendsplatError):
    code = "UNAVAILABLE"


class Unauthenticated(BlendsplatError):
    code = "UNAUTHENTICATED"


class Timeout(BlendsplatError):
    """The call did not finish within its timeout."""

    code = "DEADLINE_EXCEEDED"


class ConnectionFailed(Unavailable):
    """The server could not be reached, or the connection broke before an answer."""


class JobFailed(BlendsplatError):
    """``wait`` on a job that ended failed or cancelled: ``job`` is the job as it ended."""

    code = "FAILED_PRECONDITION"

    def __init__(self, job: dict):
        self.job = job
        error = job.get("error") or {}
        text = error.get("message") if isinstance(error, dict) else str(error)
        super().__init__(f"job {job.get('id')} {job.get('state')}" + (f": {text}" if text else ""))


CLASSES = {c.code: c for c in (Cancelled, InvalidArgument, NotFound, PermissionDenied, ResourceExhausted,
                               FailedPrecondition, Internal, Unimplemented, Unavailable, Unauthenticated, Timeout)}
_BY_HTTP = {400: InvalidArgument, 401: Unauthenticated, 403: PermissionDenied, 404: NotFound, 408: Timeout,
            409: FailedPrecondition, 413: InvalidArgument, 422: InvalidArgument, 429: ResourceExhausted,
            499: Cancelled, 503: Unavailable}


def error_for(code: str, message: str, **kw) -> BlendsplatError:
    """The typed error of a status code's name."""
    return CLASSES.get(code, BlendsplatError)(message, code=code, **kw)


def retry_after_seconds(value: str | None) -> float | None:
    """A ``Retry-After`` header in seconds (delta-seconds or an HTTP date), or None."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    from email.utils import parsedate_to_datetime

    try:
        import time

        return max(0.0, parsedate_to_datetime(value).timestamp() - time.time())
    except (TypeError, ValueError):
        return None


def from_http(status: int, body: bytes, headers) -> BlendsplatError:
    """The error of an HTTP error answer (its status, body and headers)."""
    retry_after = retry_after_seconds(headers.get("retry-after"))
    try:
        error_body = json.loads(body or b"null")
    except ValueError:
        error_body = None
    error = error_body.get("error") if isinstance(error_body, dict) else None
    if isinstance(error, dict) and error.get("code"):
        return error_for(str(error["code"]), str(error.get("message") or ""), field=str(error.get("field") or ""),
                         http_status=status, retry_after=retry_after, error_id=error.get("errorId"))
    cls = _BY_HTTP.get(status) or (Internal if status >= 500 else BlendsplatError)
    detail = error_body.get("detail") if isinstance(error_body, dict) else None  # a framework's own answer
    text = body[:200].decode(errors="replace").strip() if body else ""
    text = detail if isinstance(detail, str) and detail else text
    return cls(text or f"HTTP {status}", http_status=status, retry_after=retry_after)


def from_status(status) -> BlendsplatError:
    """The error of a ``blendsplat.v1.Status`` message (a stream's ``error`` or failed final ``status``)."""
    from ._proto import render_pb2 as pb

    return error_for(pb.Code.Name(status.code), status.message, field=status.field, frame_index=status.frame_index)


def from_grpc(exc) -> BlendsplatError:
    """The error of a failed gRPC call: the ``blendsplat-status-bin`` trailer when the service sent one, else the
    call's code and details."""
    import grpc

    from ._proto import render_pb2 as pb

    try:
        trailers = exc.trailing_metadata() or ()
    except Exception:  # noqa: BLE001 - a call that never started has none
        trailers = ()
    for key, value in trailers:
        if key == STATUS_TRAILER and isinstance(value, bytes):
            try:
                return from_status(pb.Status.FromString(value))
            except Exception:  # noqa: BLE001 - a malformed trailer: fall back to the code
                break
    code = exc.code() if callable(getattr(exc, "code", None)) else grpc.StatusCode.UNKNOWN
    details = (exc.details() if callable(getattr(exc, "details", None)) else None) or str(code)
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        return Timeout(details)
    if code == grpc.StatusCode.UNAVAILABLE:
        return ConnectionFailed(details)
    return error_for(code.name, details)
