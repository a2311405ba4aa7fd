"""The render engine: one per process, shared by the gRPC and WebSocket transports.

- Sessions: a stream's state (avatar, output, encoder, defaults) and its flow control. The client's newest pose
  wins: a pose that arrives while an older one waits replaces it (the older one is counted as dropped). At most
  ``max_in_flight`` frames are rendered-or-sent and not yet acknowledged; a reader that stops acking stops the
  rendering for its session, so the server holds at most one pending pose and ``max_in_flight`` frames for it.
- Frame indices: a stream's frames are numbered by the client from 1 up, strictly increasing (0 is "unset"); a
  frame whose index is 0 or not above the last accepted one is refused (INVALID_ARGUMENT naming ``index``, the
  stream goes on), so cumulative acks always mean "every frame up to here". An ack must name an index the server
  has answered (a frame, or an error for it); others are refused (``ack.index``) and acknowledge nothing.
- One scheduler task hands ready sessions to a single render thread (the native renderer uses every core for one
  call); sessions of the same avatar and output size that are ready together are rendered as one batched call.
- Encoding is off the render thread's path (``encode_threads`` > 0): after a batched render, each frame goes to its
  session's encode lane (:mod:`service.encoding`) and the render thread goes on with the next batch; the frames of
  a batch encode in parallel, a session's one at a time and in order, and are delivered in order (an error keeps
  its place among them); closing a session closes its encoder after its frames in flight. ``encode_threads=0``
  encodes a batch's frames on the render thread after its render. Render time, not encode time, is charged.
- Every frame is validated (:mod:`service.params`) before it joins a batch. Per-frame work is bounded: a frame
  whose estimated (Gaussian, pixel) pairs pass ``max_frame_splat_pixels`` is refused, and a batch holds at most
  that much estimated work, so the render thread is never held by one call for much longer than one budget's
  worth (a heavy frame renders alone).
- Fairness: each session is charged the render time its frames take (its share of a batch's time, by estimate);
  the ready session charged least goes first (an idle session counts from "now", so it gets no credit for having
  been idle). A session with slow frames gets its share of the render thread, not all of it.
- Single frames (``POST /v1/render``, the Render RPC: :meth:`Engine.render_once`) go through the same scheduler as
  one-frame entries (:class:`OneShot`), charged to their key's account: a key's single renders in flight share one
  stream's part of the render thread, however many it sends, and at most ``key_max_renders`` of them are in flight
  per non-admin key (more: RESOURCE_EXHAUSTED / 429 naming the setting).
- Isolation: when a batched call fails, its frames are rendered again one by one, so the failure is reported to
  the session that caused it (an error naming its frame; a failure that is not a typed error is reported as
  INVALID_ARGUMENT on ``frame``, and logged) and the others get their frames.
- Draining (SIGTERM): new streams are refused, poses already received are rendered and sent, then every stream
  ends with an UNAVAILABLE status.

Transports only frame messages, and call nothing but the engine: they pass ``StreamRequest`` messages to
:meth:`Session.handle` and forward what :meth:`Session.responses` yields; avatars are listed, described, loaded,
unloaded and uploaded through :meth:`Engine.list_avatars`, :meth:`Engine.avatar_info`, :meth:`Engine.load`,
:meth:`Engine.unload` and :meth:`Engine.replace`, retargeting adapters through :meth:`Engine.list_adapters`,
:meth:`Engine.adapter_info`, :meth:`Engine.put_adapter` and :meth:`Engine.delete_adapter`: the ownership rules and
the audit are applied here, once for every transport. The cache and the stores are the engine's own.
A transport that encodes frames itself (WebRTC's video track) takes them through ``Session.frame_sink`` instead of
``responses()``, their pixels uncopied.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import os
import time
import uuid
from collections import deque
from collections.abc import AsyncIterable, AsyncIterator, Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import astuple, dataclass, field
from typing import Any

import torch

from blendsplat.v1 import render_pb2 as pb
from render_core import host
from render_core.avatar import Avatar
from render_core.camera import Cameras
from render_core.deform import Frame
from render_core.errors import BlendsplatError, CodecError
from render_core.media.codecs import Encoder, make_encoder
from render_core.raster.native import Schedule

from . import params
from .access.auth import TRUSTED, Access, Principal
from .access.limits import Release, no_release
from .cache import AvatarCache, Loaded
from .encoding import EncodeLanes
from .errors import InvalidArgument, NotFound, ResourceExhausted, ServiceError, Unavailable, hide_paths, to_status
from .intake import Spooled, UploadIntake
from .metrics import STAGES, Metrics
from .settings import Settings
from .store import ID_PATTERN as AVATAR_ID_PATTERN  # noqa: F401 - the transports' avatar id pattern
from .store import BundleStore, check_id

log = logging.getLogger(__name__)

MAX_QUEUED_ERRORS = 32  # error replies waiting for a reader that does not read; more are counted, not queued


@dataclass(eq=False)
class Job:
    """One pose to render: validated render_core inputs plus what the reply echoes."""

    frame: Frame  # batch of 1
    camera: Cameras  # 1 camera at the output size
    background: torch.Tensor  # [3]
    index: int
    client_time_us: int
    cost: float = 0.0  # estimated (Gaussian, pixel) pairs (params.frame_cost)
    received: float = field(default_factory=time.perf_counter)
    started: float = 0.0
    drive: object | None = None  # a frame waiting for its adapter (service/adapters.py): frame is None until mapped
    reference: bool = False  # render with every speed mechanism off (RenderRequest.reference; never batched)

    @classmethod
    def build(cls, avatar: Avatar, msg: pb.FrameParams, order: list[str], out: params.Output, budget: float,
              camera: Cameras | None = None, background: torch.Tensor | None = None,
              cost: float | None = None, drive: object | None = None) -> Job:
        """The job of one FrameParams message, validated (typed errors naming the field): its camera, else
        ``camera`` (whose estimated cost is ``cost``), else the avatar's default at the output size; its
        background, else ``background``, else black; ``order`` maps positional coefficients to names. A frame
        whose estimated cost passes ``budget`` is refused (RESOURCE_EXHAUSTED naming ``camera`` or ``width``)."""
        own_camera = msg.HasField("camera")
        frame = params.frame(avatar, msg, order) if drive is None else None  # an adapter's frame: at render time
        cams = params.camera(avatar, msg.camera if own_camera else None, out, camera)
        if own_camera or cost is None:
            cost = params.check_cost(params.frame_cost(avatar, cams), budget, out,
                                     "camera" if own_camera else "width")
        return cls(
            frame=frame, camera=cams,
            background=params.background(msg.background if msg.HasField("background") else None, background),
            index=msg.index, client_time_us=msg.client_time_us, cost=cost, drive=drive,
        )


@dataclass
class Rendered:
    data: bytes
    timings: pb.StageTimings


class Session:
    """One stream. Created by :meth:`Engine.open`; every method runs on the event loop."""

    def __init__(self, engine: Engine, entry: Loaded, config: pb.SessionConfig, transport: str,
                 principal: Principal = TRUSTED):
        s = engine.settings
        self.engine, self.entry, self.transport, self.principal = engine, entry, transport, principal
        self.id = uuid.uuid4().hex
        self.opened = time.monotonic()  # max_stream_seconds counts from here
        avatar = entry.avatar
        self.out = params.output(config.width, config.height, config.codec, config.quality, s.max_size)
        if config.max_in_flight > 16:
            raise InvalidArgument(f"at most 16, got {config.max_in_flight}", field="max_in_flight")
        self.max_in_flight = config.max_in_flight or s.max_in_flight
        self.order = params.expression_order(avatar, list(config.expression_names))
        self.camera = params.camera(avatar, config.camera if config.HasField("camera") else None, self.out)
        self.cost = params.check_cost(params.frame_cost(avatar, self.camera), s.max_frame_splat_pixels, self.out,
                                      "camera" if config.HasField("camera") else "width")
        self.background = params.background(config.background if config.HasField("background") else None)
        self.adapter = engine.adapters.for_session(avatar, config, self.order,  # retargeting, smoothing (or None)
                                                   principal.may_use_adapter)
        try:
            self.encoder: Encoder = make_encoder(self.out.codec, self.out.width, self.out.height, config.quality,
                                                 config.fps_hint or 30.0)
        except CodecError as e:
            if e.field != "fps":
                raise
            raise CodecError(e.detail, field="fps_hint") from None  # the name the client sent it under
        self.frame_format = self.out.codec  # what its frames are made as (the metrics' codec label)
        self.pending: Job | None = None
        self.unacked: deque[int] = deque()  # indices rendering or sent, not yet acknowledged
        self.last_index = 0  # the index of the newest frame accepted (frames must go above it)
        self.answered = 0  # the highest index answered (a frame sent, or an error for it): acks go up to it
        self.vtime = 0.0  # render seconds charged (fair share: the least charged ready session goes first)
        self.rendering = 0
        self.sent = self.dropped = 0
        self.input_done = False
        self.closed = False
        self.release_slot = no_release  # the key's stream slot (Engine.open sets it)
        # A transport that takes its frames itself (WebRTC's video track) sets this (sink_frames): each frame is then
        # handed to it on the loop as it is delivered, a RenderedFrame without data plus the pixels as the encoder
        # made them, not queued for responses() (which keeps errors and the final status). It must not raise.
        self.frame_sink: Callable[[pb.RenderedFrame, bytes], None] | None = None
        self._replies: asyncio.Queue[pb.StreamResponse | None] = asyncio.Queue()
        self._queued_errors = 0

    # ------------------------------------------------------------------------------------------ from the client
    def header(self) -> pb.StreamResponse:
        a = self.entry.avatar
        return pb.StreamResponse(header=pb.StreamHeader(
            session_id=self.id, avatar_id=self.entry.id, expression_names=a.expression_names,
            joint_names=a.joint_names, width=self.out.width, height=self.out.height, codec=self.out.codec_enum,
            max_in_flight=self.max_in_flight, gaussians=a.num_gaussians + a.num_mouth,
            adapter_id=self.adapter.adapter_id if self.adapter else "",
            source_names=self.adapter.source_names if self.adapter else []))

    def handle(self, request: pb.StreamRequest) -> None:
        """Apply one client message. Bad messages get an ``error`` reply; the stream goes on."""
        if self.closed:
            return
        kind = request.WhichOneof("msg")
        try:
            if self.input_done and kind != "ack":
                raise InvalidArgument("the client ended its input (end); only acks are taken now", field=kind or "msg")
            if kind == "frame":
                self._submit(request.frame)
            elif kind == "ack":
                self._ack(request.ack.index)
            elif kind == "end":
                self.end_input()
            elif kind == "open":
                raise InvalidArgument("the session is already open; send frame or ack messages", field="open")
            else:
                raise InvalidArgument("empty message: set one of open, frame, ack, end", field="msg")
        except Exception as e:  # noqa: BLE001 - every failure becomes a status reply
            index = request.frame.index if kind == "frame" else 0
            self.error(to_status(e, index))

    def _submit(self, msg: pb.FrameParams) -> None:
        if self.engine.frames_closed:
            raise Unavailable("the server is shutting down; no new frames are taken")
        if msg.index == 0:
            raise InvalidArgument("frame indices start at 1 (0 is unset) and increase with every frame",
                                  field="index")
        if msg.index <= self.last_index:
            raise InvalidArgument(f"{msg.index} is not above the previous frame's index {self.last_index}; frame "
                                  "indices must increase with every frame", field="index")
        drive = self.adapter.prepare(msg) if self.adapter is not None else None
        job = Job.build(self.entry.avatar, msg, self.order, self.out, self.engine.settings.max_frame_splat_pixels,
                        self.camera, self.background, self.cost, drive)
        self.last_index = msg.index
        if self.pending is not None:
            self._drop()
        self.pending = job
        self.engine.wake()

    def _ack(self, index: int) -> None:
        """Acknowledge every frame up to and including ``index``, which must have been answered."""
        if not 0 < index <= self.answered:
            newest = f"the newest answered is {self.answered}" if self.answered else "none has been answered yet"
            raise InvalidArgument(f"acknowledges frame {index}, which this stream has not sent ({newest}); nothing "
                                  "was acknowledged", field="ack.index")
        while self.unacked and self.unacked[0] <= index:
            self.unacked.popleft()
        self.engine.wake()

    def end_input(self) -> None:
        """The client sent its last message: render what is pending (if acks allow), then end the stream."""
        self.input_done = True
        self._maybe_finish()

    def sink_frames(self, sink: Callable[[pb.RenderedFrame, bytes], None], yuv420: bool = False) -> None:
        """Hand each rendered frame to ``sink`` (see ``frame_sink``) instead of queueing it for :meth:`responses`;
        with ``yuv420`` as the 4:2:0 planes a video encoder takes (``raw_i420``: Y, U, V, unpadded, converted on the
        encode threads) instead of the session's codec. Before the first frame."""
        if yuv420:
            self.encoder = make_encoder("raw_i420", self.out.width, self.out.height)
            self.frame_format = self.encoder.codec
        self.frame_sink = sink

    # ---------------------------------------------------------------------------------------- for the engine
    @property
    def ready(self) -> bool:
        return (not self.closed and self.pending is not None and len(self.unacked) < self.max_in_flight)

    def take(self) -> Job:
        job, self.pending = self.pending, None
        self.unacked.append(job.index)
        self.rendering += 1
        return job

    def deliver(self, job: Job, result: Rendered | BaseException) -> None:
        self.rendering -= 1
        if self.closed:
            return
        self.answered = max(self.answered, job.index)
        if isinstance(result, BaseException):
            self.unacked.remove(job.index)
            self.error(to_status(result, job.index))
        else:
            self.sent += 1
            m = self.engine.metrics
            m.frames.labels(self.frame_format).inc()
            m.frame_bytes.labels(self.frame_format).inc(len(result.data))
            fields = {"index": job.index, "client_time_us": job.client_time_us, "codec": self.out.codec_enum,
                      "width": self.out.width, "height": self.out.height, "timings": result.timings,
                      "dropped": self.dropped}
            if self.frame_sink is not None:  # the pixels to a local sink: no copy into a message, no queue hop
                self.frame_sink(pb.RenderedFrame(**fields), result.data)
            else:
                self._replies.put_nowait(pb.StreamResponse(frame=pb.RenderedFrame(data=result.data, **fields)))
        self._maybe_finish()

    def error(self, status: pb.Status) -> None:
        self.engine.metrics.errors.labels(pb.Code.Name(status.code), self.transport).inc()
        if self._queued_errors >= MAX_QUEUED_ERRORS:
            return  # a client that sends bad messages and does not read: counted above, not queued
        self._queued_errors += 1
        self._replies.put_nowait(pb.StreamResponse(error=status))

    def finish(self, code: int = pb.OK, message: str = "") -> None:
        """End the stream with a final status (once)."""
        if self.closed:
            return
        if self.pending is not None:
            self._drop()
        self.closed = True
        self._replies.put_nowait(pb.StreamResponse(status=pb.Status(
            code=code, message=message, frames_sent=self.sent, dropped=self.dropped)))
        self._replies.put_nowait(None)
        self.engine.detach(self)

    async def responses(self) -> AsyncIterator[pb.StreamResponse]:
        """Everything to send to the client, ending with the final status."""
        while (reply := await self._replies.get()) is not None:
            if reply.HasField("error"):
                self._queued_errors -= 1
            yield reply

    def _drop(self) -> None:
        self.pending = None
        self.dropped += 1
        self.engine.metrics.dropped.inc()

    def _maybe_finish(self) -> None:
        if self.input_done and not self.rendering and not self.ready:
            self.finish()


