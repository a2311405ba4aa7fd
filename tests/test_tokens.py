"""Session tokens (issue 30): a backend mints a short-lived, render-only token with its key (POST /v1/tokens) for a
browser; the token reads and streams its avatar (Bearer header, WebSocket subprotocol bearer.<token>), nothing else,
until it expires or its minting key is revoked (new calls refused, open streams ended)."""

from __future__ import annotations

import re
import time

import grpc
import httpx
import pytest
from conftest import LiveServer

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import write_bundle
from render_core.tools.synth import synth_avatar
from service.access.tokens import Tokens
from service.settings import Settings
from tests.test_service import WsStream

CHECK = 0.5  # stream_key_check_seconds of the module's server
LIMIT = 10 * CHECK + 5


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    s = LiveServer(tmp_path_factory.mktemp("tokens") / "data", auth="keys", stream_key_check_seconds=CHECK,
                   token_max_seconds=900)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.http_url, timeout=60) as client:
        yield client


def make_key(server, tenant: str, *scopes: str) -> tuple[str, str]:
    key, secret = server.keys.create(tenant, scopes or ("render",))
    return key.id, secret


def auth(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def mint(http, key: str, **body) -> httpx.Response:
    return http.post("/v1/tokens", json=body, headers=auth(key))


def render(http, token: str, avatar: str = "demo") -> httpx.Response:
    return http.post("/v1/render", json={"avatar_id": avatar, "width": 32, "height": 32, "codec": "CODEC_PNG"},
                     headers=auth(token))


@pytest.fixture(scope="module")
def owned(server, http, tmp_path_factory) -> tuple[str, str]:
    """A tenant's key (render + avatars:write) and its own avatar beside the public demo."""
    _, key = make_key(server, "tok-tenant", "render", "avatars:write")
    path = tmp_path_factory.mktemp("tok-bundle") / "b.bundle"
    write_bundle(synth_avatar(gaussians=300, blendshapes=3, seed=3), path, precision="fp16")
    assert http.put("/v1/avatars/tok-own", content=path.read_bytes(), headers=auth(key)).status_code == 201
    return key, "tok-own"


def test_a_token_renders_and_streams_its_avatar_only(server, http, owned):
    key, avatar = owned
    r = mint(http, key, avatar=avatar, expires_in=120)
    assert r.status_code == 201, r.text
    body = r.json()
    token = body["token"]
    assert body["scope"] == "render" and body["avatar"] == avatar and body["tenant"] == "tok-tenant"
    assert abs(body["expires_at"] - (time.time() + 120)) < 10
    assert re.fullmatch(r"[A-Za-z0-9_.-]+", token) and token.startswith("bst.")  # a valid subprotocol token

    assert render(http, token, avatar).status_code == 200
    assert http.get(f"/v1/avatars/{avatar}", headers=auth(token)).status_code == 200
    assert [a["id"] for a in http.get("/v1/avatars", headers=auth(token)).json()["avatars"]] == [avatar]
    stream = WsStream(server.ws_url, api_key=token, avatar_id=avatar, width=32, height=32)
    try:
        assert stream.next().HasField("header")
        stream.send(frame=pb.FrameParams(index=1))
        assert stream.next().HasField("frame")
    finally:
        stream.close()

    other = render(http, token, "demo")  # public, but not the token's avatar
    assert other.status_code == 403 and "demo" in other.json()["error"]["message"]
    stream = WsStream(server.ws_url, api_key=token, avatar_id="demo", width=32, height=32)
    try:
        reply = stream.next()
        assert reply.status.code == pb.PERMISSION_DENIED and "demo" in reply.status.message
    finally:
        stream.close()


def test_a_token_works_in_grpc_metadata(server, http, owned):
    key, avatar = owned
    token = mint(http, key, avatar=avatar).json()["token"]
    metadata = (("authorization", f"Bearer {token}"),)
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = pb_grpc.RenderServiceStub(channel)
        assert stub.GetAvatar(pb.GetAvatarRequest(id=avatar), metadata=metadata, timeout=30).id == avatar
        with pytest.raises(grpc.RpcError) as caught:
            stub.GetAvatar(pb.GetAvatarRequest(id="demo"), metadata=metadata, timeout=30)
        assert caught.value.code() == grpc.StatusCode.PERMISSION_DENIED
        with pytest.raises(grpc.RpcError) as caught:
            stub.UnloadAvatar(pb.UnloadAvatarRequest(id=avatar), metadata=metadata, timeout=30)
        assert caught.value.code() == grpc.StatusCode.PERMISSION_DENIED


def test_a_token_without_avatar_reads_its_tenants_and_public_avatars(http, owned):
    key, avatar = owned
    token = mint(http, key).json()["token"]
    assert render(http, token, "demo").status_code == 200
    assert render(http, token, avatar).status_code == 200


def test_a_token_is_render_only_and_cannot_mint(server, http, owned, tmp_path):
    key, avatar = owned
    token = mint(http, key, avatar=avatar).json()["token"]
    assert http.put(f"/v1/avatars/{avatar}", content=b"x", headers=auth(token)).status_code == 403
    assert http.post("/v1/jobs", json={}, headers=auth(token)).status_code == 403
    r = mint(http, token)
    assert r.status_code == 403 and "token" in r.json()["error"]["message"]
    _, jobs_only = make_key(server, "tok-jobs", "jobs")
    assert mint(http, jobs_only).status_code == 403


def test_mint_refuses_a_long_expiry_and_another_tenants_avatar(server, http, owned):
    key, avatar = owned
    r = mint(http, key, expires_in=901)
    assert r.status_code == 422 and r.json()["error"]["field"] == "expires_in", r.text
    assert mint(http, key, expires_in=0).status_code == 422
    _, stranger = make_key(server, "tok-stranger", "render")
    assert mint(http, stranger, avatar=avatar).status_code == 403
    assert mint(http, stranger, avatar="no-such-avatar").status_code == 404
    assert http.post("/v1/tokens", json={}).status_code == 401


def test_expired_and_tampered_tokens_are_refused(http, owned):
    key, avatar = owned
    token = mint(http, key, avatar=avatar, expires_in=1).json()["token"]
    prefix, payload, sig = token.split(".")
    tampered = f"{prefix}.{payload}.{'A' if sig[0] != 'A' else 'B'}{sig[1:]}"
    r = render(http, tampered, avatar)
    assert r.status_code == 401 and "signature" in r.json()["error"]["message"]
    time.sleep(2.1)
    r = render(http, token, avatar)
    assert r.status_code == 401 and "expired" in r.json()["error"]["message"]


def test_revoking_the_minting_key_ends_its_tokens_and_their_streams(server, http):
    key_id, key = make_key(server, "tok-revoked", "render")
    token = mint(http, key, avatar="demo").json()["token"]
    assert render(http, token).status_code == 200
    stream = WsStream(server.ws_url, api_key=token, avatar_id="demo", width=32, height=32)
    try:
        assert stream.next().HasField("header")
        server.keys.revoke(key_id)  # in the database, as another process does
        t0 = time.monotonic()
        while True:
            reply = stream.next()
            if reply.HasField("status"):
                break
            assert time.monotonic() - t0 < LIMIT, "the stream went on"
        assert reply.status.code == pb.UNAUTHENTICATED
    finally:
        stream.close()
    deadline = time.monotonic() + 10  # CACHE_SECONDS on this replica at most
    while render(http, token).status_code != 401:
        assert time.monotonic() < deadline, "the token still works"
        time.sleep(0.5)


def test_the_secret_file_is_private_and_reused(tmp_path):
    settings = Settings(data_dir=tmp_path)
    token, _ = Tokens(settings).mint("k", "t", None, 60)
    assert (tmp_path / "token.secret").stat().st_mode & 0o777 == 0o600
    assert Tokens(settings).verify(token).tenant == "t"
    configured = Tokens(settings.model_copy(update={"token_secret": "another-secret"}))
    with pytest.raises(ValueError, match="signature"):
        configured.verify(token)
