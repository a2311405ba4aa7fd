"""Per-key limits: concurrent streams and single-frame renders in flight, and events (uploads, job submissions) in
a sliding hour.

Two backends with one interface (:class:`Limits`), chosen by settings (:func:`limits_for`):

- :class:`LocalLimits` (no ``redis_url``): counted in this process. Right for one replica; with N replicas a key
  may hold N times its stream limit, and the hourly windows restart with the process.
- :class:`RedisLimits` (``redis_url`` set): shared by every replica through Redis, so a limit is a limit across
  the deployment. Each check is one Lua script (atomic, timed by the Redis server's clock, so replicas' clocks do
  not matter):

  - a key's streams are leases in a sorted set ``<prefix>streams:<key id>`` scored by their expiry. Taking one
    drops expired leases, counts, and adds one; this process re-asserts its own every ``renew_seconds`` (5:
    written again whether or not Redis still has them, and the set's own TTL extended), and a release removes it.
    A replica that dies without releasing frees its leases ``lease_seconds`` later. A Redis that restarts empty
    (or fails over to a replica that never saw them) has every open stream counted again within ``renew_seconds``:
    the replicas holding them write them back. A key's single-frame renders in flight are leases the same way, in
    ``<prefix>renders:<key id>``.
  - events are members of ``<prefix><what>:<key id>`` scored by their time; older than the window they no
    longer count, and a refusal says when the oldest one leaves the window (``Retry-After``).

  One Redis server (not Redis Cluster: a renewal touches several keys at once).
  When Redis cannot be reached the limits fail open (the stream or upload goes ahead, with a warning in the log at
  most once a minute and ``blendsplat_limit_checks_failed_total`` counting): a limit store outage must not take
  live sessions down with it. Readiness does not depend on Redis for the same reason.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections import defaultdict, deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

from ..errors import ResourceExhausted

log = logging.getLogger(__name__)
HOUR = 3600.0
Release = Callable[[], None]


class RateLimited(ResourceExhausted):
    """A per-key limit: HTTP 429 with ``Retry-After``, gRPC RESOURCE_EXHAUSTED."""

    def __init__(self, message: str, *, retry_after: float, field: str | None = None):
        super().__init__(message, field=field)
        self.retry_after = max(1, int(-(-retry_after // 1)))

    def http_headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after)}


def no_release() -> None:
    """What taking a stream hands back when nothing was taken (admin keys, trusted calls)."""


# What a key holds at once (:meth:`Limits.take_stream`'s ``what``): how a refusal names it, and its setting.
CONCURRENT = {"streams": ("streams", "key_max_sessions", "end one first"),
              "renders": ("single-frame renders in flight", "key_max_renders", "wait for one to finish")}


def _refuse_stream(limit: int, what: str = "streams") -> RateLimited:
    noun, setting, advice = CONCURRENT.get(what, (what, "", "end one first"))
    named = f" ({setting})" if setting else ""
    return RateLimited(f"this key may hold {limit} {noun} at once{named}; {advice}", retry_after=1,
                       field="authorization")


def _refuse_event(limit: int, what: str, retry_after: float) -> RateLimited:
    return RateLimited(f"this key may make {limit} {what} per hour; try again later", retry_after=retry_after,
                       field="authorization")


class Limits(Protocol):
    def take_stream(self, key_id: str, limit: int, what: str = "streams") -> Release:
        """Take one of the key's concurrent streams (RateLimited at ``limit``); call what is returned, once, when
        the stream ends. ``what``: what is counted (:data:`CONCURRENT`: "streams", or "renders", single-frame
        renders in flight, counted apart). Taking may block on the network (call it off an event loop); releasing
        does not."""

    def take_event(self, key_id: str, what: str, limit: int, window: float = HOUR) -> None:
        """Count one event (``what``: "uploads", "job submissions") for the key; RateLimited when ``limit`` were
        counted in the last ``window`` seconds."""

    def close(self) -> None: ...


class LocalLimits:
    """Limits counted in this process (one replica)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._streams: dict[tuple[str, str], int] = defaultdict(int)  # (what, key id) -> held
        self._events: dict[tuple[str, str], deque[float]] = defaultdict(deque)

    def take_stream(self, key_id: str, limit: int, what: str = "streams") -> Release:
        counted = (what, key_id)
        with self._lock:
            if self._streams[counted] >= limit:
                raise _refuse_stream(limit, what)
            self._streams[counted] += 1
        released = False

        def release() -> None:
            nonlocal released
            with self._lock:
                if not released:
                    released = True
                    self._streams[counted] -= 1
                    if not self._streams[counted]:
                        del self._streams[counted]
        return release

    def take_event(self, key_id: str, what: str, limit: int, window: float = HOUR) -> None:
        now = time.monotonic()
        with self._lock:
            events = self._events[(what, key_id)]
            while events and events[0] <= now - window:
                events.popleft()
            if len(events) >= limit:
                raise _refuse_event(limit, what, events[0] + window - now)
            events.append(now)

    def close(self) -> None:
        pass


