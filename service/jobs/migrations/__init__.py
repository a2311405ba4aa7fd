"""The job database's schema history (Alembic, configured here: no alembic.ini) and :func:`migrate`.

Add a revision after changing ``service/jobs/models.py``::

    from alembic import command
    from service.jobs.migrations import alembic_config
    command.revision(alembic_config(url), message="...", autogenerate=True)

then read the generated file in ``versions/`` (autogenerate misses renames and expression indexes).
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine

from ..models import make_engine

SCRIPT_LOCATION = Path(__file__).resolve().parent
_PG_LOCK = 0x626C656E64  # pg_advisory_xact_lock key: concurrent migrate() calls on one PostgreSQL run one at a time


def alembic_config(url: str | None = None) -> Config:
    """An Alembic configuration for this package's migrations (``url`` only for commands that connect)."""
    config = Config()
    config.set_main_option("script_location", str(SCRIPT_LOCATION))
    if url is not None:
        config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))  # configparser interpolation
    return config


def head() -> str:
    """The newest revision of the schema."""
    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def current(engine: Engine) -> str | None:
    """The revision a database is at (None: never migrated)."""
    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def migrate(target: str | Engine, revision: str = "head") -> None:
    """Upgrade a job database (a URL or an engine from :func:`~service.jobs.models.make_engine`) to ``revision``.

    Idempotent, and safe when several processes start at once: on SQLite the migration runs in one
    ``BEGIN IMMEDIATE`` transaction, on PostgreSQL under a transaction-scoped advisory lock, so a second caller
    waits and then finds the database at head."""
    engine = make_engine(target) if isinstance(target, str) else target
    try:
        config = alembic_config()
        runner = engine.execution_options(sqlite_begin="IMMEDIATE")
        with runner.begin() as connection:
            if connection.dialect.name == "postgresql":
                connection.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_PG_LOCK})")
            config.attributes["connection"] = connection
            command.upgrade(config, revision)
    finally:
        if isinstance(target, str):
            engine.dispose()
