"""The job store's webhook outbox: the ``webhook_deliveries`` row of each state change of a job with a
``webhook_url``, and the dispatcher's side of it (claim due deliveries, record an attempt's outcome).

A delivery row is written by :meth:`~service.jobs.store.JobStore` in the state change's own transaction
(:func:`add_delivery`), so no state change is ever without its message and none is recorded twice. The message id
is ``msg_<job id>_<state event id>``. :mod:`service.jobs.webhooks` claims due rows (:meth:`Outbox.claim_deliveries`,
the same exclusive claim as jobs), sends them and records the outcome (:meth:`Outbox.record_attempt`).
"""

from __future__ import annotations

import json
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from ..db import Sessions
from ..errors import InvalidArgument
from .checks import MAX_LIST, canonical, utcnow
from .models import TERMINAL, DeliveryStatus, JobRecord, JobState, WebhookDelivery, WebhookDeliveryRecord

MAX_DELIVERY_ERROR = 500  # characters of a failed attempt's reason kept on the delivery


def add_delivery(session: Session, record: JobRecord, event_id: int, url: str, previous: str | None,
                 now: datetime) -> None:
    """The webhook message of a state change (Standard Webhooks' payload shape: type, timestamp, data)."""
    kind = f"job.{record.state}"
    data: dict[str, Any] = {
        "job_id": record.id, "state": record.state, "previous": previous, "attempts": record.attempts,
        "error": record.error if record.state in TERMINAL else None,
        "result": record.result if record.state == JobState.SUCCEEDED else None,
        "links": {"self": f"/v1/jobs/{record.id}", "events": f"/v1/jobs/{record.id}/events"}}
    payload = {"type": kind, "timestamp": now.isoformat(), "data": data}
    session.add(WebhookDeliveryRecord(
        id=f"msg_{record.id}_{event_id}", job_id=record.id, event=kind, url=url,
        payload=json.loads(canonical(payload, "payload")), status=DeliveryStatus.PENDING.value, attempts=0,
        next_attempt_at=now, created_at=now, updated_at=now))


class Outbox:
    """The dispatcher's side of the outbox, mixed into :class:`~service.jobs.store.JobStore` (over its sessions)."""

    _db: Sessions

    def deliveries(self, job_id: str) -> list[WebhookDelivery]:
        """A job's webhook deliveries, oldest first (none for a job without a ``webhook_url``)."""
        with self._db.reads() as session:
            return [WebhookDelivery.of(r) for r in session.scalars(
                select(WebhookDeliveryRecord).where(WebhookDeliveryRecord.job_id == job_id)
                .order_by(WebhookDeliveryRecord.created_at, WebhookDeliveryRecord.id))]

    def claim_deliveries(self, limit: int, lease_seconds: float, now: datetime | None = None) -> list[WebhookDelivery]:
        """Take up to ``limit`` pending deliveries that are due (oldest first): each gets one more attempt counted
        and is held by the caller for ``lease_seconds`` (its ``next_attempt_at`` moves there), so no other
        dispatcher sends it meanwhile; one whose sender died is due again when the lease ends. Exclusive on both
        backends (FOR UPDATE SKIP LOCKED; SQLite: BEGIN IMMEDIATE)."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIST:
            raise InvalidArgument(f"1 to {MAX_LIST}, got {limit!r}", field="limit")
        now = now or utcnow()
        with self._db.write() as session:
            records = session.scalars(
                select(WebhookDeliveryRecord)
                .where(WebhookDeliveryRecord.status == DeliveryStatus.PENDING.value,
                       WebhookDeliveryRecord.next_attempt_at <= now)
                .order_by(WebhookDeliveryRecord.next_attempt_at, WebhookDeliveryRecord.id).limit(limit)
                .with_for_update(skip_locked=True)).all()
            for record in records:
                record.attempts += 1
                record.next_attempt_at = now + timedelta(seconds=float(lease_seconds))
                record.updated_at = now
            return [WebhookDelivery.of(r) for r in records]

    def record_attempt(self, delivery_id: str, attempt: int, *, delivered: bool, status: int | None = None,
                       error: str | None = None, retry_at: datetime | None = None) -> WebhookDelivery | None:
        """The outcome of attempt number ``attempt`` of a claimed delivery: ``delivered`` (a 2xx: it is never sent
        again), else pending again at ``retry_at``, or failed for good when ``retry_at`` is None. A failure
        reported by an attempt that is no longer the latest (its claim ran out and another dispatcher took it) is
        ignored; a success always counts. The delivery after the call; None when it is gone (job deleted)."""
        now = utcnow()
        with self._db.write() as session:
            record = session.scalars(select(WebhookDeliveryRecord).where(WebhookDeliveryRecord.id == delivery_id)
                                     .with_for_update()).first()
            if record is None:
                return None
            if record.status != DeliveryStatus.PENDING.value or (not delivered and record.attempts != attempt):
                return WebhookDelivery.of(record)
            record.last_status = status
            record.updated_at = now
            if delivered:
                record.status = DeliveryStatus.DELIVERED.value
                record.delivered_at = now
                record.next_attempt_at = None
                record.last_error = None
            else:
                record.last_error = (error or f"HTTP {status}")[:MAX_DELIVERY_ERROR]
                if retry_at is None:
                    record.status = DeliveryStatus.FAILED.value
                    record.next_attempt_at = None
                else:
                    record.next_attempt_at = retry_at
            return WebhookDelivery.of(record)
