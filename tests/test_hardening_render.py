"""Hardening (issue 14), the render path, against the real servers on loopback: every frame parameter is validated in
one place (service/params.py) before it joins a batch, for every transport, with the field named; a frame that fails
to render fails only its own session; per-frame work has a budget and sessions share the render thread fairly; error
texts are bounded; frame indices strictly increase and acks name frames that were answered."""

from __future__ import annotations

import math
import queue
import threading
import time

import grpc
import httpx
import numpy as np
import pytest
from google.protobuf import json_format
from websockets.sync.client import connect

from blendsplat.v1 import render_pb2 as pb
from blendsplat.v1 import render_pb2_grpc as pb_grpc
from render_core.drive import default_camera
from service import params

SIZE = 32
EYE = [1.0, 0, 0, 0, 1, 0, 0, 0, 1]
GOOD_K = [40.0, 0, 16, 0, 40, 16, 0, 0, 1]


@pytest.fixture(scope="module")
def stub(live_server):
    with grpc.insecure_channel(live_server.grpc_target) as channel:
        yield pb_grpc.RenderServiceStub(channel)


class Stream:
    """A gRPC RenderStream: requests from a queue, every reply collected by a reader thread (frames acked at once
    when ``auto_ack``)."""

    def __init__(self, stub, auto_ack: bool = False, **config):
        self.requests: queue.Queue = queue.Queue()
        self.replies: queue.Queue = queue.Queue()
        self.auto_ack = auto_ack
        self.send(open=pb.SessionConfig(**config))
        self._responses = stub.RenderStream(iter(self.requests.get, None))
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.header = self.next().header

    def _read(self) -> None:
        try:
            for reply in self._responses:
                if self.auto_ack and reply.HasField("frame"):
                    self.send(ack=pb.Ack(index=reply.frame.index))
                self.replies.put(reply)
        except grpc.RpcError as e:
            self.replies.put(e)
        self.replies.put(None)

    def send(self, **message) -> None:
        self.requests.put(pb.StreamRequest(**message))

    def next(self, timeout: float = 60) -> pb.StreamResponse:
        reply = self.replies.get(timeout=timeout)
        if isinstance(reply, grpc.RpcError):
            raise reply
        assert reply is not None, "the stream ended"
        return reply

    def close(self) -> list[pb.StreamResponse]:
        """Half-close; every reply left, the final status last."""
        self.requests.put(None)
        self._reader.join(60)
        out = []
        while (reply := self.replies.get_nowait()) is not None:
            out.append(reply)
        return out


def expect_error(stream: Stream, code: int, field: str) -> pb.Status:
    reply = stream.next()
    assert reply.WhichOneof("msg") == "error", reply
    assert (reply.error.code, reply.error.field) == (code, field), reply.error
    return reply.error


def expect_frame(stream: Stream, index: int) -> pb.RenderedFrame:
    reply = stream.next()
    assert reply.WhichOneof("msg") == "frame", reply
    assert reply.frame.index == index
    return reply.frame


def opencv(k=GOOD_K, r=EYE, t=(0, 0, 0.6), width=SIZE, height=SIZE) -> pb.Camera:
    return pb.Camera(opencv=pb.OpenCVCamera(k=k, r=r, t=t, width=width, height=height))


# ------------------------------------------------------------------------------------------------ fuzzing
NAN, INF = float("nan"), float("inf")


