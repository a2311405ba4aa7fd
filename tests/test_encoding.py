"""Encoding off the render thread (service/encoding.py, the setting ``encode_threads``): the render thread goes on
with the next batch while a batch's frames encode in parallel; each session's frames encode one at a time and in
order (H.264 is stateful), are delivered in order, an encoder's failure is its own session's error, and closing,
draining and shutting down wait for the encodes in flight. ``encode_threads=0`` encodes on the render thread."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest
from conftest import LiveServer

from blendsplat.v1 import render_pb2 as pb
from render_core.media.codecs import H264Decoder
from service.encoding import EncodeLanes

SIZE = 32


@pytest.fixture(scope="module")
def inline_server(tmp_path_factory):
    """The service with ``encode_threads=0``: frames encoded on the render thread, as before the lanes."""
    server = LiveServer(tmp_path_factory.mktemp("inline-encode"), encode_threads=0)
    yield server
    server.stop()


class Watched:
    """A session's encoder, watched: every call's (event, call number, thread, time) in ``log``, calls that overlap
    flagged, each encode held ``delay`` seconds, the calls numbered in ``fail`` raising."""

    def __init__(self, inner, log: list, delay: float = 0.0, fail: tuple[int, ...] = ()):
        self.inner, self.log, self.delay, self.fail = inner, log, delay, fail
        self.calls = self.active = 0
        self.overlapped = False
        self.images: list[bytes] = []
        self._lock = threading.Lock()

    def _note(self, event: str, n: int = 0) -> None:
        self.log.append((event, n, threading.current_thread().name, time.perf_counter()))

    def encode(self, image: np.ndarray) -> bytes:
        with self._lock:
            self.calls += 1
            self.active += 1
            self.overlapped |= self.active > 1
            n = self.calls
        self._note("encode", n)
        try:
            time.sleep(self.delay)
            self.images.append(image.tobytes())
            if n in self.fail:
                raise RuntimeError("the encoder gave up")
            return self.inner.encode(image)
        finally:
            self._note("encoded", n)
            with self._lock:
                self.active -= 1

    def close(self) -> None:
        self._note("close")
        self.inner.close()


def _frame(index: int, **kw) -> pb.StreamRequest:
    return pb.StreamRequest(frame=pb.FrameParams(index=index, **kw))


async def _next(session) -> pb.StreamResponse:
    async for reply in session.responses():
        return reply


async def _until(check, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.005)


# ------------------------------------------------------------------------------------------------- the lanes
def test_a_lane_runs_its_work_in_order_one_at_a_time_while_lanes_run_in_parallel():
    lanes = EncodeLanes(2)
    lock, active = threading.Lock(), {}
    both = threading.Barrier(2, timeout=10)  # two lanes' first items meet: they run at the same time

    def work(key, n):
        with lock:
            active[key] = active.get(key, 0) + 1
            assert active[key] == 1, "two items of one lane at once"
        if n == 0:
            both.wait()
        time.sleep(0.002)
        with lock:
            active[key] -= 1
        if (key, n) == ("b", 3):
            raise ValueError("item 3 of b failed")
        return key, n

    done: list = []
    for n in range(20):
        for key in ("a", "b"):
            lanes.submit(key, lambda key=key, n=n: work(key, n), done.append)
    lanes.shutdown()  # waits for everything submitted
    assert [d for d in done if isinstance(d, tuple) and d[0] == "a"] == [("a", n) for n in range(20)]
    b = [d if isinstance(d, tuple) else str(d) for d in done if not (isinstance(d, tuple) and d[0] == "a")]
    assert b == [("b", n) for n in range(3)] + ["item 3 of b failed"] + [("b", n) for n in range(4, 20)]
    assert lanes.busy == 0
    with pytest.raises(RuntimeError):
        lanes.submit("a", lambda: None)


def test_a_lane_hands_each_result_over_before_its_next_item_starts_and_closes_after_its_work():
    lanes = EncodeLanes(3)
    events: list[str] = []

    class Encoder:
        def close(self):
            events.append("close")

    enc = Encoder()
    for n in range(5):
        lanes.submit(enc, lambda n=n: (time.sleep(0.01), events.append(f"work {n}"), n)[-1],
                     lambda r: events.append(f"done {r}"))
    lanes.close(enc)
    lanes.shutdown()
    assert events == [e for n in range(5) for e in (f"work {n}", f"done {n}")] + ["close"]
    closed = Encoder()
    lanes.close(closed)  # shut down: closed at once, on the caller's thread
    assert events[-1] == "close" and len(events) == 12


# ------------------------------------------------------------------------------------------- in the engine
@pytest.mark.parametrize("mode", ["lanes", "inline"])
def test_the_render_thread_renders_the_next_frame_while_the_last_one_encodes(live_server, inline_server,
                                                                              monkeypatch, mode):
    """Lanes: frame 2 renders while frame 1's (slow) encode runs, on an encode thread; encode_ms is the encoder's
    own time. encode_threads=0: the render thread encodes frame 1 before it can render frame 2."""
    server = live_server if mode == "lanes" else inline_server
    engine = server.engine
    assert (engine._lanes is None) == (mode == "inline")
    renders: list[tuple[float, float]] = []

    async def run():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, max_in_flight=2)
        session = await engine.open(config, "test")
        renderer = session.entry.renderer
        render = renderer.render_rgba8

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            out = render(*args, **kwargs)
            renders.append((t0, time.perf_counter()))
            return out

        monkeypatch.setattr(renderer, "render_rgba8", timed)
        log: list = []
        session.encoder = Watched(session.encoder, log, delay=0.4)
        session.handle(_frame(1))
        await _until(lambda: renders)
        session.handle(_frame(2))
        replies = [await _next(session), await _next(session)]
        session.end_input()
        return replies, log

    (first, second), log = server.call(run())
    assert (first.frame.index, second.frame.index) == (1, 2)
    encoded_1 = next(t for e, n, _, t in log if (e, n) == ("encoded", 1))
    if mode == "lanes":
        assert renders[1][0] < encoded_1 - 0.2  # frame 2 rendered while frame 1 encoded
        assert {name.split("_")[0] for e, _, name, _ in log if e == "encode"} == {"encode"}
    else:
        assert renders[1][0] >= encoded_1
        assert {name.split("_")[0] for e, _, name, _ in log if e == "encode"} == {"render"}
    t = first.frame.timings
    assert 400 <= t.encode_ms < 1000 and t.raster_ms < 300 and t.total_ms >= t.encode_ms


def test_h264_streams_encode_one_frame_at_a_time_in_order_and_decode_in_order(live_server):
    """Four H.264 sessions with four frames in flight each, the encodes slowed so that lanes queue up: no encoder
    ever encodes two frames at once, every session's frames arrive in index order, and each stream decodes frame
    after frame to its pose's background (the red channel rises with the index)."""
    engine = live_server.engine
    frames = 12

    async def run():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_H264, quality=100, max_in_flight=4)
        sessions = [await engine.open(config, "test") for _ in range(4)]
        watched = []
        for s in sessions:
            s.encoder = Watched(s.encoder, [], delay=0.01)
            watched.append(s.encoder)
        got: list[list[pb.RenderedFrame]] = [[] for _ in sessions]

        def taken() -> bool:  # each pose taken by the scheduler (none dropped); what arrived read and acknowledged
            for k, s in enumerate(sessions):
                while not s._replies.empty():
                    got[k].append(s._replies.get_nowait().frame)
                    s.handle(pb.StreamRequest(ack=pb.Ack(index=got[k][-1].index)))
            return all(s.pending is None for s in sessions)

        for i in range(1, frames + 1):
            for s in sessions:
                s.handle(_frame(i, background=pb.Color(r=i / frames, g=0.2, b=0.2)))
            await _until(taken)
        for k, s in enumerate(sessions):
            s.end_input()
            async for reply in s.responses():
                if reply.HasField("frame"):
                    got[k].append(reply.frame)
        return got, watched

    got, watched = live_server.call(run())
    assert not any(w.overlapped for w in watched)
    for stream in got:
        assert [f.index for f in stream] == list(range(1, frames + 1))
        decoder = H264Decoder(SIZE, SIZE)
        red = [int(decoder.decode(f.data)[0, 0, 0]) for f in stream]
        assert all(b > a for a, b in zip(red, red[1:], strict=False)), red
    assert max(f.timings.batch for stream in got for f in stream) > 1  # the sessions were batched


