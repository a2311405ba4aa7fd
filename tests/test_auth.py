"""API keys, tenants, scopes, limits and TLS (issue 17) on the real servers (gRPC + HTTP on loopback).

The route and RPC walks are what keep a new endpoint from being added unprotected: every HTTP route and WebSocket
of the app, and every RPC of the proto, is called without a key, with a revoked key and with a key that lacks the
route's scope, and must be refused.
"""

from __future__ import annotations

import json
import logging
import os
import ssl
import subprocess
import sys
import time

import grpc
import httpx
import pytest
from conftest import LiveServer
from fastapi.routing import APIRoute, APIWebSocketRoute
from websockets.sync.client import connect

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from service.access.auth import CACHE_SECONDS
from service.access.http import OPEN_PATHS
from service.access.keys import ADMIN_TENANT, SCOPES
from service.errors import InvalidArgument, PermissionDenied
from service.grpc_server import SCOPES as RPC_SCOPES
from service.http.app import routes as app_routes
from service.jobs.artefacts import job_writer

SERVICE = pb.DESCRIPTOR.services_by_name["RenderService"]
QUOTA = 1 << 20  # tenant_storage_bytes of the module's server


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = LiveServer(tmp_path_factory.mktemp("auth"), auth="keys", key_max_sessions=1, key_uploads_per_hour=5,
                   key_jobs_per_hour=2, tenant_storage_bytes=QUOTA)
    yield s
    s.stop()


def make_key(server, tenant: str, *scopes: str) -> str:
    return server.keys.create(tenant, scopes or ("render",))[1]


def auth(key: str | None) -> dict:
    return {"Authorization": f"Bearer {key}"} if key else {}


def metadata(key: str | None):
    return (("authorization", f"Bearer {key}"),) if key else None


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.http_url, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def stub(server):
    with grpc.insecure_channel(server.grpc_target) as channel:
        yield pb_grpc.RenderServiceStub(channel)


def bundle_bytes(tmp_path, seed: int = 1, gaussians: int = 300) -> bytes:
    write_bundle(synth_avatar(gaussians=gaussians, blendshapes=3, seed=seed), tmp_path / f"{seed}.bundle",
                 precision="fp16")
    return (tmp_path / f"{seed}.bundle").read_bytes()


def route_scope(route: APIRoute | APIWebSocketRoute) -> str | None:
    """The scope a route's key dependency asks for (service.access.http.need names it), None when it has none."""
    for dependency in route.dependant.dependencies:
        name = getattr(dependency.call, "__name__", "")
        if name.startswith("needs_"):
            return name.removeprefix("needs_").replace("_", ":")
    return None


def protected_routes(server):
    routes = [(path, r) for path, r in app_routes(server.service.app)
              if path not in OPEN_PATHS and isinstance(r, APIRoute | APIWebSocketRoute)]
    assert len(routes) >= 15, [path for path, _ in routes]  # the avatar, render, upload and job routes
    return routes


def call(http, path: str, route: APIRoute, headers: dict) -> httpx.Response:
    path = path.format(**{name: "x-1" for name in route.param_convertors})
    method = sorted(route.methods - {"HEAD"})[0]
    return http.request(method, path, headers=headers, content=b"{}" if method in ("POST", "PUT") else None)


def ws_status(server, key: str | None, origin: str | None = None) -> pb.StreamResponse:
    protocols = ["blendsplat.v1"] + ([f"bearer.{key}"] if key else [])
    headers = {"Origin": origin} if origin else None
    with connect(server.ws_url, subprotocols=protocols, additional_headers=headers, open_timeout=30) as ws:
        ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=32, height=32)).SerializeToString())
        return pb.StreamResponse.FromString(ws.recv(timeout=30))