def fuzz_params(rng: np.random.Generator, names: list[str], joints: list[str], huge: bool = True
                ) -> tuple[pb.FrameParams, bool | None]:
    """Random frame parameters and whether they are valid (True), invalid (False) or either (None); ``huge``:
    lists of 100,000 coefficients and 10,000 names among them."""
    weird = [NAN, INF, -INF, 0.0, -1.0, 1e30, -1e30, 1e-30, 3e38]
    msg, valid = pb.FrameParams(), True

    def bad(v=False):
        nonlocal valid
        valid = v if valid is True else (False if v is False else valid)

    case = rng.integers(0, 14)
    if case == 0:  # a valid pose
        msg.coefficients.extend(rng.uniform(0, 1, len(names)).tolist())
        msg.joints["jaw"].values.extend(rng.normal(0, 0.2, 3).tolist())
    elif case == 1:  # camera intrinsics: non-positive, non-finite or not a pinhole
        k = list(GOOD_K)
        pos = int(rng.integers(0, 9))
        choices = {0: [0.0, -40.0, NAN, INF], 4: [0.0, -1e-3, -INF], 8: [0.0, 2.0, NAN], 2: [NAN, INF],
                   5: [-INF, NAN]}.get(pos, [3.0, NAN, -INF, 0.5])
        k[pos] = float(rng.choice(choices))
        msg.camera.CopyFrom(opencv(k=k))
        bad()
    elif case == 2:  # a rotation that is not one: scaled, sheared, reflected, zero, non-finite
        r = np.eye(3)
        kind = rng.integers(0, 5)
        r = [r * 2, r + np.triu(np.ones((3, 3)), 1) * 0.5, np.diag([1.0, 1, -1]), np.zeros((3, 3)),
             np.full((3, 3), NAN)][kind]
        msg.camera.CopyFrom(opencv(r=r.ravel().tolist()))
        bad()
    elif case == 3:  # a random true rotation and a translation in front or anywhere
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.linalg.det(q))
        msg.camera.CopyFrom(opencv(r=q.ravel().tolist(), t=rng.normal(0, 1, 3).tolist()))
    elif case == 4:  # wrong lengths, a missing calibrated size
        which = rng.integers(0, 4)
        if which == 3:
            msg.camera.CopyFrom(opencv(width=0))
        else:
            lists = [GOOD_K, EYE, [0, 0, 0.6]]
            n = len(lists[which])
            lists[which] = (lists[which] * 2)[: int(rng.choice([i for i in range(2 * n) if i != n]))]
            msg.camera.CopyFrom(opencv(*lists))
        bad()
    elif case == 5:  # orbits, valid or not
        yaw, pitch, dist = (float(rng.choice([rng.uniform(-180, 180), *weird])) for _ in range(3))
        msg.camera.orbit.CopyFrom(pb.Orbit(yaw_deg=yaw, pitch_deg=pitch, distance=dist))
        if not all(math.isfinite(v) for v in (yaw, pitch, dist)) or dist < 0 or abs(pitch) >= 90:
            bad()
        else:
            bad(None)  # e.g. a distance that underflows
    elif case == 6:  # presets
        preset = str(rng.choice(["front", "left", "right", "up", "down", "behind", "", "x" * 5000]))
        msg.camera.preset = preset
        if preset not in ("front", "left", "right", "up", "down"):
            bad()
    elif case == 7:  # coefficients: wrong counts (huge lists too), non-finite, large
        counts = [1, len(names) - 1, len(names) + 1] + ([100_000] if huge else [])
        n = int(rng.choice(counts)) if rng.random() < 0.5 else len(names)
        values = rng.uniform(-1, 1, n).tolist()
        if n == len(names):
            values[int(rng.integers(0, n))] = float(rng.choice(weird))
        msg.coefficients.extend(values)
        if n != len(names) or not all(math.isfinite(v) for v in values):
            bad()
    elif case == 8:  # names: unknown ones (many), non-finite values
        if rng.random() < 0.5:
            for i in range(int(rng.choice([1, 10_000] if huge else [1, 50]))):
                msg.named_coefficients[f"nobody_{i}"] = 1.0
        else:
            msg.named_coefficients[names[0]] = float(rng.choice(weird[:3]))
        bad()
    elif case == 9:  # joint rotations: sizes, degenerate 6D, non-finite, huge angles, unknown joints
        joint = str(rng.choice(joints))
        values = [[0.0] * 6, [1, 0, 0, 2, 0, 0], [NAN, 0, 0], [0, 0], [0.0] * 9, [1e30, 0, 0], [1, 0, 0, 0, 1, 0],
                  rng.normal(0, 1, 3).tolist()][int(rng.integers(0, 8))]
        if rng.random() < 0.1:
            joint = "tail"
        msg.joints[joint].values.extend(values)
        ok = joint != "tail" and (values == [1, 0, 0, 0, 1, 0] or (len(values) == 3 and abs(values[0]) < 1e3
                                                                    and all(map(math.isfinite, values))))
        bad(True if ok else False)
    elif case == 10:  # eyelids
        values = [[0.2, 0.3], [0.5], [], [0.1, 0.2, 0.3], [NAN, 0], [1e30, 1e30]][int(rng.integers(0, 6))]
        msg.eyelids.extend(values)
        if len(values) not in (0, 2) or not all(map(math.isfinite, values)):
            bad()
        elif values and abs(values[0]) > 1e6:
            bad(None)
    elif case == 11:  # backgrounds
        c = [float(rng.choice([0.0, 0.5, 1.0, -0.1, 1.5, NAN])) for _ in range(3)]
        msg.background.CopyFrom(pb.Color(r=c[0], g=c[1], b=c[2]))
        if not all(math.isfinite(v) and 0 <= v <= 1 for v in c):
            bad()
    elif case == 12:  # coefficients and names together
        msg.coefficients.extend([0.0] * len(names))
        msg.named_coefficients[names[0]] = 1.0
        bad()
    else:  # far too close, far away, behind
        msg.camera.CopyFrom(opencv(t=[0, 0, float(rng.choice([0.02, 1e6, -0.6, 1e-7]))]))
    return msg, valid


