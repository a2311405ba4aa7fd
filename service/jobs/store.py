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
transaction, so no state change is ever without its message and none is recorded twice. The message id is
``msg_<job id>_<state event id>``. :mod:`service.webhooks` claims due rows (:meth:`JobStore.claim_deliveries`, the
same exclusive claim as jobs), sends them and records the outcome (:meth:`JobStore.record_attempt`).

Claiming is exclusive on both backends: PostgreSQL takes the oldest queued row with ``SELECT ... FOR UPDATE SKIP
LOCKED``; SQLite runs every write in a ``BEGIN IMMEDIATE`` transaction (one writer at a time, waiting up to the
busy timeout). Lease times are the clock of the process that calls the store (keep worker clocks in sync).

The store is synchronous and thread-safe (one engine, pooled connections); async callers run it in a thread.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import numbers
import re
import secrets
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import Engine, and_, delete, exists, func, or_, select
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import Session, sessionmaker

from ..errors import FailedPrecondition, InvalidArgument, NotFound
from .migrations import migrate
from .models import (
    BUSY_TIMEOUT_MS,
    TERMINAL,
    DeliveryStatus,
    EventKind,
    HeartbeatReply,
    Job,
    JobEvent,
    JobEventRecord,
    JobRecord,
    JobState,
    WebhookDelivery,
    WebhookDeliveryRecord,
    make_engine,
)
from .netfs import warn_if_sqlite_on_network_filesystem

log = logging.getLogger(__name__)

CHANNEL = "blendsplat_jobs"  # PostgreSQL NOTIFY channel: a job may be claimable (payload: its id)
POLL_SECONDS = 0.5  # SQLite: how often wait_for_work looks for queued jobs
MAX_LIST = 500
MAX_DELIVERY_ERROR = 500  # characters of a failed attempt's reason kept on the delivery
PROGRESS_FIELDS: dict[str, type] = {
    "iteration": int, "total_iterations": int, "gaussians": int,
    "fraction": float, "eta_seconds": float, "loss": float, "psnr": float,
}


class IdempotencyConflict(FailedPrecondition):
    """An idempotency key was reused with a different request body (FAILED_PRECONDITION: HTTP 409)."""


def new_job_id() -> str:
    return "job_" + secrets.token_urlsafe(15)  # 20 url-safe characters, 120 random bits


def _now() -> datetime:
    return datetime.now(UTC)


def _canonical(value: Any, field: str) -> str:
    """``value`` as canonical JSON (sorted keys, no NaN); InvalidArgument naming ``field`` if it has none."""
    try:
        return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InvalidArgument(f"not JSON-serialisable ({exc})", field=field) from None