# ------------------------------------------------------------------------------------------------- walks
def test_every_http_route_needs_a_valid_key_with_its_scope(server, http):
    revoked = make_key(server, "walk", *SCOPES)
    server.keys.revoke(revoked.split("_")[1])
    for path, route in protected_routes(server):
        if isinstance(route, APIWebSocketRoute):
            assert route_scope(route) is None and path == "/v1/stream"  # its key: the next test
            continue
        scope = route_scope(route)
        assert scope in SCOPES, f"{path} declares no key dependency"
        for headers, expected in ((None, 401), (auth("bsk_0123456789_" + "A" * 43), 401), (auth(revoked), 401),
                                  ({"Authorization": "Basic dXNlcjpwYXNz"}, 401)):
            r = call(http, path, route, headers or {})
            assert r.status_code == expected, (path, route.methods, r.status_code, r.text)
            assert r.json()["error"]["code"] == "UNAUTHENTICATED" and r.headers["www-authenticate"].startswith("Bearer")
        others = [s for s in SCOPES if s not in (scope, "admin")]
        r = call(http, path, route, auth(make_key(server, "walk", *others)))
        assert r.status_code == 403, (path, r.status_code, r.text)
        assert r.json()["error"]["code"] == "PERMISSION_DENIED" and scope in r.json()["error"]["message"]


def test_open_routes_answer_without_a_key(server, http):
    for path in ("/healthz", "/readyz", "/metrics", "/openapi.json", "/docs", "/demo", "/jobs"):
        assert http.get(path).status_code == 200, path


def test_every_rpc_needs_a_valid_key_with_its_scope(server, stub):
    assert set(RPC_SCOPES) == {m.name for m in SERVICE.methods}  # a new RPC must say what it needs
    revoked = make_key(server, "walk", *SCOPES)
    server.keys.revoke(revoked.split("_")[1])
    requests = {"Render": pb.RenderRequest(avatar_id="demo", width=16, height=16),
                "ListAvatars": pb.ListAvatarsRequest(), "GetAvatar": pb.GetAvatarRequest(id="demo"),
                "LoadAvatar": pb.LoadAvatarRequest(id="demo"), "UnloadAvatar": pb.UnloadAvatarRequest(id="demo")}
    for method in SERVICE.methods:
        others = [s for s in SCOPES if s not in (RPC_SCOPES[method.name], "admin")]
        for key, code in ((None, grpc.StatusCode.UNAUTHENTICATED), (revoked, grpc.StatusCode.UNAUTHENTICATED),
                          (make_key(server, "walk", *others), grpc.StatusCode.PERMISSION_DENIED)):
            with pytest.raises(grpc.RpcError) as caught:
                if method.name == "RenderStream":
                    opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=16, height=16))
                    list(stub.RenderStream(iter([opened]), metadata=metadata(key)))
                else:
                    getattr(stub, method.name)(requests[method.name], metadata=metadata(key))
            assert caught.value.code() == code, (method.name, key, caught.value.details())


def test_a_websocket_needs_a_key_in_its_subprotocol_and_an_allowed_origin(server):
    assert ws_status(server, None).status.code == pb.UNAUTHENTICATED
    assert ws_status(server, make_key(server, "ws", "jobs")).status.code == pb.PERMISSION_DENIED
    key = make_key(server, "ws", "render")
    assert ws_status(server, key, origin="https://evil.example").status.code == pb.PERMISSION_DENIED
    with connect(server.ws_url, subprotocols=["blendsplat.v1", f"bearer.{key}"], open_timeout=30,
                 additional_headers={"Origin": server.http_url}) as ws:
        assert ws.subprotocol == "blendsplat.v1"  # never the key's
        ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=32, height=32)).SerializeToString())
        assert pb.StreamResponse.FromString(ws.recv(timeout=30)).HasField("header")


