"""Slow, idle and half-open HTTP clients cannot hold the server's connections (issue 28): uvicorn's HTTP and
WebSocket protocols with timers and connection counts, wired in by :mod:`service.server` (``http=`` and ``ws=``).

- **Request heads.** A request's head (request line and headers) must be complete within
  ``header_timeout_seconds`` of the connection opening, or of the previous answer on a kept-alive connection; else
  the connection is closed (with a 408 when part of a head came). uvicorn has no such timer: its keep-alive timer
  stops at the first byte, so a client sending half a head held the connection for ever. The timer stops once the
  head is complete, so a WebSocket (upgraded) or a streamed answer (job events, SSE) runs as long as it lasts.
- **Request bodies.** A body that sends no bytes for ``body_timeout_seconds`` while the server reads it is refused
  with 408 by the app (:class:`~service.http.app.RequestGuard`); this protocol closes the connection
  :data:`BODY_GRACE_SECONDS` later if it is still open, which covers bodies no route reads. Time spent while the
  server does not read (its buffer full, a ``100-continue`` not sent yet) does not count. After an answer, what is
  left of a body and the next head fall under the head timer, so a trickled body cannot keep a connection either.
- **Connections.** At most ``max_connections`` open connections per server and ``max_connections_per_address``
  from one client address (the peer's IP); past either, a new connection gets a 503 with ``Retry-After`` and is
  closed at once, so one client cannot use up the process's file descriptors and readiness, other clients and
  gRPC go on. ``max_connections`` is lowered to a third of the descriptor limit (:func:`fit_to_descriptors`).

Every count is per server (:class:`ConnectionGuard`, one per HTTP server), keyed by the transport, so a connection
upgraded to a WebSocket stays counted until it closes.
"""

from __future__ import annotations

import asyncio
import json
import logging
import resource
import time
from collections import Counter

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.protocols.websockets.auto import AutoWebSocketsProtocol

log = logging.getLogger(__name__)
BODY_GRACE_SECONDS = 2.0  # after body_timeout_seconds: the app's 408 goes first, then the connection is closed
RETRY_AFTER_SECONDS = 5  # what a refused connection is told


def fit_to_descriptors(wanted: int, servers: int = 3) -> int:
    """``wanted`` connections per server, lowered so that the process's servers together hold at most
    ``(servers - 1) / servers`` of its file-descriptor limit (RLIMIT_NOFILE), the rest left for files, the
    databases and the native libraries; at least 16."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft <= 0:
        return wanted
    return max(16, min(wanted, soft // servers))


def client_address(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
    return str(peer[0]) if isinstance(peer, tuple) and peer else "local"


def _answer(status: str, message: str, code: str, field: str = "", retry_after: int | None = None) -> bytes:
    """A complete HTTP/1.1 answer in the service's JSON error shape, closing the connection."""
    body = json.dumps({"error": {"code": code, "message": message, "field": field}}).encode()
    retry = f"retry-after: {retry_after}\r\n" if retry_after else ""
    return (f"HTTP/1.1 {status}\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n{retry}"
            "connection: close\r\n\r\n").encode() + body


class ConnectionGuard:
    """One HTTP server's connection counts and timeouts (see the module docstring)."""

    def __init__(self, *, max_connections: int, max_per_address: int, header_timeout: float, body_timeout: float):
        self.max_connections, self.max_per_address = max_connections, max_per_address
        self.header_timeout, self.body_timeout = header_timeout, body_timeout
        self._open: dict[asyncio.BaseTransport, str] = {}  # transport -> client address
        self._per_address: Counter[str] = Counter()
        self.refused = self.timed_out = 0
        self._warned = 0.0

    @classmethod
    def from_settings(cls, settings) -> ConnectionGuard:
        cap = fit_to_descriptors(settings.max_connections)
        if cap < settings.max_connections:
            log.info("max_connections lowered from %d to %d per server: the file-descriptor limit (ulimit -n) is "
                     "%d", settings.max_connections, cap, resource.getrlimit(resource.RLIMIT_NOFILE)[0])
        return cls(max_connections=cap, max_per_address=min(settings.max_connections_per_address, cap),
                   header_timeout=settings.header_timeout_seconds, body_timeout=settings.body_timeout_seconds)

    @property
    def open(self) -> int:
        return len(self._open)

    def from_address(self, address: str) -> int:
        return self._per_address[address]

    def admit(self, transport: asyncio.BaseTransport) -> str | None:
        """Count a new connection: None, or why it is refused (nothing counted)."""
        if transport in self._open:
            return None  # counted already (a connection upgraded to a WebSocket)
        address = client_address(transport)
        if len(self._open) >= self.max_connections:
            why = f"this server holds {self.max_connections} connections (max_connections); try again later"
        elif self._per_address[address] >= self.max_per_address:
            why = (f"this address holds {self.max_per_address} connections (max_connections_per_address); close "
                   "one first")
        else:
            self._open[transport] = address
            self._per_address[address] += 1
            return None
        self.refused += 1
        now = time.monotonic()
        if now - self._warned > 60:
            self._warned = now
            log.warning("refusing HTTP connections: %s (from %s; %d refused so far)", why, address, self.refused)
        return why

    def release(self, transport: asyncio.BaseTransport | None) -> None:
        address = self._open.pop(transport, None)
        if address is not None:
            self._per_address[address] -= 1
            if self._per_address[address] <= 0:
                del self._per_address[address]