def test_fuzzed_frames_never_get_internal_and_a_neighbour_keeps_its_frames(live_server, stub):
    """Random valid and invalid frame parameters on one stream, while a well-behaved stream of the same avatar and
    size (so the two batch) gets every frame it asks for; nothing is ever INTERNAL, every refusal names a field,
    every invalid frame is refused and no valid one is."""
    fuzzed = Stream(stub, auto_ack=True, avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, max_in_flight=4)
    good = Stream(stub, avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA)
    names, joints = list(fuzzed.header.expression_names), list(fuzzed.header.joint_names)
    rng = np.random.default_rng(14)
    sent: dict[int, bool | None] = {}
    stop = threading.Event()
    good_frames: list[int] = []

    def well_behaved() -> None:
        i = 0
        while not stop.is_set():
            i += 1
            good.send(frame=pb.FrameParams(index=i, named_coefficients={names[1]: (i % 10) / 10}))
            reply = good.next()
            assert reply.WhichOneof("msg") == "frame" and reply.frame.index == i, reply
            good_frames.append(i)
            good.send(ack=pb.Ack(index=i))

    neighbour = threading.Thread(target=well_behaved, daemon=True)
    neighbour.start()
    index = 0
    for _ in range(240):
        msg, valid = fuzz_params(rng, names, joints)
        index += 1
        msg.index = index
        sent[index] = valid
        fuzzed.send(frame=msg)
        time.sleep(0.004)
    time.sleep(1.0)
    stop.set()
    neighbour.join(60)
    replies = fuzzed.close()
    good_rest = good.close()

    assert not neighbour.is_alive() and len(good_frames) >= 10
    assert [r.WhichOneof("msg") for r in good_rest] == ["status"] and good_rest[-1].status.code == pb.OK
    errors = [r.error for r in replies if r.HasField("error")]
    frames = [r.frame.index for r in replies if r.HasField("frame")]
    assert replies[-1].status.code == pb.OK and replies[-1].status.frames_sent == len(frames)
    assert all(e.code in (pb.INVALID_ARGUMENT, pb.RESOURCE_EXHAUSTED) and e.field for e in errors), errors
    assert all(len(e.message) <= 1000 for e in errors)
    refused = {e.frame_index for e in errors}
    assert {i for i, v in sent.items() if v is False} <= refused
    assert not {i for i, v in sent.items() if v is True} & refused
    assert not set(frames) & refused and len(frames) >= 10