# ------------------------------------------------------------------------------------------------ tenants
def test_a_tenant_reads_and_changes_only_its_own_avatars_and_the_public_demo(server, http, stub, tmp_path):
    a, b = make_key(server, "tenant-a", "render", "avatars:write"), make_key(server, "tenant-b", "render",
                                                                             "avatars:write")
    assert http.put("/v1/avatars/owned-by-a", content=bundle_bytes(tmp_path), headers=auth(a)).status_code == 201
    assert (server.service.settings.bundle_dir / "owned-by-a.bundle.owner").is_file()
    assert http.get("/v1/avatars/owned-by-a", headers=auth(a)).status_code == 200
    for method, path in (("GET", "/v1/avatars/owned-by-a"), ("POST", "/v1/avatars/owned-by-a/load"),
                         ("POST", "/v1/avatars/owned-by-a/unload"), ("DELETE", "/v1/avatars/owned-by-a")):
        r = http.request(method, path, headers=auth(b))
        assert r.status_code == 403 and "another tenant" in r.json()["error"]["message"], (method, path, r.text)
    r = http.put("/v1/avatars/owned-by-a", content=bundle_bytes(tmp_path, 2), headers=auth(b))
    assert r.status_code == 403
    r = http.post("/v1/render", json={"avatarId": "owned-by-a", "width": 32}, headers=auth(b))
    assert r.status_code == 403
    with pytest.raises(grpc.RpcError) as caught:
        opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="owned-by-a", width=16, height=16))
        list(stub.RenderStream(iter([opened]), metadata=metadata(b)))
    assert caught.value.code() == grpc.StatusCode.PERMISSION_DENIED
    listed_b = {x["id"] for x in http.get("/v1/avatars", headers=auth(b)).json()["avatars"]}
    listed_admin = {x["id"] for x in http.get("/v1/avatars", headers=server.headers | {}).json()["avatars"]} \
        if server.headers else set()
    assert "owned-by-a" not in listed_b and "demo" in listed_b  # the demo is public
    assert {"owned-by-a", "demo"} <= listed_admin
    assert http.get("/v1/avatars/demo", headers=auth(b)).status_code == 200
    assert http.post("/v1/avatars/demo/unload", headers=auth(b)).status_code == 403  # public is not theirs
    assert http.post("/v1/render", json={"avatarId": "demo", "width": 32}, headers=auth(b)).status_code == 200
    assert http.delete("/v1/avatars/owned-by-a", headers=auth(a)).status_code == 204
    assert not (server.service.settings.bundle_dir / "owned-by-a.bundle.owner").exists()


def test_a_tenant_sees_only_its_own_uploads_and_jobs(server, http, tiny_video_archive):
    a, b = make_key(server, "jobs-a", "jobs"), make_key(server, "jobs-b", "jobs")
    r = http.post("/v1/uploads", files={"file": ("v.tgz", tiny_video_archive)}, headers=auth(a))
    assert r.status_code == 201, r.text
    upload = r.json()["upload_id"]
    assert http.get(f"/v1/uploads/{upload}", headers=auth(b)).status_code == 403
    assert upload not in {u["upload_id"] for u in http.get("/v1/uploads", headers=auth(b)).json()["uploads"]}
    body = {"upload_id": upload, "preset": "tiny", "iterations": 5, "avatar_id": "from-a"}
    assert http.post("/v1/jobs", json=body, headers=auth(b)).status_code == 403  # not b's upload
    r = http.post("/v1/jobs", json=body, headers=auth(a))
    assert r.status_code == 201, r.text
    job = r.json()["id"]
    assert server.service.training.jobs.get(job).tenant == "jobs-a"
    for method, path in (("GET", f"/v1/jobs/{job}"), ("POST", f"/v1/jobs/{job}/cancel"),
                         ("GET", f"/v1/jobs/{job}/events"), ("GET", f"/v1/jobs/{job}/artefacts/log"),
                         ("DELETE", f"/v1/jobs/{job}"), ("DELETE", f"/v1/uploads/{upload}")):
        assert http.request(method, path, headers=auth(b)).status_code == 403, (method, path)
    assert job not in {j["id"] for j in http.get("/v1/jobs", headers=auth(b)).json()["jobs"]}
    assert job in {j["id"] for j in http.get("/v1/jobs", headers=auth(a)).json()["jobs"]}
    assert http.delete(f"/v1/jobs/{job}", headers=auth(a)).status_code == 204
    assert http.delete(f"/v1/uploads/{upload}", headers=auth(a)).status_code == 204


