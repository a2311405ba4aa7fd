"""Service errors and the one place that maps every error to a gRPC status code and an HTTP status."""

from __future__ import annotations

import grpc

from blendsplat.v1 import render_pb2 as pb
from render_core.errors import BlendsplatError

# Every error text on the wire is bounded: gRPC carries the details of a failed call in its trailing metadata (8 KiB
# by default; more and the client sees RESOURCE_EXHAUSTED instead of the real status), and an HTTP error body should
# not grow with what a client sent either. Lists of names say a few and a count (:func:`some`).
MAX_MESSAGE_CHARS = 1000
MAX_FIELD_CHARS = 120
SOME_NAMES = 5


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

    def __init__(self, message: str, *, field: str | None = None):
        self.field = field
        self.detail = message  # without the field (for replies that carry the field separately)
        super().__init__(f"{field}: {message}" if field else message)


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
        return pb.Status(code=code, message=bounded(exc.detail), field=bounded(exc.field or "", MAX_FIELD_CHARS),
                         frame_index=frame_index)
    if isinstance(exc, MemoryError):
        return pb.Status(code=pb.RESOURCE_EXHAUSTED, message="not enough memory for this request",
                         frame_index=frame_index)
    return pb.Status(code=pb.INTERNAL, message=f"internal error ({type(exc).__name__})", frame_index=frame_index)


def grpc_code(code: int) -> grpc.StatusCode:
    name = pb.Code.Name(code)
    return getattr(grpc.StatusCode, name)


def http_status(code: int) -> int:
    return _HTTP.get(code, 500)
