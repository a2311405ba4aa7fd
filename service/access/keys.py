"""API keys: the ``api_keys`` table of the service database (:mod:`service.db`, shared with the job store) and
:class:`KeyStore`.

A key is ``bsk_<id>_<secret>``: ``id`` (10 hex characters) names it in lists, logs and audit lines; ``secret``
(32 random bytes, URL-safe base64) is shown once, when the key is created, and stored only as its SHA-256. A
keyed hash is not needed: the secret is random, so its hash cannot be searched. Each key has one tenant and a set
of scopes (:data:`SCOPES`); a revoked key keeps its row (its id stays in the audit trail) and never verifies again.

A key made elsewhere (``admin_key``, e.g. ``openssl rand -hex 32`` in a Kubernetes Secret) may have any form of
16 to 512 printable characters: its id is the start of its SHA-256 and the whole key is hashed.

The database is shared by every replica and worker (PostgreSQL in a cluster), so a key created or revoked through
one replica holds on all of them (each caches a verified key for :data:`service.access.auth.CACHE_SECONDS`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import hmac
import re
import secrets
from collections.abc import Iterable
from datetime import UTC, datetime

from sqlalchemy import Engine, Index, String, select
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base, Sessions, open_engine
from ..errors import InvalidArgument, NotFound
from ..settings import API_KEY_PATTERN

PREFIX = "bsk"
SCOPES = ("render", "avatars:write", "jobs", "admin")
ADMIN_TENANT = "admin"  # the admin keys' tenant
SCOPE_HELP = {
    "render": "list and describe avatars, stream and render frames, load into the cache",
    "avatars:write": "upload, replace, unload and delete avatars",
    "jobs": "upload datasets, submit, watch, cancel and delete training jobs",
    "admin": "everything, every tenant's resources, and keys",
}
TENANT_PATTERN = re.compile(r"^[a-z0-9][a-z0-9._-]{0,62}$")
_TOKEN = re.compile(r"^bsk_([0-9a-f]{10})_([A-Za-z0-9_-]{43})$")
_EXTERNAL = API_KEY_PATTERN  # a key made elsewhere: printable ASCII, no spaces (the settings check admin_key with it)


class KeyRecord(Base):
    """One API key (a row of ``api_keys``)."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(16), primary_key=True)
    secret_sha256: Mapped[str] = mapped_column(String(64))
    tenant: Mapped[str] = mapped_column(String(64))
    scopes: Mapped[str] = mapped_column(String(255))  # space-separated
    name: Mapped[str] = mapped_column(String(255), default="")
    created_at: Mapped[datetime]
    revoked_at: Mapped[datetime | None]

    __table_args__ = (Index("ix_api_keys_tenant", "tenant"),)


@dataclasses.dataclass(frozen=True)
class ApiKey:
    """A key as listed (never its secret)."""

    id: str
    tenant: str
    scopes: tuple[str, ...]
    name: str
    created_at: datetime
    revoked_at: datetime | None

    @property
    def active(self) -> bool:
        return self.revoked_at is None

    @classmethod
    def of(cls, record: KeyRecord) -> ApiKey:
        return cls(record.id, record.tenant, tuple(record.scopes.split()), record.name, record.created_at,
                   record.revoked_at)

    def as_json(self) -> dict:
        return {"id": self.id, "tenant": self.tenant, "scopes": list(self.scopes), "name": self.name,
                "created_at": self.created_at.isoformat(), "active": self.active,
                "revoked_at": self.revoked_at.isoformat() if self.revoked_at else None}


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode("ascii")).hexdigest()


def parse_token(token: str) -> tuple[str, str] | None:
    """``(id, secret)`` of a well-formed key (``bsk_<id>_<secret>``, or a key made elsewhere: the start of its
    SHA-256 and the whole key), else None."""
    match = _TOKEN.match(token or "")
    if match:
        return match[1], match[2]
    if _EXTERNAL.match(token or ""):
        return hashlib.sha256(token.encode("ascii")).hexdigest()[:10], token
    return None


def check_scopes(scopes: Iterable[str]) -> tuple[str, ...]:
    chosen = tuple(dict.fromkeys(scopes))
    unknown = [s for s in chosen if s not in SCOPES]
    if unknown or not chosen:
        raise InvalidArgument(f"scopes must be some of {', '.join(SCOPES)} (got {', '.join(unknown) or 'none'})",
                              field="scopes")
    return chosen


def check_tenant(tenant: str) -> str:
    if not TENANT_PATTERN.match(tenant or ""):
        raise InvalidArgument(f"{tenant!r} is not a tenant name (lower-case letters, digits, '.', '_', '-'; at "
                              "most 63, starting with a letter or digit)", field="tenant")
    return tenant