class RenderAccount:
    """The render time charged to one key's single-frame renders together (fair share: one stream's worth)."""

    __slots__ = ("in_flight", "vtime")

    def __init__(self, vtime: float):
        self.vtime, self.in_flight = vtime, 0


class OneShot:
    """A single-frame render as one entry of the scheduler: ready with its one job until taken, charged to its key's
    :class:`RenderAccount`; :attr:`done` gets the result (a :class:`Rendered` or the error)."""

    closed = False

    def __init__(self, entry: Loaded, job: Job, out: params.Output, encoder: Encoder, account: RenderAccount):
        self.entry, self.out, self.encoder, self.account = entry, out, encoder, account
        self.pending: Job | None = job
        self.done: asyncio.Future = asyncio.get_running_loop().create_future()

    @property
    def ready(self) -> bool:
        return self.pending is not None

    @property
    def vtime(self) -> float:
        return self.account.vtime

    @vtime.setter
    def vtime(self, value: float) -> None:
        self.account.vtime = value

    def take(self) -> Job:
        job, self.pending = self.pending, None
        return job

    def deliver(self, job: Job | None, result: Rendered | BaseException) -> None:
        if not self.done.done():
            self.done.set_result(result)


class Engine:
    def __init__(self, settings: Settings, metrics: Metrics | None = None, *, access: Access | None = None,
                 store: BundleStore | None = None):
        """``access``: who may do what, the per-key limits and the audit (the service passes the process's; left
        out, every call is trusted: :meth:`Access.trusted`, for tests and tools); ``store``: the bundle store
        (default: a store of ``settings.bundle_dir``)."""
        self.settings = settings
        hide_paths(settings.data_dir)  # no server path in client-facing text (service/errors.py, redact)
        self.metrics = metrics or Metrics()
        self.store = store or BundleStore(settings.bundle_dir)
        # Render threads: the setting, else every CPU this process may use (not OpenMP's current default, which
        # torch.set_num_threads anywhere in the process would change for the native renderer too).
        threads = settings.render_threads or len(os.sched_getaffinity(0))
        self.cache = AvatarCache(self.store, settings.cache_bytes, self.metrics, settings.backend, threads,
                                 Schedule(lazy_tiles=settings.raster_lazy_tiles,
                                          square_blocks=settings.raster_square_blocks,
                                          direct_rgba8=settings.raster_direct_rgba8,
                                          eight_bit_stop=settings.raster_eight_bit_stop))
        self.access = access or Access.trusted(settings)
        self.intake = UploadIntake(self.access)
        self.sessions: dict[str, Session] = {}
        self.singles: set[OneShot] = set()  # single-frame renders waiting or rendering
        self._accounts: dict[str | None, RenderAccount] = {}  # key id -> its single renders' charge
        self.draining = False  # not ready; new streams are refused
        self.frames_closed = False  # open streams take no new frames either
        self.warmed_up = False
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="render")
        # encoding off the render thread (0: each batch's frames are encoded on it, after the render)
        self._lanes = EncodeLanes(settings.encode_threads) if settings.encode_threads else None
        self._wake = asyncio.Event()
        self._busy = False
        self._vclock = 0.0  # the render time charged to the session served last (fair share's "now")
        self._scheduler: asyncio.Task | None = None
        self._guard: asyncio.Task | None = None  # ends the streams of revoked keys, and too long ones
        from .adapters import Adapters

        # retargeting adapters (issue 19), each run held to its per-frame budget
        self.adapters = Adapters(settings.data_dir / "adapters", budget_ms=settings.adapter_budget_ms)

    # --------------------------------------------------------------------------------------------- lifecycle
    async def start(self) -> None:
        self.store.ensure()
        self._scheduler = asyncio.create_task(self._schedule(), name="render-scheduler")
        self._guard = asyncio.create_task(self._guard_streams(), name="stream-guard")

    async def _guard_streams(self) -> None:
        """Every ``stream_key_check_seconds``: the streams of a key revoked since they opened end with
        UNAUTHENTICATED (the key database is asked, not the cache: :meth:`Access.revoked`), and those open longer
        than ``max_stream_seconds`` end with UNAVAILABLE (the client opens a new one)."""
        s = self.settings
        while True:
            await asyncio.sleep(s.stream_key_check_seconds)
            open_now = [x for x in self.sessions.values() if not x.closed]
            if not open_now:
                continue
            revoked = await asyncio.to_thread(self.access.revoked, {x.principal.key_id for x in open_now})
            now = time.monotonic()
            for session in open_now:
                if session.principal.key_id in revoked:
                    session.finish(pb.UNAUTHENTICATED, "the API key of this stream was revoked")
                elif now - session.opened > s.max_stream_seconds:
                    session.finish(pb.UNAVAILABLE, f"the stream reached its maximum duration ({s.max_stream_seconds:g} "
                                                   "s, setting max_stream_seconds); open a new one")

    def readiness(self) -> dict[str, bool]:
        """What readiness waits for, check by check."""
        return {"settings": True, "bundle_store": self.store.reachable(), "warm_up": self.warmed_up,
                "not_draining": not self.draining}

    @property
    def ready(self) -> bool:
        return all(self.readiness().values())

    async def warm_up(self, avatar_id: str | None) -> None:
        """Render one frame (of ``avatar_id``, or of a tiny built-in avatar) so the first client waits for none
        of the one-time costs; readiness waits for it."""
        size = self.settings.warmup_size
        if avatar_id is not None:
            entry = await self.cache.load(avatar_id)
        else:
            from render_core.facemodel.synthetic import synth_avatar
            from render_core.renderer import AvatarRenderer

            avatar = synth_avatar(gaussians=256, blendshapes=4)
            entry = Loaded("warm-up", avatar, AvatarRenderer(avatar, self.settings.backend), "", 0, 0)
        out = params.output(size, size, pb.CODEC_JPEG, 0, max(size, self.settings.max_size))
        job = Job.build(entry.avatar, pb.FrameParams(), list(entry.avatar.expression_names), out, math.inf)
        encoder = make_encoder(out.codec, out.width, out.height)
        await asyncio.get_running_loop().run_in_executor(self._pool, _render, entry, [job], [encoder])
        self.warmed_up = True
        self.metrics.ready.set(1)

    def begin_drain(self) -> None:
        """Not ready, and no new streams; the streams already open go on until :meth:`drain`."""
        self.draining = True
        self.metrics.ready.set(0)

    async def drain(self, timeout: float) -> None:
        """Take no more frames, send the frames already received (up to ``timeout``), then end every stream
        with UNAVAILABLE."""
        self.begin_drain()
        self.frames_closed = True
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and (self.singles or any(s.ready or s.rendering
                                                                    for s in self.sessions.values())):
            await asyncio.sleep(0.01)
        for s in list(self.sessions.values()):
            s.finish(pb.UNAVAILABLE, "the server is shutting down; reconnect to another replica")

    async def close(self) -> None:
        if self._scheduler is not None:
            self._scheduler.cancel()
        for shot in list(self.singles):  # never rendered now
            shot.deliver(None, Unavailable("the server is shutting down; connect to another replica"))
        if self._guard is not None:
            self._guard.cancel()
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._lanes is not None:
            self._lanes.shutdown()  # the encodes the renders handed over, and the encoders' closes

    # --------------------------------------------------------------------------------------------- sessions
    async def open(self, config: pb.SessionConfig, transport: str, principal: Principal = TRUSTED) -> Session:
        if self.draining:
            raise Unavailable("the server is shutting down; connect to another replica")
        if len(self.sessions) >= self.settings.max_sessions:
            raise ResourceExhausted(f"this replica serves at most {self.settings.max_sessions} streams")
        self._check_read(principal, config.avatar_id, "avatar_id")
        if config.adapter:
            self._check_adapter_read(principal, config.adapter)
        release_slot = await asyncio.to_thread(self.access.take_stream, principal)  # may ask Redis: off the loop
        try:
            entry = await self.cache.acquire(check_id(config.avatar_id))
        except BaseException:
            release_slot()
            raise
        try:
            session = Session(self, entry, config, transport, principal)
        except BaseException:
            self.cache.release(entry)
            release_slot()
            raise
        session.release_slot = release_slot
        if len(self.sessions) >= self.settings.max_sessions:  # others opened while the avatar loaded
            self.cache.release(entry)
            release_slot()
            raise ResourceExhausted(f"this replica serves at most {self.settings.max_sessions} streams")
        session.vtime = self._vclock  # counts from now: no credit for time before it existed
        self.sessions[session.id] = session
        self.metrics.sessions.labels(transport).inc()
        self.metrics.sessions_total.labels(transport).inc()
        return session

    def detach(self, session: Session) -> None:
        """Forget a finished session (its last frames may still be on their way out)."""
        if self.sessions.pop(session.id, None) is None:
            return
        self.cache.release(session.entry)
        session.release_slot()
        self.metrics.sessions.labels(session.transport).dec()
        self._pool.submit(self._close_encoder, session.encoder)  # after any render and encode of it still running

    def close_session(self, session: Session) -> None:
        """The client went away: drop what is pending and free the session."""
        session.finish(pb.CANCELLED, "the client went away")

    # ------------------------------------------------------------------------------------------ single frames
    async def render_once(self, request: pb.RenderRequest, principal: Principal = TRUSTED) -> pb.RenderedFrame:
        """One frame, rendered by the scheduler like a stream's (:class:`OneShot`): one of the key's
        ``key_max_renders`` slots is held while it waits and renders (RateLimited past them)."""
        if self.draining:
            raise Unavailable("the server is shutting down; connect to another replica")
        self._check_read(principal, request.avatar_id, "avatar_id")
        release = await asyncio.to_thread(self._take_render_slot, principal)  # may ask Redis: off the loop
        try:
            entry = await self.cache.acquire(check_id(request.avatar_id))
            try:
                avatar = entry.avatar
                out = params.output(request.width, request.height, request.codec, request.quality,
                                    self.settings.max_size)
                job = Job.build(avatar, request.frame, params.expression_order(avatar,
                                                                               list(request.expression_names)),
                                out, self.settings.max_frame_splat_pixels)
                job.reference = request.reference
                encoder = make_encoder(out.codec, out.width, out.height, request.quality)
                result = await self._render_single(entry, job, out, encoder, principal.key_id)
            finally:
                self.cache.release(entry)
        finally:
            release()
        if isinstance(result, BaseException):
            raise result
        return pb.RenderedFrame(index=job.index, client_time_us=job.client_time_us, codec=out.codec_enum,
                                width=out.width, height=out.height, data=result.data, timings=result.timings)

    def _take_render_slot(self, principal: Principal) -> Release:
        """One of the key's single renders in flight (admin keys and trusted calls: no limit; blocking)."""
        if principal.key_id is None or principal.admin:
            return no_release
        return self.access.limits.take_stream(principal.key_id, self.settings.key_max_renders, "renders")

    async def _render_single(self, entry: Loaded, job: Job, out: params.Output, encoder: Encoder,
                             key_id: str | None) -> Rendered | BaseException:
        """Queue one job in the scheduler, charged to ``key_id``'s account, and wait for its result. The encoder
        is closed on the render thread after it (a render still running when the caller is cancelled ends first)."""
        account = self._accounts.get(key_id)
        if account is None:
            account = self._accounts[key_id] = RenderAccount(self._vclock)  # counts from now, as a new stream
        shot = OneShot(entry, job, out, encoder, account)
        account.in_flight += 1
        self.singles.add(shot)
        self.wake()
        try:
            return await shot.done
        finally:
            self.singles.discard(shot)
            account.in_flight -= 1
            # an idle account whose charge is behind "now" would count from now anyway: forget it
            for idle in [k for k, a in self._accounts.items() if not a.in_flight and a.vtime <= self._vclock]:
                del self._accounts[idle]
            try:
                self._pool.submit(self._close_encoder, encoder)
            except RuntimeError:  # the pool is shut down: nothing renders any more
                encoder.close()

    def _close_encoder(self, encoder: Encoder) -> None:
        """Close an encoder (on the render thread, after every render of its session): at once, or in its encode
        lane, after the frames of it still encoding."""
        if self._lanes is None:
            encoder.close()
        else:
            self._lanes.close(encoder)

    # -------------------------------------------------------------------------------------------- scheduling
    def wake(self) -> None:
        self._wake.set()

    def _next_batch(self) -> list[Session | OneShot]:
        """The ready session charged the least render time (fair share; ties: the pose waiting longest), with the
        other ready sessions of its avatar and size, least charged first, while the batch's estimated work stays
        within one frame's budget and ``max_batch``. Single renders are entries too, one frame per key's account in
        a batch (as a stream has one pose pending), so a key's many single renders never fill a call together."""
        ready = [s for s in self.sessions.values() if s.ready] + [s for s in self.singles if s.ready]
        if not ready:
            return []
        for s in ready:  # a session that was idle has no credit for that time: it counts from now
            s.vtime = max(s.vtime, self._vclock)
        ready.sort(key=lambda s: (s.vtime, s.pending.received))
        first = ready[0]
        self._vclock = first.vtime
        batch, work, payers = [first], first.pending.cost, {id(_payer(first))}
        budget = self.settings.max_frame_splat_pixels
        for s in ready[1:]:
            if len(batch) >= self.settings.max_batch:
                break
            if (s.entry is first.entry and (s.out.width, s.out.height) == (first.out.width, first.out.height)
                    and work + s.pending.cost <= budget and id(_payer(s)) not in payers
                    and not (first.pending.reference or s.pending.reference)):
                batch.append(s)
                work += s.pending.cost
                payers.add(id(_payer(s)))
        return batch

    async def _schedule(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self._wake.wait()
            self._wake.clear()
            while batch := self._next_batch():
                jobs = [s.take() for s in batch]
                entry, encoders = batch[0].entry, [s.encoder for s in batch]
                if self._lanes is not None:  # the render thread hands the frames to the encoders and goes on
                    done = [functools.partial(self._post, loop, s, j) for s, j in zip(batch, jobs, strict=True)]
                    rendered, seconds = await loop.run_in_executor(self._pool, _render_pipelined, entry, jobs,
                                                                   encoders, self._lanes, done)
                else:
                    try:
                        results, seconds = await loop.run_in_executor(self._pool, _render_isolated, entry, jobs,
                                                                      encoders)
                    except Exception as e:  # noqa: BLE001 - cannot happen (_render_isolated returns errors)
                        results, seconds = [_attributed(e)] * len(jobs), 0.0
                    rendered = any(isinstance(r, Rendered) for r in results)
                    for session, job, result in zip(batch, jobs, results, strict=True):
                        self._delivered(session, job, result)
                if rendered:
                    self.metrics.batch.observe(len(jobs))
                self._charge(batch, jobs, seconds)

    def _charge(self, batch: list[Session | OneShot], jobs: list[Job], seconds: float) -> None:
        """Each entry of a batch is charged its share of the render's ``seconds`` (by estimated cost)."""
        total = sum(j.cost for j in jobs)
        for session, job in zip(batch, jobs, strict=True):
            session.vtime += seconds * (job.cost / total if total > 0 else 1 / len(jobs))

    def _post(self, loop: asyncio.AbstractEventLoop, entry: Session | OneShot, job: Job,
              result: Rendered | BaseException) -> None:
        """An encode lane's result for ``job`` (on its worker), posted to the loop (a lane's results in order)."""
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody waits for it any more
            loop.call_soon_threadsafe(self._delivered, entry, job, result)

    def _delivered(self, entry: Session | OneShot, job: Job, result: Rendered | BaseException) -> None:
        """A frame's result to its session (on the loop), its stage times to the metrics."""
        if isinstance(result, Rendered):
            t = result.timings
            for stage in STAGES:
                self.metrics.stage.labels(stage).observe(getattr(t, f"{stage}_ms") / 1e3)
        entry.deliver(job, result)

    # ---------------------------------------------------------------------------------------------- avatars
    def _check_read(self, principal: Principal, avatar_id: str, field: str = "id") -> None:
        """PermissionDenied unless ``principal`` may read the avatar (one that does not exist is left to the
        caller's NotFound). A session token reads its own avatar only."""
        principal.check_avatar(avatar_id)
        if principal.admin or not self.store.path(check_id(avatar_id, field)).is_file():
            return
        owner = self.store.owner(avatar_id)
        principal.check_read(f"avatar {avatar_id!r}", owner.tenant, owner.public)

    def _check_write(self, principal: Principal, avatar_id: str, field: str = "id") -> None:
        self.store.writable(check_id(avatar_id, field), principal.writer)

    async def load(self, avatar_id: str, principal: Principal = TRUSTED) -> pb.AvatarInfo:
        """Load an avatar into this replica's cache (NotFound; FailedPrecondition for a broken bundle)."""
        self._check_read(principal, avatar_id)
        await self.cache.load(check_id(avatar_id))
        return self.avatar_info(avatar_id, principal)

    def unload(self, avatar_id: str, principal: Principal = TRUSTED) -> pb.AvatarInfo:
        """Drop an avatar from this replica's cache; the bundle stays, and streams using it keep it until they end.
        NotFound when the store has no such avatar."""
        info = self.avatar_info(avatar_id, principal)
        self._check_write(principal, avatar_id)
        self.access.audit(principal, "avatar.unload", avatar_id)
        self.cache.unload(avatar_id)
        info.loaded, info.memory_bytes = False, 0
        return info

    async def replace(self, avatar_id: str, chunks: AsyncIterable[bytes], declared: int | None = None,
                      principal: Principal = TRUSTED) -> pb.AvatarInfo:
        """The one avatar write from a client: create or replace an avatar's bundle from an upload's bytes
        (``declared``: its announced size, when known). Ownership first (:meth:`BundleStore.writable`: another
        tenant's avatar is refused before a byte is read), then the upload intake (the limit, admission, the body
        spooled off the event loop, the tenant's quota on what arrived), then validation and the commit (the
        rule checked again), the audit and the cache invalidation. An invalid, oversize or over-quota upload
        leaves the store unchanged; new sessions get the new bundle, running ones keep theirs."""
        check_id(avatar_id)
        writer = principal.writer
        self.store.writable(avatar_id, writer)
        spooled = await self.intake.receive(principal, chunks, self.store.staging_path(),
                                            limit=self.settings.max_upload_bytes, field="bundle", declared=declared)
        _, existed = await asyncio.to_thread(self.store.put, spooled.path, avatar_id, writer)
        self.access.audit(principal, "avatar.replace" if existed else "avatar.create", avatar_id, bytes=spooled.size)
        self.cache.unload(avatar_id)
        return self.avatar_info(avatar_id, principal)

    async def receive_upload(self, principal: Principal, chunks: AsyncIterable[bytes], *, limit: int, field: str,
                             declared: int | None = None) -> Spooled:
        """A request body through the upload intake (:class:`~service.intake.UploadIntake`) into a private file
        of the bundle store's folder; the caller removes the file when done with it."""
        return await self.intake.receive(principal, chunks, self.store.staging_path(), limit=limit, field=field,
                                         declared=declared)

    async def delete(self, avatar_id: str, principal: Principal = TRUSTED) -> None:
        """Delete an avatar: its bundle and the files beside it (verification record, owner), then its cached copy
        in this process. NotFound when the store has none. The files go first, so a session opened meanwhile finds
        the avatar gone rather than caching it again; sessions open on it keep their copy until they end (other
        replicas find it gone at their next session)."""
        path = self.store.existing(check_id(avatar_id))
        self._check_write(principal, avatar_id)

        def remove() -> None:
            try:
                path.unlink()
            except FileNotFoundError:
                raise NotFound(f"no avatar {avatar_id!r} in the bundle store", field="avatar_id") from None
            for sidecar in self.store.sidecars(avatar_id):
                sidecar.unlink(missing_ok=True)

        await asyncio.to_thread(remove)
        self.cache.unload(avatar_id)
        self.access.audit(principal, "avatar.delete", avatar_id)

    def avatar_info(self, avatar_id: str, principal: Principal = TRUSTED) -> pb.AvatarInfo:
        self.store.existing(check_id(avatar_id, "id"))
        self._check_read(principal, avatar_id)
        entry = self.cache.get(avatar_id)
        path = self.store.existing(avatar_id)
        if entry is not None:
            a = entry.avatar
            return pb.AvatarInfo(
                id=avatar_id, loaded=True, gaussians=a.num_gaussians + a.num_mouth, mouth_gaussians=a.num_mouth,
                expression_names=a.expression_names, joint_names=a.joint_names, sh_degree=a.sh_degree,
                precision=a.precision, face_model=a.face_model, file_bytes=entry.file_bytes,
                memory_bytes=entry.memory_bytes, digest=entry.digest, **training_figures(a.provenance))
        m = self.store.manifest(avatar_id)
        counts = m.get("counts", {})
        return pb.AvatarInfo(
            id=avatar_id, loaded=False, gaussians=counts.get("gaussians", 0) + counts.get("mouth", 0),
            mouth_gaussians=counts.get("mouth", 0), expression_names=m.get("expression_names", []),
            joint_names=m.get("joint_names", []), sh_degree=m.get("sh_degree", 0),
            precision=m.get("precision", ""), face_model=str(m.get("face_model", "")),
            file_bytes=path.stat().st_size, digest=m.get("digest", ""),
            **training_figures(m.get("provenance")))

    def list_avatars(self, principal: Principal = TRUSTED) -> list[pb.AvatarInfo]:
        """The avatars ``principal`` may read (its tenant's and the public ones; admin keys: all)."""
        out = []
        for avatar_id in self.store.ids():
            if principal.avatar not in (None, avatar_id) or (
                    not principal.admin and not principal.may_read(*astuple(self.store.owner(avatar_id)))):
                continue
            try:
                out.append(self.avatar_info(avatar_id))
            except (ServiceError, Exception) as e:  # noqa: BLE001 - one broken file must not hide the others
                log.warning("avatar %s unreadable: %s", avatar_id, e)
        return out

    # --------------------------------------------------------------------------------------------- adapters
    # An adapter without a tenant is the deployment's: every key may use it, only admin keys change it.
    def list_adapters(self, principal: Principal = TRUSTED) -> list[dict[str, Any]]:
        """The retargeting adapters ``principal`` may use (its tenant's and the deployment's; admin keys: all)."""
        return [a for a in self.adapters.list() if principal.may_use_adapter(a.get("tenant"))]

    def adapter_info(self, adapter_id: str, principal: Principal = TRUSTED) -> dict[str, Any]:
        """One adapter's record: manifest, owner, size, digest (NotFound; PermissionDenied: another tenant's)."""
        info = self.adapters.info(adapter_id)
        principal.check_read(f"adapter {adapter_id!r}", info.get("tenant"), info.get("tenant") is None)
        return info

    def _check_adapter_read(self, principal: Principal, adapter_id: str) -> None:
        """PermissionDenied unless ``principal`` may use the adapter (a missing one is left to the caller)."""
        if not principal.admin:
            with contextlib.suppress(NotFound, BlendsplatError):  # missing, or not an adapter id
                self.adapter_info(adapter_id, principal)

    def _check_adapter_write(self, principal: Principal, adapter_id: str) -> None:
        try:
            info = self.adapters.info(adapter_id)
        except ServiceError:
            return  # a new id (or an invalid one, refused by the store with its reason)
        principal.check_write(f"adapter {adapter_id!r}", info.get("tenant"))

    async def put_adapter(self, adapter_id: str, upload: Callable[[], Awaitable[tuple[bytes, bytes]]],
                          principal: Principal = TRUSTED) -> dict[str, Any]:
        """Create or replace an adapter. ``upload`` reads its (model, manifest) bytes, once the caller may write
        the adapter (another tenant's is refused before its upload is read). Both are validated before anything
        is stored (:meth:`~service.adapters.Adapters.put`); the adapter is the caller's tenant's (an admin key's:
        the deployment's)."""
        self._check_adapter_write(principal, adapter_id)
        model, manifest = await upload()
        info = await asyncio.to_thread(self.adapters.put, adapter_id, model, manifest,
                                       None if principal.admin else principal.tenant)
        self.access.audit(principal, "adapter.put", adapter_id)
        return info

    def delete_adapter(self, adapter_id: str, principal: Principal = TRUSTED) -> dict[str, Any]:
        """Delete an adapter (sessions using it keep their loaded copy); its record as it was (NotFound)."""
        self._check_adapter_write(principal, adapter_id)
        info = self.adapters.delete(adapter_id)
        self.access.audit(principal, "adapter.delete", adapter_id)
        return info


def _payer(entry: Session | OneShot) -> object:
    """Who a scheduler entry's render time is charged to: a stream itself, a single render its key's account."""
    return entry.account if isinstance(entry, OneShot) else entry


def training_figures(provenance: Any) -> dict[str, Any]:
    """AvatarInfo's ``trained`` and ``psnr_head`` from a bundle's provenance: trained when it records a training
    (``trained``, as `blendsplat train` and the job worker write it), psnr_head its held-out head PSNR (left unset
    when there is none)."""
    trained = provenance.get("trained") if isinstance(provenance, dict) else None
    if not isinstance(trained, dict):
        return {"trained": False}
    held_out = trained.get("held_out")
    value = held_out.get("psnr_head") if isinstance(held_out, dict) else None
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
        return {"trained": True, "psnr_head": float(value)}
    return {"trained": True}


def _attributed(exc: BaseException) -> BaseException:
    """The error a session gets for its own frame: typed errors as they are (a ``MemoryError`` is
    RESOURCE_EXHAUSTED); anything else, a failure of this frame alone once the batch was split, is logged and
    reported as INVALID_ARGUMENT on ``frame`` (its inputs passed validation, yet this frame cannot be rendered)."""
    if isinstance(exc, ServiceError | BlendsplatError | MemoryError):
        return exc
    log.error("a frame failed to render: %s: %s", type(exc).__name__, exc, exc_info=exc)
    return InvalidArgument(f"this frame could not be rendered ({type(exc).__name__}); the stream goes on",
                           field="frame")


def _render_isolated(entry: Loaded, jobs: list[Job], encoders: list[Encoder], encode: bool = True
                     ) -> tuple[list[Rendered | Unencoded | BaseException], float]:
    """:func:`_render`, and when the batched call fails, each job again on its own, so a failure is reported to the
    job that caused it only (runs on the render thread). Returns the results and the seconds spent."""
    start = time.perf_counter()
    try:
        results = _render(entry, jobs, encoders, encode)
    except Exception as e:  # noqa: BLE001 - attributed below
        if len(jobs) == 1:
            results = [e]
        else:
            log.warning("a batch of %d frames failed (%s); rendering them one by one", len(jobs), type(e).__name__)
            results = []
            for job, encoder in zip(jobs, encoders, strict=True):
                try:
                    results += _render(entry, [job], [encoder], encode)
                except Exception as e1:  # noqa: BLE001 - this job's own failure
                    results.append(e1)
    results = [_attributed(r) if isinstance(r, BaseException) else r for r in results]
    return results, time.perf_counter() - start


def _render_pipelined(entry: Loaded, jobs: list[Job], encoders: list[Encoder], lanes: EncodeLanes,
                      done: list[Callable[[Rendered | BaseException], None]]) -> tuple[bool, float]:
    """Render B jobs as :func:`_render_isolated` does, then hand each frame (or its error, which keeps its place
    among its session's frames) to its encoder's lane, whose worker encodes it and calls the job's ``done`` with
    the result; returns at once (whether any frame rendered, the render's seconds) and the render thread goes on
    with the next batch while these encode (runs on the render thread)."""
    try:
        frames, seconds = _render_isolated(entry, jobs, encoders, encode=False)
    except Exception as e:  # noqa: BLE001 - cannot happen (_render_isolated returns errors); defensive
        frames, seconds = [_attributed(e)] * len(jobs), 0.0
    for job, encoder, frame, then in zip(jobs, encoders, frames, done, strict=True):
        work = (functools.partial(_encode, job, encoder, frame) if isinstance(frame, Unencoded)
                else functools.partial(_attributed, frame))  # already attributed: itself
        try:
            lanes.submit(encoder, work, then)
        except RuntimeError:  # the lanes are shut down (the engine is closing): never encoded
            then(Unavailable("the server is shutting down; connect to another replica"))
    return any(isinstance(f, Unencoded) for f in frames), seconds


@dataclass
class Unencoded:
    """A rendered frame before its encode: its [H, W, 4] uint8 RGBA, the render's stage timings, the batch size."""

    image: Any
    timings: dict[str, float]
    batch: int


def _render(entry: Loaded, jobs: list[Job], encoders: list[Encoder], encode: bool = True
            ) -> list[Rendered | Unencoded | BaseException]:
    """Render B jobs of one avatar in one call and encode each (runs on the render thread); ``encode`` False: the
    frames as rendered, each to be passed to :func:`_encode`."""
    from .adapters import resolve_frames

    failed = resolve_frames(jobs)  # adapter-driven frames, one adapter run per adapter; refused ones never render
    if failed:
        kept = [i for i in range(len(jobs)) if i not in failed]
        done = iter(_render(entry, [jobs[i] for i in kept], [encoders[i] for i in kept], encode) if kept else [])
        return [failed[i] if i in failed else next(done) for i in range(len(jobs))]
    start = time.perf_counter()
    for job in jobs:
        job.started = start
    frames = Frame.stack([j.frame for j in jobs])
    cameras = Cameras.cat([j.camera for j in jobs])
    # 8-bit RGBA as the encoders take it (the native renderer writes it from its compositing loop)
    schedule = Schedule.baseline() if any(j.reference for j in jobs) else None  # None: the renderer's own
    images, timings = entry.renderer.render_rgba8(frames, cameras, host.stack([j.background for j in jobs]),
                                                  schedule=schedule)
    rendered = [Unencoded(image, timings, len(jobs)) for image in images]
    if not encode:
        return rendered
    return [_encode(job, encoder, frame) for job, encoder, frame in zip(jobs, encoders, rendered, strict=True)]


def _encode(job: Job, encoder: Encoder, frame: Unencoded) -> Rendered | BaseException:
    """One rendered frame through its session's encoder, with its timings (an encoder's error is returned: it is
    that session's only)."""
    t0 = time.perf_counter()
    try:
        data = encoder.encode(frame.image)
    except Exception as e:  # noqa: BLE001 - reported to that session only
        return _attributed(e)
    t1 = time.perf_counter()
    t = frame.timings
    return Rendered(data, pb.StageTimings(
        queue_ms=(job.started - job.received) * 1e3, blend_ms=t.get("blend", 0.0), lbs_ms=t.get("lbs", 0.0),
        raster_ms=t.get("raster", 0.0), encode_ms=(t1 - t0) * 1e3, total_ms=(t1 - job.received) * 1e3,
        batch=frame.batch))
