"""Waking idle workers when a job may be claimable: PostgreSQL LISTEN/NOTIFY, SQLite short polling.

:class:`WorkSignal` is the job store's part of it: a transaction that queues a job (submit, release, sweep) calls
:meth:`WorkSignal.notify` inside it (PostgreSQL: ``pg_notify`` on :data:`CHANNEL`, sent when it commits) and
:meth:`WorkSignal.wake` after it (waiters in this process); :meth:`WorkSignal.wait` is what
:meth:`~service.jobs.store.JobStore.wait_for_work` runs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from sqlalchemy import Engine, func, select
from sqlalchemy.orm import Session

log = logging.getLogger(__name__)

CHANNEL = "blendsplat_jobs"  # PostgreSQL NOTIFY channel: a job may be claimable (payload: its id)
POLL_SECONDS = 0.5  # SQLite: how often a waiter looks for queued jobs


class WorkSignal:
    """Wake-ups of the workers of one database. ``has_queued``: whether a queued job exists now (one query)."""

    def __init__(self, engine: Engine, has_queued: Callable[[], bool]):
        self.engine = engine
        self.postgres = engine.dialect.name == "postgresql"
        self._has_queued = has_queued
        self._wake = threading.Event()  # in-process wake-up for SQLite waiters
        self._listen_lock = threading.Lock()
        self._listener: Any = None  # PostgreSQL: a dedicated psycopg connection LISTENing on CHANNEL

    def notify(self, session: Session, job_id: str) -> None:
        """Wake waiting workers when ``session``'s transaction commits (PostgreSQL NOTIFY; SQLite: see wait)."""
        if self.postgres:
            session.execute(select(func.pg_notify(CHANNEL, job_id)))

    def wake(self) -> None:
        """Wake the waiters of this process at once (after a commit that queued a job)."""
        self._wake.set()

    def close(self) -> None:
        with self._listen_lock:
            if self._listener is not None:
                self._listener.close()
                self._listener = None

    def wait(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds until a job may be claimable: True on a wake-up, False on timeout.
        PostgreSQL: LISTEN on :data:`CHANNEL`; the first call also looks for queued jobs, later ones keep listening
        in between. SQLite: polls every :data:`POLL_SECONDS` (and wakes at once for a submit in this process)."""
        if self.postgres:
            return self._wait_notified(timeout)
        deadline = time.monotonic() + timeout
        while True:
            if self._has_queued():
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            if self._wake.wait(min(POLL_SECONDS, remaining)):
                self._wake.clear()

    def _wait_notified(self, timeout: float) -> bool:
        import psycopg  # PostgreSQL only

        with self._listen_lock:
            if self._listener is None:
                raw = self.engine.raw_connection()
                connection = raw.driver_connection
                raw.detach()  # ours for good: never back to the pool
                connection.rollback()
                connection.autocommit = True
                connection.execute(f"LISTEN {CHANNEL}")
                self._listener = connection
                if self._has_queued():
                    return True
            try:
                woke = any(True for _ in self._listener.notifies(timeout=timeout, stop_after=1))
                if woke:
                    for _ in self._listener.notifies(timeout=0.001):  # drain: one wake-up for a burst
                        pass
                return woke
            except psycopg.Error:
                log.warning("job store: the LISTEN connection failed; reconnecting on the next wait", exc_info=True)
                self._listener.close()
                self._listener = None
                return True  # look for work now rather than miss a notification
