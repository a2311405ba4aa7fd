"""What both clients share: where the server is, the key, TLS, timeouts and the retry policy."""

from __future__ import annotations

import os
import random
from dataclasses import dataclass
from urllib.parse import urlsplit

from .errors import BlendsplatError, ConnectionFailed, Internal, ResourceExhausted, Timeout, Unavailable

URL_ENV, TARGET_ENV, KEY_ENV = "BLENDSPLAT_URL", "BLENDSPLAT_GRPC_TARGET", "BLENDSPLAT_API_KEY"
DEFAULT_URL = "http://127.0.0.1:8080"
DEFAULT_GRPC_PORT = 50051
IDEMPOTENT = frozenset({"GET", "HEAD", "PUT", "DELETE", "OPTIONS"})


@dataclass(frozen=True)
class RetryPolicy:
    """Retries of idempotent calls (GET, PUT, DELETE; POST /v1/jobs with an Idempotency-Key; the read-only RPCs and
    opening a stream) on 408, 429, 5xx, UNAVAILABLE and connection failures: at most ``attempts`` tries, waiting
    ``backoff * 2**n`` seconds with jitter (half to all of it), at most ``max_backoff``, or what the server's
    ``Retry-After`` asks (up to ``max_retry_after``: longer and the error is raised). Timeouts are not retried."""

    attempts: int = 4
    backoff: float = 0.25
    max_backoff: float = 8.0
    max_retry_after: float = 60.0

    def delay(self, attempt: int, error: BlendsplatError, idempotent: bool) -> float | None:
        """Seconds to wait before try ``attempt + 2`` after ``error``, or None: raise it."""
        if not idempotent or attempt + 1 >= self.attempts or not retryable(error):
            return None
        if error.retry_after is not None:
            return error.retry_after if error.retry_after <= self.max_retry_after else None
        step = min(self.max_backoff, self.backoff * 2 ** attempt)
        return step * (0.5 + random.random() / 2)


NO_RETRY = RetryPolicy(attempts=1)


def retryable(error: BlendsplatError) -> bool:
    if isinstance(error, Timeout) and error.http_status != 408:
        return False  # our own timeout: the caller's budget is spent
    status = error.http_status
    if status is not None:
        return status in (408, 429) or (status >= 500 and status != 501)
    return isinstance(error, Unavailable | ConnectionFailed) or (
        isinstance(error, ResourceExhausted | Internal) and error.retry_after is not None)


@dataclass
class Settings:
    url: str
    grpc_target: str
    api_key: str | None
    timeout: float
    grpc_tls: bool
    ca_file: str | None
    retry: RetryPolicy

    @property
    def headers(self) -> dict[str, str]:
        headers = {"User-Agent": "blendsplat-client/0.1", "Accept": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        return headers

    @property
    def metadata(self) -> tuple[tuple[str, str], ...]:
        return (("authorization", f"Bearer {self.api_key}"),) if self.api_key else ()

    def verify(self):
        """httpx's ``verify``: the CA file's context, or the system's."""
        if self.ca_file:
            import ssl

            return ssl.create_default_context(cafile=self.ca_file)
        return True


def settings(url: str | None, grpc_target: str | None, api_key: str | None, timeout: float,
             grpc_tls: bool | None, ca_file: str | None, retry: RetryPolicy | None) -> Settings:
    """Arguments first, then ``BLENDSPLAT_URL``, ``BLENDSPLAT_GRPC_TARGET`` and ``BLENDSPLAT_API_KEY``; the gRPC
    target defaults to the URL's host on port 50051, TLS to the URL's scheme (https)."""
    url = (url or os.environ.get(URL_ENV) or DEFAULT_URL).strip().rstrip("/")
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"the server URL must be http:// or https://, got {url!r}")
    if parts.username or parts.password or parts.query:
        raise ValueError("the server URL must not carry credentials or a query (the key goes in api_key)")
    target = (grpc_target or os.environ.get(TARGET_ENV) or "").strip()
    if not target:
        host = parts.hostname if ":" not in parts.hostname else f"[{parts.hostname}]"
        target = f"{host}:{DEFAULT_GRPC_PORT}"
    key = api_key if api_key is not None else os.environ.get(KEY_ENV)
    key = key.strip() if key else None
    if key and (not key.isascii() or not key.isprintable() or " " in key):
        raise ValueError("the API key must be one word of printable ASCII")
    if timeout is None or timeout <= 0:
        raise ValueError("timeout must be a positive number of seconds")
    tls = parts.scheme == "https" if grpc_tls is None else grpc_tls
    return Settings(url, target, key or None, float(timeout), tls, ca_file, retry or RetryPolicy())


def grpc_channel(s: Settings, asynchronous: bool):
    """A gRPC channel to the settings' target (secure with TLS, the CA file's roots when given)."""
    import grpc

    options = [("grpc.max_receive_message_length", 64 << 20), ("grpc.enable_retries", 0)]
    make = grpc.aio if asynchronous else grpc
    if s.grpc_tls:
        roots = open(s.ca_file, "rb").read() if s.ca_file else None
        return make.secure_channel(s.grpc_target, grpc.ssl_channel_credentials(roots), options=options)
    return make.insecure_channel(s.grpc_target, options=options)


def transport_error(exc: Exception, url: str) -> BlendsplatError:
    """An httpx transport failure as a typed error."""
    import httpx

    reason = str(exc) or type(exc).__name__
    if isinstance(exc, httpx.TimeoutException) and not isinstance(exc, httpx.ConnectTimeout):
        return Timeout(f"no answer from {url} in time ({type(exc).__name__})")
    if isinstance(exc, httpx.ConnectError | httpx.ConnectTimeout):
        return ConnectionFailed(f"cannot reach the server at {url} ({reason})")
    return ConnectionFailed(f"the connection to {url} failed ({reason})")
