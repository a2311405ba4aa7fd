"""The job store's tables (SQLAlchemy 2 typed ORM, on the shared database of :mod:`service.db`) and the values the
store hands out.

Three tables. ``jobs`` is the single source of truth of the training queue: a job's state, spec, lease, attempts,
cancel flag, checkpoint, latest progress, error and result. ``job_events`` is its append-only history (state
changes, progress reports, previews, log lines), replayed in id order by the event stream
(:mod:`service.jobs.events`). ``webhook_deliveries`` is the outbox of a job's webhook (the spec's ``webhook_url``):
one row per state change, written in the state change's transaction and sent by :mod:`service.jobs.webhooks`.

The schema is owned by the Alembic migrations in ``service/migrations/versions``; these classes must match them (a
test runs Alembic's autogenerate comparison). Change both together: edit a model, then add a migration
(:mod:`service.db` says how). Timestamps are timezone-aware UTC (:class:`service.db.UTCDateTime`).
"""

from __future__ import annotations

import dataclasses
import enum
from datetime import datetime
from typing import Any

from sqlalchemy import BigInteger, Boolean, CheckConstraint, Float, ForeignKey, Index, Integer, String, Text, func
from sqlalchemy.orm import Mapped, mapped_column

from ..db import Base


class JobState(enum.StrEnum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"


TERMINAL = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})


class EventKind(enum.StrEnum):
    PROGRESS = "progress"
    STATE = "state"
    PREVIEW = "preview"
    LOG = "log"


class DeliveryStatus(enum.StrEnum):
    PENDING = "pending"  # due at next_attempt_at (a dispatcher that claimed it holds it until then)
    DELIVERED = "delivered"  # a 2xx answer: never sent again
    FAILED = "failed"  # out of attempts or time


def _states() -> str:
    return ", ".join(f"'{s.value}'" for s in JobState)


