"""The training queue's job store (service/jobs/store.py), each test against both SQLite (a file) and PostgreSQL.

PostgreSQL: 127.0.0.1:5432 with trust auth (user postgres or root); every test creates a database of its own
(``blendsplat_test_<hex>``) through the ``test`` database and drops it afterwards. Unreachable: those variants skip.
"""

from __future__ import annotations

import multiprocessing
import threading
import time
import warnings
from datetime import UTC, datetime, timedelta

import pytest
from conftest import postgres_database
from sqlalchemy import func, select

import service.access.keys  # noqa: F401 - the api_keys table, part of the schema the migrations own
from service.db import Base, current, default_url, head, make_engine, migrate
from service.errors import FailedPrecondition, InvalidArgument, NotFound
from service.jobs import EventKind, IdempotencyConflict, JobState, JobStore
from service.jobs.models import JobEventRecord

SPEC = {"upload_id": "up_1", "preset": "tiny", "iterations": 100, "avatar_id": "ada", "resolution": 256}


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.external)])
def url(request, tmp_path, pg_admin_user):
    """A fresh, empty job database's URL."""
    if request.param == "sqlite":
        yield default_url(tmp_path / "data")
        return
    with postgres_database(pg_admin_user) as pg_url:
        yield pg_url


@pytest.fixture
def store(url):
    with JobStore.open(url) as job_store:
        yield job_store


def _event_states(store: JobStore, job_id: str) -> list[str]:
    return [e.data["state"] for e in store.events(job_id) if e.kind is EventKind.STATE]


# ---- schema ----

def test_alembic_migrates_an_empty_database_to_head_and_the_models_match(url):
    from alembic.autogenerate import compare_metadata
    from alembic.runtime.migration import MigrationContext

    engine = make_engine(url)
    try:
        assert current(engine) is None
        migrate(url)
        migrate(url)  # idempotent
        assert current(engine) == head()
        with engine.connect() as connection:
            with warnings.catch_warnings():  # SQLite cannot reflect the expression index: checked below instead
                warnings.filterwarnings("ignore", message=".*expression-based index")
                diff = compare_metadata(MigrationContext.configure(connection, opts={"compare_type": True}),
                                        Base.metadata)
            assert diff == []
            if connection.dialect.name == "sqlite":
                assert connection.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
                assert connection.exec_driver_sql("PRAGMA busy_timeout").scalar() > 0
                assert connection.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
                index = connection.exec_driver_sql(
                    "SELECT sql FROM sqlite_master WHERE name = 'uq_jobs_tenant_idempotency_key'").scalar()
                assert index == ("CREATE UNIQUE INDEX uq_jobs_tenant_idempotency_key "
                                 "ON jobs (coalesce(tenant, ''), idempotency_key)")
    finally:
        engine.dispose()


# What the code before the one JobSpec stored (POST /v1/jobs wrote JobRequest.model_dump(): these six fields, and
# webhook_url only when given; jobs submitted to the store directly, as the worker's tests do, also carried the
# worker's own keys).
OLD_SPECS = {
    "api": {"upload_id": "upl_" + "a" * 22, "preset": "tiny", "iterations": 30, "avatar_id": "ada",
            "resolution": 64, "seed": 5},
    "api-defaults": {"upload_id": "upl_" + "b" * 22, "preset": "paper", "iterations": None, "avatar_id": "bob",
                     "resolution": None, "seed": 0},
    "api-webhook": {"upload_id": "upl_" + "c" * 22, "preset": "tiny", "iterations": None, "avatar_id": "cy",
                    "resolution": None, "seed": 0, "webhook_url": "https://hooks.example.com/blendsplat"},
    "worker-options": {"upload_id": "upl_" + "d" * 22, "preset": "tiny", "iterations": 40, "avatar_id": "dee",
                       "resolution": None, "seed": 3, "checkpoint_every": 4, "gaussians": 400, "mouth": 40},
}
OLD_HEAD = "0003"  # the newest revision before the one JobSpec: its revision id never changes


