"""Retargeting adapters in the service (issue 19), against the real servers on loopback: the adapter REST API and
its refusals, ARKit streams driving an avatar of another basis over gRPC and WebSocket, the NaN guard, smoothing,
and the batched mapping of one render call."""

from __future__ import annotations

import json

import grpc
import httpx
import numpy as np
import pytest
import torch

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.adapters.fit import fit
from render_core.adapters.onnx_model import model_bytes
from render_core.adapters.runtime import AdapterRuntime
from render_core.adapters.smoothing import OneEuroFilter
from render_core.bundle import write_bundle
from render_core.deform import Frame
from render_core.drive import default_camera
from render_core.facemodel.open_head import ARKIT_52
from render_core.media.codecs import decode_image
from render_core.renderer import AvatarRenderer
from tests.test_adapters import _hostile, _stripes, mixed, sqrt_adapter
from tests.test_service import GrpcStream, WsStream, next_frame

SIZE = 40
AVATAR = "mixed-head"
ADAPTER = "arkit-to-mixed"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from tests.conftest import LiveServer

    s = LiveServer(tmp_path_factory.mktemp("adapter-server"))
    yield s
    s.stop()


@pytest.fixture(scope="module")
def http(server):
    with httpx.Client(base_url=server.http_url, timeout=120) as client:
        yield client


@pytest.fixture(scope="module")
def setup(server, http, head, tmp_path_factory):
    """An avatar on the open head with a mixed basis (12 expressions that are not ARKit's) in the store, and the
    fitted ARKit -> mixed adapter uploaded; returns (avatar, renderer, fit, model bytes)."""
    from render_core.train.initialize import init_avatar

    target, _ = mixed(head, k=12)
    avatar = init_avatar(target, gaussians=1500, mouth=8, sh_degree=0, opacity=0.6, albedo=_stripes, seed=0)
    path = tmp_path_factory.mktemp("bundle") / "mixed.bundle"
    write_bundle(avatar, path, precision="fp32")
    assert http.put(f"/v1/avatars/{AVATAR}", content=path.read_bytes()).status_code == 201
    result = fit(head, target, adapter_id=ADAPTER)
    data = model_bytes(result.manifest, result.weights)
    r = put_adapter(http, ADAPTER, data, result.manifest.to_dict())
    assert r.status_code == 201, r.text
    from render_core.bundle import read_bundle

    stored = read_bundle(server.engine.store.path(AVATAR))
    return stored, AvatarRenderer(stored), result, data


def put_adapter(http, adapter_id: str, model: bytes, manifest) -> httpx.Response:
    text = manifest if isinstance(manifest, str) else json.dumps(manifest)
    return http.put(f"/v1/adapters/{adapter_id}", files={"manifest": ("manifest.json", text, "application/json"),
                                                         "model": ("model.onnx", model, "application/octet-stream")})