def test_fuzzed_frames_over_websocket_and_rest_never_get_500(live_server):
    """The same parameters over the WebSocket (protobuf JSON) and POST /v1/render: 200, or a named 4xx."""
    rng = np.random.default_rng(41)
    http = httpx.Client(base_url=live_server.http_url, timeout=60)
    names = http.get("/v1/avatars/demo").json()["expression_names"]
    joints = http.get("/v1/avatars/demo").json()["joint_names"]
    with connect(live_server.ws_url, max_size=64 << 20, open_timeout=30) as ws:
        open_ = pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=SIZE, max_in_flight=16))
        ws.send(json_format.MessageToJson(open_))
        assert json_format.Parse(ws.recv(timeout=60), pb.StreamResponse()).HasField("header")
        for i in range(1, 41):
            msg, valid = fuzz_params(rng, names, joints, huge=False)
            msg.index = i
            ws.send(json_format.MessageToJson(pb.StreamRequest(frame=msg)))
            reply = json_format.Parse(ws.recv(timeout=60), pb.StreamResponse())
            if reply.HasField("frame"):
                assert valid is not False, msg
                ws.send(json_format.MessageToJson(pb.StreamRequest(ack=pb.Ack(index=i))))
            else:
                assert reply.error.code in (pb.INVALID_ARGUMENT, pb.RESOURCE_EXHAUSTED) and reply.error.field
                assert valid is not True and reply.error.frame_index == i, (msg, reply)
    for _ in range(30):
        msg, valid = fuzz_params(rng, names, joints)
        body = json_format.MessageToJson(pb.RenderRequest(avatar_id="demo", width=SIZE, frame=msg))
        r = http.post("/v1/render", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code in (200, 413, 422, 429), r.text[:300]
        if r.status_code != 200:
            assert valid is not True and r.json()["error"]["field"] and len(r.content) < 2000
        else:
            assert valid is not False, msg


def test_fuzzed_sizes_codecs_and_names_get_a_frame_or_a_named_error(live_server, stub):
    """Render (and stream opens) with random output sizes, codecs, qualities, name orders and cameras."""
    rng = np.random.default_rng(7)
    names = list(stub.GetAvatar(pb.GetAvatarRequest(id="demo")).expression_names)
    for i in range(40):
        width, height = (int(rng.choice([0, 1, 2, 15, 33, 64, 2048, 2049, 1 << 31])) for _ in range(2))
        codec = int(rng.choice([0, 1, 2, 3, 4, 42]))
        order = [list(rng.permutation(names)), names[:2], names + names[:1], ["x" * 300], []][int(rng.integers(0, 5))]
        frame, _ = fuzz_params(rng, names, ["jaw", "neck"], huge=False)
        if order and frame.coefficients:
            del frame.coefficients[:]
        request = pb.RenderRequest(avatar_id="demo", width=width, height=height, codec=codec,
                                   quality=int(rng.choice([0, 50, 101])), expression_names=order, frame=frame)
        try:
            reply = stub.Render(request)
            assert reply.frame.data and reply.frame.width == (width or height or 512)
        except grpc.RpcError as e:
            assert e.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.RESOURCE_EXHAUSTED), e
            assert ":" in e.details() and len(e.details()) < 1200, e.details()
        if i % 8 == 0:  # the same as a stream's open
            config = pb.SessionConfig(avatar_id="demo", width=width, height=height, codec=codec,
                                      expression_names=order, camera=frame.camera if frame.HasField("camera") else None)
            try:
                stream = Stream(stub, **{f.name: v for f, v in config.ListFields()})
                stream.close()
            except grpc.RpcError as e:
                assert e.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.RESOURCE_EXHAUSTED), e


