"""A job's server-sent events (GET /v1/jobs/{id}/events, service/jobs/events.py) from a real service (uvicorn on a
free loopback port, the job database a SQLite file): events in order with their ids, resume with Last-Event-ID
(and ?after=), live events, a finished job's stream replays then closes, keep-alives, the lifetime and
per-process bounds, the JSON 404, and shutdown closing open streams at once. The events are made through the job
store as a worker would (claim, heartbeat progress, preview, finish).
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.jobs import JobStore
from service.jobs.events import streams
from service.server import Service
from service.settings import Settings

PROGRESS = {"iteration": 10, "total_iterations": 100, "fraction": 0.1, "loss": 0.25, "psnr": 18.5,
            "eta_seconds": 42.0, "gaussians": 5000}


class Server:
    """A service process's servers on an event loop in a thread (no demo avatar: the built-in one warms up)."""

    def __init__(self, data_dir: Path, **overrides):
        settings = Settings(data_dir=data_dir, host="127.0.0.1", grpc_port=0, http_port=0, demo_avatar="none",
                            warmup_size=32, drain_seconds=20, auth="off", events_poll_seconds=0.05, **overrides)
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="events-server", daemon=True)
        self.thread.start()
        self.service = Service(settings)
        self.call(self.service.start(), timeout=120)
        self.settings = settings
        self.url = f"http://127.0.0.1:{self.service.http_port}"
        self.store = JobStore.open(settings.jobs_database_url)

    def call(self, coro, timeout: float = 60):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def stop(self) -> float:
        """Stop the service; the seconds it took."""
        t0 = time.monotonic()
        self.call(self.service.stop(), timeout=60)
        took = time.monotonic() - t0
        self.store.close()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        return took


@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    s = Server(tmp_path_factory.mktemp("events") / "data")
    yield s
    s.stop()


@pytest.fixture
def client(server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=httpx.Timeout(10.0)) as c:
        yield c


def running_job(store: JobStore, progress: int = 0) -> str:
    """A running job (claimed by worker "w") with ``progress`` progress reports: events queued, running, ..."""
    job = store.submit({"upload_id": "upl_x", "avatar_id": "ada"})
    claimed = store.claim("w", 60)
    assert claimed is not None and claimed.id == job.id
    for i in range(progress):
        assert store.heartbeat(job.id, "w", 60, {**PROGRESS, "iteration": 10 * (i + 1)}).owned
    return job.id


class SSE:
    """An open event stream read block by block: events as dicts (id, event, data) and comments."""

    def __init__(self, client: httpx.Client, job_id: str, headers: dict | None = None, **params):
        self._context = client.stream("GET", f"/v1/jobs/{job_id}/events", headers=headers, params=params)
        self.response = self._context.__enter__()
        self._lines = self.response.iter_lines()
        self.comments: list[str] = []
        self.retry: int | None = None
        self.ended = False  # the server closed the stream

    def next(self) -> dict | None:
        """The next event (comments and retry lines are collected on the way); None when the stream ended."""
        fields: dict = {}
        for line in self._lines:
            if line == "":
                if fields:
                    return fields
                continue
            if line.startswith(":"):
                self.comments.append(line[1:].strip())
                continue
            name, _, value = line.partition(":")
            value = value[1:] if value.startswith(" ") else value
            if name == "retry":
                self.retry = int(value)
            elif name == "id":
                fields["id"] = int(value)
            elif name == "data":
                assert "data" not in fields, "one data line per event"
                fields["data"] = json.loads(value)
            else:
                fields[name] = value
        self.ended = True
        return None

    def take(self, n: int) -> list[dict]:
        out = []
        for _ in range(n):
            event = self.next()
            assert event is not None, f"the stream ended after {out}"
            out.append(event)
        return out

    def rest(self) -> list[dict]:
        out = []
        while (event := self.next()) is not None:
            out.append(event)
        return out

    def close(self) -> None:
        self._context.__exit__(None, None, None)

    def __enter__(self) -> SSE:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------------------------ the tests
