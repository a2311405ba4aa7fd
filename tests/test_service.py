"""The streaming service against its real servers on loopback (gRPC and HTTP/WebSocket in one process)."""

from __future__ import annotations

import json
import queue
import time

import grpc
import httpx
import numpy as np
import pytest
import torch
from grpc_health.v1 import health_pb2, health_pb2_grpc
from websockets.sync.client import connect

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.bundle import read_bundle, write_bundle
from render_core.deform import Frame
from render_core.drive import default_camera
from render_core.media.codecs import H264Decoder, decode_image
from render_core.renderer import AvatarRenderer
from render_core.tools.synth import synth_avatar

SIZE = 48


@pytest.fixture(scope="module")
def stub(live_server):
    with grpc.insecure_channel(live_server.grpc_target) as channel:
        yield pb_grpc.RenderServiceStub(channel)


@pytest.fixture(scope="module")
def reference(live_server):
    """render_core's own renderer on the store's demo bundle: what every stream must reproduce."""
    avatar = read_bundle(live_server.engine.store.path(live_server.avatar_id))
    return avatar, AvatarRenderer(avatar)


def expected_image(reference, coefficients, joints, size=SIZE) -> np.ndarray:
    """[H, W, 4] uint8 as render_core renders the pose to 8-bit RGBA, as the service does (front camera of the
    avatar, black background; the default schedule, 8-bit stop included)."""
    avatar, renderer = reference
    frame = Frame.from_params(avatar, expression=torch.tensor(np.asarray(coefficients, np.float32)),
                              joints={k: torch.tensor(np.asarray(v, np.float32)) for k, v in joints.items()})
    rgba, _ = renderer.render_rgba8(frame, default_camera(avatar, size, size), torch.zeros(3))
    return rgba[0]


def random_pose(rng: np.random.Generator, k: int) -> tuple[list[float], dict[str, list[float]]]:
    coefficients = rng.uniform(0, 1, k).astype(np.float32).tolist()
    joints = {name: rng.normal(0, 0.15, 3).astype(np.float32).tolist() for name in ("neck", "jaw")}
    return coefficients, joints


def frame_params(index: int, coefficients, joints) -> pb.FrameParams:
    return pb.FrameParams(index=index, coefficients=coefficients,
                          joints={k: pb.Rotation(values=v) for k, v in joints.items()})


class GrpcStream:
    """A RenderStream driven step by step from the test."""

    def __init__(self, stub, api_key: str | None = None, **config):
        self._requests: queue.Queue = queue.Queue()
        self._requests.put(pb.StreamRequest(open=pb.SessionConfig(**config)))
        metadata = (("authorization", f"Bearer {api_key}"),) if api_key else None
        self._responses = stub.RenderStream(iter(self._requests.get, None), metadata=metadata)

    def send(self, **message) -> None:
        self._requests.put(pb.StreamRequest(**message))

    def next(self) -> pb.StreamResponse:
        return next(self._responses)

    def close(self) -> list[pb.StreamResponse]:
        """Half-close and return what is left, the final status last."""
        self._requests.put(None)
        return list(self._responses)


class WsStream:
    """The same over the WebSocket (binary protobuf, or protobuf JSON with ``json_mode``)."""

    def __init__(self, url: str, json_mode: bool = False, api_key: str | None = None, **config):
        protocols = ["blendsplat.v1", f"bearer.{api_key}"] if api_key else None
        self._connection = connect(url, max_size=64 << 20, open_timeout=30, subprotocols=protocols)
        self.ws, self.json_mode = self._connection.__enter__(), json_mode
        self.send(open=pb.SessionConfig(**config))

    def send(self, **message) -> None:
        request = pb.StreamRequest(**message)
        from google.protobuf import json_format

        self.ws.send(json_format.MessageToJson(request) if self.json_mode else request.SerializeToString())

    def send_raw(self, data: bytes | str) -> None:
        self.ws.send(data)

    def next(self) -> pb.StreamResponse:
        from google.protobuf import json_format

        data = self.ws.recv(timeout=60)
        if isinstance(data, str):
            return json_format.Parse(data, pb.StreamResponse())
        return pb.StreamResponse.FromString(data)

    def close(self) -> None:
        self._connection.__exit__(None, None, None)


def next_frame(stream) -> pb.RenderedFrame:
    reply = stream.next()
    assert reply.WhichOneof("msg") == "frame", reply
    return reply.frame


def run_lockstep(stream, reference, frames: int, codec: str, seed: int) -> None:
    """Send a pose, wait for its frame, compare it with render_core's image, acknowledge; ``frames`` times."""
    header = stream.next().header
    assert list(header.expression_names) == reference[0].expression_names
    assert (header.width, header.height, header.max_in_flight) == (SIZE, SIZE, 2)
    rng = np.random.default_rng(seed)
    decoder = H264Decoder() if codec == "h264" else None
    for i in range(1, frames + 1):
        coefficients, joints = random_pose(rng, len(header.expression_names))
        stream.send(frame=frame_params(i, coefficients, joints))
        frame = next_frame(stream)
        assert frame.index == i and frame.dropped == 0
        expected = expected_image(reference, coefficients, joints)
        if decoder is not None:
            got = decoder.decode(frame.data)
            err = np.mean((got.astype(np.float64) - expected[..., :3]) ** 2)
            assert 10 * np.log10(255**2 / max(err, 1e-12)) > 30
        else:
            got = decode_image(codec, frame.data, SIZE, SIZE)
            assert np.abs(got.astype(int) - expected.astype(int)).max() <= 1, f"frame {i} differs"
        assert frame.timings.total_ms > 0 and frame.timings.batch >= 1
        stream.send(ack=pb.Ack(index=i))