# ------------------------------------------------------------------------------- finding 2: camera checks
BAD_CAMERAS = [
    ("fx = 0", opencv(k=[0, 0, 16, 0, 40, 16, 0, 0, 1]), "camera.opencv.k"),
    ("fy < 0", opencv(k=[40, 0, 16, 0, -40, 16, 0, 0, 1]), "camera.opencv.k"),
    ("skew", opencv(k=[40, 2, 16, 0, 40, 16, 0, 0, 1]), "camera.opencv.k"),
    ("K NaN", opencv(k=[NAN, 0, 16, 0, 40, 16, 0, 0, 1]), "camera.opencv.k"),
    ("scaled R", opencv(r=[2, 0, 0, 0, 2, 0, 0, 0, 2]), "camera.opencv.r"),
    ("sheared R", opencv(r=[1, 0.5, 0, 0, 1, 0, 0, 0, 1]), "camera.opencv.r"),
    ("det -1", opencv(r=[1, 0, 0, 0, 1, 0, 0, 0, -1]), "camera.opencv.r"),
    ("zero R", opencv(r=[0.0] * 9), "camera.opencv.r"),
    ("t inf", opencv(t=[0, INF, 0.6]), "camera.opencv.t"),
    ("orbit pitch 90", pb.Camera(orbit=pb.Orbit(pitch_deg=90)), "camera.orbit.pitch_deg"),
    ("orbit distance < 0", pb.Camera(orbit=pb.Orbit(distance=-1)), "camera.orbit.distance"),
    ("orbit yaw NaN", pb.Camera(orbit=pb.Orbit(yaw_deg=NAN)), "camera.orbit.yaw_deg"),
    ("orbit on the target", pb.Camera(orbit=pb.Orbit(distance=1e-30)), "camera.orbit"),
]