def test_a_job_may_not_train_into_another_tenants_avatar(server, http, tmp_path, tiny_video_archive):
    owner = make_key(server, "holder", "avatars:write", "render")
    assert http.put("/v1/avatars/taken", content=bundle_bytes(tmp_path, 3), headers=auth(owner)).status_code == 201
    other = make_key(server, "grabber", "jobs")
    upload = http.post("/v1/uploads", files={"file": ("v.tgz", tiny_video_archive)}, headers=auth(other))
    r = http.post("/v1/jobs", json={"upload_id": upload.json()["upload_id"], "preset": "tiny", "iterations": 5,
                                    "avatar_id": "taken"}, headers=auth(other))
    assert r.status_code == 403 and "taken" in r.json()["error"]["message"]


# ------------------------------------------------------------------------------------------------- limits
def test_limits_per_key_answer_429_with_retry_after_and_admin_keys_are_exempt(server, http, stub, tiny_video_archive):
    key = make_key(server, "limited", "render", "jobs")
    opened = pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=16, height=16))
    import queue
    held: queue.Queue = queue.Queue()
    held.put(opened)
    first = stub.RenderStream(iter(held.get, None), metadata=metadata(key))
    assert next(first).HasField("header")  # the key's one stream
    with pytest.raises(grpc.RpcError) as caught:
        list(stub.RenderStream(iter([opened]), metadata=metadata(key)))
    assert caught.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "streams" in caught.value.details()
    admin = stub.RenderStream(iter([opened]), metadata=metadata(server.api_key))
    assert next(admin).HasField("header")  # admin keys have no limit
    held.put(None)
    list(first)
    statuses = []
    for _ in range(6):  # key_uploads_per_hour = 5
        statuses.append(http.post("/v1/uploads", files={"file": ("v.tgz", b"not an archive")}, headers=auth(key)))
    assert [r.status_code for r in statuses[:5]] == [422] * 5
    assert statuses[5].status_code == 429 and int(statuses[5].headers["retry-after"]) > 0
    assert statuses[5].json()["error"]["code"] == "RESOURCE_EXHAUSTED"


def test_a_keys_event_streams_count_against_its_stream_limit(server, http, tiny_video_archive):
    key = make_key(server, "follower", "jobs")  # key_max_sessions = 1 on this server
    upload = http.post("/v1/uploads", files={"file": ("v.tgz", tiny_video_archive)}, headers=auth(key))
    job = http.post("/v1/jobs", json={"upload_id": upload.json()["upload_id"], "preset": "tiny", "iterations": 5,
                                      "avatar_id": "followed"}, headers=auth(key)).json()["id"]
    with http.stream("GET", f"/v1/jobs/{job}/events", headers=auth(key)) as first:
        assert first.status_code == 200  # the job stays queued (no worker here): the stream stays open
        second = http.get(f"/v1/jobs/{job}/events", headers=auth(key))
        assert second.status_code == 429 and int(second.headers["retry-after"]) > 0
    assert http.post(f"/v1/jobs/{job}/cancel", headers=auth(key)).status_code == 202  # ended: a stream replays
    deadline = time.monotonic() + 10  # the first stream closed: its slot comes back once the server notices
    while (again := http.get(f"/v1/jobs/{job}/events", headers=auth(key))).status_code == 429:
        assert time.monotonic() < deadline, "the closed stream's slot never came back"
        time.sleep(0.2)
    assert again.status_code == 200 and "event: end" in again.text


def test_a_tenant_cannot_store_past_its_quota(server, http, tmp_path):
    key = make_key(server, "quota", "avatars:write")
    big = bundle_bytes(tmp_path, 9, gaussians=12_000)
    assert len(big) > QUOTA
    r = http.put("/v1/avatars/too-big", content=big, headers=auth(key))
    assert r.status_code == 429 and "quota" in r.json()["error"]["message"], r.text
    assert not (server.service.settings.bundle_dir / "too-big.bundle").exists()