def test_events_arrive_in_order_with_ids_and_their_payloads(server, client):
    job_id = running_job(server.store, progress=2)
    preview = server.store.add_event(job_id, "preview", {"iteration": 20, "path": "preview.png"})
    server.store.add_event(job_id, "log", {"message": "hello"})
    with SSE(client, job_id) as sse:
        assert sse.response.status_code == 200
        assert sse.response.headers["content-type"].startswith("text/event-stream")
        assert sse.response.headers["cache-control"] == "no-cache"
        events = sse.take(6)
        assert sse.retry and sse.retry > 0
    recorded = server.store.events(job_id)
    assert [e["id"] for e in events] == [e.id for e in recorded] == sorted(e.id for e in recorded)
    assert [e["event"] for e in events] == ["state", "state", "progress", "progress", "preview", "log"]
    assert all(e["data"]["job_id"] == job_id and e["data"]["time"] for e in events)
    assert events[0]["data"] | {"time": None} == {"job_id": job_id, "time": None, "state": "queued",
                                                  "previous": None, "attempts": 0, "error": None}
    assert events[1]["data"]["state"] == "running" and events[1]["data"]["previous"] == "queued"
    assert "worker" not in events[1]["data"]
    progress = events[3]["data"]
    assert {k: progress[k] for k in PROGRESS} == {**PROGRESS, "iteration": 20}
    assert events[4]["id"] == preview.id
    assert events[4]["data"] == {"job_id": job_id, "time": events[4]["data"]["time"], "iteration": 20,
                                 "url": f"/v1/jobs/{job_id}/artefacts/preview"}
    assert events[5]["data"]["message"] == "hello"


def test_a_reconnect_with_last_event_id_gets_only_the_later_events(server, client):
    job_id = running_job(server.store, progress=3)
    with SSE(client, job_id) as sse:
        first = sse.take(3)
    server.store.heartbeat(job_id, "w", 60, {**PROGRESS, "iteration": 99})  # while away
    with SSE(client, job_id, headers={"Last-Event-ID": str(first[-1]["id"])}) as sse:
        later = sse.take(3)
    ids = [e.id for e in server.store.events(job_id)]
    assert [e["id"] for e in first + later] == ids[:6]
    assert later[0]["id"] > first[-1]["id"] and later[-1]["data"]["iteration"] == 99
    # the query fallback, and the header winning over it
    with SSE(client, job_id, after=ids[-2]) as sse:
        assert sse.take(1)[0]["id"] == ids[-1]
    with SSE(client, job_id, headers={"Last-Event-ID": str(ids[-2])}, after=0) as sse:
        assert sse.take(1)[0]["id"] == ids[-1]


def test_live_events_arrive_then_the_end_closes_the_stream(server, client):
    job_id = running_job(server.store)
    with SSE(client, job_id) as sse:
        assert [e["event"] for e in sse.take(2)] == ["state", "state"]
        t0 = time.monotonic()
        server.store.heartbeat(job_id, "w", 60, PROGRESS)
        live = sse.take(1)[0]
        assert live["event"] == "progress" and live["data"]["iteration"] == 10
        assert time.monotonic() - t0 < 5
        server.store.add_event(job_id, "preview", {"iteration": 10, "path": "preview.png"})
        assert sse.take(1)[0]["event"] == "preview"
        assert server.store.finish(job_id, "w", "failed", error="boom")
        final = sse.take(1)[0]
        assert final["event"] == "state" and final["data"]["state"] == "failed" and final["data"]["error"] == "boom"
        end = sse.take(1)[0]
        assert end == {"event": "end", "data": {"job_id": job_id, "state": "failed"}}  # no id: not resumable
        assert sse.rest() == [] and sse.ended