@pytest.mark.parametrize("name,cam,field", BAD_CAMERAS, ids=[c[0] for c in BAD_CAMERAS])
def test_a_bad_camera_is_refused_naming_its_field_in_every_transport(live_server, stub, name, cam, field):
    """One check (service/params.py) for every way a camera arrives: a stream's frame and its open (gRPC), a
    WebSocket frame, the Render RPC and POST /v1/render."""
    stream = Stream(stub, avatar_id="demo", width=SIZE)
    stream.send(frame=pb.FrameParams(index=1, camera=cam))
    assert expect_error(stream, pb.INVALID_ARGUMENT, field).frame_index == 1
    stream.send(frame=pb.FrameParams(index=2))
    expect_frame(stream, 2)
    assert stream.close()[-1].status.code == pb.OK
    with pytest.raises(grpc.RpcError) as e:
        Stream(stub, avatar_id="demo", width=SIZE, camera=cam)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and e.value.details().startswith(field + ":")
    with pytest.raises(grpc.RpcError) as e:
        stub.Render(pb.RenderRequest(avatar_id="demo", width=SIZE, frame=pb.FrameParams(camera=cam)))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and e.value.details().startswith(field + ":")
    body = json_format.MessageToJson(pb.RenderRequest(avatar_id="demo", width=SIZE, frame=pb.FrameParams(camera=cam)))
    r = httpx.post(live_server.http_url + "/v1/render", content=body, timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == field
    with connect(live_server.ws_url, open_timeout=30) as ws:
        ws.send(pb.StreamRequest(open=pb.SessionConfig(avatar_id="demo", width=SIZE)).SerializeToString())
        assert pb.StreamResponse.FromString(ws.recv(timeout=60)).HasField("header")
        ws.send(pb.StreamRequest(frame=pb.FrameParams(index=1, camera=cam)).SerializeToString())
        reply = pb.StreamResponse.FromString(ws.recv(timeout=60))
        assert (reply.error.code, reply.error.field) == (pb.INVALID_ARGUMENT, field)


def test_joint_rotations_that_are_not_rotations_are_refused_naming_the_joint(stub):
    stream = Stream(stub, avatar_id="demo", width=SIZE)
    for i, values in enumerate(([0.0] * 6, [1, 0, 0, 2, 0, 0], [1e30, 0, 0]), start=1):
        stream.send(frame=pb.FrameParams(index=i, joints={"jaw": pb.Rotation(values=values)}))
        expect_error(stream, pb.INVALID_ARGUMENT, "joints.jaw")
    stream.send(frame=pb.FrameParams(index=9, joints={"jaw": pb.Rotation(values=[2, 0, 0, 0, 3, 0])}))  # 6D: scaled
    expect_frame(stream, 9)
    stream.close()


# --------------------------------------------------------------------------------------------- isolation
MAGIC = (0.125, 0.25, 0.375)  # a background the fault below answers with an exception


def test_a_frame_that_fails_to_render_fails_only_its_own_session(live_server, monkeypatch):
    """Two sessions of one avatar batched together; the renderer fails on one session's frame (a stand-in for any
    renderer fault an input could trigger). Only that session gets an error, naming its frame, not INTERNAL; the
    other gets its frame; both go on."""
    engine = live_server.engine
    calls: list[int] = []

    async def two_sessions():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA)
        sessions = [await engine.open(config, "test") for _ in range(2)]
        renderer = sessions[0].entry.renderer
        render = renderer.render_rgba8  # what the engine calls

        def faulty(frame, cameras, background=None, **kwargs):
            calls.append(frame.batch_size)
            if background is not None and any(np.allclose(b.tolist(), MAGIC) for b in background.reshape(-1, 3)):
                raise RuntimeError("the rasterizer gave up")
            return render(frame, cameras, background, **kwargs)

        monkeypatch.setattr(renderer, "render_rgba8", faulty)
        out = []
        for round_ in (1, 2):
            for i, s in enumerate(sessions):  # both poses arrive before the scheduler runs: one batch
                bg = pb.Color(r=MAGIC[0], g=MAGIC[1], b=MAGIC[2]) if i == 0 and round_ == 1 else pb.Color()
                s.handle(pb.StreamRequest(frame=pb.FrameParams(index=round_, background=bg)))
            for s in sessions:
                async for reply in s.responses():
                    out.append(reply)
                    break
                if out[-1].HasField("frame"):
                    s.handle(pb.StreamRequest(ack=pb.Ack(index=round_)))
        for s in sessions:
            s.end_input()
        return out

    first_bad, first_good, second_a, second_b = live_server.call(two_sessions())
    assert calls[:3] == [2, 1, 1]  # the batch, then each frame alone
    assert first_bad.HasField("error") and first_bad.error.code == pb.INVALID_ARGUMENT
    assert first_bad.error.field == "frame" and first_bad.error.frame_index == 1
    assert first_good.HasField("frame") and first_good.frame.index == 1
    assert second_a.frame.index == 2 and second_b.frame.index == 2  # both sessions go on
    assert second_a.frame.timings.batch == 2


# ------------------------------------------------------------------------------- finding 5: budget, fairness
def test_a_reference_render_runs_alone_with_every_mechanism_off_within_a_level_of_a_normal_one(stub, monkeypatch):
    """RenderRequest.reference (what `bench stream --verify` asks for): the native renderer's baseline schedule,
    never batched with other frames; the pixels are those of a normal render within one level (the 8-bit stop is
    the one mechanism that changes them)."""
    from render_core.raster.native import Schedule
    from render_core.renderer import AvatarRenderer

    seen = []
    render = AvatarRenderer.render_rgba8

    def spy(self, frame, *args, **kwargs):
        seen.append((frame.batch_size, kwargs.get("schedule")))
        return render(self, frame, *args, **kwargs)

    monkeypatch.setattr(AvatarRenderer, "render_rgba8", spy)
    pose = pb.FrameParams(joints={"neck": pb.Rotation(values=[0.1, 0.2, 0])})
    frames = {ref: stub.Render(pb.RenderRequest(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, frame=pose,
                                                reference=ref)).frame for ref in (True, False)}
    assert seen == [(1, Schedule.baseline()), (1, None)]
    exact, fast = (np.frombuffer(frames[ref].data, np.uint8).astype(np.int32) for ref in (True, False))
    assert exact.size == SIZE * SIZE * 4 and np.abs(exact - fast).max() <= 1


