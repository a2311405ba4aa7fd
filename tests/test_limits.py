"""Per-key limits (service/access/limits.py): counted in the process, or shared by every replica through a real Redis
(127.0.0.1:6379; the Redis tests skip, saying why, when it is unreachable)."""

from __future__ import annotations

import queue
import socket
import time
import uuid

import grpc
import httpx
import pytest
from conftest import LiveServer

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from service.access.keys import KeyStore
from service.access.limits import LocalLimits, RateLimited, RedisLimits, no_release

REDIS_URL = "redis://127.0.0.1:6379/0"


@pytest.fixture(scope="module")
def redis_url():
    try:
        socket.create_connection(("127.0.0.1", 6379), timeout=2).close()
    except OSError as e:
        pytest.skip(f"Redis at 127.0.0.1:6379 is unreachable ({e})")
    return REDIS_URL


@pytest.fixture
def replicas(redis_url):
    """Two replicas' limits on one Redis, under a prefix of the test's own."""
    prefix = f"blendsplat-test:{uuid.uuid4().hex[:8]}:"
    made = []

    def make(**kw) -> RedisLimits:
        made.append(RedisLimits(redis_url, prefix=prefix, **kw))
        return made[-1]
    yield make
    for limits in made:
        limits.close()


# ------------------------------------------------------------------------------------------------- in process
def test_local_streams_stop_at_the_limit_and_come_back_once_per_release():
    limits = LocalLimits()
    first, second = limits.take_stream("k", 2), limits.take_stream("k", 2)
    with pytest.raises(RateLimited) as refused:
        limits.take_stream("k", 2)
    assert refused.value.retry_after >= 1 and refused.value.field == "authorization"
    limits.take_stream("other", 2)()  # another key has its own
    first()
    first()  # a second call gives back nothing more
    limits.take_stream("k", 2)
    with pytest.raises(RateLimited):
        limits.take_stream("k", 2)
    second()


def test_local_events_slide_out_of_their_window():
    limits = LocalLimits()
    limits.take_event("k", "uploads", 2, window=0.5)
    limits.take_event("k", "uploads", 2, window=0.5)
    with pytest.raises(RateLimited) as refused:
        limits.take_event("k", "uploads", 2, window=0.5)
    assert "2 uploads per hour" in str(refused.value)
    limits.take_event("k", "job submissions", 2, window=0.5)  # counted apart
    time.sleep(0.6)
    limits.take_event("k", "uploads", 2, window=0.5)


# ------------------------------------------------------------------------------------------------- Redis
def test_replicas_share_one_stream_limit_through_redis(replicas):
    a, b = replicas(), replicas()
    held = [a.take_stream("key1", 3), b.take_stream("key1", 3), a.take_stream("key1", 3)]
    for limits in (a, b):
        with pytest.raises(RateLimited):
            limits.take_stream("key1", 3)
    b.take_stream("key2", 3)()  # other keys are counted apart
    held.pop()()  # a gives one back: b may take it
    held.append(eventually(lambda: b.take_stream("key1", 3)))
    with pytest.raises(RateLimited):
        a.take_stream("key1", 3)
    assert a.held() == 1 and b.held() == 2


def test_a_replica_that_dies_frees_its_streams_when_their_leases_expire(replicas):
    dead, alive = replicas(lease_seconds=1.0), replicas(lease_seconds=1.0)
    dead.take_stream("key", 1)
    dead._stop.set()  # dies: no more renewals, nothing released
    with pytest.raises(RateLimited):
        alive.take_stream("key", 1)
    time.sleep(1.3)
    alive.take_stream("key", 1)


def test_leases_are_renewed_while_the_stream_lasts(replicas):
    holder, other = replicas(lease_seconds=0.6), replicas(lease_seconds=0.6)
    release = holder.take_stream("key", 1)
    time.sleep(1.5)  # past two lease lengths: renewed every 0.2 s
    with pytest.raises(RateLimited):
        other.take_stream("key", 1)
    release()
    eventually(lambda: other.take_stream("key", 1))


def eventually(take, seconds: float = 10):
    """``take()`` once it stops being refused (a release reaches Redis from a background thread)."""
    deadline = time.monotonic() + seconds
    while True:
        try:
            return take()
        except RateLimited:
            assert time.monotonic() < deadline, "still refused"
            time.sleep(0.02)