def test_a_stream_of_a_finished_job_replays_everything_then_closes(server, client):
    job_id = running_job(server.store, progress=2)
    server.store.finish(job_id, "w", "succeeded", result={"avatar_id": "ada"})
    t0 = time.monotonic()
    with SSE(client, job_id) as sse:
        events = sse.rest()
    assert time.monotonic() - t0 < 5
    assert [e["event"] for e in events] == ["state", "state", "progress", "progress", "state", "end"]
    assert [e["id"] for e in events[:-1]] == [e.id for e in server.store.events(job_id)]
    assert events[-2]["data"]["state"] == "succeeded" and events[-1]["data"]["state"] == "succeeded"
    # connecting after the end with the last id: nothing more, then the end
    with SSE(client, job_id, headers={"Last-Event-ID": str(events[-2]["id"])}) as sse:
        assert [e["event"] for e in sse.rest()] == ["end"]


def test_an_idle_stream_gets_keep_alives_and_ends_after_its_lifetime(server, client, monkeypatch):
    monkeypatch.setattr(server.settings, "events_keepalive_seconds", 0.2)
    monkeypatch.setattr(server.settings, "events_max_seconds", 1.0)
    job_id = running_job(server.store)
    t0 = time.monotonic()
    with SSE(client, job_id) as sse:
        events = sse.rest()  # ends by itself: the lifetime
    took = time.monotonic() - t0
    assert [e["event"] for e in events] == ["state", "state"]  # no "end": the job goes on, the client reconnects
    assert 0.9 < took < 5
    assert sse.comments.count("keep-alive") >= 2


def test_an_unknown_job_or_a_bad_last_event_id_is_a_json_error_not_a_stream(server, client):
    r = client.get("/v1/jobs/job_doesnotexist00000000/events")
    assert r.status_code == 404 and r.headers["content-type"] == "application/json"
    assert r.json()["error"]["code"] == "NOT_FOUND" and r.json()["error"]["field"] == "job_id"
    job_id = running_job(server.store)
    r = client.get(f"/v1/jobs/{job_id}/events", headers={"Last-Event-ID": "abc"})
    assert r.status_code == 422 and r.json()["error"]["field"] == "Last-Event-ID"
    r = client.get(f"/v1/jobs/{job_id}/events", params={"after": -1})
    assert r.status_code == 422 and r.json()["error"]["field"] == "after"


def test_the_number_of_streams_per_process_is_bounded(server, client, monkeypatch):
    registry = server.call(_registry(server))
    monkeypatch.setattr(registry, "limit", 2)
    job_id = running_job(server.store)
    first, second = SSE(client, job_id), SSE(client, job_id)
    try:
        first.take(2), second.take(2)
        assert registry.open == 2
        refused = client.get(f"/v1/jobs/{job_id}/events")
        assert refused.status_code == 429 and refused.json()["error"]["code"] == "RESOURCE_EXHAUSTED"
        first.close()  # the client goes away: its slot is freed
        deadline = time.monotonic() + 5
        while registry.open > 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert registry.open == 1
        with SSE(client, job_id) as third:
            assert third.response.status_code == 200 and len(third.take(2)) == 2
    finally:
        first.close()
        second.close()


async def _registry(server: Server):
    return streams(server.service.app)


def test_shutdown_closes_open_streams_at_once(tmp_path):
    s = Server(tmp_path / "data")  # drain_seconds=20: a stream that held the drain up would take that long
    try:
        job_id = running_job(s.store)
        with httpx.Client(base_url=s.url, timeout=10) as c:
            opened = [SSE(c, job_id) for _ in range(3)]
            for sse in opened:
                sse.take(2)
            results: dict[int, list] = {}
            readers = [threading.Thread(target=lambda i=i, sse=sse: results.__setitem__(i, sse.rest()))
                       for i, sse in enumerate(opened)]
            for reader in readers:
                reader.start()
            took = s.stop()
            for reader in readers:
                reader.join(5)
            assert not any(reader.is_alive() for reader in readers)
            assert took < 5
            assert all(sse.ended for sse in opened) and all(r == [] for r in results.values())  # no "end"
            for sse in opened:
                sse.close()
    finally:
        if s.thread.is_alive():
            s.stop()