def _json_object(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise InvalidArgument(f"expected a JSON object, got {type(value).__name__}", field=field)
    return json.loads(_canonical(dict(value), field))


def _progress(progress: Mapping[str, Any]) -> dict[str, Any]:
    """A progress report checked: the known fields (:data:`PROGRESS_FIELDS`) are numbers or None (a non-finite
    float, a diverged loss say, becomes None); other keys are kept for the event if they are JSON."""
    if not isinstance(progress, Mapping):
        raise InvalidArgument(f"expected a mapping, got {type(progress).__name__}", field="progress")
    out: dict[str, Any] = {}
    for key, value in progress.items():
        kind = PROGRESS_FIELDS.get(key)
        if kind is not None and value is not None:
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise InvalidArgument(f"expected a number, got {value!r}", field=f"progress.{key}")
            if kind is int:
                if not (isinstance(value, numbers.Integral) or float(value).is_integer()):
                    raise InvalidArgument(f"expected an integer, got {value!r}", field=f"progress.{key}")
                value = int(value)
            else:
                value = float(value) if math.isfinite(float(value)) else None
        out[key] = value
    return json.loads(_canonical(out, "progress"))


def _state(value: JobState | str, field: str = "state") -> JobState:
    try:
        return JobState(value)
    except ValueError:
        raise InvalidArgument(f"{value!r} is not a job state ({', '.join(JobState)})", field=field) from None


def _lease(worker_id: str, lease_seconds: float) -> timedelta:
    """A worker's lease request checked: a worker id of 1 to 255 characters and a positive duration."""
    if not (isinstance(worker_id, str) and 0 < len(worker_id) <= 255):
        raise InvalidArgument("a worker id is 1 to 255 characters", field="worker_id")
    if isinstance(lease_seconds, bool) or not isinstance(lease_seconds, numbers.Real) or not lease_seconds > 0:
        raise InvalidArgument(f"a positive number of seconds, got {lease_seconds!r}", field="lease_seconds")
    return timedelta(seconds=float(lease_seconds))


# A page cursor is the keyset position of the last job listed: its creation time in microseconds since the epoch
# and its id. Every string of this form is a position (a page that may be empty), so the API can state the pattern.
CURSOR_PATTERN = re.compile(r"^([0-9]{1,16})~([A-Za-z0-9_-]{1,64})$")
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def _encode_cursor(record: JobRecord) -> str:
    return f"{(record.created_at - _EPOCH) // timedelta(microseconds=1)}~{record.id}"


def _decode_cursor(cursor: str) -> tuple[datetime, str]:
    match = CURSOR_PATTERN.match(cursor)
    if match is None:
        raise InvalidArgument("not a cursor this listing returned (<microseconds>~<job id>)", field="cursor")
    return _EPOCH + timedelta(microseconds=int(match[1])), match[2]


class JobStore:
    """The jobs table and its events (see the module docstring for the contract). Open with :meth:`open`."""

    def __init__(self, engine: Engine):
        """A store over an engine from :func:`~service.jobs.models.make_engine`, whose schema is at head."""
        self.engine = engine
        self._postgres = engine.dialect.name == "postgresql"
        self._reads = sessionmaker(engine, expire_on_commit=False)
        self._writes = sessionmaker(engine.execution_options(sqlite_begin="IMMEDIATE"), expire_on_commit=False)
        self._wake = threading.Event()  # in-process wake-up for SQLite waiters
        self._listen_lock = threading.Lock()
        self._listener: Any = None  # PostgreSQL: a dedicated psycopg connection LISTENing on CHANNEL

    @classmethod
    def open(cls, url: str, *, busy_timeout_ms: int = BUSY_TIMEOUT_MS) -> JobStore:
        """Connect to a job database (``sqlite:///path`` or ``postgresql+psycopg://...``; see
        :func:`~service.jobs.models.default_url`) and migrate it to the newest schema."""
        warn_if_sqlite_on_network_filesystem(url)
        engine = make_engine(url, busy_timeout_ms=busy_timeout_ms)
        try:
            migrate(engine)
        except BaseException:
            engine.dispose()
            raise
        return cls(engine)

    def close(self) -> None:
        with self._listen_lock:
            if self._listener is not None:
                self._listener.close()
                self._listener = None
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

    @contextmanager
    def _write(self) -> Iterator[Session]:
        """One write transaction (SQLite: BEGIN IMMEDIATE), committed on success."""
        with self._writes.begin() as session:
            yield session

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
            self._delivery(session, record, event.id, url, previous, now)

    @staticmethod
    def _delivery(session: Session, record: JobRecord, event_id: int, url: str, previous: str | None,
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
            payload=json.loads(_canonical(payload, "payload")), status=DeliveryStatus.PENDING.value, attempts=0,
            next_attempt_at=now, created_at=now, updated_at=now))

    def _notify(self, session: Session, job_id: str) -> None:
        """Wake waiting workers when the transaction commits (PostgreSQL NOTIFY; SQLite: see wait_for_work)."""
        if self._postgres:
            session.execute(select(func.pg_notify(CHANNEL, job_id)))

    @staticmethod
    def _owned(record: JobRecord | None, worker_id: str) -> bool:
        return record is not None and record.state == JobState.RUNNING and record.lease_owner == worker_id

    # ---- submitting and reading ----

    def submit(self, spec: Mapping[str, Any], *, tenant: str | None = None, idempotency_key: str | None = None,
               max_attempts: int = 3) -> Job:
        """Queue a job. ``spec`` is its request (a JSON object: upload_id, preset, iterations, avatar_id, ...).

        With an ``idempotency_key`` (unique per tenant) a repeated submit with the same spec returns the job the
        first one created, whatever its state; the same key with a different spec raises
        :class:`IdempotencyConflict`."""
        body = _json_object(spec, "spec")
        digest = hashlib.sha256(_canonical(body, "spec").encode()).hexdigest()
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
                    now = _now()
                    record = JobRecord(
                        id=new_job_id(), tenant=tenant, state=JobState.QUEUED.value, spec=body,
                        idempotency_key=idempotency_key, request_hash=digest, attempts=0, max_attempts=max_attempts,
                        cancel_requested=False, total_iterations=total if isinstance(total, int) else None,
                        created_at=now, updated_at=now)
                    session.add(record)
                    session.flush()
                    self._event(session, record.id, EventKind.STATE,
                                {"state": JobState.QUEUED.value, "previous": None, "attempts": 0}, now)
                    self._notify(session, record.id)
                self._wake.set()
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

    def get(self, job_id: str) -> Job:
        """The job; NotFound if there is none."""
        with self._reads() as session:
            record = session.get(JobRecord, job_id)
            if record is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            return Job.of(record)

    def list(self, state: JobState | str | None = None, limit: int = 50,
             cursor: str | None = None, *, tenant: str | None = None) -> tuple[list[Job], str | None]:
        """Jobs newest first, optionally of one state and one tenant: a page of at most ``limit`` (1 to 500) and the
        cursor of the next page (None on the last). Keyset pagination: a page is stable while jobs are added."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIST:
            raise InvalidArgument(f"1 to {MAX_LIST}, got {limit!r}", field="limit")
        query = select(JobRecord).order_by(JobRecord.created_at.desc(), JobRecord.id.desc()).limit(limit + 1)
        if state is not None:
            query = query.where(JobRecord.state == _state(state).value)
        if tenant is not None:
            query = query.where(JobRecord.tenant == tenant)
        if cursor:
            created, job_id = _decode_cursor(cursor)
            query = query.where(or_(JobRecord.created_at < created,
                                    and_(JobRecord.created_at == created, JobRecord.id < job_id)))
        with self._reads() as session:
            records = list(session.scalars(query))
        more = len(records) > limit
        records = records[:limit]
        return [Job.of(r) for r in records], (_encode_cursor(records[-1]) if more else None)

    def counts_by_state(self) -> dict[JobState, int]:
        """How many jobs are in each state (every state present, zeros included)."""
        counts = dict.fromkeys(JobState, 0)
        with self._reads() as session:
            for state, count in session.execute(select(JobRecord.state, func.count()).group_by(JobRecord.state)):
                counts[JobState(state)] = count
        return counts

    # ---- the worker's side ----

    def claim(self, worker_id: str, lease_seconds: float) -> Job | None:
        """Take the oldest queued job: it becomes running, leased to ``worker_id`` for ``lease_seconds``, with one
        more attempt counted. None when nothing is queued. Never hands one job to two callers."""
        lease = _lease(worker_id, lease_seconds)
        now = _now()
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
        lease = _lease(worker_id, lease_seconds)
        report = _progress(progress) if progress is not None else None
        now = _now()
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
            record.updated_at = _now()
            return True

    def finish(self, job_id: str, worker_id: str, state: JobState | str, *, error: str | None = None,
               result: Mapping[str, Any] | None = None) -> bool:
        """End a running job as succeeded, failed or cancelled, with an error message or a result (a JSON
        object: avatar_id, evaluation links, ...). Only the lease owner may: False otherwise, nothing changed."""
        final = _state(state)
        if final not in TERMINAL:
            raise InvalidArgument(f"a job finishes as {', '.join(sorted(TERMINAL))}, not {final}", field="state")
        outcome = _json_object(result, "result") if result is not None else None
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return False
            record.error, record.result = error, outcome
            self._transition(session, record, final, _now(), worker=worker_id)
            return True

    def release(self, job_id: str, worker_id: str) -> bool:
        """Hand a running job back (the worker is shutting down; it checkpointed first): queued again with its
        checkpoint, the attempt not counted. A job whose cancel was requested ends cancelled instead. Owner only:
        False otherwise."""
        with self._write() as session:
            record = self._locked(session, job_id)
            if not self._owned(record, worker_id):
                return False
            now = _now()
            if record.cancel_requested:
                record.error = "cancelled"
                self._transition(session, record, JobState.CANCELLED, now, worker=worker_id, reason="released")
                return True
            record.attempts = max(0, record.attempts - 1)
            self._transition(session, record, JobState.QUEUED, now, worker=worker_id, reason="released")
            self._notify(session, job_id)
        self._wake.set()
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
            now = _now()
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
        now = now or _now()
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
                    self._notify(session, record.id)
                    requeued = True
                log.info("job %s: %s; now %s (attempt %d of %d)", record.id, lost, record.state, record.attempts,
                         record.max_attempts)
                changed.append(record.id)
        if requeued:
            self._wake.set()
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
        cutoff = (now or _now()) - older_than
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
        payload = _json_object(data, "data")
        with self._write() as session:
            if session.get(JobRecord, job_id) is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            record = self._event(session, job_id, event_kind, payload, _now())
            session.flush()
            return JobEvent.of(record)

    def events(self, job_id: str, after_id: int = 0, limit: int = 100) -> list[JobEvent]:
        """A job's events with ids above ``after_id``, oldest first, at most ``limit`` (1 to 500). NotFound if
        there is no job."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIST:
            raise InvalidArgument(f"1 to {MAX_LIST}, got {limit!r}", field="limit")
        with self._reads() as session:
            records = session.scalars(
                select(JobEventRecord).where(JobEventRecord.job_id == job_id, JobEventRecord.id > after_id)
                .order_by(JobEventRecord.id).limit(limit)).all()
            if not records and session.get(JobRecord, job_id) is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            return [JobEvent.of(r) for r in records]

    # ---- webhook deliveries ----

    def deliveries(self, job_id: str) -> list[WebhookDelivery]:
        """A job's webhook deliveries, oldest first (none for a job without a ``webhook_url``)."""
        with self._reads() as session:
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
        now = now or _now()
        with self._write() as session:
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
        now = _now()
        with self._write() as session:
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

    # ---- waiting for work ----

    def _has_queued(self) -> bool:
        with self._reads() as session:
            return bool(session.scalar(select(exists().where(JobRecord.state == JobState.QUEUED.value))))

    def wait_for_work(self, timeout: float) -> bool:
        """Block up to ``timeout`` seconds until a job may be claimable: True on a wake-up (then :meth:`claim`;
        it may still find nothing), False on timeout. PostgreSQL: LISTEN on :data:`CHANNEL` (submit, release and
        sweep NOTIFY it); the first call also looks for queued jobs, later ones keep listening in between.
        SQLite: polls every :data:`POLL_SECONDS` (and wakes at once for a submit in the same process)."""
        if self._postgres:
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