class JobRecord(Base):
    """One training job (a row of ``jobs``)."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    tenant: Mapped[str | None] = mapped_column(String(128))
    state: Mapped[str] = mapped_column(String(16))
    spec: Mapped[dict[str, Any]]
    idempotency_key: Mapped[str | None] = mapped_column(String(255))
    request_hash: Mapped[str | None] = mapped_column(String(64))  # SHA-256 of the canonical spec JSON
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    max_attempts: Mapped[int] = mapped_column(Integer)
    lease_owner: Mapped[str | None] = mapped_column(String(255))
    lease_expires_at: Mapped[datetime | None]
    heartbeat_at: Mapped[datetime | None]
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    checkpoint_path: Mapped[str | None] = mapped_column(Text)
    # bytes on disk of its work folder as the worker last measured it (service/usage.py): the tenant's quota
    work_bytes: Mapped[int | None] = mapped_column(BigInteger)
    # the latest progress report
    iteration: Mapped[int | None] = mapped_column(Integer)
    total_iterations: Mapped[int | None] = mapped_column(Integer)
    fraction: Mapped[float | None] = mapped_column(Float)
    eta_seconds: Mapped[float | None] = mapped_column(Float)
    loss: Mapped[float | None] = mapped_column(Float)
    psnr: Mapped[float | None] = mapped_column(Float)
    gaussians: Mapped[int | None] = mapped_column(Integer)
    error: Mapped[str | None] = mapped_column(Text)
    result: Mapped[dict[str, Any] | None]
    created_at: Mapped[datetime]
    started_at: Mapped[datetime | None]
    finished_at: Mapped[datetime | None]
    updated_at: Mapped[datetime]

    __table_args__ = (
        CheckConstraint(f"state IN ({_states()})", name="state"),
        CheckConstraint("attempts >= 0 AND max_attempts >= 1", name="attempts"),
        Index("ix_jobs_state_created_at", "state", "created_at"),  # claiming (oldest queued), list by state
        Index("ix_jobs_created_at_id", "created_at", "id"),  # list, newest first (keyset)
        # one job per (tenant, key); NULL tenants share one scope (a plain unique constraint would let NULLs repeat)
        Index("uq_jobs_tenant_idempotency_key", func.coalesce(tenant, ""), idempotency_key, unique=True),
    )


class JobEventRecord(Base):
    """One entry of a job's history (a row of ``job_events``); ids increase, so ``id`` is the replay cursor."""

    __tablename__ = "job_events"

    id: Mapped[int] = mapped_column(BigInteger().with_variant(Integer, "sqlite"), primary_key=True,
                                    autoincrement=True)
    job_id: Mapped[str] = mapped_column(String(64), ForeignKey("jobs.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(String(16))
    data: Mapped[dict[str, Any]]
    created_at: Mapped[datetime]

    __table_args__ = (
        CheckConstraint("kind IN ('progress', 'state', 'preview', 'log')", name="kind"),
        Index("ix_job_events_job_id_id", "job_id", "id"),
    )


class WebhookDeliveryRecord(Base):
    """One webhook message about a job's state change (a row of ``webhook_deliveries``). ``id`` is the message id
    the receiver sees (``webhook-id``), the same on every attempt: ``msg_<job id>_<state event id>``."""

    __tablename__ = "webhook_deliveries"

    id: Mapped[str] = mapped_column(String(128), primary_key=True)
    job_id: Mapped[str] = mapped_column(String(64), ForeignKey("jobs.id", ondelete="CASCADE"))
    event: Mapped[str] = mapped_column(String(32))  # job.running, job.succeeded, ...
    url: Mapped[str] = mapped_column(Text)
    payload: Mapped[dict[str, Any]]
    status: Mapped[str] = mapped_column(String(16))
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime | None]
    last_status: Mapped[int | None] = mapped_column(Integer)  # the last answer's HTTP status
    last_error: Mapped[str | None] = mapped_column(Text)  # the last attempt's failure, when it failed
    created_at: Mapped[datetime]
    updated_at: Mapped[datetime]
    delivered_at: Mapped[datetime | None]

    __table_args__ = (
        CheckConstraint("status IN ('pending', 'delivered', 'failed')", name="status"),
        CheckConstraint("attempts >= 0", name="attempts"),
        Index("ix_webhook_deliveries_status_next_attempt_at", "status", "next_attempt_at"),  # claiming due ones
        Index("ix_webhook_deliveries_job_id_created_at", "job_id", "created_at"),  # a job's deliveries
    )


# ---- the values the store hands out (plain snapshots: no session, safe to pass between threads) ----

@dataclasses.dataclass(frozen=True)
class Job:
    """A job as the store last saw it. ``fraction`` (0..1), ``iteration``, ``eta_seconds``, ``loss``, ``psnr`` and
    ``gaussians`` are the latest progress report (None before the first)."""

    id: str
    tenant: str | None
    state: JobState
    spec: dict[str, Any]
    idempotency_key: str | None
    attempts: int
    max_attempts: int
    lease_owner: str | None
    lease_expires_at: datetime | None
    heartbeat_at: datetime | None
    cancel_requested: bool
    checkpoint_path: str | None
    iteration: int | None
    total_iterations: int | None
    fraction: float | None
    eta_seconds: float | None
    loss: float | None
    psnr: float | None
    gaussians: int | None
    error: str | None
    result: dict[str, Any] | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime
    work_bytes: int | None = None  # its work folder on disk, as last measured (None: never measured)

    @property
    def finished(self) -> bool:
        return self.state in TERMINAL

    @classmethod
    def of(cls, record: JobRecord) -> Job:
        values = {f.name: getattr(record, f.name) for f in dataclasses.fields(cls)}
        values["state"] = JobState(record.state)
        return cls(**values)


@dataclasses.dataclass(frozen=True)
class JobEvent:
    id: int
    job_id: str
    kind: EventKind
    data: dict[str, Any]
    created_at: datetime

    @classmethod
    def of(cls, record: JobEventRecord) -> JobEvent:
        return cls(record.id, record.job_id, EventKind(record.kind), record.data, record.created_at)


@dataclasses.dataclass(frozen=True)
class WebhookDelivery:
    """A webhook message and how its delivery went (``attempts`` counts the attempts started)."""

    id: str
    job_id: str
    event: str
    url: str
    payload: dict[str, Any]
    status: DeliveryStatus
    attempts: int
    next_attempt_at: datetime | None
    last_status: int | None
    last_error: str | None
    created_at: datetime
    updated_at: datetime
    delivered_at: datetime | None

    @classmethod
    def of(cls, record: WebhookDeliveryRecord) -> WebhookDelivery:
        values = {f.name: getattr(record, f.name) for f in dataclasses.fields(cls)}
        values["status"] = DeliveryStatus(record.status)
        return cls(**values)


@dataclasses.dataclass(frozen=True)
class HeartbeatReply:
    """``owned``: the caller still holds the job's lease (False: stop at once, someone else may run it now).
    ``cancel_requested``: end the job as cancelled at the next iteration boundary."""

    owned: bool
    cancel_requested: bool
