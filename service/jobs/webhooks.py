"""Job webhooks: a signed POST to the job's ``webhook_url`` on every state change, retried until a 2xx.

**What is sent.** The job store writes one ``webhook_deliveries`` row per state change of a job whose spec has a
``webhook_url`` (in the state change's own transaction: :mod:`service.jobs.outbox`). Its body is JSON in the shape
of the `Standard Webhooks <https://www.standardwebhooks.com>`_ spec::

    {"type": "job.succeeded", "timestamp": "2026-...+00:00",
     "data": {"job_id", "state", "previous", "attempts", "error", "result", "links": {"self", "events"}}}

``type`` is ``job.running``, ``job.succeeded``, ``job.failed``, ``job.cancelled``, or ``job.queued`` when a running
job was handed back or lost its worker and waits again.

**How it is signed** (Standard Webhooks): the headers ``webhook-id`` (the message id, the same on every attempt:
deduplicate on it), ``webhook-timestamp`` (unix seconds of this attempt) and ``webhook-signature: v1,<base64 of
HMAC-SHA256(key, "{webhook-id}.{webhook-timestamp}.{body}")>``. The key: the setting ``webhook_secret``
(``BLENDSPLAT_WEBHOOK_SECRET``); a secret of the form ``whsec_<base64>`` (what is generated, and what Standard
Webhooks libraries expect) means the base64-decoded bytes, any other text its UTF-8 bytes. Unset, the first start
generates one into ``<data_dir>/webhook.secret`` (mode 0600) and every later start (and every replica sharing the
data dir) reads it there. Receivers should also refuse timestamps far from their clock (replays).

**Delivery.** :class:`WebhookDispatcher` runs in every ``serve``/``up`` process (started and stopped with the
service, :mod:`service.server`). It claims due deliveries from the job store (exclusive across replicas: ``FOR
UPDATE SKIP LOCKED`` on PostgreSQL, ``BEGIN IMMEDIATE`` on SQLite) and POSTs them with httpx (no redirects
followed, ``webhook_timeout_seconds``). A 2xx marks the delivery delivered: it is never sent again. Anything else
(another status, a timeout, a refused connection) is retried after an exponential backoff with jitter
(``webhook_backoff_seconds`` doubled per attempt, at most ``webhook_backoff_max_seconds``), for at most
``webhook_max_attempts`` attempts and ``webhook_retry_seconds`` after the state change; then the delivery is failed.
Every delivery, its attempts, last HTTP status and error are on the job (``webhooks`` in ``GET /v1/jobs/{id}``).

A claim holds a delivery for the attempt's timeout plus a margin; a process that dies (or stops) during an attempt
leaves it to be retried when that hold ends, so a receiver may see a message again after a crash (the same
``webhook-id``: at least once). Stopping is prompt: attempts in flight get :data:`STOP_GRACE_SECONDS` to finish,
then are abandoned (and retried when their claim runs out).
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import hashlib
import hmac
import ipaddress
import json
import logging
import random
import secrets
import socket
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit, urlunsplit

import httpx

from render_core.atomic import create_once

from .models import DeliveryStatus, WebhookDelivery

if TYPE_CHECKING:
    from ..settings import Settings
    from .store import JobStore

log = logging.getLogger(__name__)

MAX_URL_CHARS = 2048
SECRET_FILE = "webhook.secret"
SECRET_PREFIX = "whsec_"
BATCH = 16  # deliveries claimed (and sent concurrently) at a time
CLAIM_MARGIN_SECONDS = 30.0  # a claim holds a delivery for the attempt's timeout plus this
USER_AGENT = "blendsplat-webhooks/1"
STOP_GRACE_SECONDS = 1.0  # stopping: how long attempts in flight may take to finish before they are abandoned


# ---------------------------------------------------------------------------------------------------- URLs
def check_url(value: str) -> str:
    """A webhook URL checked: absolute http or https with a host, at most :data:`MAX_URL_CHARS` characters, no
    whitespace or control characters. ValueError saying what is wrong (the API answers 422 naming the field)."""
    if len(value) > MAX_URL_CHARS:
        raise ValueError(f"at most {MAX_URL_CHARS} characters")
    if any(ch.isspace() or ord(ch) < 32 or ord(ch) == 127 for ch in value):
        raise ValueError("a URL has no whitespace or control characters")
    try:
        parts = urlsplit(value)
        parts.port  # noqa: B018 - raises on a bad port
    except ValueError as exc:
        raise ValueError(f"not a URL ({exc})") from None
    if parts.scheme.lower() not in ("http", "https"):
        shown = f"{parts.scheme}:" if parts.scheme else "a relative URL"
        raise ValueError(f"a webhook URL is http:// or https://, not {shown[:20]}")
    if not parts.hostname:
        raise ValueError("a webhook URL names a host")
    return value


# ------------------------------------------------------------------------------------------------- signing
def signing_key(secret: str) -> bytes:
    """The HMAC key of a secret: ``whsec_<base64>`` -> the decoded bytes; any other text -> its UTF-8 bytes."""
    if secret.startswith(SECRET_PREFIX):
        try:
            key = base64.b64decode(secret[len(SECRET_PREFIX):], validate=True)
        except (binascii.Error, ValueError):
            raise ValueError("webhook_secret: 'whsec_' must be followed by base64") from None
        if not key:
            raise ValueError("webhook_secret: 'whsec_' must be followed by the key in base64")
        return key
    if not secret:
        raise ValueError("webhook_secret: empty")
    return secret.encode()


def sign(secret: str, message_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` header's value: ``v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">``."""
    signed = f"{message_id}.{timestamp}.".encode() + body
    return "v1," + base64.b64encode(hmac.new(signing_key(secret), signed, hashlib.sha256).digest()).decode()