# ---------------------------------------------------------------------------------------------- streams
@pytest.mark.parametrize("codec", ["raw_rgba", "png"])
def test_grpc_stream_of_60_frames_matches_render_core(stub, reference, codec):
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE, height=SIZE,
                        codec={"raw_rgba": pb.CODEC_RAW_RGBA, "png": pb.CODEC_PNG}[codec])
    run_lockstep(stream, reference, 60, codec, seed=1)
    rest = stream.close()
    assert rest[-1].status.code == pb.OK and rest[-1].status.frames_sent == 60


def test_websocket_stream_of_60_frames_matches_render_core(live_server, reference):
    stream = WsStream(live_server.ws_url, avatar_id="demo", width=SIZE, height=SIZE, codec=pb.CODEC_PNG)
    try:
        run_lockstep(stream, reference, 60, "png", seed=2)
    finally:
        stream.close()


def test_websocket_json_mode_and_h264(live_server, reference):
    stream = WsStream(live_server.ws_url, json_mode=True, avatar_id="demo", width=SIZE, height=SIZE,
                      codec=pb.CODEC_H264)
    try:
        run_lockstep(stream, reference, 8, "h264", seed=3)
    finally:
        stream.close()


def test_named_and_positional_coefficients_agree(stub, reference):
    names = reference[0].expression_names
    rng = np.random.default_rng(5)
    values = rng.uniform(0, 1, len(names)).astype(np.float32).tolist()
    order = names[::-1]  # the client's own order
    by_name = dict(zip(names, values, strict=True))
    frames = []
    for config, params in (
        ({}, pb.FrameParams(index=1, coefficients=values)),
        ({}, pb.FrameParams(index=1, named_coefficients=by_name)),
        ({"expression_names": order}, pb.FrameParams(index=1, coefficients=[by_name[n] for n in order])),
    ):
        stream = GrpcStream(stub, avatar_id="demo", width=SIZE, height=SIZE, codec=pb.CODEC_RAW_RGBA, **config)
        stream.next()
        stream.send(frame=params)
        frames.append(next_frame(stream).data)
        stream.close()
    assert frames[0] == frames[1] == frames[2]
    assert np.array_equal(decode_image("raw_rgba", frames[0], SIZE, SIZE), expected_image(reference, values, {}))


BAD_FRAMES = [
    ("NaN coefficient", pb.FrameParams(index=7, named_coefficients={"exp_00": float("nan")}),
     "named_coefficients.exp_00"),
    ("Inf coefficient", pb.FrameParams(index=7, coefficients=[float("inf")] + [0.0] * 7), "coefficients"),
    ("wrong count", pb.FrameParams(index=7, coefficients=[0.1, 0.2]), "coefficients"),
    ("unknown name", pb.FrameParams(index=7, named_coefficients={"smile": 1.0}), "named_coefficients"),
    ("both forms", pb.FrameParams(index=7, coefficients=[0.0] * 8, named_coefficients={"exp_00": 1.0}),
     "coefficients"),
    ("unknown joint", pb.FrameParams(index=7, joints={"tail": pb.Rotation(values=[0, 0, 0])}), "joints"),
    ("rotation size", pb.FrameParams(index=7, joints={"jaw": pb.Rotation(values=[0, 0])}), "joints.jaw"),
    ("NaN rotation", pb.FrameParams(index=7, joints={"jaw": pb.Rotation(values=[float("nan"), 0, 0])}),
     "joints.jaw"),
    ("eyelids", pb.FrameParams(index=7, eyelids=[0.5]), "eyelids"),
    ("camera preset", pb.FrameParams(index=7, camera=pb.Camera(preset="behind")), "camera.preset"),
    ("camera K", pb.FrameParams(index=7, camera=pb.Camera(opencv=pb.OpenCVCamera(k=[1, 2]))), "camera.opencv.k"),
    ("background", pb.FrameParams(index=7, background=pb.Color(r=2.0)), "background"),
]


def _check_bad_then_good(stream, message: dict, field: str | None, index: int = 99) -> None:
    stream.send(**message)
    reply = stream.next()
    assert reply.WhichOneof("msg") == "error", reply
    assert reply.error.code == pb.INVALID_ARGUMENT
    if field is not None:
        assert reply.error.field == field, reply.error
    stream.send(frame=pb.FrameParams(index=index))  # the stream goes on
    frame = next_frame(stream)
    assert frame.index == index
    stream.send(ack=pb.Ack(index=index))


@pytest.mark.parametrize("name,params,field", BAD_FRAMES, ids=[b[0] for b in BAD_FRAMES])
def test_bad_frame_gets_invalid_argument_and_the_stream_survives(stub, name, params, field):
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE, codec=pb.CODEC_JPEG)
    stream.next()
    _check_bad_then_good(stream, {"frame": params}, field)
    stream.close()


def test_bad_stream_messages_over_grpc(stub):
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE)
    stream.next()
    _check_bad_then_good(stream, {"open": pb.SessionConfig(avatar_id="demo")}, "open")
    _check_bad_then_good(stream, {}, "msg", index=100)  # frame indices increase within a stream
    assert stream.close()[-1].status.code == pb.OK