def test_a_frame_over_the_budget_is_refused_naming_the_size_or_camera(live_server, stub, monkeypatch):
    engine = live_server.engine
    avatar = engine.cache.get("demo").avatar
    out = params.output(SIZE, SIZE, pb.CODEC_JPEG, 0, 2048)
    closer = pb.Camera(orbit=pb.Orbit(distance=0.3))  # the avatar's own camera is at 0.6 m
    small = params.frame_cost(avatar, default_camera(avatar, SIZE, SIZE))
    close = params.frame_cost(avatar, params.camera(avatar, closer, out))
    large = params.frame_cost(avatar, default_camera(avatar, 512, 512))
    assert large > 50 * small > 0 and close > 1.2 * small  # the estimate grows with the pixels and up close
    monkeypatch.setattr(engine.settings, "max_frame_splat_pixels", (small + close) / 2)
    with pytest.raises(grpc.RpcError) as e:
        Stream(stub, avatar_id="demo", width=512)
    assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and e.value.details().startswith("width: ")
    assert "BLENDSPLAT_MAX_FRAME_SPLAT_PIXELS" in e.value.details()
    r = httpx.post(live_server.http_url + "/v1/render", json={"avatarId": "demo", "width": 512}, timeout=60)
    assert r.status_code == 429 and r.json()["error"]["field"] == "width"
    stream = Stream(stub, avatar_id="demo", width=SIZE)
    stream.send(frame=pb.FrameParams(index=1, camera=closer))
    assert "budget" in expect_error(stream, pb.RESOURCE_EXHAUSTED, "camera").message
    stream.send(frame=pb.FrameParams(index=2))
    expect_frame(stream, 2)
    assert stream.close()[-1].status.code == pb.OK


def test_the_default_budget_refuses_large_faint_gaussians_at_full_size_not_a_face():
    """The issue's case: an avatar of large, faint Gaussians (seconds per 2048 x 2048 frame) is over the default
    budget at that size, and fine at 512; the synthetic face it came from is far under it at 2048."""
    from dataclasses import replace

    import torch

    from render_core.tools.synth import synth_avatar
    from service.settings import Settings

    budget = Settings().max_frame_splat_pixels
    face = synth_avatar(gaussians=20_000, blendshapes=2, seed=1)
    faint = replace(face, neutral=replace(face.neutral, log_scales=face.neutral.log_scales + 3.0,
                                          opacity_logits=torch.full_like(face.neutral.opacity_logits, -4.0)))
    cost = {(name, size): params.frame_cost(a, default_camera(a, size, size))
            for name, a in (("face", face), ("faint", faint)) for size in (512, 2048)}
    assert cost["faint", 2048] > budget > cost["faint", 512]
    assert cost["face", 2048] < budget / 10
    out = params.output(2048, 2048, pb.CODEC_JPEG, 0, 2048)
    with pytest.raises(Exception) as e:
        params.check_cost(cost["faint", 2048], budget, out, "width")
    assert e.value.code == pb.RESOURCE_EXHAUSTED and e.value.field == "width"


