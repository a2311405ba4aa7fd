"""Hardening (issue 28), against the real servers with keys on: slow and half-open HTTP clients cannot hold
connections (a request head must arrive within ``header_timeout_seconds``, a stalled or trickled body is closed,
connections are capped per server and per client address; readiness, other addresses and gRPC go on), streams that
outlast the timeouts are never cut, and single-frame renders go through the fair scheduler under a per-key limit
(``key_max_renders``)."""

from __future__ import annotations

import json
import socket
import statistics
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import grpc
import httpx
import pytest
from conftest import LiveServer
from grpc_health.v1 import health_pb2, health_pb2_grpc

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from service.http.connections import BODY_GRACE_SECONDS, ConnectionGuard
from tests.test_service import WsStream

HEAD = 2.5  # header_timeout_seconds of the module's server
BODY = 0.5  # body_timeout_seconds
PER_ADDRESS = 48  # max_connections_per_address (the 40 half-sent requests fit under it)
RENDERS = 2  # key_max_renders


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = LiveServer(tmp_path_factory.mktemp("hardening-connections") / "data", auth="keys",
                   header_timeout_seconds=HEAD, body_timeout_seconds=BODY, max_connections_per_address=PER_ADDRESS,
                   key_max_renders=RENDERS, events_keepalive_seconds=0.3)
    yield s
    s.stop()


def make_key(server, tenant: str, *scopes: str) -> str:
    return server.keys.create(tenant, scopes or ("render",))[1]


def auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def connect(server, source: str) -> socket.socket:
    return socket.create_connection(("127.0.0.1", server.service.http_port), timeout=10, source_address=(source, 0))


def closed_within(sockets: list[socket.socket], limit: float) -> tuple[list[socket.socket], bytes]:
    """Read every socket until the server closes it or ``limit`` seconds pass: (the ones still open, what one of
    them was told)."""
    deadline, open_, told = time.monotonic() + limit, list(sockets), b""
    while open_ and time.monotonic() < deadline:
        for s in list(open_):
            s.settimeout(0.05)
            try:
                data = s.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                data = b""
            told = told or data
            if not data:
                open_.remove(s)
    return open_, told


def wait_until(predicate, limit: float = 10) -> None:
    deadline = time.monotonic() + limit
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def grpc_serving(server) -> bool:
    with grpc.insecure_channel(server.grpc_target) as channel:
        reply = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=5)
    return reply.status == health_pb2.HealthCheckResponse.SERVING


# ------------------------------------------------------------------------------------ heads and bodies
def test_half_sent_request_heads_are_closed_within_the_header_timeout_while_readyz_answers(server):
    socks = []
    try:
        for _ in range(40):
            s = connect(server, "127.0.0.2")
            s.sendall(b"GET /readyz HTTP/1.1\r\nHost: x\r\nX-Slow: ")
            socks.append(s)
        t0 = time.monotonic()
        assert httpx.get(server.http_url + "/readyz", timeout=5).status_code == 200  # meanwhile, another client
        assert grpc_serving(server)
        still_open, told = closed_within(socks, HEAD + 3)
        assert not still_open, f"{len(still_open)} of 40 half-sent requests still open after {HEAD + 3:g} s"
        assert time.monotonic() - t0 > HEAD * 0.5  # closed by the timer, not refused at once
        assert told.startswith(b"HTTP/1.1 408") and b"header_timeout_seconds" in told, told
    finally:
        for s in socks:
            s.close()
    assert httpx.get(server.http_url + "/readyz", timeout=5).status_code == 200


def test_an_idle_connection_that_never_sends_a_head_is_closed(server):
    s = connect(server, "127.0.0.1")
    try:
        still_open, told = closed_within([s], HEAD + 3)
        assert not still_open and told == b""  # nothing came: closed without an answer
    finally:
        s.close()


def test_a_stalled_body_is_answered_408_and_closed(server):
    s = connect(server, "127.0.0.1")
    try:
        s.sendall(b"POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n"
                  + f"Authorization: Bearer {server.api_key}\r\n\r\n".encode() + b'{"avatarId": ')
        t0 = time.monotonic()
        still_open, told = closed_within([s], BODY + BODY_GRACE_SECONDS + 3)
        assert not still_open and told.startswith(b"HTTP/1.1 408"), told
        assert time.monotonic() - t0 >= BODY * 0.8
    finally:
        s.close()


def test_a_trickled_body_that_no_route_reads_cannot_hold_the_connection(server):
    """No key: the answer (401) comes before the body is read; the client goes on sending a byte every 0.1 s (which
    kept uvicorn's own keep-alive timer from ever firing). The rest of the body and the next head have the header
    timeout: the connection is closed."""
    s = connect(server, "127.0.0.2")
    try:
        s.sendall(b"POST /v1/render HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 100000\r\n\r\n{")
        t0, received, closed = time.monotonic(), b"", False
        s.settimeout(0.1)
        while time.monotonic() - t0 < HEAD + 4 and not closed:
            try:
                s.sendall(b" ")
                data = s.recv(65536)
                received += data
                closed = not data
            except TimeoutError:
                continue
            except OSError:
                closed = True
        assert received.startswith(b"HTTP/1.1 401"), received[:100]
        assert closed, f"a trickled body held the connection for {time.monotonic() - t0:.1f} s"
    finally:
        s.close()