def test_replicas_share_hourly_windows_and_say_when_to_come_back(replicas):
    a, b = replicas(), replicas()
    a.take_event("key", "uploads", 2)
    b.take_event("key", "uploads", 2)
    with pytest.raises(RateLimited) as refused:
        a.take_event("key", "uploads", 2)
    assert 3590 <= refused.value.retry_after <= 3600
    b.take_event("key", "job submissions", 2)  # counted apart
    a.take_event("key2", "uploads", 1, window=0.3)  # the window decides what still counts
    with pytest.raises(RateLimited):
        b.take_event("key2", "uploads", 1, window=0.3)
    time.sleep(0.4)
    b.take_event("key2", "uploads", 1, window=0.3)


def test_an_unreachable_redis_fails_open_and_is_counted():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here once closed
    failures = []
    limits = RedisLimits(f"redis://127.0.0.1:{port}/0", timeout=0.2, on_failure=lambda: failures.append(1))
    try:
        assert limits.take_stream("key", 1) is no_release
        assert limits.take_stream("key", 1) is no_release
        limits.take_event("key", "uploads", 1)
        limits.take_event("key", "uploads", 1)
        assert len(failures) == 4
    finally:
        limits.close()


def test_a_redis_that_accepts_but_never_answers_fails_open_after_the_timeout():
    silent = socket.create_server(("127.0.0.1", 0))  # accepts connections (the backlog), never answers
    failures = []
    limits = RedisLimits(f"redis://127.0.0.1:{silent.getsockname()[1]}/0", timeout=0.2,
                         on_failure=lambda: failures.append(1))
    try:
        assert limits.take_stream("key", 1) is no_release
        limits.take_event("key", "uploads", 1)
        assert len(failures) == 2
    finally:
        limits.close()
        silent.close()


def test_releasing_a_lease_hands_redis_the_work_and_close_gives_back_the_rest(replicas, redis_url):
    import redis

    limits = replicas()
    first, second = limits.take_stream("key", 5), limits.take_stream("key", 5)
    sets = redis.Redis.from_url(redis_url)
    key = f"{limits.prefix}streams:key"
    assert sets.zcard(key) == 2
    first()
    deadline = time.monotonic() + 10
    while sets.zcard(key) != 1:
        assert time.monotonic() < deadline, "the released lease stayed in Redis"
        time.sleep(0.02)
    limits.close()  # a stopping replica gives back what it still holds
    assert sets.zcard(key) == 0
    second()  # after close: nothing left to do, and no error


# ------------------------------------------------------------------------------------------------- end to end
def test_two_servers_enforce_one_stream_limit_per_key(tmp_path, redis_url):
    """Two real service processes' servers (one job database for the keys, one Redis): a key holding its one
    stream on the first replica is refused on the second, over gRPC and HTTP, until the stream ends."""
    common = {"auth": "keys", "jobs_url": f"sqlite:///{tmp_path / 'jobs.db'}", "redis_url": redis_url,
              "key_max_sessions": 1, "key_uploads_per_hour": 1}
    first = LiveServer(tmp_path / "a", **common)
    second = LiveServer(tmp_path / "b", **common)
    try:
        _, key = KeyStore(first.service.training.jobs.engine).create("tenant", ["render", "jobs"])
        md = (("authorization", f"Bearer {key}"),)
        opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=16, height=16))
        with grpc.insecure_channel(first.grpc_target) as one, grpc.insecure_channel(second.grpc_target) as two:
            held: queue.Queue = queue.Queue()
            held.put(opened)
            stream = pb_grpc.RenderServiceStub(one).RenderStream(iter(held.get, None), metadata=md)
            assert next(stream).HasField("header")
            with pytest.raises(grpc.RpcError) as refused:
                list(pb_grpc.RenderServiceStub(two).RenderStream(iter([opened]), metadata=md))
            assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            held.put(None)
            list(stream)  # ended on the first replica: its lease is given back
            deadline = time.monotonic() + 10
            while True:
                again = pb_grpc.RenderServiceStub(two).RenderStream(iter([opened]), metadata=md)
                try:
                    assert next(again).HasField("header")
                    break
                except grpc.RpcError as e:  # the release reaches Redis a moment after the stream ends
                    assert e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and time.monotonic() < deadline
                    time.sleep(0.05)
            again.cancel()
        auth = {"Authorization": f"Bearer {key}"}
        r = httpx.post(first.http_url + "/v1/uploads", files={"file": ("v.tgz", b"x")}, headers=auth, timeout=30)
        assert r.status_code == 422  # counted (and refused for its content)
        r = httpx.post(second.http_url + "/v1/uploads", files={"file": ("v.tgz", b"x")}, headers=auth, timeout=30)
        assert r.status_code == 429 and int(r.headers["retry-after"]) > 3000, r.text
    finally:
        second.stop()
        first.stop()
