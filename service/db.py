"""The service's one SQL database, below both wings that keep tables in it: the training jobs (:mod:`service.jobs`:
jobs, job events, webhook deliveries) and the API keys (:mod:`service.access.keys`).

Here: the URL (a SQLite file by default, PostgreSQL by URL), the engine factory, the declarative base every table
derives from (stable constraint names, timezone-aware UTC timestamps), the read and write sessions, the warning
for a SQLite file on a network filesystem, and the Alembic migrations (``service/migrations/``) that own the
schema, with :func:`migrate` to run them and :func:`open_engine` to connect and migrate in one call.

Timestamps are timezone-aware UTC everywhere: PostgreSQL stores ``timestamptz``; SQLite stores the UTC wall time
as text, and :class:`UTCDateTime` gives it back aware.

Add a migration after changing a table (``service/jobs/models.py``, ``service/access/keys.py``)::

    from alembic import command
    from service.db import alembic_config
    command.revision(alembic_config(url), message="...", autogenerate=True)

then read the generated file in ``service/migrations/versions/`` (autogenerate misses renames and expression
indexes).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import JSON, DateTime, Engine, MetaData, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker
from sqlalchemy.types import TypeDecorator

log = logging.getLogger(__name__)

BUSY_TIMEOUT_MS = 10_000  # SQLite: how long a connection waits for another's write lock before "database is locked"
SCRIPT_LOCATION = Path(__file__).resolve().parent / "migrations"
_PG_LOCK = 0x626C656E64  # pg_advisory_xact_lock key: concurrent migrate() calls on one PostgreSQL run one at a time


# ---- the tables' base ----

class UTCDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC datetime on every backend. Binding a naive datetime is an error (it has no zone)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime: the database keeps timezone-aware UTC times only")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


_NAMING = {  # stable constraint names, so migrations can refer to them on every backend
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    """The base of every table of the database (one metadata: the migrations' ``target_metadata``)."""

    metadata = MetaData(naming_convention=_NAMING)
    type_annotation_map = {datetime: UTCDateTime(), dict[str, Any]: JSON()}


# ---- connecting ----

def default_url(data_dir: str | Path) -> str:
    """The embedded default: a SQLite file ``<data_dir>/jobs.db`` (one machine only)."""
    return f"sqlite:///{Path(data_dir).resolve() / 'jobs.db'}"


def redacted(url: str) -> str:
    """A database URL without its password (for logs and messages)."""
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # noqa: BLE001 - only for display
        return "<database>"


def make_engine(url: str, *, busy_timeout_ms: int = BUSY_TIMEOUT_MS) -> Engine:
    """An engine for a database URL: ``sqlite:///path`` or ``postgresql+psycopg://...``.

    SQLite connections get WAL journaling, a busy timeout, foreign keys (for the events' cascade) and explicit
    transaction control: a transaction starts with ``BEGIN`` or, on an engine made with
    ``execution_options(sqlite_begin="IMMEDIATE")``, with ``BEGIN IMMEDIATE`` (takes the write lock at once, so
    read-then-write transactions never fail on a lock upgrade). The folder of a SQLite file is created."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(parsed, pool_pre_ping=True)
    if parsed.database and parsed.database != ":memory:":
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(parsed, connect_args={"check_same_thread": False})

    @event.listens_for(engine, "connect")
    def _configure(dbapi_connection, _record) -> None:
        dbapi_connection.isolation_level = None  # no implicit BEGIN from the driver: the "begin" hook below owns it
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _begin(connection) -> None:
        mode = connection.get_execution_options().get("sqlite_begin", "DEFERRED")
        if mode not in ("DEFERRED", "IMMEDIATE", "EXCLUSIVE"):
            raise ValueError(f"sqlite_begin: {mode!r} is not a SQLite transaction mode")
        connection.exec_driver_sql(f"BEGIN {mode}")

    return engine


def open_engine(url: str, *, busy_timeout_ms: int = BUSY_TIMEOUT_MS) -> Engine:
    """Connect to the database (see :func:`make_engine`) and migrate it to the newest schema; warns first when it
    is a SQLite file on a network filesystem."""
    warn_if_sqlite_on_network_filesystem(url)
    engine = make_engine(url, busy_timeout_ms=busy_timeout_ms)
    try:
        migrate(engine)
    except BaseException:
        engine.dispose()
        raise
    return engine


class Sessions:
    """The two kinds of session of a store over one engine: :attr:`reads`, and :meth:`write` transactions (SQLite:
    ``BEGIN IMMEDIATE``, one writer at a time). Objects stay readable after their transaction (no expiry)."""

    def __init__(self, engine: Engine):
        self.reads = sessionmaker(engine, expire_on_commit=False)
        self._writes = sessionmaker(engine.execution_options(sqlite_begin="IMMEDIATE"), expire_on_commit=False)

    @contextmanager
    def write(self) -> Iterator[Session]:
        """One write transaction, committed on success and rolled back on an exception."""
        with self._writes.begin() as session:
            yield session


# ---- SQLite on a network filesystem ----
# SQLite (WAL mode: shared memory and POSIX locks) is for one machine; on NFS, SMB, CephFS and the like its locks are
# unreliable and concurrent writers from several machines corrupt the file. A deployment with workers on several
# machines (a ReadWriteMany volume) puts the database on PostgreSQL (``BLENDSPLAT_JOBS_URL``).

NETWORK_FILESYSTEMS = frozenset({
    "nfs", "nfs4", "cifs", "smb3", "smbfs", "ncpfs", "afs", "9p", "ceph", "glusterfs", "lustre", "gpfs", "beegfs",
    "ocfs2", "gfs2", "fuse.sshfs", "fuse.glusterfs", "fuse.cephfs", "fuse.s3fs", "fuse.gcsfuse", "fuse.juicefs",
    "fuse.rclone", "fuse.goofys", "fuse.mountpoint-s3", "fuse.azureblob", "fuse.blobfuse2", "efs",
})


def _unescape(field: str) -> str:
    """/proc/mounts escapes space, tab, newline and backslash as octal (``\\040``)."""
    return field.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\")


def filesystem_type(path: str | os.PathLike, mounts: str | os.PathLike = "/proc/mounts") -> str | None:
    """The type of the filesystem holding ``path`` (the longest mount point above it), or None when unknown."""
    target = Path(path).absolute()
    while not target.exists() and target != target.parent:
        target = target.parent  # the file (or its folder) may not exist yet
    target = target.resolve()
    try:
        lines = Path(mounts).read_text().splitlines()
    except OSError:
        return None
    best, best_type = -1, None
    for line in lines:
        fields = line.split()
        if len(fields) < 3:
            continue
        point = Path(_unescape(fields[1]))
        if (target == point or point in target.parents) and len(point.parts) >= best:
            best, best_type = len(point.parts), fields[2]
    return best_type


def warn_if_sqlite_on_network_filesystem(url: str, mounts: str | os.PathLike = "/proc/mounts") -> str | None:
    """Log a warning when ``url`` is a SQLite file on a network filesystem; the filesystem type, else None."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    fstype = filesystem_type(parsed.database, mounts)
    if fstype is None or fstype.lower() not in NETWORK_FILESYSTEMS:
        return None
    log.warning("the job database %s is a SQLite file on a network filesystem (%s): SQLite is for one machine, "
                "its locks are unreliable there and several machines writing it corrupt it; use PostgreSQL "
                "(BLENDSPLAT_JOBS_URL=postgresql+psycopg://...) for workers on several machines",
                parsed.database, fstype)
    return fstype


# ---- migrations (Alembic, configured here: no alembic.ini) ----

class _AlembicNoise(logging.Filter):
    """Alembic's INFO lines other than the migrations it runs ("Running upgrade 0001 -> 0002, ..."): plugin set-up,
    "Context impl SQLiteImpl", "Will assume non-transactional DDL". Only records of the loggers it is added to."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno > logging.INFO or str(record.msg).startswith("Running ")


_NOISE = _AlembicNoise()


def _quiet_alembic() -> None:
    """Keep Alembic's set-up chatter out of the host process's log (every ``blendsplat`` command that opens the
    database checks its revision): the lines of migrations it runs stay."""
    for name in ("alembic.runtime.plugins", "alembic.runtime.migration"):
        logger = logging.getLogger(name)
        if _NOISE not in logger.filters:
            logger.addFilter(_NOISE)


def alembic_config(url: str | None = None):
    """An Alembic configuration for the migrations in ``service/migrations`` (``url`` only for commands that
    connect)."""
    _quiet_alembic()
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(SCRIPT_LOCATION))
    if url is not None:
        config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))  # configparser interpolation
    return config


def head() -> str:
    """The newest revision of the schema."""
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def current(engine: Engine) -> str | None:
    """The revision a database is at (None: never migrated)."""
    _quiet_alembic()
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def migrate(target: str | Engine, revision: str = "head") -> None:
    """Upgrade a database (a URL or an engine from :func:`make_engine`) to ``revision``.

    Idempotent, and safe when several processes start at once: on SQLite the migration runs in one
    ``BEGIN IMMEDIATE`` transaction, on PostgreSQL under a transaction-scoped advisory lock, so a second caller
    waits and then finds the database at head. A database already at head is left alone, silently; a migration
    logs its steps (Alembic's "Running upgrade ..." lines) and one line with the revisions it went between."""
    _quiet_alembic()
    from alembic import command
    from alembic.runtime.migration import MigrationContext

    engine = make_engine(target) if isinstance(target, str) else target
    try:
        config = alembic_config()
        newest = head() if revision == "head" else revision
        runner = engine.execution_options(sqlite_begin="IMMEDIATE")
        with runner.begin() as connection:
            if connection.dialect.name == "postgresql":
                connection.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_PG_LOCK})")
            was = MigrationContext.configure(connection).get_current_revision()
            if was == newest:
                return  # nothing to migrate (the commonest case: every command opens the database)
            config.attributes["connection"] = connection
            command.upgrade(config, revision)
        log.info("migrated the database %s from revision %s to %s", engine.url.render_as_string(hide_password=True),
                 was or "(empty)", newest)
    finally:
        if isinstance(target, str):
            engine.dispose()
