"""Who is calling, and what they may do: API keys, tenants, scopes, per-key limits and the audit log.

One :class:`Access` per process, held by the :class:`~service.engine.Engine` (both transports reach it there):

- **Keys** (:mod:`service.access.keys`: ``bsk_<id>_<secret>``, hashed in the job database) carry a tenant and
  scopes: ``render`` (read and stream avatars), ``avatars:write`` (upload, replace, unload, delete),
  ``jobs`` (datasets and training jobs), ``admin`` (everything, every tenant, keys). HTTP and gRPC read
  ``authorization: Bearer <key>``; the WebSocket reads it from a subprotocol ``bearer.<key>`` offered beside
  ``blendsplat.v1`` (browsers cannot set headers on a WebSocket; a URL would end up in logs). A session token
  (``bst.<payload>.<sig>``, :mod:`service.access.tokens`, minted with a key for a browser) is accepted wherever
  a key is: render scope only, its minting key's tenant and id, perhaps one avatar (:meth:`Principal.check_avatar`).
- **Tenants**: avatar ids are global, but every avatar, upload and job has an owning tenant. A key reads what its
  tenant owns plus public avatars (the demo) and changes only what its tenant owns; admin keys see everything.
  Someone else's resource is refused with PERMISSION_DENIED (HTTP 403) naming the resource (ids are global, so a
  write must say the id is taken; reads answer the same way for consistency), on every route and when a stream
  resolves its adapter (named, or picked from ``source_names``: another tenant's is never picked). The one rule is
  :meth:`Principal.may_read`. A not-found answer names only the id asked for, never a listing of the store.
- **Open routes**: health (``/healthz``, ``/readyz``, gRPC health), ``/metrics``, the API description
  (``/openapi.json``, ``/docs``) and the static pages (which ask for a key in the browser) need no key.
- **Secure by default**: with ``auth=keys`` (the default) and no key in the database, :meth:`Access.bootstrap`
  creates an admin key in ``<data_dir>/admin.key`` (mode 0600) and logs where; ``admin_key`` (e.g. from a
  Kubernetes Secret) is registered instead. ``auth=off`` accepts every call as admin, with a warning at start.
- **Limits per key** (admin keys are exempt): concurrent streams, uploads and jobs per hour, each RESOURCE_EXHAUSTED
  (HTTP 429) with the seconds to wait (``Retry-After``). Shared by every replica through Redis when ``redis_url``
  is set, else counted per process (:mod:`service.access.limits`).
- **Audit**: one line on the ``blendsplat.audit`` logger for every avatar write, unload and delete, key change and
  job submission: the action, its target, the key and tenant.

A verified key is cached for :data:`CACHE_SECONDS` per process: a key revoked through another replica stops
working there within that time (at once on the replica that revoked it). Open streams (gRPC, WebSocket, job
events) ask the key database again every ``stream_key_check_seconds`` (:meth:`Access.revoked`) and end with
UNAUTHENTICATED when their key was revoked; render streams also end after ``max_stream_seconds``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from blendsplat.v1 import render_pb2 as pb

from ..errors import PermissionDenied, ResourceExhausted, ServiceError
from ..settings import Settings
from ..store import Writer
from .keys import ADMIN_TENANT, ApiKey, KeyStore, parse_token
from .limits import Limits, LocalLimits, limits_for, no_release
from .tokens import TokenInvalid, Tokens, is_token

log = logging.getLogger(__name__)
audit_log = logging.getLogger("blendsplat.audit")
CACHE_SECONDS = 5.0
ADMIN_KEY_FILE = "admin.key"
WS_PROTOCOL = "blendsplat.v1"  # the WebSocket subprotocol the server answers with
WS_KEY_PREFIX = "bearer."  # the subprotocol that carries the key: bearer.<key>


class Unauthenticated(ServiceError):
    """No key, or one that is not valid (unknown, revoked, malformed): HTTP 401, gRPC UNAUTHENTICATED."""

    code = pb.UNAUTHENTICATED

    def http_headers(self) -> dict[str, str]:
        return {"WWW-Authenticate": 'Bearer realm="blendsplat"'}


@dataclasses.dataclass(frozen=True)
class Principal:
    """The caller: its key id (None: auth is off or an internal call), tenant and scopes. A session token's caller
    (:mod:`service.access.tokens`) has its minting key's id and tenant, the ``render`` scope, ``token`` set and the
    one ``avatar`` it may read (None: any its tenant may)."""

    key_id: str | None
    tenant: str | None
    scopes: frozenset[str]
    avatar: str | None = None
    token: bool = False

    @property
    def admin(self) -> bool:
        return "admin" in self.scopes

    @property
    def name(self) -> str:
        if not self.key_id:
            return "an unauthenticated caller (auth off)"
        return f"{'a session token of ' if self.token else ''}key {self.key_id} (tenant {self.tenant})"

    def require(self, scope: str) -> Principal:
        if not (self.admin or scope in self.scopes):
            raise PermissionDenied(f"{self.name} lacks the scope {scope!r} (it has "
                                   f"{', '.join(sorted(self.scopes)) or 'none'})", field="authorization")
        return self

    @property
    def writer(self) -> Writer:
        """This caller as an avatar writer (:meth:`service.store.BundleStore.writable`)."""
        return Writer(self.tenant or ADMIN_TENANT, self.admin)

    def may_read(self, tenant: str | None, public: bool = False) -> bool:
        """The one visibility rule (avatars, adapters, uploads, jobs; every route and every stream's adapter): a
        key sees its tenant's resources and the public ones; an admin key sees all."""
        return self.admin or public or (tenant is not None and tenant == self.tenant)

    def may_use_adapter(self, tenant: str | None) -> bool:
        """:meth:`may_read` for an adapter: one without a tenant is the deployment's (public)."""
        return self.may_read(tenant, tenant is None)

    def may_write(self, tenant: str | None) -> bool:
        return self.admin or (tenant is not None and tenant == self.tenant)

    def check_avatar(self, avatar_id: str) -> None:
        """PermissionDenied when this caller is a session token for another avatar."""
        if self.avatar is not None and avatar_id != self.avatar:
            raise PermissionDenied(f"this session token is for avatar {self.avatar!r}, not avatar {avatar_id!r}",
                                   field="authorization")

    def check_read(self, what: str, tenant: str | None, public: bool = False) -> None:
        if not self.may_read(tenant, public):
            raise PermissionDenied(f"{what} belongs to another tenant", field="authorization")

    def check_write(self, what: str, tenant: str | None) -> None:
        if not self.may_write(tenant):
            raise PermissionDenied(f"{what} belongs to another tenant"
                                   + (" (public: only an admin key may change it)" if tenant is None else ""),
                                   field="authorization")


TRUSTED = Principal(None, None, frozenset({"admin"}))  # auth off, and the process's own calls (warm-up, demo)


def bearer(value: str | None) -> str | None:
    """The key of an ``Authorization: Bearer <key>`` value (None when absent or another scheme)."""
    if not value:
        return None
    scheme, _, token = value.strip().partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


def ws_key(protocols: list[str]) -> str | None:
    """The key a WebSocket client offered as the subprotocol ``bearer.<key>``."""
    return next((p[len(WS_KEY_PREFIX):] for p in protocols if p.startswith(WS_KEY_PREFIX)), None)


class Access:
    """Authentication, ownership rules, per-key limits and audit for one process (see the module docstring)."""

    def __init__(self, settings: Settings, keys: KeyStore | None, on_limit_failure: Callable[[], None] | None = None,
                 usage: list[Callable[[str], int]] | None = None, files: Callable[[str], int] | None = None):
        """``keys``: the key store (needed with ``auth=keys``); ``on_limit_failure``: called when the shared limits
        cannot be checked (Redis away); ``usage``: the bytes a tenant stores on disk, one callable per store (the
        bundle store, the uploads as extracted, the jobs' work folders), summed by :meth:`check_quota`; ``files``:
        the files and folders of a tenant's uploads (:meth:`check_stored`)."""
        self.settings = settings
        self.enabled = settings.auth == "keys"
        self.keys = keys
        if self.enabled and keys is None:
            raise ValueError("auth=keys needs the job database (its api_keys table)")
        self._cache: dict[str, tuple[Principal, float]] = {}
        self._lock = threading.Lock()
        # per-key limits: shared by the replicas through Redis when redis_url is set (service/access/limits.py)
        self.limits: Limits = limits_for(settings.redis_url, on_limit_failure) if self.enabled else LocalLimits()
        self.usage: list[Callable[[str], int]] = list(usage or [])
        self.tokens = Tokens(settings)  # session tokens (service/access/tokens.py): the secret is read on first use
        self.files = files

    @classmethod
    def trusted(cls, settings: Settings) -> Access:
        """Every call trusted, as with ``auth=off`` (no key store, no limits): tests and tools that build an
        :class:`~service.engine.Engine` of their own. The service builds its access from its settings."""
        return cls(settings.model_copy(update={"auth": "off"}), None)

    # ---- start-up ----
    def bootstrap(self) -> Path | None:
        """Secure by default: register ``admin_key`` if set; else, with no active key at all, create an admin key
        in ``<data_dir>/admin.key`` (mode 0600; reused when the file is there). The file written, else None."""
        if not self.enabled:
            log.warning("authentication is OFF (auth=off): anyone who reaches these ports can read, change and "
                        "delete every avatar and job. Use this on a trusted network only.")
            return None
        assert self.keys is not None
        if self.settings.admin_key:
            key, _ = self.keys.create(ADMIN_TENANT, ["admin"], "admin key (setting)", secret=self.settings.admin_key)
            log.info("admin key %s from the admin_key setting is registered", key.id)
            return None
        path = self.settings.data_dir / ADMIN_KEY_FILE
        if self.keys.any_active():
            return None
        existing = path.read_text(encoding="ascii").strip() if path.is_file() else None
        if existing and parse_token(existing):
            key, _ = self.keys.create(ADMIN_TENANT, ["admin"], "admin key (admin.key)", secret=existing)
            log.info("admin key %s from %s is registered", key.id, path)
            return path
        key, token = self.keys.create(ADMIN_TENANT, ["admin"], "admin key (created at first start)")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(token + "\n")
        os.replace(tmp, path)
        log.warning("no API key was configured: created admin key %s in %s (mode 0600). Clients send it as "
                    "'Authorization: Bearer <key>'; make scoped keys with `blendsplat keys create`.", key.id, path)
        return path

    # ---- who is calling ----
    def authenticate(self, token: str | None) -> Principal:
        """The caller of a request that presented ``token`` (None: no key). Unauthenticated when one is needed and
        missing or not valid. Blocking (a database read on a cache miss)."""
        if not self.enabled:
            return TRUSTED
        if not token:
            raise Unauthenticated("an API key is required (Authorization: Bearer <key>)", field="authorization")
        claims = None
        if is_token(token):  # a session token: its signature and expiry on every call, its minting key cached
            try:
                claims = self.tokens.verify(token)
            except TokenInvalid as e:
                raise Unauthenticated(str(e), field="authorization") from None
        digest = hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(digest)
        if hit is not None and hit[1] > now:
            return hit[0]
        assert self.keys is not None
        if claims is not None:
            if self.keys.inactive({claims.key_id}):
                raise Unauthenticated("the session token's key was revoked", field="authorization")
            principal = Principal(claims.key_id, claims.tenant, frozenset({"render"}), claims.avatar, token=True)
        else:
            key = self.keys.verify(token)
            if key is None:
                raise Unauthenticated("the API key is not valid (unknown, revoked or malformed)",
                                      field="authorization")
            principal = _principal(key)
        with self._lock:
            if len(self._cache) > 10_000:
                self._cache.clear()
            self._cache[digest] = (principal, now + CACHE_SECONDS)
        return principal

    def forget(self, key_id: str) -> None:
        """Drop a key from the cache at once (it was revoked here)."""
        with self._lock:
            self._cache = {d: hit for d, hit in self._cache.items() if hit[0].key_id != key_id}

    def revoked(self, key_ids: Iterable[str | None]) -> set[str]:
        """Which of these keys no longer verify, asked of the key database (never the cache; they are dropped from
        it). Open streams call it every ``stream_key_check_seconds`` and end the ones of a revoked key. Blocking.
        With auth off, or the database away (logged), none: a stream is not cut for a failed check."""
        ids = {k for k in key_ids if k}
        if not self.enabled or not ids:
            return set()
        assert self.keys is not None
        try:
            gone = self.keys.inactive(ids)
        except Exception as e:  # noqa: BLE001 - the database away: checked again at the next interval
            log.warning("could not check the keys of open streams: %s: %s", type(e).__name__, str(e)[:200])
            return set()
        for key_id in gone:
            self.forget(key_id)
        return gone

    # ---- limits ----
    def take_stream(self, principal: Principal) -> Callable[[], None]:
        """Take one of the key's concurrent streams (RateLimited when it holds its limit); call the function
        returned, once, when the stream ends. Admin keys and trusted calls have no limit."""
        if principal.key_id is None or principal.admin:
            return no_release
        return self.limits.take_stream(principal.key_id, self.settings.key_max_sessions)

    @staticmethod
    def exempt(principal: Principal) -> bool:
        """Whether the quota and the file bound spare the caller (admin keys, auth off, the process itself)."""
        return principal.key_id is None or principal.admin or principal.tenant is None

    def check_quota(self, principal: Principal, incoming: int) -> None:
        """ResourceExhausted when the caller's tenant would store more than ``tenant_storage_bytes`` with
        ``incoming`` more bytes on disk (its bundles, uploads as extracted and jobs' work folders; admin keys are
        exempt)."""
        if self.exempt(principal):
            return
        used = sum(source(principal.tenant) for source in self.usage)
        if used + incoming > self.settings.tenant_storage_bytes:
            raise over_quota(principal.tenant, used, incoming, self.settings.tenant_storage_bytes)

    def check_stored(self, principal: Principal, stored: int, files: int) -> None:
        """An upload as it will be kept (``stored`` bytes on disk in ``files`` entries, measured before it is
        published): the tenant's quota, then its file bound ``tenant_max_files`` (ResourceExhausted)."""
        self.check_quota(principal, stored)
        if self.exempt(principal) or self.files is None:
            return
        held, limit = self.files(principal.tenant), self.settings.tenant_max_files
        if held + files > limit:
            raise ResourceExhausted(f"tenant {principal.tenant!r} holds {held} files in its uploads; with {files} "
                                    f"more it would pass its bound of {limit} (tenant_max_files; delete uploads "
                                    "first)", field="authorization")

    def admit_upload(self, principal: Principal, incoming: int) -> None:
        """Count an upload against the key's uploads per hour, then check the tenant's quota with ``incoming``
        more bytes (RateLimited / ResourceExhausted). Blocking: the count may ask Redis, the quota reads the stores."""
        if principal.key_id is not None and not principal.admin:
            self.limits.take_event(principal.key_id, "uploads", self.settings.key_uploads_per_hour)
        self.check_quota(principal, incoming)

    def count_job(self, principal: Principal) -> None:
        if principal.key_id is not None and not principal.admin:
            self.limits.take_event(principal.key_id, "job submissions", self.settings.key_jobs_per_hour)

    def close(self) -> None:
        self.limits.close()

    # ---- audit ----
    @staticmethod
    def audit(principal: Principal, action: str, target: str, **details) -> None:
        extra = "".join(f" {k}={v}" for k, v in details.items())
        audit_log.info("%s %s by key=%s tenant=%s%s", action, target, principal.key_id or "-",
                       principal.tenant or "-", extra)


def over_quota(tenant: str, used: int, incoming: int, quota: int) -> ResourceExhausted:
    """The one refusal of the storage quota (uploads, avatars and job submissions; a running job fails with it)."""
    return ResourceExhausted(f"tenant {tenant!r} stores {used} bytes; with {incoming} more it would pass its quota of "
                             f"{quota} (tenant_storage_bytes; delete avatars, uploads or jobs first)",
                             field="authorization")


def _principal(key: ApiKey) -> Principal:
    return Principal(key.id, key.tenant, frozenset(key.scopes))