def test_bad_stream_messages_over_websocket(live_server):
    for json_mode, garbage in ((False, b"\xff\xff\xff not protobuf"), (True, "{not json")):
        stream = WsStream(live_server.ws_url, json_mode=json_mode, avatar_id="demo", width=SIZE)
        try:
            stream.next()
            stream.send_raw(garbage)
            reply = stream.next()
            assert reply.error.code == pb.INVALID_ARGUMENT and "StreamRequest" in reply.error.message
            _check_bad_then_good(stream, {"frame": BAD_FRAMES[0][1]}, "named_coefficients.exp_00")
        finally:
            stream.close()


@pytest.mark.parametrize("config,code,field", [
    ({"avatar_id": "nobody"}, grpc.StatusCode.NOT_FOUND, "avatar_id"),
    ({"avatar_id": "../etc/passwd"}, grpc.StatusCode.INVALID_ARGUMENT, "avatar_id"),
    ({"avatar_id": "demo", "width": 100_000}, grpc.StatusCode.INVALID_ARGUMENT, "width"),
    ({"avatar_id": "demo", "codec": 42}, grpc.StatusCode.INVALID_ARGUMENT, "codec"),
    ({"avatar_id": "demo", "quality": 101}, grpc.StatusCode.INVALID_ARGUMENT, "quality"),
    ({"avatar_id": "demo", "max_in_flight": 1000}, grpc.StatusCode.INVALID_ARGUMENT, "max_in_flight"),
    ({"avatar_id": "demo", "expression_names": ["smile"]}, grpc.StatusCode.INVALID_ARGUMENT, "expression_names"),
])
def test_bad_open_gets_its_status_code(stub, config, code, field):
    stream = GrpcStream(stub, **config)
    with pytest.raises(grpc.RpcError) as e:
        stream.next()
    assert e.value.code() == code
    assert e.value.details().startswith(field), e.value.details()


def test_first_message_must_open(stub):
    responses = stub.RenderStream(iter([pb.StreamRequest(frame=pb.FrameParams(index=1))]))
    with pytest.raises(grpc.RpcError) as e:
        list(responses)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_session_limit_gives_resource_exhausted(live_server, stub):
    engine = live_server.engine
    limit, engine.settings.max_sessions = engine.settings.max_sessions, len(engine.sessions) + 1
    try:
        first = GrpcStream(stub, avatar_id="demo", width=SIZE)
        first.next()
        second = GrpcStream(stub, avatar_id="demo", width=SIZE)
        with pytest.raises(grpc.RpcError) as e:
            second.next()
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        ws = WsStream(live_server.ws_url, avatar_id="demo", width=SIZE)
        reply = ws.next()
        assert reply.status.code == pb.RESOURCE_EXHAUSTED
        ws.close()
        first.close()
    finally:
        engine.settings.max_sessions = limit


def test_slow_reader_stays_bounded_and_newest_pose_wins(live_server, stub):
    engine = live_server.engine
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, max_in_flight=2)
    session_id = stream.next().header.session_id
    session = engine.sessions[session_id]
    for i in range(1, 301):  # never acknowledged
        stream.send(frame=pb.FrameParams(index=i, named_coefficients={"exp_00": i / 300}))
    deadline = time.monotonic() + 30
    while session.dropped < 290 and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.2)
    assert session.sent == 2 and len(session.unacked) == 2 and session.rendering == 0
    assert session._replies.qsize() <= 2  # at most max_in_flight frames held for this reader
    assert session.pending is not None and session.pending.index == 300  # the newest pose waits
    assert session.dropped == 300 - 2 - 1
    first, second = next_frame(stream), next_frame(stream)
    assert (first.index, second.index) == (1, 2) or first.index == 1
    stream.send(ack=pb.Ack(index=second.index))
    latest = next_frame(stream)
    assert latest.index == 300 and latest.dropped == 297
    stream.send(ack=pb.Ack(index=300))
    assert stream.close()[-1].status.dropped == 297


def test_concurrent_sessions_of_one_avatar_render_as_one_batch(live_server):
    engine = live_server.engine

    async def two_sessions():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA)
        sessions = [await engine.open(config, "test") for _ in range(2)]
        for i, s in enumerate(sessions):  # both poses arrive before the scheduler runs
            s.handle(pb.StreamRequest(frame=pb.FrameParams(index=1, named_coefficients={"exp_01": 0.5 * i})))
        frames = []
        for s in sessions:
            async for reply in s.responses():
                frames.append(reply.frame)
                break
            s.end_input()
        return frames, sessions

    frames, sessions = live_server.call(two_sessions())
    assert [f.timings.batch for f in frames] == [2, 2]
    assert frames[0].data != frames[1].data
    assert all(s.closed for s in sessions)