# ------------------------------------------------------------------------------------------ connection caps
def test_connections_over_the_per_address_cap_are_refused_while_other_addresses_and_grpc_are_served(server):
    guard: ConnectionGuard = server.service.connections
    held = []
    try:
        for _ in range(PER_ADDRESS):
            held.append(connect(server, "127.0.0.3"))
        wait_until(lambda: guard.from_address("127.0.0.3") == PER_ADDRESS, limit=HEAD * 0.4)
        extra = connect(server, "127.0.0.3")
        t0 = time.monotonic()
        still_open, told = closed_within([extra], 1.0)
        extra.close()
        assert not still_open and time.monotonic() - t0 < HEAD * 0.5, "over the cap: not refused at once"
        assert told.startswith(b"HTTP/1.1 503") and b"max_connections_per_address" in told, told
        assert b"retry-after:" in told.lower()
        with httpx.Client(transport=httpx.HTTPTransport(local_address="127.0.0.4"), timeout=5) as other:
            assert other.get(server.http_url + "/readyz").status_code == 200  # another address is served
        assert grpc_serving(server)
        assert guard.from_address("127.0.0.3") == PER_ADDRESS  # the refused one was never counted
    finally:
        for s in held:
            s.close()
    wait_until(lambda: guard.from_address("127.0.0.3") == 0)


def test_the_guard_counts_connections_per_server_and_per_address():
    class Transport:
        def __init__(self, address):
            self.address = address

        def get_extra_info(self, name):
            return (self.address, 1234) if name == "peername" else None

    guard = ConnectionGuard(max_connections=3, max_per_address=2, header_timeout=1, body_timeout=1)
    a1, a2, a3, b1, c1 = (Transport(x) for x in ("a", "a", "a", "b", "c"))
    assert guard.admit(a1) is None and guard.admit(a2) is None
    assert "max_connections_per_address" in guard.admit(a3)
    assert guard.admit(a1) is None and guard.open == 2  # the same transport again (a WebSocket): counted once
    assert guard.admit(b1) is None
    assert "max_connections" in guard.admit(c1)  # the server's cap
    guard.release(a1)
    guard.release(a1)  # once only
    assert guard.open == 2 and guard.from_address("a") == 1
    assert guard.admit(c1) is None


# ------------------------------------------------------------------------------------------------ streams
def test_streams_that_outlast_the_header_and_body_timeouts_are_not_cut(server):
    """A WebSocket render stream and a job's event stream (SSE) both run past every timeout of the guard."""
    span = HEAD + BODY + BODY_GRACE_SECONDS + 1
    job = server.service.training.jobs.submit({"upload_id": "upl_x", "avatar_id": "sse"}).id
    sse: dict = {}

    def read_events() -> None:
        t0, chunks = time.monotonic(), 0
        with httpx.stream("GET", f"{server.http_url}/v1/jobs/{job}/events", headers=server.headers,
                          timeout=httpx.Timeout(10, read=5)) as r:
            sse["status"] = r.status_code
            for _ in r.iter_raw():
                chunks += 1
                if time.monotonic() - t0 > span:
                    break
        sse["seconds"], sse["chunks"] = time.monotonic() - t0, chunks

    reader = threading.Thread(target=read_events)
    reader.start()
    stream = WsStream(server.ws_url, api_key=make_key(server, "ws-long"), avatar_id="demo", width=32, height=32)
    try:
        assert stream.next().HasField("header")
        t0, index = time.monotonic(), 0
        while time.monotonic() - t0 < span:
            index += 1
            stream.send(frame=pb.FrameParams(index=index))
            reply = stream.next()
            assert reply.HasField("frame"), reply
            stream.send(ack=pb.Ack(index=index))
            time.sleep(0.4)
    finally:
        stream.close()
        reader.join(span + 15)
    assert sse["status"] == 200 and sse["seconds"] > span and sse["chunks"] >= 3, sse


