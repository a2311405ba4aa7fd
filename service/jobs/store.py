"""The durable job store of the training queue: the jobs table is the single source of truth, no broker.

Life of a job::

    submit -> queued --claim--> running --finish--> succeeded | failed | cancelled
                 ^                 |
                 +-- release ------+   (SIGTERM hand-back: the attempt is not counted)
                 +-- sweep --------+   (lease expired: requeued while attempts < max_attempts, else failed)

A worker that claims a job holds a lease until ``lease_expires_at`` and extends it with :meth:`JobStore.heartbeat`.
Only the lease owner may report progress, set the checkpoint, finish or release the job. A lease is taken away
only by :meth:`JobStore.sweep` (someone must call it periodically: the workers do), so a worker whose heartbeat is
late but not yet swept still owns its job; one whose job was swept, finished or deleted gets ``owned=False`` and
must stop at once. Every state change is recorded as a ``state`` event and every progress report as a
``progress`` event (:meth:`JobStore.events` replays them in order).

Webhooks: a job whose spec has a ``webhook_url`` gets a ``webhook_deliveries`` row for every state change after
its submission (running, queued again, succeeded, failed, cancelled), written in the state change's own
transaction (:mod:`service.jobs.outbox`: the rows, and the dispatcher's claim and outcome methods).

Claiming is exclusive on both backends: PostgreSQL takes the oldest queued row with ``SELECT ... FOR UPDATE SKIP
LOCKED``; SQLite runs every write in a ``BEGIN IMMEDIATE`` transaction (one writer at a time, waiting up to the
busy timeout). Lease times are the clock of the process that calls the store (keep worker clocks in sync).

The store is synchronous and thread-safe (one engine, pooled connections); async callers run it in a thread. Its
input checks are :mod:`service.jobs.checks`; waking idle workers is :mod:`service.jobs.wakeup`.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Mapping
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Engine, delete, exists, func, select, update
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session

from ..db import BUSY_TIMEOUT_MS, Sessions, open_engine
from ..errors import FailedPrecondition, InvalidArgument, NotFound, redact
from .checks import (
    PROGRESS_FIELDS,
    canonical,
    check_lease,
    job_state,
    json_object,
    new_job_id,
    progress_report,
    utcnow,
)
from .models import TERMINAL, EventKind, HeartbeatReply, Job, JobEvent, JobEventRecord, JobRecord, JobState
from .outbox import Outbox, add_delivery
from .queries import JobQueries
from .wakeup import WorkSignal

log = logging.getLogger(__name__)


class IdempotencyConflict(FailedPrecondition):
    """An idempotency key was reused with a different request body (FAILED_PRECONDITION: HTTP 409)."""


class JobStore(JobQueries, Outbox):
    """The jobs table and its events (see the module docstring for the contract), their reads
    (:class:`~service.jobs.queries.JobQueries`) and the webhook outbox (:class:`~service.jobs.outbox.Outbox`).
    Open with :meth:`open`."""

    def __init__(self, engine: Engine):
        """A store over an engine of the service database (:func:`service.db.make_engine`) whose schema is at
        head."""
        self.engine = engine
        self._db = Sessions(engine)
        self._reads = self._db.reads
        self._write = self._db.write
        self._signal = WorkSignal(engine, self._has_queued)

    @classmethod
    def open(cls, url: str, *, busy_timeout_ms: int = BUSY_TIMEOUT_MS) -> JobStore:
        """Connect to a job database (``sqlite:///path`` or ``postgresql+psycopg://...``; see
        :func:`service.db.default_url`) and migrate it to the newest schema."""
        return cls(open_engine(url, busy_timeout_ms=busy_timeout_ms))

    def close(self) -> None:
        self._signal.close()
        self.engine.dispose()

    def __enter__(self) -> JobStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reachable(self) -> bool:
        """Whether the database answers (for readiness checks)."""
        try:
            with self.engine.connect() as connection:
                connection.exec_driver_sql("SELECT 1")
            return True
        except OperationalError:
            return False

    # ---- transactions and shared steps ----

    def _locked(self, session: Session, job_id: str) -> JobRecord | None:
        return session.scalars(select(JobRecord).where(JobRecord.id == job_id).with_for_update()).first()

    def _event(self, session: Session, job_id: str, kind: EventKind, data: dict[str, Any],
               now: datetime) -> JobEventRecord:
        record = JobEventRecord(job_id=job_id, kind=kind.value, data=data, created_at=now)
        session.add(record)
        return record

    def _transition(self, session: Session, record: JobRecord, state: JobState, now: datetime,
                    **details: Any) -> None:
        previous = record.state
        record.state = state.value
        record.updated_at = now
        if state in TERMINAL:
            record.finished_at = now
            record.lease_owner = record.lease_expires_at = None
        elif state is JobState.QUEUED:
            record.lease_owner = record.lease_expires_at = record.started_at = None
        data = {"state": state.value, "previous": previous, "attempts": record.attempts, **details}
        if record.error and state in TERMINAL:
            data.setdefault("error", record.error)
        event = self._event(session, record.id, EventKind.STATE, data, now)
        url = record.spec.get("webhook_url") if isinstance(record.spec, dict) else None
        if isinstance(url, str) and url:
            session.flush()  # the state event's id names the message
            add_delivery(session, record, event.id, url, previous, now)

    @staticmethod
    def _owned(record: JobRecord | None, worker_id: str) -> bool:
        return record is not None and record.state == JobState.RUNNING and record.lease_owner == worker_id

    # ---- submitting ----

    def submit(self, spec: Mapping[str, Any], *, tenant: str | None = None, idempotency_key: str | None = None,
               max_attempts: int = 3) -> Job:
        """Queue a job. ``spec`` is its request (a JSON object: upload_id, preset, iterations, avatar_id, ...).

        With an ``idempotency_key`` (unique per tenant) a repeated submit with the same spec returns the job the
        first one created, whatever its state; the same key with a different spec raises
        :class:`IdempotencyConflict`."""
        body = json_object(spec, "spec")
        digest = hashlib.sha256(canonical(body, "spec").encode()).hexdigest()
        if tenant is not None and not (isinstance(tenant, str) and 0 < len(tenant) <= 128):
            raise InvalidArgument("a tenant is 1 to 128 characters", field="tenant")
        if idempotency_key is not None and not (isinstance(idempotency_key, str) and 0 < len(idempotency_key) <= 255):
            raise InvalidArgument("an idempotency key is 1 to 255 characters", field="idempotency_key")
        if isinstance(max_attempts, bool) or not isinstance(max_attempts, int) or max_attempts < 1:
            raise InvalidArgument(f"at least 1, got {max_attempts!r}", field="max_attempts")
        total = body.get("iterations")
        for attempt in range(2):  # PostgreSQL: a concurrent submit with the same key wins the insert; then replay
            try:
                with self._write() as session:
                    if idempotency_key is not None:
                        existing = session.scalars(select(JobRecord).where(
                            func.coalesce(JobRecord.tenant, "") == (tenant or ""),
                            JobRecord.idempotency_key == idempotency_key)).first()
                        if existing is not None:
                            return self._replay(existing, digest, idempotency_key)
                    now = utcnow()
                    record = JobRecord(
                        id=new_job_id(), tenant=tenant, state=JobState.QUEUED.value, spec=body,
                        idempotency_key=idempotency_key, request_hash=digest, attempts=0, max_attempts=max_attempts,
                        cancel_requested=False, total_iterations=total if isinstance(total, int) else None,
                        created_at=now, updated_at=now)
                    session.add(record)
                    session.flush()
                    self._event(session, record.id, EventKind.STATE,
                                {"state": JobState.QUEUED.value, "previous": None, "attempts": 0}, now)
                    self._signal.notify(session, record.id)
                self._signal.wake()
                return Job.of(record)
            except IntegrityError:
                if idempotency_key is None or attempt:
                    raise
        raise AssertionError("unreachable")

    @staticmethod
    def _replay(record: JobRecord, digest: str, key: str) -> Job:
        if record.request_hash != digest:
            raise IdempotencyConflict(f"the key {key!r} was used for job {record.id} with a different request body",
                                      field="idempotency_key")
        return Job.of(record)
    # ---- the worker's side ----

    def claim(self, worker_id: str, lease_seconds: float) -> Job | None:
        """Take the oldest queued job: it becomes running, leased to ``worker_id`` for ``lease_seconds``, with one
        more attempt counted. None when nothing is queued. Never hands one job to two callers."""
        lease = check_lease(worker_id, lease_seconds)
        now = utcnow()
        with self._write() as session:
            record = session.scalars(
                select(JobRecord).where(JobRecord.state == JobState.QUEUED.value)
                .order_by(JobRecord.created_at, JobRecord.id).limit(1).with_for_update(skip_locked=True)).first()
            if record is None:
                return None
            record.attempts += 1
            self._transition(session, record, JobState.RUNNING, now, worker=worker_id)
            record.lease_owner = worker_id
            record.lease_expires_at = now + lease
            record.heartbeat_at = record.started_at = now
        return Job.of(record)

    def heartbeat(self, job_id: str, worker_id: str, lease_seconds: float,
                  progress: Mapping[str, Any] | None = None) -> HeartbeatReply:
        """Extend the lease by ``lease_seconds`` from now and record ``progress`` (keys of
        :data:`PROGRESS_FIELDS` update the job; the whole report becomes a ``progress`` event).

        ``owned=False`` when the caller no longer holds the job (swept, finished, released or deleted): the worker
        must stop without touching it. ``cancel_requested``: end it as cancelled."""
        lease = check_lease(worker_id, lease_seconds)
        report = progress_report(progress) if progress is not None else None
        now = utcnow()
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return HeartbeatReply(owned=False, cancel_requested=bool(record and record.cancel_requested))
            record.heartbeat_at = record.updated_at = now
            record.lease_expires_at = now + lease
            if report:
                for key in PROGRESS_FIELDS.keys() & report.keys():
                    setattr(record, key, report[key])
                self._event(session, job_id, EventKind.PROGRESS, report, now)
            return HeartbeatReply(owned=True, cancel_requested=record.cancel_requested)

    def set_checkpoint(self, job_id: str, worker_id: str, path: str) -> bool:
        """Record where the job's latest checkpoint is (the next attempt resumes from it). Owner only: False
        otherwise."""
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return False
            record.checkpoint_path = str(path)
            record.updated_at = utcnow()
            return True

    def set_work_bytes(self, job_id: str, work_bytes: int) -> bool:
        """Record what the job's work folder takes on disk (the worker after measuring it; 0 once it is removed).
        Not a state change: any caller, any state; False when there is no such job."""
        with self._write() as session:
            return session.execute(update(JobRecord).where(JobRecord.id == job_id)
                                   .values(work_bytes=max(0, int(work_bytes)))).rowcount > 0

    def finish(self, job_id: str, worker_id: str, state: JobState | str, *, error: str | None = None,
               result: Mapping[str, Any] | None = None) -> bool:
        """End a running job as succeeded, failed or cancelled, with an error message or a result (a JSON
        object: avatar_id, evaluation links, ...). Only the lease owner may: False otherwise, nothing changed."""
        final = job_state(state)
        if final not in TERMINAL:
            raise InvalidArgument(f"a job finishes as {', '.join(sorted(TERMINAL))}, not {final}", field="state")
        outcome = json_object(result, "result") if result is not None else None
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return False
            # clients read the error (GET, SSE, webhooks): no server path in it (service/errors.py, redact)
            record.error, record.result = (redact(error) if error else error), outcome
            self._transition(session, record, final, utcnow(), worker=worker_id)
            return True

    def release(self, job_id: str, worker_id: str) -> bool:
        """Hand a running job back (the worker is shutting down; it checkpointed first): queued again with its
        checkpoint, the attempt not counted. A job whose cancel was requested ends cancelled instead. Owner only:
        False otherwise."""
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return False
            now = utcnow()
            if record.cancel_requested:
                record.error = "cancelled"
                self._transition(session, record, JobState.CANCELLED, now, worker=worker_id, reason="released")
                return True
            record.attempts = max(0, record.attempts - 1)
            self._transition(session, record, JobState.QUEUED, now, worker=worker_id, reason="released")
            self._signal.notify(session, job_id)
        self._signal.wake()
        return True

    # ---- control ----

    def request_cancel(self, job_id: str) -> Job:
        """Cancel a job: a queued one is cancelled at once; a running one gets its cancel flag (its worker sees it
        in the next heartbeat and ends it as cancelled); a finished one is left as it is. Returns the job after the
        call: its state tells which case it was. NotFound if there is none."""
        with self._write() as session:
            record = self._locked(session, job_id)
            if record is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            now = utcnow()
            if record.state == JobState.QUEUED:
                record.cancel_requested = True
                record.error = "cancelled before it started"
                self._transition(session, record, JobState.CANCELLED, now)
            elif record.state == JobState.RUNNING and not record.cancel_requested:
                record.cancel_requested = True
                record.updated_at = now
                self._event(session, job_id, EventKind.LOG, {"message": "cancel requested"}, now)
            return Job.of(record)

    def sweep(self, now: datetime | None = None) -> list[str]:
        """Take back running jobs whose lease expired (their worker died or stalled): requeued while attempts <
        max_attempts, else failed with a reason naming the lost attempts; a job whose cancel was requested ends
        cancelled. Returns the ids it changed. Safe to call from many processes at once."""
        now = now or utcnow()
        changed: list[str] = []
        requeued = False
        with self._write() as session:
            records = session.scalars(
                select(JobRecord).where(JobRecord.state == JobState.RUNNING.value, JobRecord.lease_expires_at < now)
                .order_by(JobRecord.lease_expires_at).with_for_update(skip_locked=True)).all()
            for record in records:
                owner, expired = record.lease_owner, record.lease_expires_at
                lost = f"worker {owner!r} lost its lease (expired {expired.isoformat()})"
                if record.cancel_requested:
                    record.error = f"cancelled; {lost}"
                    self._transition(session, record, JobState.CANCELLED, now, reason="lease expired", worker=owner)
                elif record.attempts >= record.max_attempts:
                    record.error = (f"gave up after {record.attempts} attempts, every one lost its lease (the worker "
                                    f"crashed, was killed or stopped heartbeating); the last: {lost}")
                    self._transition(session, record, JobState.FAILED, now, reason="lease expired", worker=owner)
                else:
                    self._transition(session, record, JobState.QUEUED, now, reason="lease expired", worker=owner)
                    self._signal.notify(session, record.id)
                    requeued = True
                log.info("job %s: %s; now %s (attempt %d of %d)", record.id, lost, record.state, record.attempts,
                         record.max_attempts)
                changed.append(record.id)
        if requeued:
            self._signal.wake()
        return changed

    def delete(self, job_id: str) -> None:
        """Delete a job and its events, whatever its state (a worker still running it finds it gone at its next
        heartbeat). Files derived from it are the caller's to remove. NotFound if there is none."""
        with self._write() as session:
            if session.execute(delete(JobRecord).where(JobRecord.id == job_id)).rowcount == 0:
                raise NotFound(f"no job {job_id!r}", field="job_id")

    def purge_finished(self, older_than: timedelta, *, now: datetime | None = None) -> list[str]:
        """Delete the jobs (and events) that finished more than ``older_than`` ago; returns their ids so the caller
        can remove their files (retention)."""
        cutoff = (now or utcnow()) - older_than
        with self._write() as session:
            ids = list(session.scalars(select(JobRecord.id).where(
                JobRecord.state.in_([s.value for s in TERMINAL]), JobRecord.finished_at < cutoff)))
            if ids:
                session.execute(delete(JobRecord).where(JobRecord.id.in_(ids)))
        return ids

    # ---- events ----

    def add_event(self, job_id: str, kind: EventKind | str, data: Mapping[str, Any]) -> JobEvent:
        """Append an event (a preview written, a log line, ...) to a job's history. NotFound if there is no job."""
        try:
            event_kind = EventKind(kind)
        except ValueError:
            raise InvalidArgument(f"{kind!r} is not an event kind ({', '.join(EventKind)})", field="kind") from None
        payload = json_object(data, "data")
        with self._write() as session:
            if session.get(JobRecord, job_id) is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            record = self._event(session, job_id, event_kind, payload, utcnow())
            session.flush()
            return JobEvent.of(record)

    # ---- waiting for work ----

    def _has_queued(self) -> bool:
        with self._reads() as session:
            return bool(session.scalar(select(exists().where(JobRecord.state == JobState.QUEUED.value))))

    def wait_for_work(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds until a job may be claimable: True on a wake-up (then :meth:`claim`;
        it may still find nothing), False on timeout. PostgreSQL: LISTEN on :data:`~service.jobs.wakeup.CHANNEL`
        (submit, release and sweep NOTIFY it); SQLite: polls every :data:`~service.jobs.wakeup.POLL_SECONDS` (and
        wakes at once for a submit in the same process)."""
        return self._signal.wait(timeout)