# ------------------------------------------------------------------------------------------ unary and REST
def test_unary_grpc_calls(stub, reference):
    listed = stub.ListAvatars(pb.ListAvatarsRequest())
    assert [a.id for a in listed.avatars] == ["demo"]
    info = stub.GetAvatar(pb.GetAvatarRequest(id="demo"))
    assert info.gaussians == reference[0].num_gaussians + reference[0].num_mouth
    assert list(info.joint_names) == reference[0].joint_names
    with pytest.raises(grpc.RpcError) as e:
        stub.GetAvatar(pb.GetAvatarRequest(id="nobody"))
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    assert stub.UnloadAvatar(pb.UnloadAvatarRequest(id="demo")).loaded is False
    assert stub.GetAvatar(pb.GetAvatarRequest(id="demo")).loaded is False
    assert stub.LoadAvatar(pb.LoadAvatarRequest(id="demo")).loaded is True
    coefficients, joints = random_pose(np.random.default_rng(9), len(info.expression_names))
    reply = stub.Render(pb.RenderRequest(avatar_id="demo", width=SIZE, codec=pb.CODEC_PNG,
                                         frame=frame_params(3, coefficients, joints)))
    got = decode_image("png", reply.frame.data, SIZE, SIZE)
    assert np.abs(got.astype(int) - expected_image(reference, coefficients, joints).astype(int)).max() <= 1
    with pytest.raises(grpc.RpcError) as e:
        stub.Render(pb.RenderRequest(avatar_id="demo", frame=pb.FrameParams(eyelids=[1, 2, 3])))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "eyelids" in e.value.details()


TYPED_ERRORS = [  # (error raised by the engine, gRPC code, HTTP status): the one mapping in service.errors
    ("InvalidArgument", grpc.StatusCode.INVALID_ARGUMENT, 422),
    ("NotFound", grpc.StatusCode.NOT_FOUND, 404),
    ("ResourceExhausted", grpc.StatusCode.RESOURCE_EXHAUSTED, 429),
    ("FailedPrecondition", grpc.StatusCode.FAILED_PRECONDITION, 409),
    ("Unavailable", grpc.StatusCode.UNAVAILABLE, 503),
    ("CodecError", grpc.StatusCode.INVALID_ARGUMENT, 422),
    ("FrameError", grpc.StatusCode.INVALID_ARGUMENT, 422),
    ("OptionError", grpc.StatusCode.INVALID_ARGUMENT, 422),
]


def _error(name: str) -> Exception:
    import render_core.errors
    import service.errors

    cls = getattr(service.errors, name, None) or getattr(render_core.errors, name)
    return cls("made up for the test", field="some_field")


@pytest.mark.parametrize("name,code,http_status", TYPED_ERRORS, ids=[e[0] for e in TYPED_ERRORS])
def test_every_unary_rpc_maps_errors_to_their_status(live_server, stub, monkeypatch, name, code, http_status):
    """One helper turns an engine error into the call's status, for every RPC (ListAvatars included)."""
    engine = live_server.engine

    def fail(*args, **kwargs):
        raise _error(name)

    async def fail_async(*args, **kwargs):
        raise _error(name)

    for method in ("list_avatars", "avatar_info", "unload"):
        monkeypatch.setattr(engine, method, fail)
    for method in ("load", "render_once", "open"):
        monkeypatch.setattr(engine, method, fail_async)
    calls = [
        lambda: stub.ListAvatars(pb.ListAvatarsRequest()),
        lambda: stub.GetAvatar(pb.GetAvatarRequest(id="demo")),
        lambda: stub.LoadAvatar(pb.LoadAvatarRequest(id="demo")),
        lambda: stub.UnloadAvatar(pb.UnloadAvatarRequest(id="demo")),
        lambda: stub.Render(pb.RenderRequest(avatar_id="demo")),
        lambda: GrpcStream(stub, avatar_id="demo").next(),
    ]
    for call in calls:
        with pytest.raises(grpc.RpcError) as e:
            call()
        assert e.value.code() == code
        assert e.value.details() == "some_field: made up for the test"
    # The same errors over HTTP: the same table, as HTTP statuses.
    http = httpx.Client(base_url=live_server.http_url, timeout=60)
    for r in (http.get("/v1/avatars"), http.get("/v1/avatars/demo"), http.post("/v1/avatars/demo/load"),
              http.post("/v1/avatars/demo/unload"), http.post("/v1/render", json={"avatarId": "demo"})):
        assert r.status_code == http_status, r.text
        assert r.json()["error"]["field"] == "some_field"


def test_untyped_errors_are_internal_without_details(live_server, stub, monkeypatch):
    def fail(*args, **kwargs):
        raise KeyError("secret internals")

    monkeypatch.setattr(live_server.engine, "list_avatars", fail)
    with pytest.raises(grpc.RpcError) as e:
        stub.ListAvatars(pb.ListAvatarsRequest())
    assert e.value.code() == grpc.StatusCode.INTERNAL
    assert e.value.details() == "internal error (KeyError)"


def test_codec_settings_are_invalid_argument_naming_the_field(live_server, stub):
    """Codec settings fail as render_core's CodecError, which both transports map to INVALID_ARGUMENT / 422."""
    with pytest.raises(grpc.RpcError) as e:
        stub.Render(pb.RenderRequest(avatar_id="demo", width=SIZE, quality=101))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details().startswith("quality: must be an integer in [0, 100]"), e.value.details()
    r = httpx.post(live_server.http_url + "/v1/render", json={"avatarId": "demo", "width": SIZE, "quality": 101},
                   timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == "quality"
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE, codec=pb.CODEC_H264, fps_hint=-5.0)
    with pytest.raises(grpc.RpcError) as e:
        stream.next()
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and e.value.details().startswith("fps_hint: ")