def _announces_body(headers: list[tuple[bytes, bytes]]) -> bool:
    return any(name == b"transfer-encoding" or (name == b"content-length" and value.strip().lstrip(b"0"))
               for name, value in headers)


class _GuardedHttp(HttpToolsProtocol):
    """uvicorn's httptools protocol with the guard's counts and timers (made per server by :func:`protocols`)."""

    guard: ConnectionGuard

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._refused = False
        self._head_timer: asyncio.TimerHandle | None = None
        self._head_started = False  # bytes of a head came since the head timer started
        self._body_timer: asyncio.TimerHandle | None = None

    # ---- connections
    def connection_made(self, transport) -> None:  # type: ignore[override]
        why = self.guard.admit(transport)
        if why is not None:
            self._refused, self.transport = True, transport
            transport.write(_answer("503 Service Unavailable", why, "UNAVAILABLE",
                                    retry_after=RETRY_AFTER_SECONDS))
            transport.close()
            return
        super().connection_made(transport)
        self._start_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._stop_timers()
        if self._refused:
            return
        self.guard.release(self.transport)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if self._head_timer is not None:
            self._head_started = True
        if self._body_timer is not None:
            self._start_body_timer()  # bytes came: the body's idle time starts again
        super().data_received(data)

    # ---- the parser's and the cycle's callbacks
    def on_headers_complete(self) -> None:
        self._stop_head_timer()
        super().on_headers_complete()
        if _announces_body(self.headers) and not self.parser.should_upgrade():
            self._start_body_timer()

    def on_message_complete(self) -> None:
        self._stop_body_timer()
        super().on_message_complete()

    def on_response_complete(self) -> None:
        self._stop_body_timer()  # what is left of the body is the next head's business
        super().on_response_complete()
        if not self.transport.is_closing() and (self.cycle is None or self.cycle.response_complete):
            self._start_head_timer()  # no request waits (pipelined): the next head has its time from now

    # ---- timers
    def _start_head_timer(self) -> None:
        self._stop_head_timer()
        self._head_started = False
        self._head_timer = self.loop.call_later(self.guard.header_timeout, self._head_timed_out)

    def _stop_head_timer(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _start_body_timer(self) -> None:
        self._stop_body_timer()
        self._body_timer = self.loop.call_later(self.guard.body_timeout + BODY_GRACE_SECONDS, self._body_timed_out)

    def _stop_body_timer(self) -> None:
        if self._body_timer is not None:
            self._body_timer.cancel()
            self._body_timer = None

    def _stop_timers(self) -> None:
        self._stop_head_timer()
        self._stop_body_timer()

    def _head_timed_out(self) -> None:
        self._head_timer = None
        if self.transport.is_closing():
            return
        self.guard.timed_out += 1
        if self._head_started:
            self.transport.write(_answer(
                "408 Request Timeout", f"the request head did not arrive within {self.guard.header_timeout:g} s "
                "(header_timeout_seconds)", "INVALID_ARGUMENT", "headers"))
        self.transport.close()

    def _body_timed_out(self) -> None:
        self._body_timer = None
        cycle = self.cycle
        if self.transport.is_closing() or cycle is None or cycle.response_complete:
            return
        if self.flow.read_paused or cycle.waiting_for_100_continue:
            self._start_body_timer()  # the server is not reading: not the client's stall
            return
        self.guard.timed_out += 1
        self.transport.close()  # the app sees the disconnect (what the upload wrote is removed)


class _GuardedWebSocket(AutoWebSocketsProtocol):  # type: ignore[misc, valid-type]
    """uvicorn's WebSocket protocol, giving back the guard's count of its (upgraded) connection when it closes."""

    guard: ConnectionGuard

    def connection_made(self, transport) -> None:  # type: ignore[override]
        self._guarded = transport
        self.guard.admit(transport)  # counted by the HTTP protocol it was upgraded from
        super().connection_made(transport)

    def connection_lost(self, exc: Exception | None) -> None:
        self.guard.release(getattr(self, "_guarded", None))
        super().connection_lost(exc)


def protocols(guard: ConnectionGuard) -> tuple[type, type]:
    """uvicorn's ``http`` and ``ws`` protocol classes bound to ``guard`` (each server its own)."""
    http = type("GuardedHttpProtocol", (_GuardedHttp,), {"guard": guard})
    ws = type("GuardedWebSocketProtocol", (_GuardedWebSocket,), {"guard": guard})
    return http, ws
