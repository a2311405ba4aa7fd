"""The training queue's durable job store (SQLAlchemy 2 + Alembic; SQLite by default, PostgreSQL by URL).

The jobs table is the single source of truth: no broker holds a job. :class:`JobStore` is the one API (submit,
claim, heartbeat, finish, release, cancel, sweep, events); ``store.py`` states the contract.
"""

from .keys import SCOPES, ApiKey, KeyStore
from .migrations import migrate
from .models import TERMINAL, EventKind, HeartbeatReply, Job, JobEvent, JobState, default_url, make_engine
from .store import CHANNEL, PROGRESS_FIELDS, IdempotencyConflict, JobStore, new_job_id

__all__ = [
    "CHANNEL", "PROGRESS_FIELDS", "SCOPES", "TERMINAL", "ApiKey", "EventKind", "HeartbeatReply", "IdempotencyConflict",
    "Job", "JobEvent", "KeyStore",
    "JobState", "JobStore", "default_url", "make_engine", "migrate", "new_job_id",
]