def test_a_slow_session_gets_its_share_not_the_render_thread(live_server, stub):
    """A session whose frames are slow (large, close up) and a fast one, both always ready: the fast one gets
    many frames for each slow one (fair share of render time), not one for one (first come, first served)."""
    heavy = Stream(stub, auto_ack=True, avatar_id="demo", width=2048, max_in_flight=4,
                   camera=pb.Camera(orbit=pb.Orbit(distance=0.35)))
    light = Stream(stub, auto_ack=True, avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, max_in_flight=4)
    counts = {"heavy": 0, "light": 0}
    deadline = time.monotonic() + 3.0
    i = 0
    while time.monotonic() < deadline:
        i += 1
        heavy.send(frame=pb.FrameParams(index=i))
        light.send(frame=pb.FrameParams(index=i))
        time.sleep(0.002)
    for name, s in (("heavy", heavy), ("light", light)):
        replies = s.close()
        assert replies[-1].status.code == pb.OK
        counts[name] = replies[-1].status.frames_sent
    # First come, first served gives about one light frame per heavy one; the fair share gave 3.5 to 4.5 on the
    # 2-core AVX2 machine and 3.6 to 3.7 on the AVX-512 one before render_core.host (1b90acf), 2.6 to 2.8 there
    # since (measured: the light stream's frames fell by a quarter, the heavy one's did not move; not understood
    # yet, see the closing note of 2026-11-28), so 2x tells them apart without riding on either machine's noise.
    assert counts["heavy"] >= 1 and counts["light"] >= 2 * counts["heavy"], counts


# ---------------------------------------------------------------------------------- finding 8: bounded text
def test_an_open_with_10000_unknown_names_is_invalid_argument_with_a_bounded_text(live_server, stub):
    names = [f"not_a_name_{i}" for i in range(10_000)]
    with pytest.raises(grpc.RpcError) as e:
        Stream(stub, avatar_id="demo", expression_names=names)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    details = e.value.details()
    assert details.startswith("expression_names: unknown expression names 'not_a_name_0'") and len(details) < 1000
    assert "and 9995 more" in details
    stream = Stream(stub, avatar_id="demo", width=SIZE)
    stream.send(frame=pb.FrameParams(index=1, named_coefficients=dict.fromkeys(names, 1.0)))
    error = expect_error(stream, pb.INVALID_ARGUMENT, "named_coefficients")
    assert "and 9995 more" in error.message and len(error.message) < 1000
    stream.close()
    r = httpx.post(live_server.http_url + "/v1/render", json={"avatarId": "demo", "expressionNames": names},
                   timeout=60)
    assert r.status_code == 422 and len(r.content) < 2000


def test_every_error_text_is_bounded():
    from service.errors import InvalidArgument, bounded, some, to_status

    assert some(["a", "b", "c"]) == "'a', 'b', 'c'"
    assert some([str(i) for i in range(10_000)], 3) == "'0', '1', '2' and 9997 more"
    status = to_status(InvalidArgument("x" * 400_000, field="f" * 10_000))
    assert len(status.message) <= 1000 and len(status.field) <= 120 and "more characters" in status.message
    assert bounded("short") == "short"


# --------------------------------------------------------------------------------------- finding 9: indices
def test_frame_indices_strictly_increase_and_acks_name_answered_frames(stub):
    stream = Stream(stub, avatar_id="demo", width=SIZE, max_in_flight=4)
    stream.send(frame=pb.FrameParams(index=10))
    expect_frame(stream, 10)
    stream.send(frame=pb.FrameParams(index=5))  # backwards: refused, nothing taken
    assert expect_error(stream, pb.INVALID_ARGUMENT, "index").frame_index == 5
    stream.send(frame=pb.FrameParams(index=10))  # a repeat
    expect_error(stream, pb.INVALID_ARGUMENT, "index")
    stream.send(frame=pb.FrameParams())  # 0 is unset
    assert "start at 1" in expect_error(stream, pb.INVALID_ARGUMENT, "index").message
    stream.send(ack=pb.Ack(index=11))  # never sent
    expect_error(stream, pb.INVALID_ARGUMENT, "ack.index")
    stream.send(ack=pb.Ack())
    expect_error(stream, pb.INVALID_ARGUMENT, "ack.index")
    stream.send(ack=pb.Ack(index=10))
    for i in (11, 12, 20):
        stream.send(frame=pb.FrameParams(index=i))
        expect_frame(stream, i)
        stream.send(ack=pb.Ack(index=i))
    status = stream.close()[-1].status
    assert (status.code, status.frames_sent) == (pb.OK, 4)