class KeyStore:
    """The ``api_keys`` table over an engine of the service database whose schema is at head (:func:`open`, or
    the job store's engine: one database)."""

    def __init__(self, engine: Engine):
        self.engine = engine
        self._db = Sessions(engine)
        self._sessions = self._db.reads
        self._writes = self._db.write
        self._owned = False

    @classmethod
    def open(cls, url: str) -> KeyStore:
        """Connect to the database at ``url`` and migrate it to head (:func:`service.db.open_engine`); :meth:`close`
        disposes of the engine."""
        store = cls(open_engine(url))
        store._owned = True
        return store

    def close(self) -> None:
        if self._owned:
            self.engine.dispose()

    def __enter__(self) -> KeyStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def create(self, tenant: str, scopes: Iterable[str], name: str = "", *, secret: str | None = None
               ) -> tuple[ApiKey, str]:
        """A new key: the record and the whole key (``bsk_<id>_<secret>``, shown once). ``secret``: register a
        key made elsewhere (``parse_token`` must accept it), e.g. the admin key from a Kubernetes Secret."""
        tenant, chosen = check_tenant(tenant), check_scopes(scopes)
        if tenant == ADMIN_TENANT and "admin" not in chosen:  # the admin tenant's work is admin work (jobs' commits)
            raise InvalidArgument(f"keys of the {ADMIN_TENANT!r} tenant hold the admin scope; choose another tenant "
                                  "for this key", field="tenant")
        if len(name) > 255:
            raise InvalidArgument("a key name is at most 255 characters", field="name")
        if secret is None:
            key_id, secret_part = secrets.token_hex(5), secrets.token_urlsafe(32)
        else:
            parsed = parse_token(secret)
            if parsed is None:
                raise InvalidArgument("not an API key: bsk_<10 hex>_<43 URL-safe base64 characters> (`blendsplat keys "
                                      "create`), or 16 to 512 printable characters without spaces", field="key")
            key_id, secret_part = parsed
        record = KeyRecord(id=key_id, secret_sha256=_digest(secret_part), tenant=tenant, scopes=" ".join(chosen),
                           name=name, created_at=datetime.now(UTC), revoked_at=None)
        with self._writes() as session:
            existing = session.get(KeyRecord, key_id)
            if existing is not None:
                if secret is not None and hmac.compare_digest(existing.secret_sha256, record.secret_sha256):
                    return ApiKey.of(existing), secret  # already registered
                raise InvalidArgument(f"a key with id {key_id} exists already", field="key")
            session.add(record)
        return ApiKey.of(record), secret or f"{PREFIX}_{key_id}_{secret_part}"

    def verify(self, token: str) -> ApiKey | None:
        """The active key ``token`` is, or None (malformed, unknown, wrong secret or revoked)."""
        parsed = parse_token(token)
        if parsed is None:
            return None
        key_id, secret_part = parsed
        with self._sessions() as session:
            record = session.get(KeyRecord, key_id)
            if record is None or not hmac.compare_digest(record.secret_sha256, _digest(secret_part)):
                return None
            return ApiKey.of(record) if record.revoked_at is None else None

    def list(self, *, tenant: str | None = None, include_revoked: bool = False) -> list[ApiKey]:
        query = select(KeyRecord).order_by(KeyRecord.created_at, KeyRecord.id)
        if tenant is not None:
            query = query.where(KeyRecord.tenant == tenant)
        if not include_revoked:
            query = query.where(KeyRecord.revoked_at.is_(None))
        with self._sessions() as session:
            return [ApiKey.of(r) for r in session.scalars(query)]

    def revoke(self, key_id: str) -> ApiKey:
        with self._writes() as session:
            record = session.get(KeyRecord, key_id)
            if record is None:
                raise NotFound(f"no API key {key_id!r}", field="key_id")
            if record.revoked_at is None:
                record.revoked_at = datetime.now(UTC)
            return ApiKey.of(record)

    def inactive(self, key_ids: Iterable[str]) -> set[str]:
        """Which of ``key_ids`` no longer verify (revoked, or gone), asked of the database (open streams' re-check)."""
        wanted = set(key_ids)
        if not wanted:
            return set()
        with self._sessions() as session:
            active = set(session.scalars(select(KeyRecord.id).where(KeyRecord.id.in_(wanted),
                                                                    KeyRecord.revoked_at.is_(None))))
        return wanted - active

    def any_active(self) -> bool:
        with self._sessions() as session:
            return session.scalars(select(KeyRecord.id).where(KeyRecord.revoked_at.is_(None)).limit(1)).first() \
                is not None