def load_secret(settings: Settings) -> str:
    """The signing secret: ``settings.webhook_secret``, else ``<data_dir>/webhook.secret``, created (mode 0600,
    published atomically so concurrent starts agree) when there is none. ValueError for an unusable secret."""
    secret = settings.webhook_secret
    if not secret:
        path = Path(settings.data_dir) / SECRET_FILE
        secret = _read_secret(path)
        if secret is None:
            new = SECRET_PREFIX + base64.b64encode(secrets.token_bytes(32)).decode()
            if create_once(path, new + "\n"):  # else another process got there first: its secret is the one
                log.info("webhooks: generated a signing secret in %s (set BLENDSPLAT_WEBHOOK_SECRET to choose "
                         "one)", path)
            secret = _read_secret(path)
            if secret is None:
                raise ValueError(f"webhook_secret: {path} is empty")
    signing_key(secret)
    return secret


def _read_secret(path: Path) -> str | None:
    try:
        text = path.read_text().strip()
    except FileNotFoundError:
        return None
    return text or None


def retry_delay(attempt: int, base: float, cap: float, rng: random.Random | None = None) -> float:
    """Seconds before the attempt after number ``attempt``: ``base * 2**(attempt - 1)``, at most ``cap``, with
    jitter (a uniform draw in its upper half), so receivers that failed together are not retried together."""
    delay = min(cap, base * 2.0 ** max(0, min(attempt - 1, 60)))
    return delay * (0.5 + 0.5 * (rng or random).random())


# ---------------------------------------------------------------------------------------------- dispatcher
class WebhookDispatcher:
    """Sends the job store's due webhook deliveries (see the module docstring). :meth:`start` on the event loop,
    :meth:`stop` at shutdown (prompt: attempts in flight are abandoned and retried later)."""

    def __init__(self, settings: Settings, store: JobStore, secret: str, *,
                 transport: httpx.AsyncBaseTransport | None = None):
        signing_key(secret)
        self.settings, self.store, self.secret = settings, store, secret
        self._transport = transport
        self._stop = asyncio.Event()
        self._task: asyncio.Task | None = None
        self.sent = 0  # attempts made by this dispatcher

    def start(self) -> None:
        self._stop.clear()
        self._task = asyncio.create_task(self._run(), name="webhooks")

    async def stop(self, grace: float = STOP_GRACE_SECONDS) -> None:
        """Stop: attempts in flight get ``grace`` seconds to finish and be recorded, then are abandoned."""
        self._stop.set()
        task, self._task = self._task, None
        if task is None:
            return
        done, _ = await asyncio.wait({task}, timeout=grace)
        if not done:
            task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    async def _run(self) -> None:
        s = self.settings
        lease = s.webhook_timeout_seconds + CLAIM_MARGIN_SECONDS
        async with httpx.AsyncClient(transport=self._transport, follow_redirects=False, trust_env=False,
                                     timeout=s.webhook_timeout_seconds,
                                     headers={"user-agent": USER_AGENT}) as client:
            while not self._stop.is_set():
                try:
                    due = await asyncio.to_thread(self.store.claim_deliveries, BATCH, lease)
                except Exception:  # noqa: BLE001 - the database away: try again at the next poll
                    log.warning("webhooks: claiming deliveries failed; retrying", exc_info=True)
                    due = []
                if due:
                    await asyncio.gather(*(self._attempt(client, d) for d in due))
                    continue  # more may be due
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stop.wait(), s.webhook_poll_seconds)

    async def _attempt(self, client: httpx.AsyncClient, delivery: WebhookDelivery) -> None:
        s = self.settings
        body = json.dumps(delivery.payload, separators=(",", ":")).encode()
        timestamp = int(time.time())
        headers = {"content-type": "application/json", "webhook-id": delivery.id,
                   "webhook-timestamp": str(timestamp),
                   "webhook-signature": sign(self.secret, delivery.id, timestamp, body)}
        status: int | None = None
        url, extensions, error = delivery.url, {}, None
        if not s.webhook_private_networks:
            address, error = await _public_address(delivery.url)
            if address is not None:
                url, headers["host"], extensions = _pinned(delivery.url, address)
        if error is None:
            try:
                async with client.stream("POST", url, content=body, headers=headers,
                                         extensions=extensions) as response:
                    status = response.status_code  # the body is not read
            except httpx.HTTPError as exc:  # its text may quote the URL: logged and recorded without its tokens
                error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                error = error.replace(delivery.url, loggable_url(delivery.url)).replace(url, loggable_url(url))
        self.sent += 1
        delivered = status is not None and 200 <= status < 300
        retry_at = None
        if not delivered:
            now = datetime.now(UTC)
            when = now + timedelta(seconds=retry_delay(delivery.attempts, s.webhook_backoff_seconds,
                                                       s.webhook_backoff_max_seconds))
            if (delivery.attempts < s.webhook_max_attempts and not (error or "").startswith(REFUSED)
                    and when <= delivery.created_at + timedelta(seconds=s.webhook_retry_seconds)):
                retry_at = when
        try:
            after = await asyncio.to_thread(self.store.record_attempt, delivery.id, delivery.attempts,
                                            delivered=delivered, status=status, error=error, retry_at=retry_at)
        except Exception:  # noqa: BLE001 - not recorded: the claim runs out and it is sent again
            log.warning("webhooks: recording attempt %d of %s failed", delivery.attempts, delivery.id, exc_info=True)
            return
        outcome = after.status if after is not None else "gone"
        if outcome is DeliveryStatus.FAILED:
            log.warning("webhook %s (%s) to %s failed for good after %d attempts: %s", delivery.id, delivery.event,
                        _host(delivery.url), delivery.attempts, error or f"HTTP {status}")
        elif not delivered:
            log.info("webhook %s attempt %d: %s; retrying at %s", delivery.id, delivery.attempts,
                     error or f"HTTP {status}", retry_at.isoformat() if retry_at else "-")