# ------------------------------------------------------------------------------------------- single renders
def test_single_renders_of_one_key_are_limited_over_http_and_grpc(server):
    """The render thread held: a key's first RENDERS renders wait in the scheduler; one more is refused at once on
    either transport, naming key_max_renders; another key is not; when the thread is free every waiting one is
    answered."""
    token, other = make_key(server, "renders-a"), make_key(server, "renders-b")
    body = {"avatarId": "demo", "width": 32, "height": 32}
    url, engine = server.http_url + "/v1/render", server.engine
    blocker = threading.Event()
    engine._pool.submit(blocker.wait, 30)  # the render thread is busy until released
    with ThreadPoolExecutor(RENDERS + 1) as pool:
        try:
            waiting = [pool.submit(httpx.post, url, json=body, headers=auth(token), timeout=60)
                       for _ in range(RENDERS)]
            wait_until(lambda: len(engine.singles) == RENDERS)
            refused = httpx.post(url, json=body, headers=auth(token), timeout=10)
            assert refused.status_code == 429 and "Retry-After" in refused.headers, refused.text
            assert "key_max_renders" in refused.json()["error"]["message"], refused.text
            with grpc.insecure_channel(server.grpc_target) as channel:
                with pytest.raises(grpc.RpcError) as caught:
                    pb_grpc.RenderServiceStub(channel).Render(
                        pb.RenderRequest(avatar_id="demo", width=32, height=32),
                        metadata=(("authorization", f"Bearer {token}"),), timeout=10)
            assert caught.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "key_max_renders" in caught.value.details()
            another = pool.submit(httpx.post, url, json=body, headers=auth(other), timeout=60)
            wait_until(lambda: len(engine.singles) == RENDERS + 1)  # another key's render waits, not refused
        finally:
            blocker.set()
        assert [f.result().status_code for f in [*waiting, another]] == [200] * (RENDERS + 1)
    assert httpx.post(url, json=body, headers=auth(token), timeout=30).status_code == 200  # slots given back


def test_single_renders_share_the_render_thread_fairly_with_a_stream(server):
    """One key fires many large single renders at once (an admin key: no per-key limit, so only the scheduler
    stands between them and the stream); another key's stream keeps getting frames: its longest gap between frames
    stays near one large render, not the whole queue of them (first come, first served on the render thread gives
    about ``flooders`` of them). Figures are relative to the large render's own time, measured alone and under
    the flood (a noisy machine slows both)."""
    heavy = {"avatarId": "demo", "width": 2048, "height": 2048, "codec": "CODEC_JPEG"}
    url, flooders = server.http_url + "/v1/render", 12
    alone = min(_render_seconds(httpx.post(url, json=heavy, headers=server.headers, timeout=60)) for _ in range(2))
    arrivals: list[float] = []
    render_times: list[float] = []
    stop = threading.Event()

    def flood() -> None:
        with httpx.Client(headers=server.headers, timeout=60) as client:
            while not stop.is_set():
                render_times.append(_render_seconds(client.post(url, json=heavy)))

    with grpc.insecure_channel(server.grpc_target) as channel:
        driver = _StreamDriver(pb_grpc.RenderServiceStub(channel), make_key(server, "fair-stream"), arrivals)
        try:
            time.sleep(1.0)
            baseline = _max_gap(arrivals, arrivals[0] + 0.3 if arrivals else 0, time.monotonic())
            with ThreadPoolExecutor(flooders) as pool:
                futures = [pool.submit(flood) for _ in range(flooders)]
                start = time.monotonic() + 2 * alone  # the flood's requests all in
                time.sleep(max(3.0, 2 * flooders * alone))
                end = time.monotonic()
                stop.set()
                for f in futures:
                    f.result()
        finally:
            driver.close()
    one = max(alone, statistics.median(render_times))
    gap = _max_gap(arrivals, start, end)
    assert gap < 4 * one + baseline + 0.3, f"longest gap {gap:.2f} s; one large render {one:.2f} s"


def _render_seconds(r: httpx.Response) -> float:
    """A rendered frame's time on the render thread (its stages, not its wait)."""
    assert r.status_code == 200, r.text
    t = json.loads(r.headers["X-Blendsplat-Timings"])
    return (t["totalMs"] - t["queueMs"]) / 1e3


def _max_gap(times: list[float], start: float, end: float) -> float:
    """The longest time between frames in [start, end], its ends included."""
    inside = [start, *(t for t in times if start < t < end), end]
    return max(b - a for a, b in zip(inside, inside[1:], strict=False))


class _StreamDriver:
    """A gRPC render stream at 32 x 32 that sends the next pose and acks as soon as a frame comes, recording when
    each frame came."""

    def __init__(self, stub, token: str, arrivals: list[float]):
        import queue

        self._queue: queue.Queue = queue.Queue()
        self._queue.put(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=32, height=32)))
        self._queue.put(pb.StreamRequest(frame=pb.FrameParams(index=1)))
        self._responses = stub.RenderStream(iter(self._queue.get, None), metadata=(("authorization",
                                                                                    f"Bearer {token}"),))
        self._thread = threading.Thread(target=self._run, args=(arrivals,), daemon=True)
        self._thread.start()

    def _run(self, arrivals: list[float]) -> None:
        try:
            for reply in self._responses:
                if reply.HasField("frame"):
                    arrivals.append(time.monotonic())
                    index = reply.frame.index
                    self._queue.put(pb.StreamRequest(ack=pb.Ack(index=index)))
                    self._queue.put(pb.StreamRequest(frame=pb.FrameParams(index=index + 1)))
        except grpc.RpcError:
            pass

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(30)