# KEYS[1]: the key's lease set; ARGV: limit, lease id, lease seconds. 1: taken, 0: at the limit.
_TAKE_STREAM = """
local t = redis.call('TIME')
local now = tonumber(t[1]) + tonumber(t[2]) / 1000000
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now)
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[1]) then return 0 end
redis.call('ZADD', KEYS[1], now + tonumber(ARGV[3]), ARGV[2])
redis.call('EXPIRE', KEYS[1], math.ceil(tonumber(ARGV[3])) * 2)
return 1
"""
# KEYS: lease sets; ARGV[1]: lease seconds, ARGV[2..]: the lease id in KEYS[i - 1]. Re-asserts the leases this
# process holds: extended, or written back when Redis lost them (a restart, a failover).
_RENEW = """
local t = redis.call('TIME')
local expiry = tonumber(t[1]) + tonumber(t[2]) / 1000000 + tonumber(ARGV[1])
for i, key in ipairs(KEYS) do
  redis.call('ZADD', key, expiry, ARGV[i + 1])
  redis.call('EXPIRE', key, math.ceil(tonumber(ARGV[1])) * 2)
end
return #KEYS
"""
# KEYS[1]: the key's event set; ARGV: limit, window seconds, event id. "-1": counted; else seconds to wait.
_TAKE_EVENT = """
local t = redis.call('TIME')
local now = tonumber(t[1]) + tonumber(t[2]) / 1000000
local window = tonumber(ARGV[2])
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now - window)
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[1]) then
  local oldest = redis.call('ZRANGE', KEYS[1], 0, 0, 'WITHSCORES')
  return tostring(tonumber(oldest[2]) + window - now)
end
redis.call('ZADD', KEYS[1], now, ARGV[3])
redis.call('EXPIRE', KEYS[1], math.ceil(window))
return '-1'
"""


class RedisLimits:
    """Limits shared by every replica through Redis (see the module docstring)."""

    def __init__(self, url: str, *, prefix: str = "blendsplat:limits:", lease_seconds: float = 30.0,
                 renew_seconds: float = 5.0, timeout: float = 0.5, on_failure: Callable[[], None] | None = None):
        import redis  # only deployments that set redis_url need it loaded

        self._errors = (redis.RedisError, OSError)
        self.redis = redis.Redis.from_url(url, socket_timeout=timeout, socket_connect_timeout=timeout)
        self.prefix, self.lease_seconds = prefix, lease_seconds
        self.renew_seconds = min(renew_seconds, lease_seconds / 3)
        self._take_stream = self.redis.register_script(_TAKE_STREAM)
        self._renew = self.redis.register_script(_RENEW)
        self._take_event = self.redis.register_script(_TAKE_EVENT)
        self._on_failure = on_failure
        self._lock = threading.Lock()
        self._leases: dict[str, str] = {}  # lease id -> its set, renewed until released
        # a renewal and a give-back never overlap: a lease released meanwhile is never written back after its ZREM
        self._writing = threading.Lock()
        self._warned = 0.0
        self._giving_back = ThreadPoolExecutor(1, thread_name_prefix="limits-release")  # releases never block
        self._stop = threading.Event()
        self._renewer = threading.Thread(target=self._renew_loop, name="limits-renew", daemon=True)
        self._renewer.start()

    def take_stream(self, key_id: str, limit: int, what: str = "streams") -> Release:
        key, lease = f"{self.prefix}{what}:{key_id}", uuid.uuid4().hex
        try:
            taken = self._take_stream(keys=[key], args=[limit, lease, self.lease_seconds])
        except self._errors as e:
            self._failed(e)
            return no_release
        if not taken:
            raise _refuse_stream(limit, what)
        with self._lock:
            self._leases[lease] = key

        def release() -> None:  # called where streams end (the event loop): Redis is asked on another thread
            with self._lock:
                if self._leases.pop(lease, None) is None:
                    return
            try:
                self._giving_back.submit(self._give_back, key, lease)
            except RuntimeError:  # closed: close() gave the leases back
                pass
        return release

    def _give_back(self, key: str, lease: str) -> None:
        try:
            with self._writing:
                self.redis.zrem(key, lease)
        except self._errors as e:  # the lease expires by itself
            self._failed(e)

    def take_event(self, key_id: str, what: str, limit: int, window: float = HOUR) -> None:
        key = f"{self.prefix}{what.replace(' ', '-')}:{key_id}"
        try:
            wait = float(self._take_event(keys=[key], args=[limit, window, uuid.uuid4().hex]))
        except self._errors as e:
            self._failed(e)
            return
        if wait >= 0:
            raise _refuse_event(limit, what, wait)

    def held(self) -> int:
        """Leases this process holds (renewed until released)."""
        with self._lock:
            return len(self._leases)

    def renew(self) -> None:
        """Re-assert this process's leases: extended, or written back when Redis lost them (the renewal thread
        calls it every ``renew_seconds``)."""
        with self._writing:
            with self._lock:  # read under the write lock: a lease released before this is not written back
                leases = list(self._leases.items())
            if leases:
                self._renew(keys=[key for _, key in leases],
                            args=[self.lease_seconds, *(lease for lease, _ in leases)])

    def _renew_loop(self) -> None:
        while not self._stop.wait(self.renew_seconds):
            try:
                self.renew()
            except self._errors as e:
                self._failed(e)

    def _failed(self, e: BaseException) -> None:
        if self._on_failure is not None:
            self._on_failure()
        now = time.monotonic()
        if now - self._warned > 60:
            self._warned = now
            log.warning("per-key limits: Redis is not answering (%s: %s); limits are not enforced until it does",
                        type(e).__name__, str(e)[:200])

    def close(self) -> None:
        """Stop renewing and give back this process's leases."""
        self._stop.set()
        self._giving_back.shutdown(wait=True)
        with self._lock:
            leases, self._leases = list(self._leases.items()), {}
        try:
            for lease, key in leases:
                self.redis.zrem(key, lease)
            self.redis.close()
        except self._errors:
            pass


def limits_for(redis_url: str | None, on_failure: Callable[[], None] | None = None) -> Limits:
    """Shared limits when ``redis_url`` is set, else this process's."""
    return RedisLimits(redis_url, on_failure=on_failure) if redis_url else LocalLimits()