def test_an_encoder_failure_is_its_own_sessions_error_in_its_frames_order(live_server):
    """One session's encoder fails on its second frame: that session gets frame 1, an INVALID_ARGUMENT error for
    frame 2 (naming ``frame``), then frame 3, in that order; the session batched with it gets all three frames;
    the delivered data is what the encoder was given, frame after frame."""
    engine = live_server.engine

    async def run():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA, max_in_flight=4)
        sessions = [await engine.open(config, "test") for _ in range(2)]
        sessions[0].encoder = Watched(sessions[0].encoder, [], delay=0.05, fail=(2,))
        sessions[1].encoder = Watched(sessions[1].encoder, [], delay=0.05)
        replies: list[list] = [[], []]
        for i in (1, 2, 3):
            for s in sessions:
                s.handle(_frame(i, named_coefficients={"exp_00": i / 3}))
            await _until(lambda: all(s.pending is None for s in sessions))
        for k, s in enumerate(sessions):
            s.end_input()
            async for reply in s.responses():
                replies[k].append(reply)
        return replies, [s.encoder for s in sessions]

    (bad, good), encoders = live_server.call(run())
    assert [r.WhichOneof("msg") for r in bad] == ["frame", "error", "frame", "status"]
    assert (bad[1].error.code, bad[1].error.field, bad[1].error.frame_index) == (pb.INVALID_ARGUMENT, "frame", 2)
    assert [r.frame.index for r in bad if r.HasField("frame")] == [1, 3]
    assert [r.frame.index for r in good if r.HasField("frame")] == [1, 2, 3]
    assert [r.frame.data for r in good if r.HasField("frame")] == encoders[1].images
    assert [r.frame.data for r in bad if r.HasField("frame")] == [encoders[0].images[0], encoders[0].images[2]]
    assert len(set(encoders[1].images)) == 3


