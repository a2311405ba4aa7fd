"""The Python client (clients/python: ``blendsplat_client``), sync and asyncio, against a real `blendsplat up` on
loopback (the service and one worker, keys on, the trained demo avatar): every call's happy path, typed errors for
bad input, retries of idempotent calls on an injected 503 / UNAVAILABLE (an httpx transport that fails once, a TCP
proxy that drops the first connection) and none of a non-idempotent call, Retry-After honoured, timeouts; its
generated stubs against the proto; its examples run as written (subprocesses).
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]
CLIENT = ROOT / "clients" / "python"
sys.path.insert(0, str(CLIENT))  # the client from the checkout (CI also installs it)

from blendsplat_client import AsyncClient, Client, RetryPolicy, errors  # noqa: E402

DATA = CLIENT / "examples" / "data"
READY = re.compile(r"ready: gRPC on port (\d+), HTTP on port (\d+)")
SERVER_ENV = {"BLENDSPLAT_WARMUP_SIZE": "32", "BLENDSPLAT_DRAIN_SECONDS": "1", "BLENDSPLAT_HEARTBEAT_SECONDS": "0.5",
              "PYTHONUNBUFFERED": "1"}
FAST = RetryPolicy(attempts=4, backoff=0.05, max_backoff=0.5)


def clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("BLENDSPLAT_")}


class Up:
    """`blendsplat up` on free loopback ports with its own data dir and admin key."""

    def __init__(self, data_dir: Path):
        self.log = data_dir.parent / "up.log"
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "up", "--grpc-port", "0",
                                          "--http-port", "0", "--data-dir", str(data_dir)], cwd=ROOT,
                                         env={**clean_env(), **SERVER_ENV}, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 180
        while not (match := READY.search(self.log.read_text(errors="replace"))):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail(f"`blendsplat up` did not become ready:\n{self.log.read_text()[-3000:]}")
            time.sleep(0.1)
        self.grpc_port, self.http_port = int(match.group(1)), int(match.group(2))
        self.url, self.target = f"http://127.0.0.1:{self.http_port}", f"127.0.0.1:{self.grpc_port}"
        self.key = (data_dir / "admin.key").read_text().strip()
        self.env = {**clean_env(), "BLENDSPLAT_URL": self.url, "BLENDSPLAT_GRPC_TARGET": self.target,
                    "BLENDSPLAT_API_KEY": self.key}

    def client(self, **kw) -> Client:
        return Client(self.url, self.target, self.key, **{"retry": FAST, **kw})

    def aclient(self, **kw) -> AsyncClient:
        return AsyncClient(self.url, self.target, self.key, **{"retry": FAST, **kw})

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def up(tmp_path_factory):
    server = Up(tmp_path_factory.mktemp("clients-python") / "data")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def client(up):
    with up.client() as c:
        yield c


def poses() -> list[dict]:
    return [json.loads(line) for line in (DATA / "drive.jsonl").read_text().splitlines() if line.strip()]


class Flaky(httpx.BaseTransport):
    """The real server behind a transport that answers the first ``fail`` requests matching ``match`` itself."""

    def __init__(self, match, fail: int = 1, status: int = 503, headers=None):
        self.inner, self.match, self.left, self.status = httpx.HTTPTransport(), match, fail, status
        self.headers, self.requests = headers or {}, []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.requests.append((request.method, request.url.path))
        if self.left > 0 and self.match(request):
            self.left -= 1
            request.read()
            return httpx.Response(self.status, headers=self.headers, json={"error": {
                "code": "UNAVAILABLE", "message": "injected", "field": ""}})
        return self.inner.handle_request(request)

    def close(self) -> None:
        self.inner.close()


# ------------------------------------------------------------------------------------------------ the package
def test_the_checked_in_stubs_are_what_the_proto_generates(tmp_path):
    pytest.importorskip("grpc_tools", reason="grpcio-tools generates the stubs (pip install -e '.[dev]')")
    out = subprocess.run([sys.executable, str(CLIENT / "generate_proto.py"), "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for name in ("render_pb2.py", "render_pb2.pyi", "render_pb2_grpc.py"):
        assert (tmp_path / name).read_text() == (CLIENT / "blendsplat_client" / "_proto" / name).read_text(), (
            f"{name} drifted from proto/: run python clients/python/generate_proto.py")


def test_the_client_needs_no_server_package_nor_torch():
    import tomllib

    deps = tomllib.loads((CLIENT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert sorted(re.match(r"[a-z]+", d).group() for d in deps) == ["grpcio", "httpx", "protobuf"]
    code = ("import sys, blendsplat_client; bad = [m for m in ('torch', 'numpy', 'service', 'render_core', "
            "'blendsplat.v1') if m in sys.modules]; assert not bad, bad")
    out = subprocess.run([sys.executable, "-c", code], cwd=CLIENT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


# ------------------------------------------------------------------------------------------------ streams
def test_a_stream_sends_poses_and_receives_decoded_frames(client):
    with client.stream("demo", size=96, codec="jpeg") as s:
        assert s.header.width == 96 and "jawOpen" in s.header.expression_names
        assert s.send(expression={"jawOpen": 0.6}, joints={"jaw": [0.2, 0, 0]}, camera="front") == 1
        frame = s.receive()
        assert frame.index == 1 and frame.image.shape == (96, 96, 3) and frame.latency_ms > 0
        assert frame.timings["total"] > 0
        s.send(expression=[0.1] * len(s.header.expression_names), camera={"yaw": 10, "pitch": 0})
        assert s.receive().index == 2
        frames = list(s.render(poses()[:5]))
        assert [f.index for f in frames] == [3, 4, 5, 6, 7]
    assert s.final.frames_sent == 7 and s.final.dropped == 0  # closed: ended and drained


def test_frames_stay_bytes_without_decoding_and_png_keeps_alpha(up):
    with up.client(decode=False) as c, c.stream("demo", size=(64, 48), codec="png") as s:
        s.send()
        frame = s.receive()
        assert frame.image is None and frame.data[:4] == b"\x89PNG" and (frame.width, frame.height) == (64, 48)
    with up.client() as c:
        assert c.render("demo", 32, "raw").image.shape == (32, 32, 4)


def test_stream_errors_are_typed_and_carry_the_field(client):
    with pytest.raises(errors.NotFound) as info:
        client.stream("no-such-avatar")
    assert info.value.status.field == "avatar_id" and "no-such-avatar" in info.value.message
    with client.stream("demo", size=64) as s:
        s.send(expression={"noSuchName": 1.0})
        with pytest.raises(errors.InvalidArgument) as info:
            s.receive()
        assert info.value.field == "named_coefficients" and info.value.status.frame_index == 1
        s.send(expression={"jawOpen": 1.0})  # the stream goes on
        assert s.receive().index == 2
    with pytest.raises(errors.InvalidArgument) as info:
        client.stream("demo", size=64, codec="png", quality=500)
    with Client(client.settings.url, client.settings.grpc_target, "bsk_wrong", retry=FAST) as bad:
        with pytest.raises(errors.Unauthenticated):
            bad.stream("demo")
        with pytest.raises(errors.Unauthenticated) as info:
            bad.list_avatars()
        assert info.value.http_status == 401


def test_a_stream_receive_times_out(client):
    with client.stream("demo", size=64) as s:
        t0 = time.monotonic()
        with pytest.raises(errors.Timeout):
            s.receive(timeout=0.3)  # nothing sent
        assert time.monotonic() - t0 < 2


def test_an_exception_inside_the_block_cancels_the_stream(client):
    with pytest.raises(RuntimeError), client.stream("demo", size=64) as s:
        s.send()
        raise RuntimeError("app failure")
    assert s._closed and not s._reader.is_alive()


class DropFirst:
    """A TCP proxy to ``target`` that closes its first ``drop`` connections at once (gRPC: UNAVAILABLE)."""

    def __init__(self, target: str, drop: int = 1):
        self.host, port = target.rsplit(":", 1)
        self.port_to, self.drop, self.accepted = int(port), drop, 0
        self.server = socket.create_server(("127.0.0.1", 0))
        self.target = f"127.0.0.1:{self.server.getsockname()[1]}"
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            self.accepted += 1
            if self.accepted <= self.drop:
                conn.close()
                continue
            upstream = socket.create_connection((self.host, self.port_to))
            for a, b in ((conn, upstream), (upstream, conn)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            for s in (a, b):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self.server.close()


def test_grpc_calls_and_stream_opens_are_retried_on_unavailable(up):
    proxy = DropFirst(up.target)
    try:
        with Client(up.url, proxy.target, up.key, retry=RetryPolicy(attempts=6, backoff=0.3)) as c:
            assert c.render("demo", 32).width == 32
        assert proxy.accepted >= 2
        proxy2 = DropFirst(up.target)
        with Client(up.url, proxy2.target, up.key, retry=RetryPolicy(attempts=6, backoff=0.3)) as c, \
                c.stream("demo", size=32) as s:
            s.send()
            assert s.receive().index == 1
        assert proxy2.accepted >= 2
        proxy2.close()
        with Client(up.url, DropFirst(up.target, drop=100).target, up.key, retry=RetryPolicy(attempts=1)) as c, \
                pytest.raises(errors.Unavailable):
            c.render("demo", 32)
    finally:
        proxy.close()


# ------------------------------------------------------------------------------------------------ REST
def test_avatars_list_get_put_load_unload_delete(client, avatar, tmp_path):
    from render_core.bundle import write_bundle

    bundle = tmp_path / "a.bundle"
    write_bundle(avatar, bundle)
    seen = []
    made = client.put_avatar("client-test", bundle, progress=lambda sent, total: seen.append((sent, total)))
    assert made["id"] == "client-test" and seen[-1] == (bundle.stat().st_size,) * 2
    assert "client-test" in {a["id"] for a in client.list_avatars()}
    assert client.get_avatar("client-test")["gaussians"] == made["gaussians"]
    assert client.load_avatar("client-test")["loaded"] is True
    assert client.unload_avatar("client-test")["loaded"] is False
    assert client.put_avatar("client-test", bundle.read_bytes())["id"] == "client-test"  # bytes, replaced
    assert client.delete_avatar("client-test") is None
    with pytest.raises(errors.NotFound) as info:
        client.get_avatar("client-test")
    assert info.value.field == "avatar_id" and info.value.http_status == 404
    with pytest.raises(errors.InvalidArgument):
        client.put_avatar("client-bad", b"not a bundle")


def test_adapters_put_list_get_delete(client, head):
    from render_core.adapters.fit import fit
    from render_core.adapters.onnx_model import model_bytes
    from tests.test_adapters import mixed

    result = fit(head, mixed(head, k=6)[0], adapter_id="client-adapter")
    made = client.put_adapter("client-adapter", result.manifest.to_dict(),
                              model_bytes(result.manifest, result.weights))
    assert made["id"] == "client-adapter"
    assert "client-adapter" in {a["id"] for a in client.list_adapters()}
    assert client.get_adapter("client-adapter")["id"] == "client-adapter"
    assert client.delete_adapter("client-adapter")["id"] == "client-adapter"
    with pytest.raises(errors.NotFound):
        client.get_adapter("client-adapter")


def test_idempotent_calls_are_retried_on_503_honouring_retry_after(up):
    flaky = Flaky(lambda r: r.method == "GET", fail=2, headers={"Retry-After": "1"})
    with up.client(transport=flaky) as c:
        t0 = time.monotonic()
        assert any(a["id"] == "demo" for a in c.list_avatars())
        assert time.monotonic() - t0 >= 2.0  # two waits of Retry-After: 1
    assert flaky.requests == [("GET", "/v1/avatars")] * 3
    flaky = Flaky(lambda r: r.method == "DELETE", status=502)
    with up.client(transport=flaky) as c, pytest.raises(errors.NotFound):
        c.delete_avatar("never-was")  # retried after the 502, then the real answer
    assert len(flaky.requests) == 2


def test_a_non_idempotent_call_is_not_retried(up):
    flaky = Flaky(lambda r: r.method == "POST", fail=2)
    with up.client(transport=flaky) as c:
        with pytest.raises(errors.Unavailable) as info:
            c.upload(DATA / "dataset.tar.gz")
        assert info.value.http_status == 503
        assert flaky.requests == [("POST", "/v1/uploads")]
        with pytest.raises(errors.Unavailable):
            c.submit_job("upl_x", avatar_id="x", idempotency_key=None)  # no key: a retry could make two jobs
        assert flaky.requests[-1] == ("POST", "/v1/jobs") and len(flaky.requests) == 2


def test_a_call_past_its_timeout_raises_timeout_and_is_not_retried():
    silent = socket.create_server(("127.0.0.1", 0))  # accepts, never answers
    held = []
    threading.Thread(target=lambda: held.append(silent.accept()), daemon=True).start()
    try:
        with Client(f"http://127.0.0.1:{silent.getsockname()[1]}", timeout=0.5, api_key="k" * 20) as c:
            t0 = time.monotonic()
            with pytest.raises(errors.Timeout):
                c.get_job("job_x")
            assert time.monotonic() - t0 < 3
    finally:
        silent.close()


def test_nothing_listening_is_connection_failed_after_retries():
    free = socket.create_server(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    with Client(f"http://127.0.0.1:{port}", retry=FAST) as c, pytest.raises(errors.ConnectionFailed,
                                                                          match="cannot reach the server at"):
        c.list_avatars()


def test_keys_and_tls_settings_come_from_arguments_or_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("BLENDSPLAT_URL", "https://render.example:8443")
    monkeypatch.setenv("BLENDSPLAT_API_KEY", "bsk_fromenv")
    monkeypatch.delenv("BLENDSPLAT_GRPC_TARGET", raising=False)
    with Client() as c:
        assert c.settings.grpc_target == "render.example:50051" and c.settings.grpc_tls
        assert c.http.headers["authorization"] == "Bearer bsk_fromenv"
    with Client(api_key="bsk_arg", grpc_target="h:1", grpc_tls=False) as c:
        assert c.settings.metadata == (("authorization", "Bearer bsk_arg"),) and not c.settings.grpc_tls
    with pytest.raises(ValueError):
        Client("ftp://x")


# ------------------------------------------------------------------------------------------------ jobs
@pytest.fixture(scope="module")
def trained(up):
    """A dataset uploaded with progress and a short job trained on it, followed to its end by its events."""
    with up.client() as c:
        sent, events = [], []
        upload = c.upload(DATA / "dataset.tar.gz", progress=lambda n, total: sent.append((n, total)))
        job = c.submit_job(upload["upload_id"], preset="tiny", iterations=5, avatar_id="client-job")
        done = c.wait(job["id"], on_event=events.append, timeout=600)
        return upload, sent, job, done, events


def test_upload_submit_and_wait_with_progress_events(up, trained):
    upload, sent, job, done, events = trained
    assert upload["kind"] == "dataset" and sent[-1][0] == sent[-1][1] == (DATA / "dataset.tar.gz").stat().st_size
    assert job["state"] in ("queued", "running") and done["state"] == "succeeded"
    assert [e.data["iteration"] for e in events if e.event == "progress" and e.data.get("iteration")][-1] == 5
    assert any(e.event == "state" and e.data["state"] == "succeeded" for e in events)
    with up.client() as c:
        assert "psnr_head" in json.loads(c.artefact(job["id"], "report")) or c.artefact(job["id"], "report")
        assert c.get_upload(upload["upload_id"])["upload_id"] == upload["upload_id"]
        assert upload["upload_id"] in {u["upload_id"] for u in c.list_uploads()}
        assert c.get_avatar("client-job")["trained"] is True


def test_jobs_page_by_page_cancel_delete_and_a_retried_submit(up, trained):
    upload = trained[0]
    flaky = Flaky(lambda r: r.method == "POST" and r.url.path == "/v1/jobs")
    with up.client(transport=flaky) as c:
        second = c.submit_job(upload["upload_id"], iterations=5000, avatar_id="client-job-2")  # retried once
        assert [p for p in flaky.requests if p == ("POST", "/v1/jobs")] == [("POST", "/v1/jobs")] * 2
        ids = [j["id"] for j in c.jobs(page_size=1)]
        assert ids[:2] == [second["id"], trained[2]["id"]] and len(ids) == len(set(ids))
        assert c.cancel_job(second["id"])["id"] == second["id"]
        with pytest.raises(errors.JobFailed) as info:
            c.wait(second["id"], timeout=120)
        assert info.value.job["state"] == "cancelled"
        assert c.delete_job(second["id"]) is None
        with pytest.raises(errors.NotFound) as missing:
            c.get_job(second["id"])
        assert missing.value.field == "job_id"
        with pytest.raises(errors.InvalidArgument) as bad:
            c.submit_job(upload["upload_id"], iterations=-1, avatar_id="x")
        assert bad.value.field == "iterations"


# ------------------------------------------------------------------------------------------------ jobs, fake servers
def fake_job(state: str) -> dict:
    return {"id": "job_fake", "state": state, "spec": {"avatar_id": "fake"}, "progress": {}, "error": None}


def wait_on_fake(asynchronous: bool, handler, **kw) -> tuple[dict, list[float]]:
    """``wait("job_fake", **kw)`` of the sync or asyncio client on a fake server (``handler``): (the job, the
    pauses it took)."""
    naps: list[float] = []
    transport = httpx.MockTransport(handler)
    if not asynchronous:
        with Client("http://fake", api_key="", transport=transport, retry=FAST) as c:
            c._sleep = naps.append
            return c.wait("job_fake", **kw), naps

    async def main():
        async def nap(seconds: float) -> None:
            naps.append(seconds)

        async with AsyncClient("http://fake", api_key="", transport=transport, retry=FAST) as c:
            c._sleep = nap
            return await c.wait("job_fake", **kw)

    return asyncio.run(main()), naps


@pytest.mark.parametrize("asynchronous", [False, True], ids=["sync", "asyncio"])
@pytest.mark.parametrize("route", ["missing", "not-sse", "failing"])
def test_wait_polls_where_the_event_stream_is_missing_or_keeps_failing(asynchronous, route):
    """No events route (404), a route that is not an event stream, or one that keeps failing (503): the job is read
    every ``poll_seconds``, each read to ``on_job``; a job that is missing is an error, not a fallback."""
    states = iter(["queued"] + ["running"] * 4 + ["succeeded"])
    paths: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        paths.append(request.url.path)
        if request.url.path.endswith("/events"):
            if route == "missing":
                return httpx.Response(404, json={"error": {"code": "NOT_FOUND", "message": "Not Found"}})
            if route == "not-sse":
                return httpx.Response(200, json={"hello": "world"})
            return httpx.Response(503, json={"error": {"code": "UNAVAILABLE", "message": "draining"}})
        return httpx.Response(200, json=fake_job(next(states)))

    reads: list[str] = []
    job, naps = wait_on_fake(asynchronous, handler, on_job=lambda j: reads.append(j["state"]), poll_seconds=2.0,
                             check=False)
    assert job["state"] == "succeeded" and reads == ["queued"] + ["running"] * 4 + ["succeeded"]
    streams = paths.count("/v1/jobs/job_fake/events")
    if route == "failing":  # reconnects with a backoff, then polling
        assert streams == 3 and naps == [0.5, 1.0, 2.0, 2.0]
    else:
        assert streams == 1 and naps == [2.0] * 4

    def gone(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events") or paths:
            paths.append(request.url.path)
            return httpx.Response(404, json={"error": {"code": "NOT_FOUND", "message": "no job 'job_fake'",
                                                       "field": "job_id"}})
        return httpx.Response(200, json=fake_job("running"))

    paths.clear()
    with pytest.raises(errors.NotFound) as info:
        wait_on_fake(asynchronous, gone)
    assert info.value.field == "job_id" and paths == ["/v1/jobs/job_fake/events", "/v1/jobs/job_fake"]


@pytest.mark.parametrize("asynchronous", [False, True], ids=["sync", "asyncio"])
def test_wait_resumes_after_the_last_event_and_reports_a_deleted_job(asynchronous):
    def sse(*events: tuple[str | None, str, dict]) -> bytes:
        return b"".join((f"id: {i}\n" if i else "").encode() + f"event: {kind}\ndata: {json.dumps(data)}\n\n".encode()
                        for i, kind, data in events)

    bodies = iter([sse(("1", "state", {"state": "running"}), ("2", "progress", {"iteration": 3})),  # then closed
                   sse(("3", "progress", {"iteration": 6}), ("4", "state", {"state": "succeeded"}))])
    resumed: list[str | None] = []

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            resumed.append(request.headers.get("Last-Event-ID"))
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=next(bodies))
        return httpx.Response(200, json=fake_job("succeeded" if len(resumed) == 2 else "running"))

    events: list = []
    job, naps = wait_on_fake(asynchronous, handler, on_event=events.append)
    assert job["state"] == "succeeded" and resumed == [None, "2"] and naps == []
    assert [e.id for e in events] == ["1", "2", "3", "4"]

    def deleted(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, headers={"content-type": "text/event-stream; charset=utf-8"},
                                  content=sse((None, "end", {"state": "deleted"})))
        return httpx.Response(200, json=fake_job("running"))

    with pytest.raises(errors.NotFound, match="job job_fake was deleted"):
        wait_on_fake(asynchronous, deleted)
    with pytest.raises(errors.Timeout, match="timed out after 0.2 s waiting for job job_fake"):
        wait_on_fake(asynchronous, lambda r: httpx.Response(404 if r.url.path.endswith("/events") else 200,
                                                            json=fake_job("running")), timeout=0.2)


def test_an_upload_sends_exactly_its_content_length(tmp_path):
    """A file that shrinks while it is sent raises OSError (the request's Content-Length would be a lie); the
    progress is (bytes sent, total) after each MiB."""
    from blendsplat_client._rest import CHUNK

    path = tmp_path / "take.tar.gz"
    path.write_bytes(os.urandom(2 * CHUNK + 5))
    seen: list[tuple[int, int]] = []

    def handler(request: httpx.Request) -> httpx.Response:
        body = request.read()
        assert len(body) == int(request.headers["Content-Length"])
        return httpx.Response(201, json={"upload_id": "upl_x"})

    with Client("http://fake", api_key="", transport=httpx.MockTransport(handler)) as c:
        assert c.upload(path, progress=lambda sent, total: seen.append((sent, total)))["upload_id"] == "upl_x"
        assert seen == [(CHUNK, 2 * CHUNK + 5), (2 * CHUNK, 2 * CHUNK + 5), (2 * CHUNK + 5, 2 * CHUNK + 5)]

        def shrink(sent: int, total: int) -> None:
            with open(path, "r+b") as f:
                f.truncate(CHUNK + 10)

        with pytest.raises(OSError, match="shrank while it was sent"):
            c.upload(path, progress=shrink)


def test_framework_answers_and_unreachable_servers_read_well():
    error = errors.from_http(405, b'{"detail": "Method Not Allowed"}', {})
    assert error.message == "Method Not Allowed" and error.http_status == 405
    assert isinstance(errors.error_for("UNIMPLEMENTED", "no such call"), errors.Unimplemented)


# ------------------------------------------------------------------------------------------------ asyncio
def test_the_async_client_has_the_same_calls(up, trained):
    async def main():
        async with up.aclient() as c:
            assert any(a["id"] == "demo" for a in await c.list_avatars())
            with pytest.raises(errors.NotFound):
                await c.get_avatar("nope")
            async with c.stream("demo", size=64) as s:
                await s.send(expression={"jawOpen": 0.3})
                frame = await s.receive()
                assert frame.index == 1 and frame.image.shape == (64, 64, 3)
                assert [f.index async for f in s.render(poses()[:3])] == [2, 3, 4]
            assert s.final.frames_sent == 4

            async def one(n: int) -> int:
                async with c.stream("demo", size=48, camera={"yaw": 5.0 * n}) as st:
                    return len([f async for f in st.render(poses()[:4])])

            assert await asyncio.gather(*(one(n) for n in range(3))) == [4, 4, 4]
            with pytest.raises(errors.NotFound):
                await c.stream("nope").open()
            assert (await c.render("demo", 32)).width == 32
            job_id = trained[2]["id"]
            assert [j["id"] async for j in c.jobs(page_size=1)][-1] == job_id
            events = [e async for e in c.events(job_id)]
            assert events[-1].event == "end" and (await c.wait(job_id))["state"] == "succeeded"
            assert (await c.download(job_id, "summary", up.log.parent / "summary.json")).stat().st_size > 0

    asyncio.run(main())


def test_async_retries_and_timeouts(up):
    async def main():
        flaky = httpx.AsyncHTTPTransport()
        calls = []

        class AsyncFlaky(httpx.AsyncBaseTransport):
            async def handle_async_request(self, request):
                calls.append(request.method)
                if len(calls) == 1:
                    return httpx.Response(503, json={"error": {"code": "UNAVAILABLE", "message": "x", "field": ""}})
                return await flaky.handle_async_request(request)

        async with up.aclient(transport=AsyncFlaky()) as c:
            assert await c.list_avatars()
            assert calls == ["GET", "GET"]
            async with c.stream("demo", size=32) as s:
                with pytest.raises(errors.Timeout):
                    await s.receive(timeout=0.2)

    asyncio.run(main())


# ------------------------------------------------------------------------------------------------ examples
@pytest.mark.slow
@pytest.mark.parametrize("example", sorted(p.name for p in (CLIENT / "examples").glob("*.py")))
def test_the_examples_run_as_written(up, example, tmp_path):
    env = {**up.env, "BLENDSPLAT_EXAMPLE_ITERATIONS": "5", "PYTHONPATH": str(CLIENT)}
    out = subprocess.run([sys.executable, str(CLIENT / "examples" / example)], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if "frames" in result:
        assert result["frames"] > 0
        if result.get("out"):
            import av

            with av.open(str(tmp_path / result["out"])) as video:
                assert sum(1 for _ in video.decode(video=0)) == result["frames"]
    else:
        assert result["state"] == "succeeded" and result["job"].startswith("job_")