def expected(setup, source: np.ndarray, joints: dict | None = None) -> np.ndarray:
    """[H, W, 4] uint8: render_core's image of the avatar driven by the adapter's output for ``source``."""
    avatar, renderer, result, data = setup
    expression, adapter_joints, errors = AdapterRuntime(data, result.manifest).run(source[None].astype(np.float32))
    assert errors == [None]
    rot = {n: torch.tensor(adapter_joints[0, i]) for i, n in enumerate(result.manifest.target_joint_names)}
    rot = {**{k: torch.tensor(v, dtype=torch.float32) for k, v in (joints or {}).items()}, **rot}
    names = result.manifest.target_expression_names
    frame = Frame.from_params(avatar, expression={n: float(expression[0, i]) for i, n in enumerate(names)},
                              joints=rot)
    out = renderer.render(frame, default_camera(avatar, SIZE, SIZE), torch.zeros(3))
    rgba = torch.cat([out.rgb[0], out.alpha[0, ..., None]], -1)
    return (rgba.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


def _lockstep(stream, setup, frames: int, seed: int, named: bool = False) -> pb.StreamHeader:
    header = stream.next().header
    rng = np.random.default_rng(seed)
    for i in range(1, frames + 1):
        arkit = (rng.uniform(0, 1, 52) * (rng.uniform(size=52) < 0.3)).astype(np.float32)
        neck = rng.normal(0, 0.1, 3).astype(np.float32)
        joints = {"neck": pb.Rotation(values=neck.tolist())}
        if named:
            stream.send(frame=pb.FrameParams(index=i, named_coefficients={n: float(v) for n, v in zip(
                ARKIT_52, arkit, strict=True) if v}, joints=joints))
        else:
            stream.send(frame=pb.FrameParams(index=i, coefficients=arkit.tolist(), joints=joints))
        frame = next_frame(stream)
        got = decode_image("png", frame.data, SIZE, SIZE)
        want = expected(setup, arkit, {"neck": neck})
        assert np.abs(got.astype(int) - want.astype(int)).max() <= 1, f"frame {i} differs"
        stream.send(ack=pb.Ack(index=i))
    return header


def test_arkit_stream_drives_an_avatar_of_another_basis_over_grpc(server, setup):
    """The client declares ARKit's names only; the service picks the adapter whose target is the avatar's face
    model, says so in the header, and every frame is the avatar driven by the adapter's output."""
    with grpc.insecure_channel(server.grpc_target) as channel:
        stream = GrpcStream(pb_grpc.RenderServiceStub(channel), avatar_id=AVATAR, width=SIZE, height=SIZE,
                            codec=pb.CODEC_PNG, source_names=ARKIT_52)
        header = _lockstep(stream, setup, 6, seed=1)
        assert header.adapter_id == ADAPTER and list(header.source_names) == ARKIT_52
        assert len(header.expression_names) == 12  # the avatar's own (not ARKit's)
        assert stream.close()[-1].status.code == pb.OK


def test_arkit_stream_drives_an_avatar_of_another_basis_over_websocket(server, setup):
    stream = WsStream(server.ws_url, avatar_id=AVATAR, width=SIZE, height=SIZE, codec=pb.CODEC_PNG, adapter=ADAPTER)
    try:
        header = _lockstep(stream, setup, 4, seed=2, named=True)
        assert header.adapter_id == ADAPTER
    finally:
        stream.close()
    json_stream = WsStream(server.ws_url, json_mode=True, avatar_id=AVATAR, width=SIZE, height=SIZE,
                           codec=pb.CODEC_PNG, adapter=ADAPTER, source_names=["jawOpen", "mouthSmileLeft"])
    try:
        assert json_stream.next().header.source_names == ["jawOpen", "mouthSmileLeft"]
        json_stream.send(frame=pb.FrameParams(index=1, coefficients=[0.6, 0.4]))
        got = decode_image("png", next_frame(json_stream).data, SIZE, SIZE)
        source = np.zeros(52, np.float32)
        source[ARKIT_52.index("jawOpen")], source[ARKIT_52.index("mouthSmileLeft")] = 0.6, 0.4
        assert np.abs(got.astype(int) - expected(setup, source).astype(int)).max() <= 1
    finally:
        json_stream.close()


def test_adapter_sessions_refuse_what_does_not_fit(server, setup):
    with grpc.insecure_channel(server.grpc_target) as channel:
        stub = pb_grpc.RenderServiceStub(channel)
        for config, code, field in (
                (dict(avatar_id=AVATAR, adapter="ghost"), grpc.StatusCode.NOT_FOUND, "adapter"),
                (dict(avatar_id="demo", adapter=ADAPTER), grpc.StatusCode.INVALID_ARGUMENT, "adapter"),
                (dict(avatar_id="demo", source_names=ARKIT_52), grpc.StatusCode.INVALID_ARGUMENT, "source_names"),
                (dict(avatar_id=AVATAR, adapter=ADAPTER, source_names=["nope"]), grpc.StatusCode.INVALID_ARGUMENT,
                 "source_names"),
                (dict(avatar_id=AVATAR, adapter=ADAPTER, smoothing=pb.OneEuro(beta=-1)),
                 grpc.StatusCode.INVALID_ARGUMENT, "smoothing.beta")):
            stream = GrpcStream(stub, width=SIZE, height=SIZE, **config)
            with pytest.raises(grpc.RpcError) as e:
                stream.next()
            assert e.value.code() == code and e.value.details().startswith(f"{field}: "), e.value.details()
        stream = GrpcStream(stub, avatar_id=AVATAR, width=SIZE, height=SIZE, codec=pb.CODEC_PNG, adapter=ADAPTER)
        stream.next()
        stream.send(frame=pb.FrameParams(index=1, coefficients=[1.0] * 3))
        assert stream.next().error.field == "coefficients"
        stream.send(frame=pb.FrameParams(index=2, named_coefficients={"exp_00": 1.0}))
        assert stream.next().error.field == "named_coefficients"
        stream.send(frame=pb.FrameParams(index=3, coefficients=[float("nan")] * 52))
        assert stream.next().error.field == "coefficients"
        stream.send(frame=pb.FrameParams(index=4, coefficients=[0.1] * 52))
        assert next_frame(stream).index == 4
        stream.close()


def test_adapter_rest_api_lists_uploads_validates_and_deletes(http, setup):
    _, _, result, data = setup
    listed = http.get("/v1/adapters").json()["adapters"]
    assert [a["id"] for a in listed] == [ADAPTER] and listed[0]["tenant"] is None
    one = http.get(f"/v1/adapters/{ADAPTER}").json()
    assert one["manifest"]["source"]["names"] == ARKIT_52 and one["model_bytes"] == len(data)
    assert http.get("/v1/adapters/ghost").status_code == 404
    full = result.manifest.to_dict()
    manifest = {k: v for k, v in full.items() if k != "id"}  # the id comes from the path
    for kind, field in (("custom_domain", "model.opset_import"), ("external_data", "model.external_data"),
                        ("wrong_shapes", "model.graph.input"), ("bad_op", "model.graph.node")):
        r = put_adapter(http, "hostile", _hostile(result, kind), manifest)
        assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
    for body, field in ((b"\x08\x01garbage" * 50, "model"), (b"\0" * ((16 << 20) + 1), "model.size")):
        r = put_adapter(http, "hostile", body, manifest)
        assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
    assert put_adapter(http, "hostile", data, "{not json").json()["error"]["field"] == "manifest"
    assert put_adapter(http, "hostile", data, full).json()["error"]["field"] == "manifest.id"
    assert http.put("/v1/adapters/hostile", content=data).status_code == 422  # not multipart
    assert http.put("/v1/adapters/hostile", content=b"x" * (19 << 20)).status_code == 413  # over the body limit
    assert [a["id"] for a in http.get("/v1/adapters").json()["adapters"]] == [ADAPTER]  # nothing stored
    assert put_adapter(http, "copy", data, manifest).status_code == 201
    assert http.delete("/v1/adapters/copy").json()["id"] == "copy"
    assert http.get("/v1/adapters/copy").status_code == 404


def test_adapter_nan_output_is_a_frame_error_and_never_reaches_the_renderer(server, http, setup, monkeypatch):
    _, _, result, _ = setup
    weights = np.zeros_like(result.weights)
    weights[:, 0] = 1.0  # sqrt(browDownLeft): NaN when it is negative
    assert put_adapter(http, "sqrt", sqrt_adapter(result.manifest, weights),
                       {**result.manifest.to_dict(), "id": "sqrt"}).status_code == 201
    seen = []
    render = AvatarRenderer.render_rgba8  # what the engine calls

    def spy(self, frame, *args, **kwargs):
        seen.append(bool(torch.isfinite(frame.expression).all() and torch.isfinite(frame.joint_rotations).all()))
        return render(self, frame, *args, **kwargs)

    monkeypatch.setattr(AvatarRenderer, "render_rgba8", spy)
    with grpc.insecure_channel(server.grpc_target) as channel:
        stream = GrpcStream(pb_grpc.RenderServiceStub(channel), avatar_id=AVATAR, width=SIZE, height=SIZE,
                            codec=pb.CODEC_PNG, adapter="sqrt")
        assert stream.next().header.adapter_id == "sqrt"
        for i, value in enumerate((0.25, -1.0, 4.0), start=1):
            stream.send(frame=pb.FrameParams(index=i, named_coefficients={"browDownLeft": value}))
            reply = stream.next()
            if value < 0:
                assert reply.error.field == "adapter" and reply.error.frame_index == i
                assert reply.error.code == pb.INVALID_ARGUMENT and "non-finite" in reply.error.message
            else:
                assert reply.frame.index == i
                stream.send(ack=pb.Ack(index=i))
        assert stream.close()[-1].status.frames_sent == 2
    assert seen and all(seen)


def test_adapter_ownership_is_the_engines_rule(server, setup, caplog):
    """Who may use, replace and delete an adapter is decided by the engine (both transports call it): a tenant's
    adapter is its own; the deployment's (no tenant) every key may use and only admin keys change; another
    tenant's is refused before its upload is read, and in a session that names it. Changes are audited."""
    from service.access.auth import PermissionDenied, Principal

    engine, (_, _, result, data) = server.engine, setup
    alice = Principal("ka", "alice", frozenset({"render", "avatars:write"}))
    bob = Principal("kb", "bob", frozenset({"render", "avatars:write"}))
    manifest = json.dumps({k: v for k, v in result.manifest.to_dict().items() if k != "id"}).encode()

    async def upload():
        return data, manifest

    async def never():
        raise AssertionError("the upload of a refused write was read")

    with caplog.at_level("INFO", logger="blendsplat.audit"):
        assert server.call(engine.put_adapter("alices", upload, alice))["tenant"] == "alice"
    assert "adapter.put alices by key=ka tenant=alice" in caplog.text
    for adapter_id, who in (("alices", bob), (ADAPTER, alice)):  # another tenant's; the deployment's
        with pytest.raises(PermissionDenied):
            server.call(engine.put_adapter(adapter_id, never, who))
        with pytest.raises(PermissionDenied):
            engine.delete_adapter(adapter_id, who)
    with pytest.raises(PermissionDenied):
        engine.adapter_info("alices", bob)
    assert engine.adapter_info(ADAPTER, bob)["tenant"] is None
    deployments = {a["id"] for a in engine.list_adapters() if a["tenant"] is None}
    assert ADAPTER in deployments
    assert {a["id"] for a in engine.list_adapters(bob)} == deployments
    assert {a["id"] for a in engine.list_adapters(alice)} == deployments | {"alices"}
    config = pb.SessionConfig(avatar_id="demo", width=SIZE, height=SIZE, adapter="alices")  # a public avatar
    with pytest.raises(PermissionDenied, match="adapter 'alices'"):
        server.call(engine.open(config, "grpc", bob))
    with caplog.at_level("INFO", logger="blendsplat.audit"):
        assert engine.delete_adapter("alices", alice)["id"] == "alices"
    assert "adapter.delete alices by key=ka tenant=alice" in caplog.text


def test_smoothing_filters_the_coefficients_of_a_session(server, setup):
    """One Euro smoothing in open: a step in the input reaches the avatar filtered as the One Euro filter computes
    it from the frames' client times."""
    params = dict(min_cutoff=0.5, beta=0.0, d_cutoff=1.0)
    f = OneEuroFilter(**params)
    step = np.zeros(52, np.float32)
    step[ARKIT_52.index("jawOpen")] = 1.0
    with grpc.insecure_channel(server.grpc_target) as channel:
        stream = GrpcStream(pb_grpc.RenderServiceStub(channel), avatar_id=AVATAR, width=SIZE, height=SIZE,
                            codec=pb.CODEC_PNG, adapter=ADAPTER, smoothing=pb.OneEuro(**params))
        stream.next()
        for i, (source, t_us) in enumerate(((np.zeros(52, np.float32), 1_000_000), (step, 1_033_333)), start=1):
            stream.send(frame=pb.FrameParams(index=i, client_time_us=t_us, coefficients=source.tolist()))
            got = decode_image("png", next_frame(stream).data, SIZE, SIZE)
            stream.send(ack=pb.Ack(index=i))
            filtered = f(source, t_us / 1e6).astype(np.float32)
        assert 0.05 < filtered[ARKIT_52.index("jawOpen")] < 0.2  # the step is damped
        assert np.abs(got.astype(int) - expected(setup, filtered).astype(int)).max() <= 1
        assert np.abs(got.astype(int) - expected(setup, step).astype(int)).max() > 10  # not the raw input
        stream.close()


def test_one_render_call_maps_its_frames_in_one_adapter_run(setup, monkeypatch):
    """resolve_frames: the adapter-driven jobs of a render call go through their adapter together (one run of B
    frames), a refused frame is reported at its position and the others get frames."""
    from render_core.adapters.manifest import AdapterError
    from service.adapters import Loaded, SessionAdapter, resolve_frames
    from service.engine import Job

    avatar, _, result, data = setup
    entry = Loaded(ADAPTER, result.manifest, {}, AdapterRuntime(data, result.manifest), "")
    sessions = [SessionAdapter(entry, avatar, list(ARKIT_52), None) for _ in range(3)]
    calls = []
    run = entry.runtime.run

    def counting(x):  # the real run, with the second frame's output refused as non-finite
        calls.append(len(x))
        expression, joints, errors = run(x)
        errors[1] = AdapterError("non-finite", field="adapter")
        return expression, joints, errors

    monkeypatch.setattr(entry.runtime, "run", counting)
    jobs = []
    for i, s in enumerate(sessions):
        drive = s.prepare(pb.FrameParams(index=i + 1, coefficients=[0.1 * i] * 52))
        jobs.append(Job(frame=None, camera=None, background=torch.zeros(3), index=i + 1, client_time_us=0,
                        drive=drive))
    failed = resolve_frames(jobs)
    assert calls == [3] and list(failed) == [1] and failed[1].field == "adapter"
    assert jobs[0].frame is not None and jobs[1].frame is None and jobs[2].frame is not None


def test_a_picked_adapter_is_never_another_tenants(server, setup, tmp_path):
    """source_names makes the service pick an adapter: among the ones the caller may use only (hardening 2). Alice's
    copy of the deployment's adapter sorts first, so without the rule bob's stream would run through it; a named
    one of alice's is refused to bob at open, and a not-found answer lists no other adapter."""
    from service.access.auth import PermissionDenied, Principal
    from service.errors import NotFound

    engine, (_, _, result, data) = server.engine, setup
    alice = Principal("ka", "alice", frozenset({"render", "avatars:write"}))
    bob = Principal("kb", "bob", frozenset({"render", "avatars:write"}))
    manifest = json.dumps({k: v for k, v in result.manifest.to_dict().items() if k != "id"}).encode()

    async def upload():
        return data, manifest

    async def chunks():
        yield (tmp_path / "h.bundle").read_bytes()

    write_bundle(setup[0], tmp_path / "h.bundle", precision="fp32")
    server.call(engine.replace("shared-head", chunks(), principal=Principal(None, None, frozenset({"admin"}))))
    (server.service.settings.bundle_dir / "shared-head.bundle.owner").write_text('{"tenant": null, "public": true}')
    server.call(engine.put_adapter("alices-copy", upload, alice))
    try:
        config = pb.SessionConfig(avatar_id="shared-head", width=SIZE, height=SIZE, source_names=list(ARKIT_52))
        picked = {}
        for who in (alice, bob):
            session = server.call(engine.open(config, "grpc", who))
            picked[who.tenant] = session.header().header.adapter_id
            engine.close_session(session)
        assert picked == {"alice": "alices-copy", "bob": ADAPTER}
        named = pb.SessionConfig(avatar_id="shared-head", width=SIZE, height=SIZE, adapter="alices-copy")
        with pytest.raises(PermissionDenied):
            server.call(engine.open(named, "grpc", bob))
        with pytest.raises(NotFound) as missing:
            engine.adapter_info("no-such-adapter", bob)
        assert "alices-copy" not in str(missing.value) and ADAPTER not in str(missing.value)
    finally:
        engine.delete_adapter("alices-copy", alice)
        server.call(engine.delete("shared-head"))