REFUSED = "refused: "  # an attempt the dispatcher would not make (not retried)


async def _public_address(url: str) -> tuple[str | None, str | None]:
    """The address to send a webhook to, or None and why it may not be called: its host resolves to a loopback,
    private, link-local, multicast or reserved address (a job's owner must not reach the service's own network
    through it). Resolved once per attempt, and the request goes to the address checked (:func:`_pinned`), so a
    name that answers a public address to the check and a private one to the connection (DNS rebinding) gains
    nothing."""
    parts = urlsplit(url)
    try:
        infos = await asyncio.get_running_loop().getaddrinfo(parts.hostname, parts.port or 443,
                                                             type=socket.SOCK_STREAM)
    except OSError as exc:
        return None, f"cannot resolve {parts.hostname!r} ({exc.strerror or exc})"  # retried: DNS may come back
    addresses = [ipaddress.ip_address(address[0].split("%", 1)[0]) for *_, address in infos]
    for ip in addresses:
        if not public_address(ip):
            return None, (f"{REFUSED}{parts.hostname} resolves to {ip}, not a public address (setting "
                          "webhook_private_networks)")
    if not addresses:
        return None, f"cannot resolve {parts.hostname!r} (no address)"
    return str(addresses[0]), None


def public_address(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    """Whether a webhook may go to ``ip``: a global unicast address (``is_global`` alone lets multicast through; an
    IPv4-mapped IPv6 address is judged as the IPv4 address it carries)."""
    mapped = getattr(ip, "ipv4_mapped", None)
    if mapped is not None:
        ip = mapped
    return ip.is_global and not (ip.is_multicast or ip.is_reserved or ip.is_unspecified or ip.is_loopback
                                 or ip.is_link_local or ip.is_private)


def loggable_url(url: str) -> str:
    """What a log line says of a webhook URL: scheme, host and port, the path and query cut (they may hold tokens,
    as may user info)."""
    try:
        parts = urlsplit(url)
        port = f":{parts.port}" if parts.port else ""
        return f"{parts.scheme}://{parts.hostname or '?'}{port}/..."
    except ValueError:
        return "?"


def _pinned(url: str, address: str) -> tuple[str, str, dict[str, str]]:
    """``url`` sent to ``address``: the URL with that address as its host (user info and port kept), the Host
    header it had, and for https the name TLS sends (SNI) and verifies the certificate against."""
    parts = urlsplit(url)
    userinfo, _, host_port = parts.netloc.rpartition("@")
    host = f"[{address}]" if ":" in address else address
    netloc = (f"{userinfo}@" if userinfo else "") + host + (f":{parts.port}" if parts.port else "")
    extensions = {"sni_hostname": parts.hostname or ""} if parts.scheme == "https" else {}
    return urlunsplit(parts._replace(netloc=netloc)), host_port, extensions


def _host(url: str) -> str:
    """What a log line says of a URL: its host (the path and query may hold tokens)."""
    try:
        return urlsplit(url).hostname or "?"
    except ValueError:
        return "?"