def test_transports_call_only_the_engine():
    """The gRPC and HTTP adapters reach the avatar cache, the bundle store and the adapter store only through
    Engine methods (which apply who may do what)."""
    import ast
    import importlib
    import inspect
    import pkgutil

    import service.grpc_server
    import service.http
    from service.engine import Engine

    public = {name for name in dir(Engine) if not name.startswith("_")}
    http = [importlib.import_module(f"service.http.{m.name}") for m in pkgutil.iter_modules(service.http.__path__)]
    assert len(http) >= 6, http
    for module in (service.grpc_server, *http):
        tree = ast.parse(inspect.getsource(module))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert node.module not in ("cache", "store", "service.cache", "service.store"), module.__name__
            if isinstance(node, ast.Attribute):
                assert node.attr not in ("cache", "store", "adapters"), \
                    f"{module.__name__}:{node.lineno} uses .{node.attr}"
    for method in ("load", "unload", "replace", "list_avatars", "avatar_info", "readiness", "render_once", "open",
                   "list_adapters", "adapter_info", "put_adapter", "delete_adapter"):
        assert method in public, method


def test_engine_load_unload_replace(live_server, tmp_path):
    """The engine's avatar calls: replacing a loaded avatar drops the cached copy, so the next load serves the
    new bundle; unloading keeps the bundle."""
    engine, http = live_server.engine, httpx.Client(base_url=live_server.http_url, timeout=60)
    data = {}
    for n in (300, 200):
        write_bundle(synth_avatar(gaussians=n, blendshapes=3, seed=n), tmp_path / f"{n}.bundle", precision="fp16")
        data[n] = (tmp_path / f"{n}.bundle").read_bytes()

    async def chunks(blob: bytes):
        for i in range(0, len(blob), 4096):
            yield blob[i:i + 4096]

    try:
        info = live_server.call(engine.replace("swap", chunks(data[300])))
        assert (info.gaussians, info.loaded) == (300 + 300 // 8, False)
        loaded = live_server.call(engine.load("swap"))
        assert loaded.loaded and loaded.memory_bytes > loaded.file_bytes
        # Over HTTP, replacing it while it is loaded: the new bundle is what the next load gets.
        r = http.put("/v1/avatars/swap", content=data[200])
        assert r.status_code == 201 and r.json()["loaded"] is False and r.json()["gaussians"] == 200 + 25
        assert live_server.call(engine.load("swap")).gaussians == 200 + 25
        assert engine.unload("swap").loaded is False and engine.avatar_info("swap").loaded is False
        with pytest.raises(Exception, match="bundle: not a valid avatar bundle"):
            live_server.call(engine.replace("swap", chunks(b"hello")))
        assert engine.avatar_info("swap").gaussians == 200 + 25  # a failed upload left the store as it was
    finally:
        (engine.settings.bundle_dir / "swap.bundle").unlink(missing_ok=True)
        engine.cache.unload("swap")


def test_grpc_health_and_reflection(live_server):
    from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

    with grpc.insecure_channel(live_server.grpc_target) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        for service in ("", "blendsplat.v1.RenderService"):
            status = health.Check(health_pb2.HealthCheckRequest(service=service)).status
            assert status == health_pb2.HealthCheckResponse.SERVING
        stub = reflection_pb2_grpc.ServerReflectionStub(channel)
        reply = next(stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")])))
        names = {s.name for s in reply.list_services_response.service}
        assert {"blendsplat.v1.RenderService", "grpc.health.v1.Health"} <= names


def test_rest_avatars_render_and_errors(live_server, reference):
    http = httpx.Client(base_url=live_server.http_url, timeout=60)
    assert http.get("/healthz").json() == {"status": "ok"}
    ready = http.get("/readyz")
    assert ready.status_code == 200 and ready.json()["ready"] is True
    avatars = http.get("/v1/avatars").json()["avatars"]
    assert avatars[0]["id"] == "demo" and avatars[0]["expression_names"] == reference[0].expression_names
    assert http.get("/v1/avatars/nobody").status_code == 404
    assert http.post("/v1/avatars/demo/unload").json()["loaded"] is False
    assert http.post("/v1/avatars/demo/load").json()["loaded"] is True

    coefficients, joints = random_pose(np.random.default_rng(4), 8)
    body = {"avatarId": "demo", "width": SIZE, "codec": "CODEC_PNG",
            "frame": {"coefficients": coefficients, "joints": {k: {"values": v} for k, v in joints.items()}}}
    r = http.post("/v1/render", json=body)
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert "raster_ms" in r.headers["x-blendsplat-timings"] or "rasterMs" in r.headers["x-blendsplat-timings"]
    got = decode_image("png", r.content, SIZE, SIZE)
    assert np.abs(got.astype(int) - expected_image(reference, coefficients, joints).astype(int)).max() <= 1

    bad = http.post("/v1/render", json={"avatarId": "demo", "frame": {"coefficients": [1.0]}})
    assert bad.status_code == 422 and bad.json()["error"]["field"] == "coefficients"
    assert http.post("/v1/render", content=b"{nope").status_code == 422
    assert http.post("/v1/render", json={"avatarId": "ghost"}).status_code == 404
    assert http.get("/docs").status_code == 200
    paths = http.get("/openapi.json").json()["paths"]
    assert {"/v1/avatars", "/v1/avatars/{avatar_id}", "/v1/render", "/readyz"} <= set(paths)


def test_rest_upload_validates_before_storing(live_server, tmp_path):
    http = httpx.Client(base_url=live_server.http_url, timeout=60)
    store = live_server.engine.store
    bundle = tmp_path / "small.bundle"
    write_bundle(synth_avatar(gaussians=300, blendshapes=3, seed=8), bundle, precision="fp16")
    data = bundle.read_bytes()
    try:
        r = http.put("/v1/avatars/small", content=data)
        assert r.status_code == 201, r.text
        assert r.json()["gaussians"] == 300 + 300 // 8
        assert "small" in [a["id"] for a in http.get("/v1/avatars").json()["avatars"]]

        corrupt = bytearray(data)
        corrupt[-10] ^= 0xFF
        for body in (bytes(corrupt), data[: len(data) // 2], b"hello"):
            r = http.put("/v1/avatars/broken", content=body)
            assert r.status_code == 422 and r.json()["error"]["field"] == "bundle", r.text
        limit, live_server.engine.settings.max_upload_bytes = live_server.engine.settings.max_upload_bytes, 1024
        try:
            r = http.put("/v1/avatars/big", content=data)
            assert r.status_code == 413 and "larger than 1024 bytes" in r.json()["error"]["message"]
        finally:
            live_server.engine.settings.max_upload_bytes = limit
        assert http.put("/v1/avatars/..%2Fescape", content=data).status_code in (404, 422)
        assert sorted(store.ids()) == ["demo", "small"]
        assert not [p for p in store.root.iterdir() if p.name.endswith(".tmp")]  # nothing staged is left
    finally:
        store.path("small").unlink(missing_ok=True)
        live_server.engine.cache.unload("small")


def _metric(text: str, name: str, labels: str = "") -> float:
    for line in text.splitlines():
        if line.startswith(name + (labels and "{") ) and (not labels or labels in line):
            return float(line.rsplit(" ", 1)[1])
    return 0.0


def test_metrics_counters_move(live_server, stub):
    http = httpx.Client(base_url=live_server.http_url, timeout=60)
    before = http.get("/metrics").text
    stream = GrpcStream(stub, avatar_id="demo", width=SIZE, codec=pb.CODEC_JPEG)
    stream.next()
    stream.send(frame=pb.FrameParams(index=1))
    next_frame(stream)
    stream.send(frame=pb.FrameParams(index=2, coefficients=[1.0]))
    stream.next()
    stream.close()
    after = http.get("/metrics").text
    assert "# TYPE blendsplat_frames_total counter" in after
    for name, labels in (("blendsplat_frames_total", 'codec="jpeg"'), ("blendsplat_frame_bytes_total", 'codec="jpeg"'),
                         ("blendsplat_sessions_total", 'transport="grpc"'),
                         ("blendsplat_errors_total", 'code="INVALID_ARGUMENT",transport="grpc"'),
                         ("blendsplat_avatar_cache_hits_total", ""),
                         ("blendsplat_stage_seconds_count", 'stage="raster"')):
        assert _metric(after, name, labels) > _metric(before, name, labels), name
    assert _metric(after, "blendsplat_ready") == 1.0


def test_drain_flips_health_and_ends_streams_with_unavailable(tmp_path):
    from tests.conftest import LiveServer

    server = LiveServer(tmp_path, shutdown_delay_seconds=1.5, drain_seconds=5)
    http = httpx.Client(base_url=server.http_url, timeout=30)
    channel = grpc.insecure_channel(server.grpc_target)
    health = health_pb2_grpc.HealthStub(channel)
    stub = pb_grpc.RenderServiceStub(channel)
    try:
        stream = GrpcStream(stub, avatar_id="demo", width=SIZE)
        stream.next()
        ws = WsStream(server.ws_url, avatar_id="demo", width=SIZE)
        ws.next()
        assert http.get("/readyz").status_code == 200
        stopping = __import__("asyncio").run_coroutine_threadsafe(server.service.stop(), server.loop)
        time.sleep(0.3)
        # Not ready at once, but open streams still get frames during the shutdown delay.
        r = http.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["not_draining"] is False
        assert health.Check(health_pb2.HealthCheckRequest(service="")).status == \
            health_pb2.HealthCheckResponse.NOT_SERVING
        with pytest.raises(grpc.RpcError) as e:
            late = GrpcStream(stub, avatar_id="demo", width=SIZE)
            late.next()
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE
        stream.send(frame=pb.FrameParams(index=5))
        assert next_frame(stream).index == 5
        ws.send(frame=pb.FrameParams(index=6))
        assert next_frame(ws).index == 6
        # Then every stream ends with UNAVAILABLE, and so does the gRPC call.
        assert stream.next().status.code == pb.UNAVAILABLE
        with pytest.raises(grpc.RpcError) as e:
            stream.next()
        assert e.value.code() == grpc.StatusCode.UNAVAILABLE
        assert ws.next().status.code == pb.UNAVAILABLE
        stopping.result(30)
    finally:
        channel.close()
        server.loop.call_soon_threadsafe(server.loop.stop)
        server.thread.join(10)


def test_settings_come_from_the_environment(monkeypatch, tmp_path):
    from pydantic import ValidationError

    from service.settings import Settings

    monkeypatch.setenv("BLENDSPLAT_MAX_SESSIONS", "7")
    monkeypatch.setenv("BLENDSPLAT_DATA_DIR", str(tmp_path))
    s = Settings()
    assert s.max_sessions == 7 and s.bundle_dir == tmp_path / "bundles"
    monkeypatch.setenv("BLENDSPLAT_GRPC_PORT", "99999")
    with pytest.raises(ValidationError, match="grpc_port"):
        Settings()


def test_error_json_shape(live_server):
    r = httpx.get(live_server.http_url + "/v1/avatars/no-such-avatar")
    error = r.json()["error"]
    assert r.status_code == 404 and error["code"] == "NOT_FOUND" and error["field"] == "avatar_id"
    assert json.loads(json.dumps(error))


def test_bench_stream_cli_reports_fps_latency_and_flat_memory(live_server, capsys):
    from service.cli import main

    assert main(["bench", "stream", "--target", live_server.grpc_target, "--avatar", "demo", "--streams", "2",
                 "--seconds", "1", "--warmup", "0.2", "--fps", "20", "--size", "32", "--codec", "png", "--json",
                 "--metrics-url", live_server.http_url + "/metrics"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert {"streams", "gaussians", "size", "codec", "fps_per_stream", "latency_ms", "dropped", "errors"} <= set(report)
    assert report["streams"] == 2 and report["gaussians"] == 3000 and report["codec"] == "png"
    assert report["errors"] == 0 and report["fps_per_stream"] > 0
    assert report["latency_ms"]["p50"] <= report["latency_ms"]["p99"]
    assert report["server_rss_mb"]["before"] > 0

    assert main(["bench", "stream", "--target", live_server.grpc_target, "--avatar", "demo", "--seconds", "1",
                 "--warmup", "0", "--fps", "100", "--size", "32", "--no-ack", "--json"]) == 0
    stalled = json.loads(capsys.readouterr().out)
    assert stalled["frames"] == 2 and stalled["dropped"] > 50  # max_in_flight frames, the rest dropped


def _strict(name):
    raise ValueError(f"not strict JSON: {name}")


def test_bench_stream_reads_the_server_s_memory_and_prints_strict_json_when_no_frame_arrives(live_server, capsys,
                                                                                               monkeypatch):
    from service import bench_stream
    from service.cli import build_parser, main

    assert build_parser().parse_args(["bench", "stream", "--avatar", "demo"]).target == "127.0.0.1:50051"
    assert bench_stream.default_metrics_url("10.1.2.3:50051") == "http://10.1.2.3:8080/metrics"
    # Without --metrics-url the server's /metrics is found from the target (here: the live server's, on its port).
    monkeypatch.setattr(bench_stream, "default_metrics_url", lambda target: live_server.http_url + "/metrics")
    base = ["bench", "stream", "--target", live_server.grpc_target, "--seconds", "0.5", "--warmup", "0", "--size",
            "32", "--json"]
    assert main([*base, "--avatar", "demo"]) == 0
    report = json.loads(capsys.readouterr().out, parse_constant=_strict)
    assert report["server_rss_mb"]["before"] > 0 and report["server_rss_mb"]["end"] > 0
    # No frame at all (an unknown avatar): exit 1, the reason on stderr, and the figures null, never NaN.
    assert main([*base, "--avatar", "no-such-avatar"]) == 1
    out, err = capsys.readouterr()
    failed = json.loads(out, parse_constant=_strict)
    assert failed["frames"] == 0 and failed["latency_ms"]["p50"] is None and failed["server_ms"]["p99"] is None
    assert "no frames from" in err and "no-such-avatar" in err
    # A /metrics that cannot be read: null, and the report and stderr say why.
    monkeypatch.setattr(bench_stream, "default_metrics_url", lambda target: "http://127.0.0.1:9/metrics")
    assert main([*base, "--avatar", "demo"]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out, parse_constant=_strict)
    assert report["server_rss_mb"] == {"before": None, "end": None} and "127.0.0.1:9" in report["server_rss_note"]
    assert "server_rss_mb is null" in err


def test_bench_stream_against_a_closed_port_exits_non_zero_saying_why():
    """What a newcomer types with a wrong port: a quick failure, the reason on stderr, stdout empty or strict JSON."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "service.cli", "bench", "stream", "--target", "127.0.0.1:1",
                           "--avatar", "demo", "--streams", "1", "--seconds", "1", "--json"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and done.stderr.strip()
    assert "127.0.0.1:1" in done.stderr and "blendsplat serve" in done.stderr
    for line in done.stdout.splitlines():
        json.loads(line, parse_constant=_strict)


def test_serve_command_starts_ready_and_exits_cleanly_on_sigterm(tmp_path):
    """The real `blendsplat serve` process: demo avatar on first start, ready, then SIGTERM drains and exits 0."""
    import os
    import signal
    import socket
    import subprocess
    import sys

    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    env = {k: v for k, v in os.environ.items() if k != "BLENDSPLAT_HOST"}  # the default host: 127.0.0.1
    env.update(BLENDSPLAT_DEMO_GAUSSIANS="2000", BLENDSPLAT_DEMO_AVATAR="open-head", BLENDSPLAT_WARMUP_SIZE="64",
               BLENDSPLAT_DRAIN_SECONDS="3")
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--grpc-port", str(ports[0]),
                             "--http-port", str(ports[1]), "--data-dir", str(tmp_path)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"http://127.0.0.1:{ports[1]}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None, proc.stdout.read()
            time.sleep(0.2)
        else:
            pytest.fail("the service did not become ready")
        assert (tmp_path / "bundles" / "demo.bundle").is_file()
        assert listening_addresses(ports[1]) in ({"127.0.0.1"}, None)  # this machine only, unless told otherwise
        key = (tmp_path / "admin.key").read_text().strip()  # secure by default: an admin key was created
        assert (tmp_path / "admin.key").stat().st_mode & 0o777 == 0o600
        with grpc.insecure_channel(f"127.0.0.1:{ports[0]}") as channel:
            stream = GrpcStream(pb_grpc.RenderServiceStub(channel), api_key=key, avatar_id="demo", width=SIZE)
            header = stream.next().header
            assert header.gaussians == 2000 and "jawOpen" in header.expression_names  # the open head's
            proc.send_signal(signal.SIGTERM)
            assert stream.next().status.code == pb.UNAVAILABLE
        assert proc.wait(timeout=20) == 0
        log = proc.stdout.read()
        assert "draining" in log
        # The start-up log says what to open.
        for page in ("demo", "docs", "jobs"):
            assert f"http://127.0.0.1:{ports[1]}/{page}" in log, log[-2000:]
        assert f"gRPC streams: 127.0.0.1:{ports[0]}" in log
    finally:
        proc.kill()
        proc.wait()


def listening_addresses(port: int) -> set[str] | None:
    """The IPv4 addresses a TCP socket listens on at ``port`` (Linux's /proc/net/tcp; None elsewhere)."""
    import ipaddress
    from pathlib import Path

    try:
        lines = Path("/proc/net/tcp").read_text().splitlines()[1:]
    except OSError:
        return None
    found = set()
    for line in lines:
        local, state = line.split()[1], line.split()[3]
        address, hex_port = local.split(":")
        if state == "0A" and int(hex_port, 16) == port:  # LISTEN
            found.add(str(ipaddress.IPv4Address(bytes.fromhex(address)[::-1])))
    return found


def test_the_addresses_to_open():
    from service.server import open_urls

    assert open_urls("127.0.0.1", 8080, 50051) == {
        "demo": "http://127.0.0.1:8080/demo", "docs": "http://127.0.0.1:8080/docs",
        "jobs": "http://127.0.0.1:8080/jobs", "grpc": "127.0.0.1:50051"}
    assert open_urls("0.0.0.0", 8443, 50051, tls=True)["demo"] == "https://127.0.0.1:8443/demo"
    assert open_urls("::", 80, 1)["jobs"] == "http://127.0.0.1:80/jobs"
    assert open_urls("::1", 80, 1)["docs"] == "http://[::1]:80/docs"
    assert open_urls("10.0.0.7", 80, 1)["grpc"] == "10.0.0.7:1"


def test_avatar_cache_is_lru_under_its_budget_and_keeps_avatars_in_use(tmp_path):
    import asyncio

    from service.cache import AvatarCache
    from service.errors import NotFound, ResourceExhausted
    from service.metrics import Metrics
    from service.store import BundleStore

    store = BundleStore(tmp_path)
    store.ensure()
    for name in ("a", "b", "c"):
        write_bundle(synth_avatar(gaussians=400, blendshapes=3, seed=ord(name)), store.path(name))

    async def scenario():
        probe = AvatarCache(store, 1 << 40, Metrics())
        one = (await probe.load("a")).memory_bytes
        cache = AvatarCache(store, int(2.5 * one), Metrics())  # room for two
        a = await cache.acquire("a")  # in use: never evicted
        await cache.load("b")
        await cache.load("c")  # evicts b, the least recently used one not in use
        assert cache.loaded_ids() == ["a", "c"]
        again = await cache.load("a")
        assert again is a and cache.metrics.cache_hits._value.get() == 1
        cache.release(a)
        await cache.load("b")  # evicts c: a was used more recently
        assert cache.loaded_ids() == ["a", "b"]
        both = [await cache.acquire(i) for i in cache.loaded_ids()]
        missing = [i for i in ("a", "b", "c") if i not in cache.loaded_ids()][0]
        try:
            await cache.load(missing)
            raise AssertionError("loaded past the budget with every avatar in use")
        except ResourceExhausted as e:
            assert "in use" in str(e)
        for entry in both:
            cache.release(entry)
        try:
            await cache.load("zzz")
            raise AssertionError("unknown avatar loaded")
        except NotFound:
            pass
        # Concurrent requests for one avatar share one load.
        fresh = AvatarCache(store, 1 << 40, Metrics())
        x, y = await asyncio.gather(fresh.load("c"), fresh.load("c"))
        assert x is y and fresh.metrics.cache_misses._value.get() == 1
        # An entry counts the file plus what its renderer holds (the native packing here).
        assert x.memory_bytes == x.file_bytes + x.renderer.nbytes and x.renderer.nbytes > 0

    asyncio.run(scenario())


def test_avatar_cache_counts_the_cuda_backends_device_memory(tmp_path, monkeypatch):
    """A cuda avatar's entry counts its GPU copy (the cuda path emulated on the CPU), not just the file."""
    import asyncio

    pytest.importorskip("gsplat", reason="gsplat is not installed")
    import gsplat_cpu

    from service.cache import AvatarCache
    from service.metrics import Metrics
    from service.store import BundleStore

    gsplat_cpu.emulate_cuda_backend(monkeypatch)
    store = BundleStore(tmp_path)
    store.ensure()
    write_bundle(synth_avatar(gaussians=400, blendshapes=3, seed=1), store.path("a"), precision="fp16")
    entry = asyncio.run(AvatarCache(store, 1 << 40, Metrics(), backend="cuda").load("a"))
    assert entry.renderer.backend == "cuda"
    device = entry.renderer.device_avatar
    assert entry.memory_bytes == entry.file_bytes + entry.renderer.nbytes
    assert entry.renderer.nbytes >= device.nbytes > 0
