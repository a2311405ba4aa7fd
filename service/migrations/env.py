"""Alembic's environment for the service database (configured in code by :mod:`service.db`, no alembic.ini).

Online runs use the connection handed over in ``config.attributes["connection"]`` (what :func:`service.db.migrate`
does) or else connect to the configured ``sqlalchemy.url`` through the engine factory (WAL, busy timeout). Offline
runs (``--sql``) render the SQL for the configured URL's dialect. Never configures logging: the host process does.
The target metadata (for autogenerate) is every table of the database: the job store's and the API keys'.
"""

from __future__ import annotations

from alembic import context

import service.access.keys  # noqa: F401 - registers api_keys on Base.metadata
import service.jobs.models  # noqa: F401 - registers jobs, job_events, webhook_deliveries on Base.metadata
from service.db import Base, make_engine

config = context.config
target_metadata = Base.metadata


def _configure(**kwargs) -> None:
    context.configure(target_metadata=target_metadata, compare_type=True, **kwargs)


def run_offline() -> None:
    _configure(url=config.get_main_option("sqlalchemy.url"), literal_binds=True,
               dialect_opts={"paramstyle": "named"})
    with context.begin_transaction():
        context.run_migrations()


def _run(connection) -> None:
    _configure(connection=connection, render_as_batch=connection.dialect.name == "sqlite")
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    engine = make_engine(config.get_main_option("sqlalchemy.url"))
    try:
        with engine.execution_options(sqlite_begin="IMMEDIATE").connect() as connection:
            _run(connection)
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_offline()
else:
    run_online()
