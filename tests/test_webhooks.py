"""Job webhooks (service/jobs/webhooks.py, the webhook_deliveries outbox in service/jobs/outbox.py): a real receiver
(http.server on a free loopback port, in a thread) checks every request's Standard Webhooks signature with its own
few lines of HMAC, answers 500 to the first attempts and then 2xx, and counts what it accepted. Through a real
service (the REST API stores webhook_url, the service's dispatcher delivers, the job shows its deliveries), and with
the dispatcher alone: a wrong secret, the attempt and time bounds, durability across a dispatcher restart, and
claims that never hand one delivery to two dispatchers (SQLite and PostgreSQL)."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import httpx
import pytest
from conftest import postgres_database
from test_archive import make_dataset, tar_archive
from test_job_events import Server

from service.db import default_url
from service.jobs import JobStore
from service.jobs.models import DeliveryStatus
from service.jobs.webhooks import WebhookDispatcher, load_secret, retry_delay, sign
from service.settings import Settings

SECRET = "whsec_" + base64.b64encode(b"a test key of thirty-two bytes!!").decode()
OTHER_SECRET = "whsec_" + base64.b64encode(b"another key, not the service's").decode()
# the receivers listen on loopback, which production refuses (webhook_private_networks; tested on its own below)
FAST = {"webhook_backoff_seconds": 0.02, "webhook_backoff_max_seconds": 0.2, "webhook_poll_seconds": 0.02,
        "webhook_private_networks": True}


def verify(secret: str, headers, body: bytes, tolerance: float = 300) -> bool:
    """A receiver's check (Standard Webhooks), written apart from the service's code."""
    msg_id, timestamp, signatures = (headers.get("webhook-id"), headers.get("webhook-timestamp"),
                                     headers.get("webhook-signature"))
    if not (msg_id and timestamp and signatures) or abs(time.time() - int(timestamp)) > tolerance:
        return False
    key = base64.b64decode(secret.removeprefix("whsec_"))
    expected = base64.b64encode(hmac.new(key, f"{msg_id}.{timestamp}.".encode() + body, hashlib.sha256).digest())
    return any(version == "v1" and hmac.compare_digest(value.encode(), expected)
               for version, _, value in (s.partition(",") for s in signatures.split()))


class Receiver:
    """A webhook receiver on a free loopback port: verifies each request with ``secret`` (401 if it fails),
    answers 500 to the first ``failures`` attempts of each message, then 204, and accepts each message id once."""

    def __init__(self, secret: str = SECRET, failures: int = 2, delay: float = 0.0):
        self.secret, self.failures, self.delay = secret, failures, delay
        self.requests: list[dict] = []  # every request: id, verified, status answered, body
        self.accepted: list[str] = []  # message ids answered 2xx (a duplicate would appear twice)
        self._lock = threading.Lock()
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("content-length", 0)))
                status = receiver._answer(self.headers, body, self.path)
                time.sleep(receiver.delay)
                self.send_response(status)
                self.send_header("content-length", "0")
                self.end_headers()

            def log_message(self, *args):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hooks/blendsplat"
        self.thread = threading.Thread(target=self.server.serve_forever, name="receiver", daemon=True)
        self.thread.start()

    def _answer(self, headers, body: bytes, path: str) -> int:
        verified = verify(self.secret, headers, body)
        msg_id = headers.get("webhook-id")
        with self._lock:
            seen = sum(1 for r in self.requests if r["id"] == msg_id and r["verified"])
            status = 401 if not verified else (500 if seen < self.failures else 204)
            self.requests.append({"id": msg_id, "verified": verified, "status": status, "path": path,
                                  "body": json.loads(body), "raw": body, "content_type": headers.get("content-type"),
                                  "headers": {k.lower(): v for k, v in headers.items()}})
            if status == 204:
                self.accepted.append(msg_id)
        return status

    def attempts(self, msg_id: str) -> int:
        return sum(1 for r in self.requests if r["id"] == msg_id)

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    yield r
    r.close()


def wait_for(predicate: Callable[[], bool], timeout: float = 15, what: str = "the condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def settings(tmp_path: Path, **overrides) -> Settings:
    return Settings(data_dir=tmp_path / "data", auth="off", **{"webhook_secret": SECRET, **FAST, **overrides})


def job_with_webhook(store: JobStore, url: str) -> str:
    """A job with a webhook, claimed by worker "w": one delivery (job.running) pending."""
    job = store.submit({"upload_id": "upl_x", "avatar_id": "ada", "webhook_url": url})
    assert store.claim("w", 60).id == job.id
    return job.id


def run_dispatcher(config: Settings, store: JobStore, until: Callable[[], bool], timeout: float = 15,
                   secret: str | None = None) -> WebhookDispatcher:
    """Run a dispatcher on a fresh event loop until ``until()`` holds (checked off the loop), then stop it."""
    dispatcher_box: list[WebhookDispatcher] = []

    async def main() -> None:
        dispatcher = WebhookDispatcher(config, store, secret or config.webhook_secret)
        dispatcher_box.append(dispatcher)
        dispatcher.start()
        try:
            deadline = time.monotonic() + timeout
            while not await asyncio.to_thread(until):
                if time.monotonic() > deadline:
                    raise TimeoutError("the dispatcher did not get there")
                await asyncio.sleep(0.02)
        finally:
            t0 = time.monotonic()
            await dispatcher.stop()
            assert time.monotonic() - t0 < 2, "stopping the dispatcher must be prompt"

    asyncio.run(main())
    return dispatcher_box[0]


# --------------------------------------------------------------------------------- through the real service
@pytest.fixture(scope="module")
def server(tmp_path_factory) -> Iterator[Server]:
    s = Server(tmp_path_factory.mktemp("webhooks") / "data", webhook_secret=SECRET, webhook_max_attempts=5, **FAST)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def upload_id(server, tmp_path_factory) -> str:
    folder = tmp_path_factory.mktemp("ds")
    root = make_dataset(folder / "ds")
    files = {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
    archive = tar_archive(folder / "a.tgz", files, prefix="take/", gz=True).read_bytes()
    r = httpx.post(f"{server.url}/v1/uploads", files={"file": ("take.tgz", archive, "application/octet-stream")},
                   timeout=60)
    assert r.status_code == 201, r.text
    return r.json()["upload_id"]


def test_a_job_webhook_is_signed_retried_and_accepted_exactly_once(server, upload_id, receiver):
    r = httpx.post(f"{server.url}/v1/jobs", json={"upload_id": upload_id, "avatar_id": "ada",
                                                  "webhook_url": receiver.url})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["spec"]["webhook_url"] == receiver.url and job["webhooks"] == []  # submitting is no state change
    assert server.store.claim("w", 60).id == job["id"]  # a worker takes it: job.running

    def deliveries() -> list[dict]:
        return httpx.get(f"{server.url}/v1/jobs/{job['id']}").json()["webhooks"]

    wait_for(lambda: [d["status"] for d in deliveries()] == ["delivered"], what="job.running delivered")
    assert server.store.finish(job["id"], "w", "succeeded", result={"avatar_id": "ada"})
    wait_for(lambda: [d["status"] for d in deliveries()] == ["delivered"] * 2, what="job.succeeded delivered")
    time.sleep(0.5)  # dozens of dispatcher polls: nothing more may be sent

    running, succeeded = deliveries()
    events = server.store.events(job["id"])
    assert running["id"] == f"msg_{job['id']}_{events[1].id}" and succeeded["id"] == f"msg_{job['id']}_{events[2].id}"
    for delivery, event in ((running, "job.running"), (succeeded, "job.succeeded")):
        assert delivery["event"] == event and delivery["attempts"] == 3 and delivery["last_status"] == 204
        assert delivery["last_error"] is None and delivery["delivered_at"] and delivery["next_attempt_at"] is None
        assert receiver.attempts(delivery["id"]) == 3
    assert sorted(receiver.accepted) == sorted([running["id"], succeeded["id"]])  # each exactly once
    assert all(r["verified"] for r in receiver.requests) and len(receiver.requests) == 6
    assert [r["status"] for r in receiver.requests if r["id"] == running["id"]] == [500, 500, 204]
    assert receiver.requests[0]["path"] == "/hooks/blendsplat"
    assert receiver.requests[0]["content_type"] == "application/json"
    body = next(r["body"] for r in receiver.requests if r["id"] == succeeded["id"])
    assert body["type"] == "job.succeeded" and datetime.fromisoformat(body["timestamp"]).tzinfo is not None
    assert body["data"] | {"links": None} == {"job_id": job["id"], "state": "succeeded", "previous": "running",
                                              "attempts": 1, "error": None, "result": {"avatar_id": "ada"},
                                              "links": None}
    # the README's receiver check accepts what was sent, and nothing altered
    readme_verify = readme_verifier()
    assert all(readme_verify(SECRET, r["headers"], r["raw"]) for r in receiver.requests)
    assert not readme_verify(OTHER_SECRET, receiver.requests[0]["headers"], receiver.requests[0]["raw"])
    assert not readme_verify(SECRET, receiver.requests[0]["headers"], receiver.requests[0]["raw"] + b"x")
    # a job without a webhook_url has none, and its spec has no webhook_url key
    plain = httpx.post(f"{server.url}/v1/jobs", json={"upload_id": upload_id, "avatar_id": "ada"}).json()
    assert "webhook_url" not in plain["spec"] and plain["webhooks"] == []


def readme_verifier() -> Callable:
    """The README's example receiver check (section "Job events and webhooks"), as written."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text(encoding="utf-8")
    section = text.split("## Job events and webhooks", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope: dict = {}
    exec(compile(code, "README.md:webhooks", "exec"), scope)  # noqa: S102 - our own README
    return scope["verify"]


@pytest.mark.parametrize("url", [
    "ftp://example.com/hook", "javascript:alert(1)", "/relative/path", "file:///etc/passwd", "http://",
    "http://exa mple.com/", "https://example.com/" + "x" * 2100, "http://example.com:99999/",
])
def test_a_webhook_url_that_is_not_http_or_https_is_refused(server, upload_id, url):
    r = httpx.post(f"{server.url}/v1/jobs", json={"upload_id": upload_id, "avatar_id": "ada", "webhook_url": url})
    assert r.status_code == 422, r.text
    assert r.json()["error"]["field"] == "webhook_url"


# ----------------------------------------------------------------------------------------- the dispatcher
def test_a_wrong_secret_fails_verification(tmp_path):
    body = b'{"type":"job.running"}'
    now = int(time.time())
    headers = {"webhook-id": "msg_1", "webhook-timestamp": str(now), "webhook-signature": sign(SECRET, "msg_1",
                                                                                               now, body)}
    assert verify(SECRET, headers, body)
    assert not verify(OTHER_SECRET, headers, body)
    assert not verify(SECRET, headers, body + b" ")
    assert not verify(SECRET, {**headers, "webhook-id": "msg_2"}, body)
    assert not verify(SECRET, {**headers, "webhook-timestamp": str(now - 3600)}, body)
    # a receiver holding another secret refuses every attempt: the delivery is never accepted, then failed
    receiver = Receiver(secret=OTHER_SECRET, failures=0)
    try:
        config = settings(tmp_path, webhook_max_attempts=2)
        with JobStore.open(config.jobs_database_url) as store:
            job_id = job_with_webhook(store, receiver.url)
            run_dispatcher(config, store, lambda: store.deliveries(job_id)[0].status is DeliveryStatus.FAILED)
            (delivery,) = store.deliveries(job_id)
        assert delivery.attempts == 2 and delivery.last_status == 401
        assert receiver.accepted == [] and [r["verified"] for r in receiver.requests] == [False, False]
    finally:
        receiver.close()


def test_retries_stop_after_the_attempt_bound_and_the_time_bound(tmp_path):
    receiver = Receiver(failures=1000)  # always 500
    try:
        by_attempts = settings(tmp_path / "a", webhook_max_attempts=3)
        with JobStore.open(by_attempts.jobs_database_url) as store:
            job_id = job_with_webhook(store, receiver.url)
            run_dispatcher(by_attempts, store, lambda: store.deliveries(job_id)[0].status is DeliveryStatus.FAILED)
            time.sleep(0.2)
            (delivery,) = store.deliveries(job_id)
        assert delivery.attempts == 3 and delivery.last_status == 500 and delivery.next_attempt_at is None
        assert receiver.attempts(delivery.id) == 3 and receiver.accepted == []

        by_time = settings(tmp_path / "b", webhook_max_attempts=100, webhook_retry_seconds=0.6,
                           webhook_backoff_seconds=0.1, webhook_backoff_max_seconds=0.1)
        t0 = time.monotonic()
        with JobStore.open(by_time.jobs_database_url) as store:
            job_id = job_with_webhook(store, receiver.url)
            run_dispatcher(by_time, store, lambda: store.deliveries(job_id)[0].status is DeliveryStatus.FAILED)
            (delivery,) = store.deliveries(job_id)
        assert time.monotonic() - t0 < 5
        assert 2 <= delivery.attempts < 20 and receiver.attempts(delivery.id) == delivery.attempts

        unreachable = settings(tmp_path / "c", webhook_max_attempts=2)
        with JobStore.open(unreachable.jobs_database_url) as store:
            job_id = job_with_webhook(store, "http://127.0.0.1:9/nothing-listens-here")
            run_dispatcher(unreachable, store, lambda: store.deliveries(job_id)[0].status is DeliveryStatus.FAILED)
            (delivery,) = store.deliveries(job_id)
        assert delivery.attempts == 2 and delivery.last_status is None and "Connect" in delivery.last_error
    finally:
        receiver.close()


def test_deliveries_survive_a_dispatcher_restart(tmp_path):
    receiver = Receiver(failures=1)
    try:
        config = settings(tmp_path, webhook_backoff_seconds=0.5, webhook_backoff_max_seconds=0.5)
        with JobStore.open(config.jobs_database_url) as store:  # state changes while no dispatcher runs
            job_id = job_with_webhook(store, receiver.url)
            assert store.finish(job_id, "w", "cancelled", error="cancelled")
        with JobStore.open(config.jobs_database_url) as store:  # the first dispatcher: one failed attempt each
            run_dispatcher(config, store, lambda: [d.last_status for d in store.deliveries(job_id)] == [500, 500])
            assert [(d.status, d.attempts) for d in store.deliveries(job_id)] == [(DeliveryStatus.PENDING, 1)] * 2
        with JobStore.open(config.jobs_database_url) as store:  # another one, another store: it finishes the work
            run_dispatcher(config, store, lambda: all(d.status is DeliveryStatus.DELIVERED
                                                      for d in store.deliveries(job_id)))
            deliveries = store.deliveries(job_id)
        assert [(d.event, d.attempts) for d in deliveries] == [("job.running", 2), ("job.cancelled", 2)]
        assert sorted(receiver.accepted) == sorted(d.id for d in deliveries)
        cancelled = next(r["body"] for r in receiver.requests if r["id"] == deliveries[1].id)
        assert cancelled["data"]["state"] == "cancelled" and cancelled["data"]["error"] == "cancelled"
    finally:
        receiver.close()


def test_stopping_the_dispatcher_is_prompt_with_an_attempt_in_flight(tmp_path):
    receiver = Receiver(failures=0, delay=20)  # answers after 20 s
    try:
        config = settings(tmp_path, webhook_timeout_seconds=60)
        with JobStore.open(config.jobs_database_url) as store:
            job_id = job_with_webhook(store, receiver.url)
            run_dispatcher(config, store, lambda: len(receiver.requests) == 1)  # asserts the stop took < 2 s
            (delivery,) = store.deliveries(job_id)
        # abandoned, not lost: still pending, held by its claim, sent again when that runs out
        assert delivery.status is DeliveryStatus.PENDING and delivery.attempts == 1
        assert delivery.next_attempt_at > datetime.now(UTC) + timedelta(seconds=30)
    finally:
        receiver.close()


def test_a_service_shutdown_is_not_held_up_by_a_webhook_in_flight(tmp_path):
    receiver = Receiver(failures=0, delay=20)
    s = Server(tmp_path / "data", webhook_secret=SECRET, webhook_timeout_seconds=60, **FAST)
    try:
        job_id = job_with_webhook(s.store, receiver.url)
        wait_for(lambda: len(receiver.requests) == 1, what="the attempt to start")
        assert s.stop() < 5  # drain_seconds=20: the dispatcher does not wait for the receiver
        with JobStore.open(s.settings.jobs_database_url) as store:
            (delivery,) = store.deliveries(job_id)
        assert delivery.status is DeliveryStatus.PENDING and delivery.attempts == 1  # sent again later
    finally:
        if s.thread.is_alive():
            s.stop()
        receiver.close()


def test_the_secret_is_generated_once_into_the_data_dir_with_mode_0600(tmp_path):
    config = Settings(data_dir=tmp_path / "data", auth="off")
    secret = load_secret(config)
    path = tmp_path / "data" / "webhook.secret"
    assert secret.startswith("whsec_") and len(base64.b64decode(secret[6:])) == 32
    assert path.stat().st_mode & 0o777 == 0o600 and path.read_text().strip() == secret
    assert load_secret(config) == secret  # the next start reads it
    assert load_secret(Settings(data_dir=tmp_path / "data", auth="off", webhook_secret="plain text")) == "plain text"
    with pytest.raises(ValueError, match="base64"):
        load_secret(Settings(data_dir=tmp_path / "data", auth="off", webhook_secret="whsec_not base64!"))


def test_the_backoff_grows_exponentially_with_jitter_up_to_the_cap():
    delays = [retry_delay(n, 1.0, 30.0) for n in range(1, 9)]
    for n, d in enumerate(delays, start=1):
        full = min(30.0, 2.0 ** (n - 1))
        assert full / 2 <= d <= full
    assert len({retry_delay(3, 1.0, 30.0) for _ in range(20)}) > 1  # jitter


# ----------------------------------------------------------------------------------------------- claiming
@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.external)])
def url(request, tmp_path, pg_admin_user):
    if request.param == "sqlite":
        yield default_url(tmp_path / "data")
        return
    with postgres_database(pg_admin_user, "blendsplat_webhooks_test") as pg_url:
        yield pg_url