def test_a_chunked_dataset_upload_over_the_quota_is_refused_after_its_body_and_nothing_is_kept(server, http,
                                                                                             tiny_video_archive):
    """A chunked body declares no length, so it is admitted on 0 bytes: the quota is checked again on what arrived
    (before anything is extracted), the refusal names the quota, and the upload store keeps nothing."""
    key = make_key(server, "chunked", "jobs")
    uploads = server.service.training.uploads

    def chunked(data: bytes):
        boundary = "q9q9q9"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"v.tgz\"\r\n"
                "Content-Type: application/gzip\r\n\r\n").encode()
        body = head + data + f"\r\n--{boundary}--\r\n".encode()
        headers = auth(key) | {"Content-Type": f"multipart/form-data; boundary={boundary}"}
        return http.post("/v1/uploads", content=iter([body[i:i + 65536] for i in range(0, len(body), 65536)]),
                         headers=headers)

    before = {u.id for u in uploads.list()}
    padding = b"\0" * (QUOTA + 4096)  # gzip ignores nothing: a body over the quota must be refused on its size
    r = chunked(padding)
    assert r.status_code in (413, 429, 507) and "quota" in r.json()["error"]["message"], r.text
    assert {u.id for u in uploads.list()} == before
    assert not [p for p in uploads.root.iterdir() if p.name.startswith(".")]  # no spool, no staging left
    ok = chunked(tiny_video_archive)  # under the quota: accepted
    assert ok.status_code == 201, ok.text
    assert {u.id for u in uploads.list()} - before == {ok.json()["upload_id"]}


def test_one_owner_rule_for_the_avatar_put_the_job_submission_and_the_workers_commit(server, http, tmp_path):
    """Another tenant's avatar: refused by the PUT, by the job submission's check and by the worker's commit
    alike; an admin replace (PUT or an admin job's commit) keeps the avatar's owner."""
    from service.jobs.artefacts import commit_bundle
    from service.store import Owner

    store = server.service.engine.store
    a, b = make_key(server, "owner-a", "avatars:write", "render", "jobs"), make_key(server, "owner-b",
                                                                                  "avatars:write", "jobs")
    data = bundle_bytes(tmp_path, 5)
    assert http.put("/v1/avatars/owned", content=data, headers=auth(a)).status_code == 201
    assert store.owner("owned") == Owner("owner-a")
    # tenant B: the PUT, the job submission and a commit are refused, and nothing changes
    assert http.put("/v1/avatars/owned", content=data, headers=auth(b)).status_code == 403
    upload = server.service.training.uploads.list()
    if upload:
        r = http.post("/v1/jobs", json={"upload_id": upload[0].id, "avatar_id": "owned"}, headers=auth(b))
        assert r.status_code in (403, 404), r.text  # 404: the upload is another tenant's; never accepted
    (tmp_path / "trained.bundle").write_bytes(data)
    with pytest.raises(PermissionDenied):
        commit_bundle(store, tmp_path / "trained.bundle", "owned", "owner-b")
    with pytest.raises(PermissionDenied):
        server.service.training.writable("owned", job_writer("owner-b"))
    # an admin replace keeps tenant A's ownership, by the PUT and by an admin job's commit
    assert http.put("/v1/avatars/owned", content=data, headers=server.headers).status_code == 201
    assert store.owner("owned") == Owner("owner-a")
    commit_bundle(store, tmp_path / "trained.bundle", "owned", ADMIN_TENANT)
    assert store.owner("owned") == Owner("owner-a")
    assert http.get("/v1/avatars/owned", headers=auth(a)).status_code == 200
    # tenant A's own job commit keeps it A's
    commit_bundle(store, tmp_path / "trained.bundle", "owned", "owner-a")
    assert store.owner("owned") == Owner("owner-a")


def test_keys_of_the_admin_tenant_hold_the_admin_scope(server):
    with pytest.raises(InvalidArgument, match="admin scope"):
        server.keys.create(ADMIN_TENANT, ["jobs"])


