"""Hardening, second round (a hostile probe against real servers with keys on): other tenants' ids never appear in
an answer (adapters picked per tenant: tests/test_adapter_service.py), event cursors past a bigint are a named 4xx,
no server path reaches a client, and a revoked key's open streams end within seconds."""

from __future__ import annotations

import json
import os
import queue
import time

import grpc
import httpx
import pytest
from conftest import LiveServer

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from tests.test_service import GrpcStream, WsStream
from tests.test_webhooks import FAST, SECRET, Receiver

CHECK = 0.5  # stream_key_check_seconds of the module's server
LIMIT = 10 * CHECK + 5  # the seconds a stream may take to end (without the check they never would)


class BoundedGrpcStream(GrpcStream):
    """tests/test_service.py's GrpcStream with a deadline: a stream that never ends fails the test, not hangs it."""

    def __init__(self, stub, api_key: str, **config):
        self._requests = queue.Queue()
        self._requests.put(pb.StreamRequest(open=pb.SessionConfig(**config)))
        self._responses = stub.RenderStream(iter(self._requests.get, None), timeout=LIMIT + 10,
                                            metadata=(("authorization", f"Bearer {api_key}"),))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = LiveServer(tmp_path_factory.mktemp("hardening2") / "data", auth="keys", stream_key_check_seconds=CHECK,
                   webhook_secret=SECRET, **FAST)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.http_url, timeout=60) as client:
        yield client


def make_key(server, tenant: str, *scopes: str) -> tuple[str, str]:
    key, token = server.keys.create(tenant, scopes or ("render",))
    return key.id, token


def auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def upload(http, headers, archive: bytes) -> str:
    r = http.post("/v1/uploads", files={"file": ("v.tgz", archive)}, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()["upload_id"]


def submit(http, headers, upload_id: str, avatar_id: str, **spec) -> str:
    r = http.post("/v1/jobs", json={"upload_id": upload_id, "preset": "tiny", "iterations": 5,
                                    "avatar_id": avatar_id, **spec}, headers=headers)
    assert r.status_code == 201, r.text
    return r.json()["id"]


# --------------------------------------------------------------------------------------------- 1. ids
def test_not_found_answers_never_list_another_tenants_ids(server, http, tmp_path):
    _, a = make_key(server, "tenant-a", "avatars:write", "render")
    _, b = make_key(server, "tenant-b", "render")
    write_bundle(synth_avatar(gaussians=300, blendshapes=3, seed=2), tmp_path / "a.bundle", precision="fp16")
    r = http.put("/v1/avatars/secret-avatar-a", content=(tmp_path / "a.bundle").read_bytes(), headers=auth(a))
    assert r.status_code == 201, r.text
    answers = [http.get("/v1/avatars/no-such-avatar", headers=auth(b)),
               http.post("/v1/avatars/no-such-avatar/load", headers=auth(b)),
               http.post("/v1/render", json={"avatarId": "no-such-avatar", "width": 32}, headers=auth(b)),
               http.get("/v1/adapters/no-such-adapter", headers=auth(b))]
    for r in answers:
        assert r.status_code == 404 and "secret-avatar-a" not in r.text and "demo" not in r.text, r.text
    with grpc.insecure_channel(server.grpc_target) as channel:
        with pytest.raises(grpc.RpcError) as caught:
            pb_grpc.RenderServiceStub(channel).GetAvatar(pb.GetAvatarRequest(id="no-such-avatar"),
                                                         metadata=(("authorization", f"Bearer {b}"),))
    assert caught.value.code() == grpc.StatusCode.NOT_FOUND and "secret-avatar-a" not in caught.value.details()
    # another tenant's resource: 403 on every route, the same answer however it is reached (documented choice)
    assert http.get("/v1/avatars/secret-avatar-a", headers=auth(b)).status_code == 403


# ------------------------------------------------------------------------------------------ 2. cursors
def test_event_cursors_past_a_bigint_are_a_named_4xx(server, http, tiny_video_archive):
    job = submit(http, server.headers, upload(http, server.headers, tiny_video_archive), "cursor-check")
    url = f"/v1/jobs/{job}/events"
    for value in (2**63, 2**64, 10**19):
        r = http.get(url, headers=server.headers | {"Last-Event-ID": str(value)})
        assert r.status_code == 422 and r.json()["error"]["field"] == "Last-Event-ID", r.text
        r = http.get(url, params={"after": value}, headers=server.headers)
        assert r.status_code == 422 and r.json()["error"]["field"] == "after", r.text
    with http.stream("GET", url, headers=server.headers | {"Last-Event-ID": str(2**63 - 1)}) as r:
        assert r.status_code == 200
    assert http.delete(f"/v1/jobs/{job}", headers=server.headers).status_code == 204


# ---------------------------------------------------------------------------------------------- 3. paths
def test_no_server_path_reaches_a_client_in_a_scripted_session(server, http, tiny_video_archive):
    """Upload, a job that fails (a face model the server lacks: the error names its folder), one that succeeds
    (summary.json records the bundle's path), their answers, events and webhooks, and /readyz, an avatar and a
    load with the bundle store gone: no body carries the data folder's path."""
    from service.jobs.worker import Worker

    settings = server.service.settings
    data = str(settings.data_dir.absolute())
    receiver = Receiver(failures=0)
    bodies: list[tuple[str, str]] = []
    try:
        h = server.headers
        flame = upload(http, h, tiny_video_archive)
        record = settings.upload_dir / flame / "upload.json"  # as if the dataset had been tracked with FLAME
        record.write_text(json.dumps({**json.loads(record.read_text()), "face_model": "flame-2023"}))
        failing = submit(http, h, flame, "never", webhook_url=receiver.url)
        good = submit(http, h, upload(http, h, tiny_video_archive), "path-check", webhook_url=receiver.url)
        with Worker(settings, worker_id="w") as worker:
            assert {worker.run_one().id, worker.run_one().id} == {failing, good}
        failed = http.get(f"/v1/jobs/{failing}", headers=h)
        assert failed.json()["state"] == "failed" and "facemodels" in failed.json()["error"], failed.text
        for job in (failing, good):
            bodies.append((f"job {job}", http.get(f"/v1/jobs/{job}", headers=h).text))
            bodies.append((f"events {job}", http.get(f"/v1/jobs/{job}/events", headers=h).text))
            for name in ("summary", "report", "log", "curves"):
                r = http.get(f"/v1/jobs/{job}/artefacts/{name}", headers=h)
                bodies.append((f"{name} {job} {r.status_code}", r.content.decode("latin-1")))
        summary = http.get(f"/v1/jobs/{good}/artefacts/summary", headers=h)
        assert summary.status_code == 200 and json.loads(summary.text)["bundle"], summary.text
        bundles = settings.bundle_dir
        os.rename(bundles, str(bundles) + ".away")
        try:
            for method, path, key in (("GET", "/readyz", {}), ("GET", "/v1/avatars/path-check", h),
                                      ("POST", "/v1/avatars/path-check/load", h), ("GET", "/v1/avatars", h)):
                r = http.request(method, path, headers=key)
                assert r.status_code >= 400 or path == "/v1/avatars", (path, r.status_code)
                bodies.append((f"{method} {path} {r.status_code}", r.text))
        finally:
            os.rename(str(bundles) + ".away", bundles)
        deadline = time.monotonic() + 30
        while len({r["body"]["data"]["job_id"] for r in receiver.requests if r["body"].get("data")}) < 2:
            assert time.monotonic() < deadline, f"webhooks: {receiver.requests}"
            time.sleep(0.1)
        bodies += [(f"webhook {r['id']}", r["raw"].decode()) for r in receiver.requests]
    finally:
        receiver.close()
    leaks = [(where, body[:300]) for where, body in bodies if data in body or str(settings.data_dir.resolve()) in body]
    assert not leaks
    assert any("bundles" in body for where, body in bodies if where.startswith("GET /readyz"))  # says which, relative


# ----------------------------------------------------------------------------------------- 4. revocation
def _until_status(stream, limit: float) -> tuple[pb.Status, float]:
    t0 = time.monotonic()
    while True:
        reply = stream.next()
        if reply.HasField("status"):
            return reply.status, time.monotonic() - t0
        assert time.monotonic() - t0 < limit, "the stream went on"


@pytest.mark.parametrize("transport", ["grpc", "websocket"])
def test_a_revoked_keys_render_stream_ends_unauthenticated_within_seconds(server, transport):
    key_id, token = make_key(server, f"revoked-{transport}", "render")
    config = dict(avatar_id="demo", width=32, height=32)
    if transport == "grpc":
        channel = grpc.insecure_channel(server.grpc_target)
        stream = BoundedGrpcStream(pb_grpc.RenderServiceStub(channel), token, **config)
    else:
        channel, stream = None, WsStream(server.ws_url, api_key=token, **config)
    try:
        assert stream.next().HasField("header")
        stream.send(frame=pb.FrameParams(index=1))
        assert stream.next().HasField("frame")
        server.keys.revoke(key_id)  # in the database, as another process (`blendsplat keys revoke`) does
        try:
            status, took = _until_status(stream, LIMIT)
        except grpc.RpcError as e:  # the status ended the call: its code is the call's
            status, took = pb.Status(code=pb.Code.Value(e.code().name)), 0.0
        assert status.code == pb.UNAUTHENTICATED and took < LIMIT, status
    finally:
        stream.close() if transport == "websocket" else None
        if channel is not None:
            channel.close()


def test_a_render_stream_ends_after_max_stream_seconds(server):
    _, token = make_key(server, "long-stream", "render")
    with grpc.insecure_channel(server.grpc_target) as channel:
        stream = BoundedGrpcStream(pb_grpc.RenderServiceStub(channel), token, avatar_id="demo", width=32, height=32)
        session_id = stream.next().header.session_id
        session = server.engine.sessions[session_id]
        session.opened -= server.service.settings.max_stream_seconds + 1  # as if it had been open that long
        try:
            status, _ = _until_status(stream, LIMIT)
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.UNAVAILABLE and "max_stream_seconds" in e.details()
        else:
            assert status.code == pb.UNAVAILABLE and "max_stream_seconds" in status.message


def test_a_revoked_keys_event_stream_ends(server, http, tiny_video_archive):
    key_id, token = make_key(server, "revoked-events", "jobs")
    job = submit(http, auth(token), upload(http, auth(token), tiny_video_archive), "events-revoked")
    with http.stream("GET", f"/v1/jobs/{job}/events", headers=auth(token),
                     timeout=httpx.Timeout(60, read=LIMIT)) as r:  # a keep-alive comes every 15 s only
        assert r.status_code == 200
        t0 = time.monotonic()
        server.keys.revoke(key_id)
        text = "".join(r.iter_text())  # the stream ends (a queued job's stream would go on for an hour)
    assert time.monotonic() - t0 < LIMIT
    assert "event: error" in text and "UNAUTHENTICATED" in text


# ------------------------------------------------------------------------------------------------ 5. webhooks
def test_a_webhook_url_is_never_logged_whole(server, http, tiny_video_archive, caplog):
    url = "http://127.0.0.1:9/hooks/blendsplat?token=s3cret-query-token"
    with caplog.at_level("INFO"):
        submit(http, server.headers, upload(http, server.headers, tiny_video_archive), "logged", webhook_url=url)
        time.sleep(1)  # the dispatcher's first attempt (refused connection) is logged too
    assert "s3cret-query-token" not in caplog.text and "hooks/blendsplat" not in caplog.text
    assert "http://127.0.0.1:9/..." in caplog.text


def test_multicast_broadcast_and_reserved_webhook_addresses_are_refused_like_private_ones(tmp_path):
    import ipaddress

    from service.jobs.webhooks import public_address
    from tests.test_webhooks import DeliveryStatus, JobStore, job_with_webhook, run_dispatcher
    from tests.test_webhooks import settings as webhook_settings
    for text in ("224.0.0.1", "239.255.255.250", "255.255.255.255", "240.0.0.1", "0.0.0.0", "ff02::1", "ff0e::1",
                 "::ffff:10.0.0.1", "::", "100.64.0.1"):
        assert not public_address(ipaddress.ip_address(text)), text
    for text in ("93.184.216.34", "2606:4700:4700::1111"):
        assert public_address(ipaddress.ip_address(text)), text
    config = webhook_settings(tmp_path, webhook_private_networks=False)
    urls = ["http://224.0.0.1/x", "http://239.255.255.250:1900/", "http://[ff0e::1]/"]
    with JobStore.open(config.jobs_database_url) as store:
        jobs = [job_with_webhook(store, u) for u in urls]
        run_dispatcher(config, store, lambda: all(store.deliveries(j)[0].status is DeliveryStatus.FAILED for j in jobs))
        deliveries = [store.deliveries(j)[0] for j in jobs]
    for delivery in deliveries:
        assert delivery.attempts == 1 and "not a public address" in delivery.last_error, delivery.last_error