def test_a_job_database_written_before_the_one_job_spec_upgrades_and_its_queued_jobs_validate(url):
    """A database at the old head with queued jobs inserted as rows (the old code's spec JSON, request hash and
    state event, no ORM model involved) opens (migrated to head), and every queued job's spec validates against
    the one JobSpec the worker trains with, unchanged: re-serialised it is the stored spec, so the idempotency hash
    of the same request still matches (a retried POST replays the job instead of a 409)."""
    import hashlib
    import json

    from sqlalchemy import MetaData, Table

    from service.jobs.schemas import JobSpec

    migrate(url, OLD_HEAD)
    engine = make_engine(url)
    try:
        assert current(engine) == OLD_HEAD
        tables = MetaData()
        with warnings.catch_warnings():  # SQLite cannot reflect the expression index (not needed to insert)
            warnings.filterwarnings("ignore", message=".*expression-based index")
            jobs, events = (Table(name, tables, autoload_with=engine) for name in ("jobs", "job_events"))
        now = datetime.now(UTC)
        if engine.dialect.name == "sqlite":
            now = now.replace(tzinfo=None)  # the old store wrote SQLite's UTC wall time
        with engine.begin() as connection:
            for i, (key, spec) in enumerate(OLD_SPECS.items()):
                digest = hashlib.sha256(json.dumps(spec, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
                connection.execute(jobs.insert().values(
                    id=f"job_old{i}", tenant="acme", state="queued", spec=spec, idempotency_key=key,
                    request_hash=digest, attempts=0, max_attempts=3, cancel_requested=False,
                    total_iterations=spec["iterations"], created_at=now + timedelta(seconds=i),
                    updated_at=now + timedelta(seconds=i)))
                connection.execute(events.insert().values(
                    job_id=f"job_old{i}", kind="state", data={"state": "queued", "previous": None, "attempts": 0},
                    created_at=now))
    finally:
        engine.dispose()

    with JobStore.open(url) as store:
        assert current(store.engine) == head()
        queued, _ = store.list(state=JobState.QUEUED)
        assert sorted(j.id for j in queued) == [f"job_old{i}" for i in range(len(OLD_SPECS))]
        for job in queued:
            spec = JobSpec.parse(job.spec)
            assert spec.stored() == job.spec == OLD_SPECS[job.idempotency_key]
            assert _event_states(store, job.id) == ["queued"]
            replay = store.submit(spec.stored(), tenant="acme", idempotency_key=job.idempotency_key)
            assert replay.id == job.id  # the same request body: the first job, not a conflict
        api = JobSpec.parse(OLD_SPECS["api"])
        assert (api.resolution, api.iterations, api.seed, api.preset_overrides()) == (64, 30, 5, {})
        assert JobSpec.parse(OLD_SPECS["worker-options"]).preset_overrides() == {
            "checkpoint_every": 4, "gaussians": 400, "mouth": 40}
        claimed = store.claim("w1", 30)  # the oldest queued job is claimable as before
        assert claimed is not None and claimed.id == "job_old0" and claimed.spec == OLD_SPECS["api"]


# ---- submit, get, list ----

def test_submit_get_list_pagination_and_filter(store):
    jobs = [store.submit({**SPEC, "n": i}) for i in range(5)]
    first = store.get(jobs[0].id)
    assert first == jobs[0]
    assert first.id.startswith("job_") and len(first.id) == 24
    assert first.state is JobState.QUEUED and first.attempts == 0 and first.max_attempts == 3
    assert first.spec == {**SPEC, "n": 0} and first.total_iterations == 100
    assert first.created_at.tzinfo is not None and first.created_at.utcoffset() == timedelta(0)
    assert abs(first.created_at - datetime.now(UTC)) < timedelta(seconds=30)
    with pytest.raises(NotFound):
        store.get("job_missing")

    seen, cursor = [], None
    while True:
        page, cursor = store.list(limit=2, cursor=cursor)
        seen += page
        if cursor is None:
            break
    assert [j.id for j in seen] == [j.id for j in reversed(jobs)]  # newest first, each once

    claimed = store.claim("w1", 30)
    running, more = store.list(state="running")
    assert [j.id for j in running] == [claimed.id] and more is None
    assert len(store.list(state=JobState.QUEUED)[0]) == 4
    assert store.counts_by_state() == {**dict.fromkeys(JobState, 0), JobState.QUEUED: 4, JobState.RUNNING: 1}
    with pytest.raises(InvalidArgument, match="not a job state") as bad:
        store.list(state="paused")
    assert bad.value.field == "state"
    with pytest.raises(InvalidArgument) as bad:
        store.list(cursor="nonsense")
    assert bad.value.field == "cursor"
    with pytest.raises(InvalidArgument):
        store.list(limit=0)
    with pytest.raises(InvalidArgument) as bad:
        store.submit({"iterations": float("nan")})
    assert bad.value.field == "spec"


def test_idempotency_key_returns_the_same_job_and_refuses_a_different_body(store):
    job = store.submit(SPEC, idempotency_key="key-1")
    again = store.submit(dict(reversed(list(SPEC.items()))), idempotency_key="key-1")  # key order is no difference
    assert again.id == job.id
    store.claim("w1", 30)
    assert store.submit(SPEC, idempotency_key="key-1").id == job.id  # whatever state it is in
    with pytest.raises(IdempotencyConflict, match=job.id) as conflict:
        store.submit({**SPEC, "iterations": 200}, idempotency_key="key-1")
    assert isinstance(conflict.value, FailedPrecondition) and conflict.value.field == "idempotency_key"
    acme = store.submit(SPEC, tenant="acme", idempotency_key="key-1")
    assert acme.id != job.id and acme.tenant == "acme"  # keys are per tenant
    assert store.submit(SPEC, tenant="acme", idempotency_key="key-1").id == acme.id
    assert store.submit(SPEC).id != store.submit(SPEC).id  # no key: a new job each time
    assert store.counts_by_state()[JobState.QUEUED] == 3


def test_concurrent_submits_with_one_key_make_one_job(store):
    barrier = threading.Barrier(4)
    ids: list[str] = []

    def submit() -> None:
        barrier.wait(5)
        ids.append(store.submit(SPEC, idempotency_key="same").id)

    threads = [threading.Thread(target=submit) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    assert len(ids) == 4 and len(set(ids)) == 1
    assert store.counts_by_state()[JobState.QUEUED] == 1


# ---- the worker's side ----

def test_claim_takes_the_oldest_and_finish_only_by_the_owner(store):
    a, b, c = (store.submit({**SPEC, "n": i}) for i in range(3))
    got = store.claim("w1", 30)
    assert got.id == a.id and got.state is JobState.RUNNING and got.attempts == 1
    assert got.lease_owner == "w1" and got.started_at is not None
    assert got.lease_expires_at - got.started_at == timedelta(seconds=30)
    assert store.claim("w2", 30).id == b.id

    assert store.finish(a.id, "w2", "succeeded") is False  # not the owner
    assert store.get(a.id).state is JobState.RUNNING
    with pytest.raises(InvalidArgument):
        store.finish(a.id, "w1", "queued")
    assert store.finish(a.id, "w1", JobState.SUCCEEDED, result={"avatar_id": "ada", "evaluation": "/e"}) is True
    done = store.get(a.id)
    assert done.state is JobState.SUCCEEDED and done.result == {"avatar_id": "ada", "evaluation": "/e"}
    assert done.finished_at is not None and done.lease_owner is None and done.lease_expires_at is None
    assert store.finish(a.id, "w1", "failed") is False  # finished already
    assert _event_states(store, a.id) == ["queued", "running", "succeeded"]

    assert store.finish(b.id, "w2", "failed", error="out of memory") is True
    assert store.get(b.id).error == "out of memory"
    with pytest.raises(InvalidArgument) as bad:
        store.claim("w1", 0)
    assert bad.value.field == "lease_seconds"
    assert store.claim("w1", 30).id == c.id
    assert store.claim("w1", 30) is None


def test_heartbeat_records_progress_and_reports_cancel_and_lost_leases(store):
    job = store.submit(SPEC)
    store.claim("w1", 30)
    reply = store.heartbeat(job.id, "w1", 60, {"iteration": 10, "total_iterations": 100, "fraction": 0.1,
                                               "eta_seconds": 90.0, "loss": float("inf"), "psnr": 21.5,
                                               "gaussians": 5000, "lr": 1e-3})
    assert reply.owned and not reply.cancel_requested
    now = store.get(job.id)
    assert (now.iteration, now.fraction, now.loss, now.psnr, now.gaussians) == (10, 0.1, None, 21.5, 5000)
    assert now.lease_expires_at - now.heartbeat_at == timedelta(seconds=60)
    progress = [e for e in store.events(job.id) if e.kind is EventKind.PROGRESS]
    assert len(progress) == 1 and progress[0].data["lr"] == 1e-3 and progress[0].data["loss"] is None
    with pytest.raises(InvalidArgument) as bad:
        store.heartbeat(job.id, "w1", 60, {"iteration": "ten"})
    assert bad.value.field == "progress.iteration"

    assert store.heartbeat(job.id, "w2", 60).owned is False  # not the owner
    assert store.set_checkpoint(job.id, "w2", "/work/ckpt") is False
    assert store.set_checkpoint(job.id, "w1", "/work/ckpt") is True
    assert store.get(job.id).checkpoint_path == "/work/ckpt"

    store.request_cancel(job.id)
    reply = store.heartbeat(job.id, "w1", 60)
    assert reply.owned and reply.cancel_requested

    other = store.submit(SPEC)
    store.claim("w3", 30)
    assert store.sweep(now=datetime.now(UTC) + timedelta(seconds=45)) == [other.id]  # w3's lease expired
    lost = store.heartbeat(other.id, "w3", 30)
    assert lost.owned is False


def test_lease_expiry_requeues_until_max_attempts_then_fails_with_the_reason(store):
    job = store.submit(SPEC, max_attempts=2)
    store.claim("w1", 30)
    store.set_checkpoint(job.id, "w1", "/work/ckpt-40")
    assert store.sweep() == []  # nothing expired yet
    later = datetime.now(UTC) + timedelta(seconds=31)
    assert store.sweep(now=later) == [job.id]
    requeued = store.get(job.id)
    assert requeued.state is JobState.QUEUED and requeued.lease_owner is None and requeued.attempts == 1
    assert requeued.checkpoint_path == "/work/ckpt-40"  # the next attempt resumes from it
    second = store.claim("w2", 30)
    assert second.id == job.id and second.attempts == 2 and second.lease_owner == "w2"
    assert store.sweep(now=later + timedelta(seconds=60)) == [job.id]
    failed = store.get(job.id)
    assert failed.state is JobState.FAILED and failed.finished_at is not None
    assert "2 attempts" in failed.error and "lost its lease" in failed.error and "'w2'" in failed.error
    assert _event_states(store, job.id) == ["queued", "running", "queued", "running", "failed"]
    assert store.claim("w3", 30) is None


def test_release_hands_the_job_back_without_counting_the_attempt(store):
    job = store.submit(SPEC, max_attempts=1)
    store.claim("w1", 30)
    store.set_checkpoint(job.id, "w1", "/work/ckpt")
    assert store.release(job.id, "w2") is False
    assert store.release(job.id, "w1") is True
    back = store.get(job.id)
    assert back.state is JobState.QUEUED and back.attempts == 0 and back.lease_owner is None
    assert back.lease_expires_at is None and back.checkpoint_path == "/work/ckpt"
    assert store.claim("w2", 30).attempts == 1  # max_attempts=1 still allows this run
    store.request_cancel(job.id)
    assert store.release(job.id, "w2") is True  # a cancel was requested: it ends cancelled
    assert store.get(job.id).state is JobState.CANCELLED


def test_cancel_of_queued_running_and_finished_jobs(store):
    queued = store.submit({**SPEC, "n": 1})
    running = store.submit({**SPEC, "n": 2})
    cancelled = store.request_cancel(queued.id)
    assert cancelled.state is JobState.CANCELLED and cancelled.finished_at is not None
    assert store.claim("w1", 30).id == running.id  # the cancelled one is never claimed
    flagged = store.request_cancel(running.id)
    assert flagged.state is JobState.RUNNING and flagged.cancel_requested
    reply = store.heartbeat(running.id, "w1", 30)
    assert reply.owned and reply.cancel_requested
    assert store.finish(running.id, "w1", "cancelled") is True
    assert store.get(running.id).state is JobState.CANCELLED
    finished = store.request_cancel(running.id)
    assert finished.state is JobState.CANCELLED and finished.updated_at == store.get(running.id).updated_at
    with pytest.raises(NotFound):
        store.request_cancel("job_missing")


def test_a_cancelled_job_whose_worker_died_ends_cancelled_on_sweep(store):
    job = store.submit(SPEC)
    store.claim("w1", 30)
    store.request_cancel(job.id)
    assert store.sweep(now=datetime.now(UTC) + timedelta(minutes=5)) == [job.id]
    assert store.get(job.id).state is JobState.CANCELLED


def test_delete_removes_the_job_and_its_events(store):
    job = store.submit({**SPEC, "n": 1})
    keep = store.submit(SPEC)
    assert store.claim("w1", 30).id == job.id
    store.add_event(keep.id, "log", {"message": "kept"})
    store.add_event(job.id, EventKind.PREVIEW, {"path": "previews/000100.png"})
    assert len(store.events(job.id)) == 3
    store.delete(job.id)
    with pytest.raises(NotFound):
        store.get(job.id)
    with pytest.raises(NotFound):
        store.events(job.id)
    with store.engine.connect() as connection:
        rows = connection.execute(select(func.count()).select_from(JobEventRecord)
                                  .where(JobEventRecord.job_id == job.id)).scalar()
    assert rows == 0
    assert len(store.events(keep.id)) == 2
    with pytest.raises(NotFound):
        store.delete(job.id)
    assert store.heartbeat(job.id, "w1", 30).owned is False


def test_events_replay_in_order_and_validate(store):
    job = store.submit(SPEC)
    for i in range(4):
        store.add_event(job.id, "log", {"message": f"line {i}"})
    events = store.events(job.id)
    assert [e.kind for e in events] == [EventKind.STATE] + [EventKind.LOG] * 4
    assert [e.id for e in events] == sorted(e.id for e in events)
    rest = store.events(job.id, after_id=events[2].id, limit=1)
    assert [e.data for e in rest] == [{"message": "line 2"}]
    assert events[1].created_at.utcoffset() == timedelta(0)
    with pytest.raises(InvalidArgument) as bad:
        store.add_event(job.id, "metrics", {})
    assert bad.value.field == "kind"
    with pytest.raises(NotFound):
        store.add_event("job_missing", "log", {})


def test_purge_finished_deletes_old_finished_jobs_only(store):
    done = store.submit({**SPEC, "n": 1})
    waiting = store.submit({**SPEC, "n": 2})
    store.claim("w1", 30)
    store.finish(done.id, "w1", "succeeded")
    assert store.purge_finished(timedelta(days=1)) == []
    assert store.purge_finished(timedelta(days=1), now=datetime.now(UTC) + timedelta(days=2)) == [done.id]
    with pytest.raises(NotFound):
        store.get(done.id)
    assert store.get(waiting.id).state is JobState.QUEUED


def test_restart_loses_no_job(url):
    with JobStore.open(url) as first:
        ids = [first.submit({**SPEC, "n": i}).id for i in range(3)]
        claimed = first.claim("w1", 30)
        first.heartbeat(claimed.id, "w1", 30, {"iteration": 7})
    with JobStore.open(url) as second:
        assert {j.id for j in second.list()[0]} == set(ids)
        again = second.get(claimed.id)
        assert again.state is JobState.RUNNING and again.lease_owner == "w1" and again.iteration == 7
        assert second.claim("w2", 30).id == ids[1]


def test_wait_for_work_wakes_on_submit(url):
    with JobStore.open(url) as worker, JobStore.open(url) as api:  # two connections, as two processes would be
        assert worker.wait_for_work(0.05) is False  # nothing queued (and, on PostgreSQL, now LISTENing)
        woke: list[float] = []
        waiter = threading.Thread(target=lambda: worker.wait_for_work(5) and woke.append(time.monotonic()))
        waiter.start()
        time.sleep(0.2)
        submitted = time.monotonic()
        api.submit(SPEC)
        waiter.join(5)
        assert woke, "wait_for_work did not wake"
        assert woke[0] - submitted < 1.0
        assert worker.claim("w1", 30) is not None


# ---- two worker processes racing ----

def _race_worker(url: str, worker_id: str, ready, start, claims) -> None:
    """A worker process: claim until the queue is empty, finish each job, report the ids it claimed."""
    mine: list[str] = []
    try:
        with JobStore.open(url) as store:
            ready.put(worker_id)
            start.wait(30)
            while (job := store.claim(worker_id, 30)) is not None:
                mine.append(job.id)
                store.heartbeat(job.id, worker_id, 30, {"iteration": 1})
                time.sleep(0.01)  # a little work, so the two interleave
                if not store.finish(job.id, worker_id, "succeeded", result={"worker": worker_id}):
                    raise AssertionError(f"{worker_id} lost {job.id} before finishing it")
    except BaseException as exc:
        ready.put(worker_id)  # never leave the test waiting
        claims.put((worker_id, f"{type(exc).__name__}: {exc}"))
        raise
    claims.put((worker_id, mine))


def test_two_worker_processes_claim_each_of_20_jobs_exactly_once(url):
    with JobStore.open(url) as store:
        ids = {store.submit({**SPEC, "n": i}).id for i in range(20)}
        context = multiprocessing.get_context("spawn")
        ready, start, claims = context.Queue(), context.Event(), context.Queue()
        workers = [context.Process(target=_race_worker, args=(url, f"w{i}", ready, start, claims))
                   for i in range(2)]
        for process in workers:
            process.start()
        for _ in workers:
            ready.get(timeout=60)  # both connected: start them together
        start.set()
        results = dict(claims.get(timeout=60) for _ in workers)
        for process in workers:
            process.join(30)
        assert all(isinstance(mine, list) for mine in results.values()), results
        assert [p.exitcode for p in workers] == [0, 0]
        claimed = results["w0"] + results["w1"]
        assert len(claimed) == len(set(claimed)) == 20 and set(claimed) == ids
        assert results["w0"] and results["w1"], "one worker took every job: no race happened"
        jobs, _ = store.list(limit=50)
        assert all(j.state is JobState.SUCCEEDED and j.attempts == 1 for j in jobs)
        assert all(j.id in results[j.result["worker"]] for j in jobs)  # finished by the one that claimed it
        assert all(_event_states(store, j.id) == ["queued", "running", "succeeded"] for j in jobs)