def test_two_dispatchers_never_claim_one_delivery_and_a_lost_claim_comes_back(url):
    with JobStore.open(url) as store:
        jobs = [job_with_webhook(store, "http://127.0.0.1:9/") for _ in range(30)]
        claimed: list[list[str]] = [[], []]
        start = threading.Barrier(2)

        def claimer(i: int) -> None:
            with JobStore.open(url) as own:
                start.wait()
                while batch := own.claim_deliveries(3, 60):
                    claimed[i].extend(d.id for d in batch)

        threads = [threading.Thread(target=claimer, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        every = claimed[0] + claimed[1]
        assert len(every) == len(set(every)) == 30 and Counter(d[4:].rsplit("_", 1)[0] for d in every) == \
            Counter(jobs)
        assert store.claim_deliveries(10, 60) == []  # all held
        # a claim whose dispatcher died comes back when it runs out, as the next attempt
        later = datetime.now(UTC) + timedelta(seconds=61)
        again = store.claim_deliveries(100, 60, now=later)
        assert len(again) == 30 and {d.attempts for d in again} == {2}
        # a failure reported by the stale first attempt is ignored; a success counts
        stale = again[0]
        assert store.record_attempt(stale.id, 1, delivered=False, status=500,
                                    retry_at=later).status is DeliveryStatus.PENDING
        assert store.deliveries(stale.job_id)[0].last_status is None
        done = store.record_attempt(stale.id, 1, delivered=True, status=200)
        assert done.status is DeliveryStatus.DELIVERED
        assert store.record_attempt(stale.id, 2, delivered=False, status=500, retry_at=later).status \
            is DeliveryStatus.DELIVERED
        assert stale.id not in {d.id for d in store.claim_deliveries(100, 60, now=later + timedelta(hours=1))}


def test_a_webhook_to_a_non_public_address_is_refused_without_a_request(tmp_path):
    """By default a job cannot make the service call into its own network: loopback, private and link-local
    addresses are refused before any request, once (not retried), with the reason on the job."""
    receiver = Receiver()
    try:
        config = settings(tmp_path, webhook_private_networks=False)
        with JobStore.open(config.jobs_database_url) as store:
            job_id = job_with_webhook(store, receiver.url)
            other = job_with_webhook(store, "http://169.254.169.254/latest/meta-data")  # a cloud metadata address
            run_dispatcher(config, store, lambda: all(store.deliveries(j)[0].status is DeliveryStatus.FAILED
                                                      for j in (job_id, other)))
            deliveries = [store.deliveries(j)[0] for j in (job_id, other)]
        for delivery in deliveries:
            assert delivery.attempts == 1 and delivery.last_status is None
            assert "not a public address" in delivery.last_error
        assert receiver.attempts(deliveries[0].id) == 0 and receiver.accepted == []
    finally:
        receiver.close()


def test_a_webhook_goes_to_the_address_that_was_checked(tmp_path, monkeypatch):
    """DNS rebinding gains nothing: the name is resolved once per attempt and the request is sent to the address
    that passed the check (the Host header and TLS's name stay the URL's), not resolved again on connect."""
    answers = iter(["93.184.216.34"] + ["127.0.0.1"] * 10)  # public to the check, then loopback
    resolved: list[str] = []

    async def getaddrinfo(self, host, port, *args, **kwargs):
        resolved.append(host)
        return [(2, 1, 6, "", (next(answers), port))]
    monkeypatch.setattr(asyncio.base_events.BaseEventLoop, "getaddrinfo", getaddrinfo)
    sent: list[httpx.Request] = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request)
        return httpx.Response(204)
    config = settings(tmp_path, webhook_private_networks=False)
    with JobStore.open(config.jobs_database_url) as store:
        job_id = job_with_webhook(store, "https://hooks.example.com:8443/blendsplat?token=t")

        async def main() -> None:
            dispatcher = WebhookDispatcher(config, store, SECRET, transport=httpx.MockTransport(answer))
            dispatcher.start()
            deadline = time.monotonic() + 15
            while store.deliveries(job_id)[0].status is not DeliveryStatus.DELIVERED:
                assert time.monotonic() < deadline, "not delivered"
                await asyncio.sleep(0.02)
            await dispatcher.stop()
        asyncio.run(main())
    (request,) = sent
    assert resolved == ["hooks.example.com"]
    assert str(request.url) == "https://93.184.216.34:8443/blendsplat?token=t"
    assert request.headers["host"] == "hooks.example.com:8443"
    assert request.extensions["sni_hostname"] == "hooks.example.com"  # TLS verifies the name's certificate


def test_pinned_urls_keep_port_path_and_bracket_ipv6():
    from service.jobs.webhooks import _pinned

    assert _pinned("http://user:pw@hooks.example.com/x?y=1", "2606:2800:220:1::1") == (
        "http://user:pw@[2606:2800:220:1::1]/x?y=1", "hooks.example.com", {})
    assert _pinned("https://h.example/", "93.184.216.34") == ("https://93.184.216.34/", "h.example",
                                                              {"sni_hostname": "h.example"})