def test_closing_a_session_closes_its_encoder_after_its_encode_in_flight(live_server):
    engine = live_server.engine

    async def run():
        config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_H264)
        session = await engine.open(config, "test")
        log: list = []
        session.encoder = Watched(session.encoder, log, delay=0.3)
        session.handle(_frame(1))
        await _until(lambda: log)  # encoding now
        engine.close_session(session)
        await _until(lambda: any(e == "close" for e, *_ in log))
        return log

    log = live_server.call(run())
    assert [e for e, *_ in log] == ["encode", "encoded", "close"]


def test_a_drain_sends_the_frames_still_encoding_before_it_ends_the_streams(tmp_path):
    server = LiveServer(tmp_path)
    try:
        engine = server.engine

        async def run():
            config = pb.SessionConfig(avatar_id="demo", width=SIZE, codec=pb.CODEC_RAW_RGBA)
            session = await engine.open(config, "test")
            log: list = []
            session.encoder = Watched(session.encoder, log, delay=0.5)
            session.handle(_frame(1))
            await _until(lambda: log)  # rendered, encoding now
            await engine.drain(timeout=10)
            return [reply async for reply in session.responses()], log

        replies, log = server.call(run())
        assert [r.WhichOneof("msg") for r in replies] == ["frame", "status"]
        assert replies[0].frame.index == 1 and replies[1].status.code == pb.UNAVAILABLE
        assert replies[0].frame.timings.encode_ms >= 500
        assert [e for e, *_ in log][:2] == ["encode", "encoded"]
    finally:
        server.stop()
