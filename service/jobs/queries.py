"""Reading the job store: one job, a page of jobs (keyset pagination), the counts by state, a job's events, the job an
idempotency key made, and a tenant's work folders' bytes (its storage quota).

Mixed into :class:`~service.jobs.store.JobStore` (over its read sessions); the writes are the store's own.
"""

from __future__ import annotations

from sqlalchemy import and_, func, or_, select

from ..db import Sessions
from ..errors import InvalidArgument, NotFound
from .checks import MAX_LIST, decode_cursor, encode_cursor, job_state
from .models import Job, JobEvent, JobEventRecord, JobRecord, JobState


class JobQueries:
    """The store's reads (see :class:`~service.jobs.store.JobStore`)."""

    _db: Sessions

    def get(self, job_id: str) -> Job:
        """The job; NotFound if there is none."""
        with self._db.reads() as session:
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
            query = query.where(JobRecord.state == job_state(state).value)
        if tenant is not None:
            query = query.where(JobRecord.tenant == tenant)
        if cursor:
            created, job_id = decode_cursor(cursor)
            query = query.where(or_(JobRecord.created_at < created,
                                    and_(JobRecord.created_at == created, JobRecord.id < job_id)))
        with self._db.reads() as session:
            records = list(session.scalars(query))
        more = len(records) > limit
        records = records[:limit]
        return [Job.of(r) for r in records], (encode_cursor(records[-1]) if more else None)

    def by_idempotency_key(self, tenant: str | None, key: str) -> Job | None:
        """The job ``tenant`` submitted with the idempotency key ``key``, if any (a submission with it is a replay
        or a conflict: it does not count against the key's hourly job allowance)."""
        with self._db.reads() as session:
            record = session.scalars(select(JobRecord).where(func.coalesce(JobRecord.tenant, "") == (tenant or ""),
                                                             JobRecord.idempotency_key == key)).first()
            return Job.of(record) if record is not None else None

    def tenant_work_bytes(self, tenant: str) -> int:
        """Bytes on disk of ``tenant``'s jobs' work folders, as their workers last measured them (one query)."""
        with self._db.reads() as session:
            return int(session.scalar(select(func.coalesce(func.sum(JobRecord.work_bytes), 0))
                                      .where(JobRecord.tenant == tenant)) or 0)

    def counts_by_state(self) -> dict[JobState, int]:
        """How many jobs are in each state (every state present, zeros included)."""
        counts = dict.fromkeys(JobState, 0)
        with self._db.reads() as session:
            for state, count in session.execute(select(JobRecord.state, func.count()).group_by(JobRecord.state)):
                counts[JobState(state)] = count
        return counts

    def events(self, job_id: str, after_id: int = 0, limit: int = 100) -> list[JobEvent]:
        """A job's events with ids above ``after_id``, oldest first, at most ``limit`` (1 to 500). NotFound if
        there is no job."""
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_LIST:
            raise InvalidArgument(f"1 to {MAX_LIST}, got {limit!r}", field="limit")
        with self._db.reads() as session:
            records = session.scalars(
                select(JobEventRecord).where(JobEventRecord.job_id == job_id, JobEventRecord.id > after_id)
                .order_by(JobEventRecord.id).limit(limit)).all()
            if not records and session.get(JobRecord, job_id) is None:
                raise NotFound(f"no job {job_id!r}", field="job_id")
            return [JobEvent.of(r) for r in records]