# ------------------------------------------------------------------------------------------- keys, audit
def test_keys_command_creates_lists_and_revokes_and_a_revoked_key_stops_working(server, http):
    env_dir = ["--data-dir", str(server.service.settings.data_dir)]
    out = subprocess.run([sys.executable, "-m", "service.cli", "keys", "create", "--tenant", "cli", "--scope", "render",
                          "--name", "from the cli", "--json", *env_dir], capture_output=True, text=True, check=True)
    created = json.loads(out.stdout)
    assert created["key"].startswith("bsk_") and created["scopes"] == ["render"]
    assert "alembic" not in out.stderr  # the database is at head: nothing migrates, nothing about it is logged
    assert http.get("/v1/avatars", headers=auth(created["key"])).status_code == 200
    listed = subprocess.run([sys.executable, "-m", "service.cli", "keys", "list", "--json", *env_dir],
                            capture_output=True, text=True, check=True)
    assert created["id"] in {k["id"] for k in json.loads(listed.stdout)}
    assert created["key"] not in listed.stdout  # secrets are never shown again
    subprocess.run([sys.executable, "-m", "service.cli", "keys", "revoke", created["id"], *env_dir], check=True,
                   capture_output=True)
    deadline = time.monotonic() + CACHE_SECONDS + 5
    while http.get("/v1/avatars", headers=auth(created["key"])).status_code != 401:
        assert time.monotonic() < deadline, "the revoked key still works"
        time.sleep(0.5)


def test_keys_commands_log_migrations_only_when_something_migrates(tmp_path):
    """A fresh database is migrated and says so (Alembic's "Running upgrade" lines and one summary); after that a
    `keys` command logs nothing about the database, and Alembic's set-up chatter never shows."""
    command = [sys.executable, "-m", "service.cli", "keys", "list", "--data-dir", str(tmp_path)]
    env = {k: v for k, v in os.environ.items() if not k.startswith("BLENDSPLAT_")}
    first = subprocess.run(command, capture_output=True, text=True, check=True, env=env)
    assert "Running upgrade" in first.stderr and "migrated the database" in first.stderr
    assert "setup plugin" not in first.stderr and "Context impl" not in first.stderr
    again = subprocess.run(command, capture_output=True, text=True, check=True, env=env)
    assert again.stderr == "" and again.stdout == ""


def test_avatar_writes_and_job_submissions_are_audited(server, http, tmp_path, caplog):
    key = make_key(server, "audited", "avatars:write", "render")
    with caplog.at_level(logging.INFO, logger="blendsplat.audit"):
        assert http.put("/v1/avatars/audited", content=bundle_bytes(tmp_path, 4), headers=auth(key)).status_code \
            == 201
        assert http.delete("/v1/avatars/audited", headers=auth(key)).status_code == 204
    lines = [r.getMessage() for r in caplog.records if r.name == "blendsplat.audit"]
    key_id = key.split("_")[1]
    assert any("avatar.create audited" in line and key_id in line and "tenant=audited" in line for line in lines)
    assert any("avatar.delete audited" in line for line in lines)


def test_the_admin_key_is_created_once_private_and_reused(tmp_path):
    first = LiveServer(tmp_path / "data", auth="keys")
    try:
        path = tmp_path / "data" / "admin.key"
        assert path.stat().st_mode & 0o777 == 0o600 and first.api_key.startswith("bsk_")
        with httpx.Client(base_url=first.http_url) as client:
            assert client.get("/v1/avatars").status_code == 401
            assert client.get("/v1/avatars", headers=first.headers).status_code == 200
    finally:
        first.stop()
    second = LiveServer(tmp_path / "data", auth="keys")
    try:
        assert second.api_key == first.api_key
    finally:
        second.stop()


def test_auth_off_is_loud(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="service.access.auth"):
        s = LiveServer(tmp_path / "data", auth="off")
    try:
        assert any("authentication is OFF" in r.getMessage() for r in caplog.records)
        assert not (tmp_path / "data" / "admin.key").exists()
        assert httpx.get(s.http_url + "/v1/avatars").status_code == 200
    finally:
        s.stop()


# ---------------------------------------------------------------------------------------------------- TLS
def test_both_servers_speak_tls_with_a_certificate_from_files(tmp_path):
    cert, key_file = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key_file), "-out",
                    str(cert), "-days", "1", "-subj", "/CN=localhost", "-addext",
                    "subjectAltName=DNS:localhost,IP:127.0.0.1"], check=True, capture_output=True)
    s = LiveServer(tmp_path / "data", auth="keys", tls_cert_file=cert, tls_key_file=key_file)
    try:
        https = s.http_url.replace("http://", "https://")
        with pytest.raises(httpx.TransportError):
            httpx.get(s.http_url + "/healthz", timeout=5)  # plain HTTP is not served
        trusted = ssl.create_default_context(cafile=str(cert))
        r = httpx.get(https + "/v1/avatars", headers=s.headers, verify=trusted, timeout=30)
        assert r.status_code == 200 and "demo" in {a["id"] for a in r.json()["avatars"]}
        credentials = grpc.ssl_channel_credentials(root_certificates=cert.read_bytes())
        with grpc.secure_channel(s.grpc_target, credentials,
                                 options=[("grpc.ssl_target_name_override", "localhost")]) as channel:
            reply = pb_grpc.RenderServiceStub(channel).Render(pb.RenderRequest(avatar_id="demo", width=32, height=32),
                                                              metadata=metadata(s.api_key), timeout=30)
            assert reply.frame.width == 32 and reply.frame.data
    finally:
        s.stop()


def test_tls_settings_come_in_pairs_of_readable_files(tmp_path):
    from pydantic import ValidationError

    from service.settings import Settings

    with pytest.raises(ValidationError, match="go together"):
        Settings(tls_cert_file=tmp_path / "x.pem")
    with pytest.raises(ValidationError, match="not a readable file"):
        Settings(tls_cert_file=tmp_path / "x.pem", tls_key_file=tmp_path / "y.pem")


def test_bench_stream_takes_the_key_from_the_environment(server):
    import os

    command = [sys.executable, "-m", "service.cli", "bench", "stream", "--target", server.grpc_target, "--avatar",
               "demo", "--seconds", "1", "--warmup", "0.2", "--size", "64", "--json"]
    env = {**os.environ, "BLENDSPLAT_API_KEY": server.api_key}
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout)["frames"] > 0
    env.pop("BLENDSPLAT_API_KEY")
    refused = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and "UNAUTHENTICATED" in refused.stderr + refused.stdout


def test_cors_answers_only_the_allowed_origins(tmp_path):
    s = LiveServer(tmp_path / "data", auth="keys", allowed_origins=["https://app.example"])
    try:
        preflight = {"Access-Control-Request-Method": "GET", "Access-Control-Request-Headers": "authorization"}
        ok = httpx.options(s.http_url + "/v1/avatars", headers={"Origin": "https://app.example", **preflight})
        assert ok.status_code == 200 and ok.headers["access-control-allow-origin"] == "https://app.example"
        assert "authorization" in ok.headers["access-control-allow-headers"].lower()
        other = httpx.options(s.http_url + "/v1/avatars", headers={"Origin": "https://evil.example", **preflight})
        assert "access-control-allow-origin" not in other.headers
        r = httpx.get(s.http_url + "/v1/avatars", headers={"Origin": "https://app.example", **s.headers})
        assert r.status_code == 200 and r.headers["access-control-allow-origin"] == "https://app.example"
        with connect(s.ws_url, subprotocols=["blendsplat.v1", f"bearer.{s.api_key}"], open_timeout=30,
                     additional_headers={"Origin": "https://app.example"}) as ws:  # allowed for the stream too
            ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=16, height=16)).SerializeToString())
            assert pb.StreamResponse.FromString(ws.recv(timeout=30)).HasField("header")
    finally:
        s.stop()


def test_an_admin_key_from_the_settings_may_be_any_long_secret(tmp_path):
    """BLENDSPLAT_ADMIN_KEY from a Kubernetes Secret (e.g. `openssl rand -hex 32`): registered at start, accepted,
    and no admin.key file is written."""
    secret = "trial-admin-key-change-me"
    s = LiveServer(tmp_path / "data", auth="keys", admin_key=secret)
    try:
        assert not (tmp_path / "data" / "admin.key").exists()
        assert httpx.get(s.http_url + "/v1/avatars", headers=auth(secret)).status_code == 200
        assert httpx.get(s.http_url + "/v1/avatars", headers=auth(secret[:-1] + "X")).status_code == 401
    finally:
        s.stop()
    from pydantic import ValidationError

    from service.settings import Settings

    with pytest.raises(ValidationError, match="an admin key is"):  # a bad deployment fails at start, named
        Settings(admin_key="short")
